"""``gelsim render``: one tactile frame of a fabric or an indenter, for a first look."""
from __future__ import annotations

import os
import time
from pathlib import Path

from . import HelpFormatter, print_json
from ..errors import GelsimError

#: Force used when neither --force-n nor --depth-mm is given: a light press by hand
#: (the ViTac data were pressed by hand; about 1 N makes a clear imprint on a 0.2 MPa gel).
DEFAULT_FORCE_N = 1.0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="render one frame (fabric or indenter) to a PNG", formatter_class=HelpFormatter,
        description="Press a fabric (--fabric ID) or an indenter (--indenter) into the gel and render one "
                    "camera frame with markers and noise. Give the press as --force-n or --depth-mm.")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--fabric", type=int, default=None, metavar="ID",
                      help="fabric id from `gelsim fabrics list` (default: an indenter)")
    what.add_argument("--indenter", default=None, metavar="sphere|cylinder|PATH.stl",
                      help="indenter shape or mesh file (default: sphere when no --fabric)")
    p.add_argument("--diameter-mm", type=float, default=4.0, help="sphere or cylinder diameter, mm")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--force-n", type=float, default=None,
                     help=f"normal force, N (default {DEFAULT_FORCE_N} when --depth-mm is not given)")
    how.add_argument("--depth-mm", type=float, default=None, help="approach past first touch, mm")
    p.add_argument("--profile", default="vitac", metavar="NAME|PATH", help="sensor profile name or .toml path")
    p.add_argument("--backend", default=None, choices=["fast", "pyrender"],
                   help="renderer (default: the fidelity level's)")
    p.add_argument("--fidelity", default="balanced", choices=["fast", "balanced", "reference"],
                   help="fidelity level (imprint model, supersampling, default backend)")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed: fabric irregularities, background field, marker jitter, noise (integer)")
    p.add_argument("--out", required=True, metavar="FILE.png", help="output PNG file (required)")
    p.add_argument("--json", action="store_true", help="also print what was rendered and each stage's time (ms)")
    p.set_defaults(handler=run)


def _write_png(path: Path, rgb) -> None:
    import cv2

    if path.suffix.lower() != ".png":
        raise GelsimError(f"--out {path} must end in .png; give a PNG file name")
    if path.parent and not path.parent.exists():
        raise GelsimError(f"folder {path.parent} does not exist; create it or choose another --out")
    ok, buf = cv2.imencode(".png", rgb[..., ::-1])
    if not ok:
        raise GelsimError(f"could not encode {path}; check the image")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(buf.tobytes())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def render_one(*, fabric: int | None = None, indenter: str | None = None, diameter_mm: float = 4.0,
               force_n: float | None = None, depth_mm: float | None = None, profile="vitac",
               backend: str | None = None, fidelity="balanced", seed: int = 0) -> tuple:
    """One frame: ``(rgb uint8 (H, W, 3), info dict with the inputs, the imprint and stage times in ms)``."""
    import cv2
    import numpy as np

    from ..fidelity import get_fidelity
    from ..gel import press
    from ..markers import displace
    from ..optics import Renderer
    from ..sensor import load_profile

    times: dict[str, float] = {}
    t = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal t
        now = time.perf_counter()
        times[stage] = round((now - t) * 1e3, 2)
        t = now

    prof = profile if not isinstance(profile, (str, Path)) else load_profile(profile)
    fid = get_fidelity(fidelity)
    backend = backend or fid.render_backend
    if force_n is None and depth_mm is None:
        force_n = DEFAULT_FORCE_N
    for name, v in (("--force-n", force_n), ("--depth-mm", depth_mm), ("--diameter-mm", diameter_mm)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise GelsimError(f"{name} {v} must be a finite number >= 0")
    lap("setup")
    info: dict = {"profile": prof.name, "shape_hw": list(prof.shape), "backend": backend, "fidelity": fid.name,
                  "seed": seed}
    support = texture = None
    if fabric is not None:
        from ..fabrics import heightfield, load_catalog
        fab = load_catalog()[fabric]
        h, w = prof.shape
        mm = prof.image.mm_per_px
        prot = heightfield(fab, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                           mm_per_px=mm, seed=seed)
        support, texture = fab.support(), fab.texture_mm
        info["object"] = {"fabric": fab.id, "name": fab.name, "family": fab.family}
    else:
        from ..indenters import load_indenter
        name = indenter or "sphere"
        prot = load_indenter(name, prof, diameter_mm=diameter_mm) if name in ("sphere", "cylinder") \
            else load_indenter(name, prof)
        info["object"] = {"indenter": name, "diameter_mm": diameter_mm if name in ("sphere", "cylinder") else None}
    lap("object")
    imprint = press(prot, prof, fid, force_n=force_n, depth_mm=depth_mm, support=support, texture_mm=texture)
    lap("imprint")
    markers = displace(prof, fid, imprint, seed=seed) if prof.markers.enabled else None
    lap("markers")
    renderer = Renderer(prof, backend, supersample=fid.supersample, seed=seed)
    lap("renderer_setup")
    try:
        rgb = renderer.render(imprint.depth_mm, markers, seed=seed)
    finally:
        renderer.close()
    lap("render")
    info["imprint"] = {"indentation_mm": imprint.indentation_mm, "normal_force_n": imprint.normal_force_n,
                       "contact_area_mm2": imprint.contact_area_mm2, "bottomed_out": imprint.bottomed_out,
                       "max_depth_mm": float(imprint.depth_mm.max())}
    info["markers"] = 0 if markers is None else len(markers)
    info["stages_ms"] = times
    return rgb, info


def run(args) -> int:
    t0 = time.perf_counter()
    rgb, info = render_one(fabric=args.fabric, indenter=args.indenter, diameter_mm=args.diameter_mm,
                           force_n=args.force_n, depth_mm=args.depth_mm, profile=args.profile,
                           backend=args.backend, fidelity=args.fidelity, seed=args.seed)
    t = time.perf_counter()
    out = Path(args.out)
    _write_png(out, rgb)
    info["stages_ms"]["write_png"] = round((time.perf_counter() - t) * 1e3, 2)
    info["total_ms"] = round((time.perf_counter() - t0) * 1e3, 2)
    info["out"] = str(out)
    if args.json:
        print_json(info)
    else:
        print(f"wrote {out} ({rgb.shape[1]}x{rgb.shape[0]}, {info['backend']}, {info['total_ms']:.0f} ms)")
    return 0
