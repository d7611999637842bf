"""The pitch study: the texture kept by each imprint model and scale against the pixels per texture
period, on the catalog's finest weaves (:func:`run_pitch_study`) and its reports."""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..atomic import write_figure
from ..fidelity import get_fidelity
from ..runtime import configure_worker
from ..scene import press_properties
from ..sensor import load_profile
from ..stream import stage_clock
from ..texture import band_rms, contact_region, pitches_mm, texture_frames
from .cache import RunCache
from .metrics import rounded
from .reports import fmt
from .runs import load_avg
from .texture import texture_band


# The catalog's finest textures (texture scale 0.11-0.36 mm), and a weave either side of 4 px per
# period at the fast level's half-scale 960x720 imprint grid (0.039 mm per px: 0.158 mm).
PITCH_FABRICS = (13, 44, 15, 30, 14, 17, 2, 4, 1, 8)
# Mid-range hand press (assets/motions.toml: 1-4 N).
PITCH_FORCE_N = 2.5
# (model, imprint scale) variants of the balanced level compared with its elastic model at full scale.
PITCH_VARIANTS = (("twoscale", 0.5), ("twoscale", 1.0), ("pyramid", 0.5), ("pyramid", 1.0))


def run_pitch_study(resolution: tuple[int, int], *, fabrics: tuple[int, ...] = PITCH_FABRICS,
                    force_n: float = PITCH_FORCE_N, variants=PITCH_VARIANTS, base: str = "balanced",
                    profile: str = "vitac", seed: int = 0, cache_dir: str = "",
                    progress: Callable[[str], None] | None = None) -> dict:
    """Each fabric pressed flat over the whole pad at ``force_n`` (N), as `gelsim texture` presses
    it, by each (imprint model, imprint scale) of ``variants`` and by the elastic model at full
    scale (the yardstick, kept in ``cache_dir``): the kept relief and image texture (fast renderer
    for all, so that only the imprint differs) in the fabric's pitch band over the elastic model's
    contact region, and the contact-area ratio, against the pixels per period of the fabric's
    texture scale and finest pitch on the imprint's grid. Returns ``{"settings", "rows"}``."""
    from ..fabrics import heightfield, load_catalog
    from ..gel import press, work_shape
    from ..gel.twoscale import MIN_TEXTURE_PX
    from ..optics import Renderer

    configure_worker()
    say = progress or (lambda s: None)
    t_start = time.perf_counter()
    prof = load_profile(profile).with_resolution(*resolution)
    catalog = load_catalog()
    base_fid = get_fidelity(base)
    elastic = dataclasses.replace(base_fid, name="elastic", imprint_model="elastic", imprint_scale=1.0)
    cache = RunCache(cache_dir)
    renderer = Renderer(prof, "fast", seed=seed)
    h, w = prof.shape
    mm = prof.image.mm_per_px
    rows = []
    try:
        for fid in fabrics:
            fab = catalog[fid]
            prot = heightfield(fab, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                               mm_per_px=mm, seed=seed, rotation_deg=fab.orientation_deg)
            kw = dict(force_n=force_n, **press_properties(fab))
            key = cache.key({"pitch": fid, "force_n": force_n, "resolution": list(resolution), "seed": seed,
                             "profile": hashlib.sha256(repr(prof).encode()).hexdigest(),
                             "fidelity": {**dataclasses.asdict(elastic), "name": ""}})
            hit = cache.load(key)
            if hit is None:
                c0 = stage_clock()
                im = press(prot, prof, elastic, **kw)
                ref_depth, ref_mask, ref_area, ref_s = im.depth_mm, im.contact_mask, im.contact_area_mm2, stage_clock() - c0
                cache.save(key, {"depth": ref_depth, "mask": ref_mask}, {"area_mm2": ref_area, "cpu_s": ref_s})
            else:
                ref_depth, ref_mask = hit["depth"], hit["mask"]
                ref_area, ref_s = hit["meta"]["area_mm2"], hit["meta"]["cpu_s"]
            band, close_px, rim_px = texture_band(fab, prof)
            region = contact_region(ref_mask, close_px, rim_px)

            def texture(depth):
                clean, macro = texture_frames(renderer, depth, band, mm)
                return (band_rms(depth, region, band, mm),
                        band_rms(clean.astype(np.float32) - macro.astype(np.float32), region, band, mm))

            g0, i0 = texture(ref_depth)
            fine, _ = pitches_mm(fab)
            for model, scale in variants:
                fid_v = dataclasses.replace(base_fid, imprint_model=model, imprint_scale=scale)
                press(prot, prof, fid_v, **kw)  # warm: one-off tables and kernels
                c0 = stage_clock()
                im = press(prot, prof, fid_v, **kw)
                cpu = stage_clock() - c0
                g, i = texture(im.depth_mm)
                dx = mm * w / work_shape(prof, scale)[1]
                tex_px = min(fab.texture_mm, prof.gel.thickness_mm) / dx
                rows.append({"fabric": fid, "name": fab.name, "family": fab.family, "texture_mm": fab.texture_mm,
                             "finest_pitch_mm": fine, "model": model, "imprint_scale": scale,
                             "px_per_period": round(tex_px, 2), "px_per_finest_period": round(fine / dx, 2),
                             "texture_stage": model == "twoscale" and tex_px >= MIN_TEXTURE_PX,
                             "kept_relief": rounded(g / g0 if g0 > 0 else None, 4),
                             "image_texture": rounded(i / i0 if i0 > 0 else None, 4),
                             "contact_area_ratio": rounded(im.contact_area_mm2 / ref_area if ref_area > 0 else None, 4),
                             "imprint_ms": round(1000 * cpu, 1), "elastic_s": round(ref_s, 1),
                             "elastic_gel_relief_um": round(1000 * g0, 3), "elastic_image_dn": round(i0, 3)})
                r = rows[-1]
                say(f"{resolution[0]}x{resolution[1]} fabric {fid} ({fab.name}, {fab.texture_mm} mm) {model} {scale}: "
                    f"{r['px_per_period']} px/period, kept {r['kept_relief']}, image {r['image_texture']}")
    finally:
        renderer.close()
    settings = {"resolution": list(resolution), "force_n": force_n, "base": base, "profile": profile, "seed": seed,
                "min_texture_px": MIN_TEXTURE_PX, "load_avg": load_avg(),
                "date": datetime.datetime.now().isoformat(timespec="seconds"),
                "bench_seconds": round(time.perf_counter() - t_start, 1)}
    return {"settings": settings, "rows": rows}


def pitch_markdown(studies: list[dict]) -> str:
    lines = []
    for st in studies:
        s = st["settings"]
        lines += [f"Kept texture against pixels per period at {s['resolution'][0]}x{s['resolution'][1]}: each fabric "
                  f"pressed flat over the pad at {s['force_n']} N, ratios to the elastic model at full scale over its "
                  f"contact region (fast renderer for all); px/period: the texture scale (finest pitch) on the "
                  f"imprint grid; the two-scale model's texture stage needs {s['min_texture_px']:g}. Load average "
                  f"{s['load_avg']}, {s['date']}, {s['bench_seconds']} s.", "",
                  "| fabric | texture mm (finest) | model | scale | px/period (finest) | texture stage | kept relief "
                  "| image texture | contact area ratio | imprint ms |", "|---" * 10 + "|"]
        for r in st["rows"]:
            lines.append(f"| {r['fabric']} {r['name']} | {r['texture_mm']} ({r['finest_pitch_mm']}) | {r['model']} | "
                         f"{r['imprint_scale']} | {r['px_per_period']:.1f} ({r['px_per_finest_period']:.1f}) | "
                         f"{'yes' if r['texture_stage'] else 'no'} | {fmt(r['kept_relief'], 2)} | "
                         f"{fmt(r['image_texture'], 2)} | {fmt(r['contact_area_ratio'], 2)} | {r['imprint_ms']:.0f} |")
        lines.append("")
    return "\n".join(lines)


def pitch_plot(studies: list[dict], path: Path) -> None:
    """Kept relief (left) and image texture (right) against px per period, one series per (model,
    scale) and resolution; the two-scale model's texture threshold dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    markers = {"twoscale": "o", "pyramid": "s"}
    for ax, key, label in ((axes[0], "kept_relief", "kept relief (gel, ratio to elastic)"),
                           (axes[1], "image_texture", "image texture (ratio to elastic)")):
        for st in studies:
            res = "x".join(str(v) for v in st["settings"]["resolution"])
            for model, scale in sorted({(r["model"], r["imprint_scale"]) for r in st["rows"]}):
                pts = sorted((r["px_per_period"], r[key]) for r in st["rows"]
                             if r["model"] == model and r["imprint_scale"] == scale and r[key] is not None)
                ax.plot(*zip(*pts), markers.get(model, "^") + ("-" if scale == 1.0 else ":"), ms=4,
                        label=f"{model} {scale} @ {res}")
        ax.axvline(studies[0]["settings"]["min_texture_px"], color="grey", ls="--", lw=1)
        ax.axhline(1.0, color="black", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("texture period in imprint-grid px (log)")
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle("Fine weaves: texture kept against the imprint grid's pixels per period")
    fig.tight_layout()
    write_figure(path, fig, dpi=100)
