"""The level table: every fidelity level on every scene, timed and scored against the reference
(:func:`run_bench`, :func:`run_benches`)."""
from __future__ import annotations

import dataclasses
import time
from typing import Callable

from ..fidelity import Fidelity, get_fidelity
from ..runtime import configure_worker
from .cache import RunCache, measured_run
from .metrics import ErrorAcc, accumulate
from .runs import TIMED_STAGES, LevelRun, bench_settings, make_renderer, warm_up
from .scenes import BenchConfig, bench_profile, scene_motion, scenes_for
from .shortcuts import run_shortcut_study
from .texture import SceneTexture, fast_shader


def run_bench(config: BenchConfig = BenchConfig(), progress: Callable[[str], None] | None = None) -> dict:
    """Run every level on every scene at ``config.resolution``; returns ``{"levels": [...],
    "settings", "shortcuts"}``.

    Each level entry: name, cpu_ms_per_frame (process CPU, end to end), wall_ms_per_frame,
    stages_ms (main-thread CPU ms per frame by stage) and ms_per_frame (their sum), the errors of
    :meth:`ErrorAcc.summary` (image_l1, psnr, ssim, marker_err_mm, marker_err_contact_mm,
    force_err_n, contact_area_err, kept_relief[_min, _max], image_texture[_min, _max] (through each
    one's renderer), image_texture_fast[_min, _max] (both through the fast shader: the gel's part),
    texture_err, image_texture_err, image_texture_fast_err), the level's knobs, per_scene (the same errors per scene), and
    cached_scenes (how many of its scenes came from the cache: their times are those measured then).
    """
    from ..fabrics import load_catalog

    config.validate()
    configure_worker()  # timings are per core, like a `gelsim generate` worker
    say = progress or (lambda s: None)
    t_start, c_start = time.perf_counter(), time.process_time()
    profile = bench_profile(config)
    catalog = load_catalog()
    scenes = scenes_for(config)
    levels = config.level_names()
    ref_name = config.reference
    order = [ref_name] + [n for n in levels if n != ref_name]
    cache = RunCache(config.cache_dir)
    warm_up(scenes[0], config, profile, catalog, [get_fidelity(n) for n in levels if n != ref_name])
    ref_runs: dict[str, tuple[LevelRun, SceneTexture]] = {}
    results = {}
    mmpp = profile.image.mm_per_px
    for name in order:
        fid = get_fidelity(name)
        renderer = make_renderer(profile, fid, config.seed)
        shader = fast_shader(profile, fid, config.seed)
        acc = ErrorAcc()
        secs = {s: 0.0 for s in TIMED_STAGES}
        cpu = wall = 0.0
        nframes = cached = 0
        per_scene = []
        try:
            for sc in scenes:
                motion = scene_motion(sc, config)
                ref = ref_runs.get(sc.name)
                run, tex = measured_run(sc, motion, profile, fid, catalog=catalog, renderer=renderer,
                                        contact=None if ref is None else ref[0].contact, config=config,
                                        yardstick=None if ref is None else ref[1],
                                        cache=cache if ref is None else None, encode=config.video_format,
                                        shader=shader)
                if ref is None:
                    ref_runs[sc.name] = ref = (run, tex)
                sacc = ErrorAcc()
                for a in (acc, sacc):
                    accumulate(a, run, ref[0], mmpp, sc.name, tex, ref[1])
                for k, v in run.seconds.items():
                    secs[k] += v
                cpu += run.cpu_s
                wall += run.wall_s
                cached += run.cached
                nframes += motion.num_frames
                per_scene.append({"scene": sc.name, **sacc.summary(), "cached": run.cached,
                                  "cpu_ms_per_frame": round(1000 * run.cpu_s / motion.num_frames, 2)})
                ps = per_scene[-1]
                say(f"{name:>10} {sc.name:<18} {ps['cpu_ms_per_frame']:9.1f} CPU ms/frame"
                    + (" (cached)" if run.cached else "")
                    + (f"  kept relief {ps['kept_relief']:.3f} image texture {ps['image_texture']:.3f}"
                       f" (fast shader {ps['image_texture_fast']:.3f})"
                       if ps["kept_relief"] is not None and ps["image_texture"] is not None else ""))
        finally:
            renderer.close()
            if shader is not None:
                shader.close()
        stages_ms = {k: round(1000 * v / nframes, 3) for k, v in secs.items()}
        results[name] = {"name": name, "cpu_ms_per_frame": round(1000 * cpu / nframes, 2),
                         "wall_ms_per_frame": round(1000 * wall / nframes, 2),
                         "ms_per_frame": round(sum(stages_ms.values()), 2), "stages_ms": stages_ms,
                         **acc.summary(), "knobs": knobs_of(fid), "cached_scenes": cached, "per_scene": per_scene}
    out = {"levels": [results[n] for n in levels], "settings": bench_settings(config, scenes)}
    if config.shortcut_level:
        out["shortcuts"] = run_shortcut_study(config, profile, catalog, scenes, progress=say)
    out["settings"]["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    out["settings"]["bench_cpu_seconds"] = round(time.process_time() - c_start, 1)
    return out


def run_benches(configs: list[BenchConfig], progress: Callable[[str], None] | None = None) -> dict:
    """:func:`run_bench` at each config (e.g. each resolution): ``{"runs": [result, ...]}``."""
    t0 = time.perf_counter()
    runs = []
    for c in configs:
        if progress:
            progress(f"bench at {c.resolution[0]}x{c.resolution[1]}, {c.frames} frames per scene")
        runs.append(run_bench(c, progress))
    return {"runs": runs, "bench_seconds": round(time.perf_counter() - t0, 1)}


def knobs_of(fid: Fidelity) -> dict:
    d = dataclasses.asdict(fid)
    d.pop("name")
    for k in ("est_ms_per_frame_vga", "est_ms_per_frame_960", "est_worker_efficiency"):
        d.pop(k)
    return d
