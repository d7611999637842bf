"""``gelsim texture``: how much of a fabric's weave reaches the image, stage by stage."""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from ..errors import GelsimError


def register(sub) -> None:
    from . import HelpFormatter, seed_arg

    p = sub.add_parser(
        "texture", formatter_class=HelpFormatter,
        help="texture budget: fabric relief, gel relief and slopes, image contrast vs camera noise, after H.264",
        description=(
            "Press catalog fabrics flat on the sensor and follow their texture through the pipeline, in each\n"
            "fabric's pitch band (half its finest pitch to twice its coarsest):\n"
            "  fabric relief (mm) -> gel relief (mm) and the share it keeps -> gel slopes ->\n"
            "  image contrast (DN, RMS over pixels and colour channels) against the camera noise in the\n"
            "  same band -> both again after the dataset's H.264 codec.\n"
            "A fabric counts as visible when its contrast is at least 3x the noise in its band (after H.264).\n"
            "Measured over the contact patch, away from its rim. See gelsim/texture.py for the definitions.\n\n"
            "examples:\n"
            "  gelsim texture --fabric 21 --force-n 3\n"
            "  gelsim texture --fabrics 1-100 --forces 1,4 --out out/texture   # table, JSON and plot"),
    )
    p.add_argument("--fabric", type=int, default=None, metavar="ID", help="one catalog fabric")
    p.add_argument("--fabrics", default=None, metavar="A-B|A,B,..",
                   help="several fabrics: a range 1-100 or a list [default: --fabric, else all]")
    p.add_argument("--force-n", type=float, default=None, help="one normal force, N")
    p.add_argument("--forces", default="1,4", metavar="F,F,..", help="normal forces, N, comma-separated")
    p.add_argument("--profile", default="vitac", metavar="NAME|PATH", help="sensor profile")
    p.add_argument("--fidelity", default="balanced", choices=["fast", "balanced", "reference"],
                   help="fidelity level (the dataset's default is balanced)")
    p.add_argument("--resolution", default=None, metavar="WxH",
                   help="render at this size, same field of view [default: the profile's]")
    p.add_argument("--no-codec", action="store_true", help="skip the H.264 round trip")
    p.add_argument("--seed", type=seed_arg, default=0, help="fabric irregularity and noise seed")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="write texture.json, texture.md (per family) and texture.png there")
    p.add_argument("--sheet", default=None, metavar="FILE.png",
                   help="also write a contact sheet: each fabric's frame as the dataset holds it (markers, noise, "
                        "H.264) at the first force, cropped at the contact's centre at full resolution")
    p.add_argument("--crop", default="144x108", metavar="WxH", help="size of each sheet tile, px")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.set_defaults(handler=run_texture)


def _ids(args, n_catalog: int) -> list[int]:
    if args.fabric is not None and args.fabrics is not None:
        raise GelsimError("give --fabric ID or --fabrics A-B, not both")
    if args.fabric is not None:
        spec = str(args.fabric)
    else:
        spec = args.fabrics or f"1-{n_catalog}"
    ids: list[int] = []
    try:
        for part in spec.split(","):
            if "-" in part:
                a, b = (int(v) for v in part.split("-", 1))
                if a > b:
                    raise GelsimError(f"--fabrics {spec!r}: the range {part} is inverted; write A-B with A <= B, "
                                      "e.g. 1-100")
                ids += list(range(a, b + 1))
            else:
                ids.append(int(part))
    except ValueError:
        raise GelsimError(f"--fabrics {spec!r} is not a range or list of ids; write e.g. 1-100 or 8,21,50") from None
    bad = [i for i in ids if not 1 <= i <= n_catalog]
    if bad or not ids:
        raise GelsimError(f"fabric id {bad[0] if bad else spec} is not in the catalog; ids run 1-{n_catalog}")
    return ids


def _forces(args) -> list[float]:
    if args.force_n is not None:
        vals = [args.force_n]
    else:
        try:
            vals = [float(v) for v in args.forces.split(",")]
        except ValueError:
            raise GelsimError(f"--forces {args.forces!r} is not a list of numbers; write e.g. 1,4") from None
    for f in vals:
        if not (math.isfinite(f) and 0 < f <= 50):
            raise GelsimError(f"force {f} N is out of range; give forces in (0, 50] N")
    return vals


def run_texture(args) -> int:
    from ..fabrics import load_catalog
    from ..fidelity import get_fidelity
    from ..optics import Renderer
    from ..runtime import configure_worker
    from ..sensor import load_profile
    from ..texture import crop_at, texture_budget
    from . import print_json, say_first_run

    say_first_run("gelsim texture")

    configure_worker()
    cat = load_catalog()
    ids = _ids(args, len(cat))
    forces = _forces(args)
    prof = load_profile(args.profile)
    if args.resolution:
        try:
            w, h = (int(v) for v in args.resolution.lower().split("x"))
        except ValueError:
            raise GelsimError(f"--resolution {args.resolution!r} is not WxH; write e.g. 960x720") from None
        prof = prof.with_resolution(w, h)
    fid = get_fidelity(args.fidelity)
    out_dir = Path(args.out) if args.out else None
    if out_dir is not None and out_dir.exists() and not out_dir.is_dir():
        raise GelsimError(f"--out {out_dir} exists and is not a directory; give a directory")
    ren = Renderer(prof, "fast", seed=0)
    crop = None
    if args.sheet:
        try:
            crop = tuple(int(v) for v in args.crop.lower().split("x"))
            assert len(crop) == 2 and 16 <= crop[0] <= prof.shape[1] and 16 <= crop[1] <= prof.shape[0]
        except (ValueError, AssertionError):
            raise GelsimError(f"--crop {args.crop!r} must be WxH within the {prof.shape[1]}x{prof.shape[0]} frame") from None
        from ..atomic import check_out_file

        check_out_file(args.sheet)
    tiles = []
    rows = []
    t0 = time.perf_counter()
    bar = None
    if not args.json and len(ids) * len(forces) > 2 and sys.stderr.isatty():
        from tqdm import tqdm
        bar = tqdm(total=len(ids) * len(forces), desc="texture", unit="press")
    for fid_ in ids:
        for i, f in enumerate(forces):
            want = crop is not None and i == 0
            res = texture_budget(cat[fid_], f, prof, fid, seed=args.seed, codec=not args.no_codec, renderer=ren,
                                 frame=want)
            b = res[0] if want else res
            rows.append(b.to_dict() | {"name": cat[fid_].name})
            if want:
                h, w = prof.shape
                snr = b.codec_snr if b.codec_snr is not None else b.snr
                tiles.append((crop_at(res[1], ((w - 1) / 2, (h - 1) / 2), crop),
                              f"{fid_} {cat[fid_].name[:18]} {snr:.1f}x"))
            if bar:
                bar.update(1)
    if bar:
        bar.close()
    doc = {"profile": prof.name, "resolution": list(prof.shape[::-1]), "fidelity": fid.name,
           "forces_n": forces, "codec": not args.no_codec, "seconds": round(time.perf_counter() - t0, 1),
           "rows": rows, "families": summarize(rows)}
    if out_dir is not None:
        write_report(doc, out_dir)
    if tiles:
        from ..atomic import write_png
        from ..texture import sheet

        write_png(args.sheet, sheet(tiles))
    if args.json:
        print_json(doc)
        return 0
    print(format_rows(rows))
    if len(rows) > 2:
        print()
        print(format_families(doc["families"]))
    if out_dir is not None:
        print(f"wrote {out_dir / 'texture.json'}, {out_dir / 'texture.md'}, {out_dir / 'texture.png'}")
    return 0


def _snr(r) -> float:
    return r["codec_snr"] if r.get("codec_snr") is not None else r["snr"]


def summarize(rows: list[dict]) -> list[dict]:
    """Per family and force: medians and the worst fabric (lowest contrast over noise)."""
    import numpy as np

    out = []
    keys = sorted({(r["family"], r["force_n"]) for r in rows}, key=lambda k: (min(
        rr["fabric_id"] for rr in rows if rr["family"] == k[0]), k[1]))
    for fam, f in keys:
        rs = [r for r in rows if r["family"] == fam and r["force_n"] == f]
        worst = min(rs, key=_snr)
        out.append({"family": fam, "force_n": f, "fabrics": len(rs),
                    "fabric_relief_um": float(np.median([r["fabric_relief_mm"] for r in rs]) * 1e3),
                    "gel_relief_um": float(np.median([r["gel_relief_mm"] for r in rs]) * 1e3),
                    "kept": float(np.median([r["kept"] for r in rs])),
                    "gel_slope_rms": float(np.median([r["gel_slope_rms"] for r in rs])),
                    "image_dn": float(np.median([r["image_dn"] for r in rs])),
                    "noise_dn": float(np.median([r["noise_dn"] for r in rs])),
                    "snr": float(np.median([_snr(r) for r in rs])),
                    "worst_fabric": worst["fabric_id"], "worst_snr": _snr(worst),
                    "visible": sum(bool(r["visible"]) for r in rs)})
    return out


def format_rows(rows: list[dict]) -> str:
    head = (f"{'id':>3} {'family':<11} {'F N':>4} {'band mm':>10} {'fabric um':>9} {'gel um':>7} {'kept':>5} "
            f"{'slope':>6} {'img DN':>7} {'noise':>6} {'SNR':>6} {'H264 DN':>8} {'noise':>6} {'SNR':>6} vis")
    lines = [head]
    for r in rows:
        c = r.get("codec_snr")
        lines.append(
            f"{r['fabric_id']:>3} {r['family']:<11} {r['force_n']:>4g} {r['band_mm'][0]:>4.2f}-{r['band_mm'][1]:<5.2f} "
            f"{r['fabric_relief_mm'] * 1e3:>9.1f} {r['gel_relief_mm'] * 1e3:>7.2f} {r['kept']:>5.2f} "
            f"{r['gel_slope_rms']:>6.3f} {r['image_dn']:>7.2f} {r['noise_dn']:>6.2f} {r['snr']:>6.1f} "
            + (f"{r['codec_image_dn']:>8.2f} {r['codec_noise_dn']:>6.2f} {c:>6.1f} " if c is not None else
               f"{'-':>8} {'-':>6} {'-':>6} ")
            + ("yes" if r["visible"] else "NO"))
    return "\n".join(lines)


def format_families(fams: list[dict]) -> str:
    lines = ["| family | force N | fabrics | fabric relief um | gel relief um | kept | gel slope | image DN | "
             "noise DN | contrast / noise | worst (id: ratio) | visible |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in fams:
        lines.append(f"| {r['family']} | {r['force_n']:g} | {r['fabrics']} | {r['fabric_relief_um']:.1f} | "
                     f"{r['gel_relief_um']:.2f} | {r['kept']:.2f} | {r['gel_slope_rms']:.3f} | {r['image_dn']:.2f} | "
                     f"{r['noise_dn']:.2f} | {r['snr']:.1f} | {r['worst_fabric']}: {r['worst_snr']:.1f} | "
                     f"{r['visible']}/{r['fabrics']} |")
    return "\n".join(lines)


def write_report(doc: dict, out_dir: Path) -> None:
    """texture.json, texture.md and texture.png (contrast over noise per family and force), atomically."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from ..atomic import atomic_write_text, write_figure

    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "texture.json", json.dumps(doc, indent=1))
    md = (f"# Texture budget ({doc['profile']} at {doc['resolution'][0]}x{doc['resolution'][1]}, {doc['fidelity']}, "
          f"{'after H.264' if doc['codec'] else 'no codec'})\n\n" + format_families(doc["families"]) + "\n")
    atomic_write_text(out_dir / "texture.md", md)
    fams = []
    for r in doc["families"]:
        if r["family"] not in fams:
            fams.append(r["family"])
    fig, ax = plt.subplots(figsize=(10, 4.2))
    x = np.arange(len(fams))
    forces = doc["forces_n"]
    wbar = 0.8 / max(len(forces), 1)
    for i, f in enumerate(forces):
        snr = [next((r["snr"] for r in doc["families"] if r["family"] == fam and r["force_n"] == f), np.nan)
               for fam in fams]
        worst = [next((r["worst_snr"] for r in doc["families"] if r["family"] == fam and r["force_n"] == f), np.nan)
                 for fam in fams]
        xs = x + (i - (len(forces) - 1) / 2) * wbar
        ax.bar(xs, snr, wbar, label=f"{f:g} N, median")
        ax.plot(xs, worst, "k_", ms=10, mew=2, label="worst fabric" if i == 0 else None)
    ax.axhline(3.0, color="r", ls="--", lw=1, label="3x the noise")
    ax.set_yscale("log")
    ax.set_xticks(x, fams, rotation=45, ha="right")
    ax.set_ylabel("texture contrast / noise in the pitch band")
    ax.set_title(f"Fabric texture reaching the image ({doc['profile']}, {doc['fidelity']}"
                 f"{', after H.264' if doc['codec'] else ''})")
    ax.legend(fontsize=8, ncol=4)
    fig.tight_layout()
    write_figure(out_dir / "texture.png", fig, dpi=110)
