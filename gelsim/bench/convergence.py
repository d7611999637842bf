"""The convergence study: each knob of a level swept alone against its finest value (:func:`run_convergence`)
and its reports (convergence.md, .json, .png)."""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Callable

from ..atomic import write_figure
from ..contact import ContactFrames, simulate
from ..fidelity import get_fidelity
from ..runtime import configure_worker
from .cache import RunCache, measured_run
from .metrics import ErrorAcc, accumulate
from .reports import fmt, write_report
from .runs import TIMED_STAGES, LevelRun, bench_settings, make_renderer, warm_up
from .scenes import BenchConfig, bench_profile, prepare_scene, scene_motion, scenes_for
from .texture import SceneTexture, fast_shader


# Errors the imprint knobs are judged by (texture first: what the data is for).
IMPRINT_METRICS = ("texture_err", "image_texture_err", "contact_area_err", "marker_err_contact_mm", "image_l1")
# Each sweep: knob, values from cheapest to dearest (the last is the converged value the others are
# compared with), the stage whose time is its cost, and the errors it reports (the first is plotted
# first). macro_cells: the two-scale model's coarse grid, 64 cells across the touched region by
# default (gelsim.fidelity), swept without the valley rule (SWEEP_HOLD), which
# macro_cells_per_valley sweeps on its own (it refines the grid only for objects with narrow envelope
# valleys: the corduroys); imprint_model: the old pyramid, the two-scale model, the elastic reference.
SWEEPS = (
    ("physics_dt_s", (0.004, 0.002, 0.001, 0.0005, 0.00025, 0.000125), "physics", ("force_err_n",)),
    ("imprint_scale", (0.25, 0.5, 0.75, 1.0), "imprint", IMPRINT_METRICS),
    ("macro_cells", (16, 32, 64, 128, 256), "imprint", IMPRINT_METRICS),
    ("macro_cells_per_valley", (0.0, 1.0, 2.0, 3.0, 4.0), "imprint", IMPRINT_METRICS),
    ("imprint_model", ("pyramid", "twoscale", "elastic"), "imprint", IMPRINT_METRICS),
    ("supersample", (1, 2, 3, 4), "optics", ("image_texture_err", "image_l1")),
    ("marker_model", ("gaussian", "elastic"), "markers", ("marker_err_contact_mm", "marker_err_mm")),
    ("render_backend", ("fast", "pyrender"), "optics", ("image_texture_err", "image_l1")),
)
# Knobs held at another value while a sweep runs: the grid alone, not its refinement for narrow valleys.
SWEEP_HOLD = {"macro_cells": {"macro_cells_per_valley": 0.0}}


def run_convergence(config: BenchConfig = BenchConfig(), base: str = "balanced", knobs: tuple[str, ...] = (),
                    progress: Callable[[str], None] | None = None) -> dict:
    """Sweep each knob of ``base`` alone over :data:`SWEEPS` on the bench's scenes.

    For every value: the cost (main-thread CPU ms per frame of the knob's stage, pyrender's GL
    threads counted under optics, and of the whole run) and the errors of :meth:`ErrorAcc.summary`
    against the sweep's last (finest) value on the same contact (the base level's; the physics
    sweep compares forces, each value with its own physics), with the texture ratios per fabric
    scene. The finest value's runs are the yardstick, kept in ``config.cache_dir`` if given.
    Returns ``{"base", "settings", "sweeps": [{"knob", "resolution", "stage", "metrics",
    "converged_value", "base_value", "points": [{"value", "stage_ms", "ms_per_frame", errors...,
    "per_scene": {scene: {"kept_relief", "image_texture", "contact_area_err"}}}]}]}``.
    """
    from ..fabrics import load_catalog

    config.validate()
    configure_worker()
    say = progress or (lambda s: None)
    t_start = time.perf_counter()
    profile = bench_profile(config)
    catalog = load_catalog()
    scenes = scenes_for(config)
    base_fid = get_fidelity(base)
    cache = RunCache(config.cache_dir)
    mmpp = profile.image.mm_per_px
    warm_up(scenes[0], config, profile, catalog, [base_fid])
    sweeps = []
    contacts: dict[str, ContactFrames] = {}
    for knob, values, stage, metrics in SWEEPS:
        if knobs and knob not in knobs:
            continue
        fids = [dataclasses.replace(base_fid, name=f"{knob}={v}", **{**SWEEP_HOLD.get(knob, {}), knob: v})
                for v in values]
        finest = fids[-1]
        yard: dict[str, tuple[LevelRun, SceneTexture | None]] = {}
        points = []
        physics_only = knob == "physics_dt_s"
        outputs = () if physics_only else ("frames", "imprint", "markers")
        for fid in reversed(fids):
            renderer = None if physics_only else make_renderer(profile, fid, config.seed)
            shader = None if physics_only else fast_shader(profile, fid, config.seed)
            acc = ErrorAcc()
            secs = {s: 0.0 for s in TIMED_STAGES}
            n = 0
            per_scene = {}
            try:
                for sc in scenes:
                    motion = scene_motion(sc, config)
                    if not physics_only and sc.name not in contacts:
                        _, surf = prepare_scene(sc, motion, profile, catalog)
                        contacts[sc.name] = simulate(motion, surf, profile, base_fid)
                    y = yard.get(sc.name)
                    run, tex = measured_run(sc, motion, profile, fid, catalog=catalog, renderer=renderer,
                                            contact=None if physics_only else contacts[sc.name], config=config,
                                            yardstick=None if y is None else y[1],
                                            cache=cache if y is None else None, outputs=outputs, shader=shader)
                    if y is None:
                        yard[sc.name] = y = (run, tex)
                    sacc = ErrorAcc()
                    for a in (acc, sacc):
                        accumulate(a, run, y[0], mmpp, sc.name, tex, y[1])
                    ss = sacc.summary()
                    if ss["kept_relief"] is not None:
                        per_scene[sc.name] = {k: ss[k] for k in ("kept_relief", "image_texture", "contact_area_err")}
                    for k, v in run.seconds.items():
                        secs[k] += v
                    n += motion.num_frames
            finally:
                for r in (renderer, shader):
                    if r is not None:
                        r.close()
            value = getattr(fid, knob)
            pt = {"value": value, "stage_ms": round(1000 * secs[stage] / n, 3),
                  "ms_per_frame": round(1000 * sum(secs.values()) / n, 2), **acc.summary(), "per_scene": per_scene}
            points.append(pt)
            say(f"{config.resolution[0]}x{config.resolution[1]} {knob}={value}: {pt['stage_ms']:.2f} ms ({stage}), "
                + ", ".join(f"{m} {pt[m]}" for m in metrics[:2]))
        points.reverse()
        sweeps.append({"knob": knob, "resolution": list(config.resolution), "stage": stage, "metrics": list(metrics),
                       "metric": metrics[0], "converged_value": getattr(finest, knob),
                       "base_value": getattr(base_fid, knob), "points": points})
    settings = bench_settings(config, scenes)
    settings["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    return {"base": base, "settings": settings, "sweeps": sweeps}


_METRIC_LABELS = {"force_err_n": "force err (N)", "texture_err": "texture err", "image_texture_err": "image texture err",
                  "contact_area_err": "contact area err", "marker_err_contact_mm": "marker err in contact (mm)",
                  "marker_err_mm": "marker err (mm)", "image_l1": "image L1 (DN)"}


def convergence_markdown(result: dict) -> str:
    s = result["settings"]
    lines = [f"Convergence from `{result['base']}`, one knob at a time: {len(s['scenes'])} scenes "
             f"({', '.join(s['scenes'])}); error against the knob's finest value on the same contact (in bold: "
             f"the base level's value); texture as kept relief / image texture ratios to the finest value "
             f"(geometric mean over the fabric scenes, then per fabric scene); load average {s['load_avg']}, "
             f"{s['date']}, {s.get('bench_seconds', '?')} s in all.", ""]
    for sw in result["sweeps"]:
        res = "x".join(str(v) for v in sw.get("resolution", s["resolution"]))
        metrics = sw.get("metrics", [sw["metric"]])
        fabric_scenes = sorted({sc for p in sw["points"] for sc in p.get("per_scene", {})})
        textured = any(p.get("kept_relief") is not None for p in sw["points"])
        lines += [f"**{sw['knob']}** at {res} px (cost: {sw['stage']} stage, CPU ms per frame)", "",
                  "| value | stage ms/frame | ms/frame | " + " | ".join(_METRIC_LABELS.get(m, m) for m in metrics)
                  + (" | kept relief / image texture | " + " | ".join(fabric_scenes) if textured else "") + " |",
                  "|---" * (3 + len(metrics) + ((1 + len(fabric_scenes)) if textured else 0)) + "|"]
        for p in sw["points"]:
            v = f"**{p['value']}**" if p["value"] == sw["base_value"] else f"{p['value']}"
            row = (f"| {v} | {p['stage_ms']:.2f} | {p['ms_per_frame']:.1f} | "
                   + " | ".join(fmt(p.get(m), 4 if m.endswith("_mm") else 3) for m in metrics))
            if textured:
                row += f" | {fmt(p.get('kept_relief'), 2)} / {fmt(p.get('image_texture'), 2)} | " + " | ".join(
                    f"{fmt(p['per_scene'].get(sc, {}).get('kept_relief'), 2)} / "
                    f"{fmt(p['per_scene'].get(sc, {}).get('image_texture'), 2)}" for sc in fabric_scenes)
            lines.append(row + " |")
        lines.append("")
    return "\n".join(lines)


def convergence_plot(result: dict, path: Path) -> None:
    """One panel per sweep: its first two errors (second on the right axis) against its stage's CPU
    ms per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    sw = result["sweeps"]
    n = len(sw)
    cols = min(3, n)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows), squeeze=False)
    for ax, s in zip(axes.ravel(), sw):
        pts = s["points"]  # the last (finest) value has zero error by construction
        metrics = [m for m in s.get("metrics", [s["metric"]]) if any(p.get(m) is not None for p in pts)][:2]
        xs = [p["stage_ms"] for p in pts]
        for j, (m, a, colour) in enumerate(zip(metrics, (ax, ax.twinx() if len(metrics) > 1 else None),
                                               ("tab:blue", "tab:orange"))):
            ok = [(x, p[m], p) for x, p in zip(xs, pts) if p.get(m) is not None]
            a.plot([o[0] for o in ok], [o[1] for o in ok], "-o" if j == 0 else "--s", color=colour, ms=4)
            a.set_ylabel(_METRIC_LABELS.get(m, m), color=colour, fontsize=8)
            a.set_ylim(bottom=0)
            if j == 0:
                for x, y, p in ok:
                    style = dict(fontweight="bold") if p["value"] == s["base_value"] else {}
                    a.annotate(str(p["value"]), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8, **style)
        res = "x".join(str(v) for v in s.get("resolution", result["settings"]["resolution"]))
        ax.set_title(f"{s['knob']} (vs {s['converged_value']}), {res}", fontsize=10)
        ax.set_xlabel(f"{s['stage']} CPU ms per frame")
        if all(x > 0 for x in xs) and max(xs) > 5 * min(xs):
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(True, alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    write_figure(path, fig, dpi=100)


def write_convergence(result: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write convergence.json, convergence.md and convergence.png under ``out_dir``."""
    return write_report(result, out_dir, "convergence", "convergence", convergence_markdown, convergence_plot)
