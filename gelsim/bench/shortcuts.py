"""The shortcut study: the balanced level with and without the shortcuts of :mod:`gelsim.sequence`, and
with labels only (:func:`run_shortcut_study`)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..contact import simulate
from ..fidelity import get_fidelity
from .runs import TIMED_STAGES, LevelRun, make_renderer, run_level
from .scenes import BenchConfig, prepare_scene, scene_motion


def run_shortcut_study(config: BenchConfig, profile, catalog, scenes, *, progress=None) -> list[dict]:
    """The shortcut level with all shortcuts, without them, and with labels only, on the bench's
    scenes as ViTac-like sequences (``config.shortcut_frames`` frames, ``shortcut_precontact``
    before contact), all three on one contact simulation per scene.

    Each row: variant, ms_per_frame (main-thread CPU, sum of the stages), cpu_ms_per_frame
    (process CPU), stages_ms, and the largest difference from the run with all shortcuts:
    max_abs_dn (frame pixels), max_marker_px, max_indentation_mm.
    """
    say = progress or (lambda s: None)
    fid = get_fidelity(config.shortcut_level)
    long = dataclasses.replace(config, frames=config.shortcut_frames, precontact=config.shortcut_precontact)
    contacts = {}
    for sc in scenes:
        motion = scene_motion(sc, long)
        _, surface = prepare_scene(sc, motion, profile, catalog)
        contacts[sc.name] = simulate(motion, surface, profile, fid)
    rows = []
    base_runs: dict[str, LevelRun] = {}
    variants = (("all shortcuts", True, ("frames", "imprint", "markers")),
                ("no shortcuts", False, ("frames", "imprint", "markers")),
                ("labels only", True, ()))
    for label, sc_on, outputs in variants:
        renderer = make_renderer(profile, fid, config.seed) if outputs else None
        secs = {s: 0.0 for s in TIMED_STAGES}
        n = 0
        cpu = 0.0
        dmax = {"max_abs_dn": 0.0, "max_marker_px": 0.0, "max_indentation_mm": 0.0}
        try:
            for sc in scenes:
                motion = scene_motion(sc, long)
                run = run_level(sc, motion, profile, fid, catalog=catalog, renderer=renderer, contact=contacts[sc.name],
                                shortcuts=sc_on, outputs=outputs, encode=config.video_format if outputs else None,
                                sensor_seed=config.seed)
                base = base_runs.setdefault(sc.name, run)
                if run is not base:
                    if run.frames is not None:
                        dmax["max_abs_dn"] = max(dmax["max_abs_dn"], float(np.abs(
                            run.frames.astype(np.int16) - base.frames.astype(np.int16)).max()))
                    if "markers_xy_px" in run.labels:
                        dmax["max_marker_px"] = max(dmax["max_marker_px"], float(np.abs(
                            run.labels["markers_xy_px"] - base.labels["markers_xy_px"]).max(initial=0.0)))
                    if "indentation_mm" in run.labels:
                        dmax["max_indentation_mm"] = max(dmax["max_indentation_mm"], float(np.abs(
                            run.labels["indentation_mm"] - base.labels["indentation_mm"]).max()))
                for k, v in run.seconds.items():
                    secs[k] += v
                cpu += run.cpu_s
                n += motion.num_frames
        finally:
            if renderer is not None:
                renderer.close()
        stages_ms = {k: round(1000 * v / n, 3) for k, v in secs.items()}
        rows.append({"variant": label, "level": fid.name, "ms_per_frame": round(sum(stages_ms.values()), 2),
                     "cpu_ms_per_frame": round(1000 * cpu / n, 2), "stages_ms": stages_ms, **{k: round(v, 6) for k, v in dmax.items()}})
        say(f"{fid.name:>10} {label:<18} {rows[-1]['cpu_ms_per_frame']:8.1f} CPU ms/frame")
    return rows
