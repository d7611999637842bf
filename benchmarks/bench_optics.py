"""CPU milliseconds per rendered frame at 960x720 on one core, for the optics backends.

Shadings: the calibrated table (``lut``, the ``vitac`` profile as shipped) and Phong from the
lights (``phong``, the same profile with ``[shading] model = "phong"``). Scenes: a flat gel, a
sphere press (4 mm ball, 0.5 mm deep) and a full-frame fabric press (a catalog fabric's
heightfield pressed by :func:`gelsim.gel.press`, every pixel touched, as in the dataset); each
with and without markers and noise. The fabric imprint is computed once and cached in the
temporary directory, so that the benchmark times the optics only. The figure per case is the
median CPU time (``time.process_time``) with OpenCV on one thread; the machine's load average is
printed with it, since other processes on the machine slow the memory-bound passes.

    .venv/bin/python benchmarks/bench_optics.py [--reps 30] [--backends fast] [--json]

Target (issue): a whole 960x720 frame, markers and noise included, in at most 15 ms on one core.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")   # before numpy and OpenCV load their thread pools

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from gelsim.cli import print_result, run_script  # noqa: E402
from gelsim.optics import Renderer, available_backends  # noqa: E402
from gelsim.runtime import configure_worker  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402

TARGET_MS = 15.0        # the budget per frame, markers and noise included


def sphere_depth(profile, radius_mm=2.0, depth_mm=0.5) -> np.ndarray:
    """Imprint of a ball of ``radius_mm`` pressed ``depth_mm`` at the centre, softened by 3 px: float32 mm."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    x = (np.arange(w) - (w - 1) / 2) * mm
    y = (np.arange(h) - (h - 1) / 2) * mm
    r2 = x[None] ** 2 + y[:, None] ** 2
    d = np.maximum(0.0, np.sqrt(np.maximum(radius_mm ** 2 - r2, 0)) - (radius_mm - depth_mm))
    return cv2.GaussianBlur(d.astype(np.float32), (0, 0), 3.0)


def fabric_depth(profile, fabric_id: int = 12, force_n: float = 3.0, seed: int = 1,
                 cache_dir: str | None = None) -> np.ndarray:
    """Imprint of catalog fabric ``fabric_id`` over the whole pad under ``force_n`` N (fast fidelity):
    float32 mm at the profile's resolution, cached as .npy in ``cache_dir`` (the temporary directory)."""
    h, w = profile.shape
    cache = Path(cache_dir or tempfile.gettempdir()) / \
        f"gelsim-bench-optics-{profile.name}-{w}x{h}-f{fabric_id}-{force_n:g}N-s{seed}-v2.npy"
    if cache.is_file():
        d = np.load(cache)
        if d.shape == (h, w):
            return d
    from gelsim.atomic import atomic_open
    from gelsim.fabrics import load_catalog
    from gelsim.frame import press_object
    from gelsim.scene import FabricObject

    # the fabric with its own compliance (cloth compression, yarn flattening), centred under the pad
    imp = press_object(FabricObject(load_catalog()[fabric_id]), profile, "fast", force_n=force_n, seed=seed)
    d = np.ascontiguousarray(imp.depth_mm, np.float32)
    with atomic_open(cache) as f:
        np.save(f, d)
    return d


def marker_corners(profile) -> np.ndarray:
    """The profile's marker grid as float32 ``(N, 4, 2)`` corner pixels."""
    mm = profile.image.mm_per_px
    pitch, size = profile.markers.pitch_mm / mm, profile.markers.size_mm / mm
    h, w = profile.shape
    c = np.array([(x, y) for y in np.arange(pitch / 2, h, pitch) for x in np.arange(pitch / 2, w, pitch)], np.float32)
    half = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32) * size / 2
    return c[:, None] + half[None]


def time_ms(fn, reps: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds per call (CPU time is steadier on a shared machine;
    for pyrender it sums llvmpipe's render threads)."""
    fn(0)                                    # warm-up: caches, first-touch allocations
    wall, cpu = [], []
    for i in range(reps):
        t, c = time.perf_counter(), time.process_time()
        fn(i + 1)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.median(wall) * 1e3), float(np.median(cpu) * 1e3)


def with_shading(profile, model: str):
    return dataclasses.replace(profile, shading=dataclasses.replace(profile.shading, model=model))


def run(reps: int = 30, gl_reps: int = 3, backends=("fast",), profile_name: str = "vitac",
        shadings=("lut", "phong"), fabric_id: int = 12, force_n: float = 3.0) -> dict:
    """All cases as one dict (what ``--json`` prints)."""
    configure_worker()
    base = load_profile(profile_name)
    scenes = {"flat": None, "sphere press": sphere_depth(base),
              "full-frame fabric": fabric_depth(base, fabric_id, force_n)}
    corners = marker_corners(base)
    usable = available_backends() if any(b != "fast" for b in backends) else ["fast"]
    rows = []
    for backend in backends:
        if backend not in usable:
            rows.append({"backend": backend, "skipped": "not available on this machine"})
            continue
        for shading in (shadings if backend == "fast" else ("lights",)):
            profile = base if backend != "fast" else with_shading(base, shading)
            if backend == "fast" and shading == "lut" and not profile.shading.table:
                rows.append({"backend": backend, "shading": shading, "skipped": "profile has no table"})
                continue
            t = time.perf_counter()
            r = Renderer(profile, backend, seed=0)
            setup_ms = (time.perf_counter() - t) * 1e3
            n = reps if backend == "fast" else gl_reps
            for scene, depth in scenes.items():
                for markers, noise in ((False, False), (True, False), (False, True), (True, True)):
                    mk = corners if markers else None
                    ms, cpu = time_ms(lambda s: r.render(depth, mk, seed=s, noise=noise), n)
                    rows.append({"backend": backend, "shading": shading, "scene": scene, "markers": markers,
                                 "noise": noise, "ms": round(ms, 2), "cpu_ms": round(cpu, 2),
                                 "setup_ms": round(setup_ms, 1)})
            r.close()
    return {"profile": profile_name, "shape_hw": list(base.shape), "threads": 1, "reps": reps,
            "fabric_id": fabric_id, "fabric_force_n": force_n, "target_ms": TARGET_MS,
            "load_avg": [round(v, 2) for v in os.getloadavg()], "cpus": os.cpu_count(),
            "cpu": platform.processor() or platform.machine(), "rows": rows}


def markdown(info: dict) -> str:
    h, w = info["shape_hw"]
    la = info["load_avg"]
    lines = [f"Optics, {info['profile']} {w}x{h}, one core, median over {info['reps']} frames "
             f"(load average {la[0]:.2f} / {la[1]:.2f} / {la[2]:.2f} on {info['cpus']} CPUs)", "",
             "| backend | shading | scene | markers | noise | CPU ms/frame | wall ms/frame |",
             "|---|---|---|---|---|---:|---:|"]
    for row in info["rows"]:
        if "skipped" in row:
            lines.append(f"| {row['backend']} | {row.get('shading', '')} | ({row['skipped']}) | | | | |")
        else:
            lines.append(f"| {row['backend']} | {row['shading']} | {row['scene']} | "
                         f"{'yes' if row['markers'] else 'no'} | {'yes' if row['noise'] else 'no'} | "
                         f"{row['cpu_ms']:.1f} | {row['ms']:.1f} |")
    setups = {(r["backend"], r["shading"]): r["setup_ms"] for r in info["rows"] if "setup_ms" in r}
    lines.append("")
    lines.append("Renderer set-up (background, light maps or table mosaic, noise bank; GL context): "
                 + ", ".join(f"{b}/{s} {ms:.0f} ms" for (b, s), ms in setups.items()))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=30, help="timed frames per case (fast backend), count; default 30")
    ap.add_argument("--gl-reps", type=int, default=3, help="timed frames per case (pyrender backend), count; default 3")
    ap.add_argument("--backends", default="fast", help="comma-separated backends to time; default fast "
                    "(add pyrender to time the OpenGL yardstick)")
    ap.add_argument("--shadings", default="lut,phong", help="fast backend's shading models; default lut,phong")
    ap.add_argument("--profile", default="vitac", help="sensor profile; default vitac (960x720)")
    ap.add_argument("--fabric", type=int, default=12, help="catalog fabric id of the full-frame press; default 12")
    ap.add_argument("--force", type=float, default=3.0, help="normal force of the fabric press, N; default 3")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    args = ap.parse_args(argv)
    info = run(args.reps, args.gl_reps, tuple(args.backends.split(",")), args.profile,
               tuple(args.shadings.split(",")), args.fabric, args.force)
    return print_result(args.json, info, markdown(info))


if __name__ == "__main__":
    run_script(main)
