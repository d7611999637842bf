"""Milliseconds per rendered frame at 960x720, one core, for both optics backends.

Scenes: a flat gel, a sphere press (4 mm ball, 0.5 mm deep), and a full-frame
fabric-like texture (a woven relief over the whole image); each with and without
markers and noise. Prints a Markdown table, or one JSON document with --json.

    .venv/bin/python benchmarks/bench_optics.py [--reps 30] [--backends fast,pyrender] [--json]

The fast backend's target is 15 ms per frame with markers and noise (sphere press).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from gelsim.optics import Renderer, available_backends  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402


def sphere_depth(profile, radius_mm=2.0, depth_mm=0.5) -> np.ndarray:
    h, w = profile.shape
    mm = profile.image.mm_per_px
    x = (np.arange(w) - (w - 1) / 2) * mm
    y = (np.arange(h) - (h - 1) / 2) * mm
    r2 = x[None] ** 2 + y[:, None] ** 2
    d = np.maximum(0.0, np.sqrt(np.maximum(radius_mm ** 2 - r2, 0)) - (radius_mm - depth_mm))
    return cv2.GaussianBlur(d.astype(np.float32), (0, 0), 3.0)


def texture_depth(profile, pitch_mm=0.5, relief_mm=0.05, base_mm=0.1) -> np.ndarray:
    """A plain-weave-like relief pressed over the whole frame (every pixel > 0)."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    x = (np.arange(w) * mm)[None]
    y = (np.arange(h) * mm)[:, None]
    k = 2 * np.pi / pitch_mm
    weave = np.abs(np.sin(k * x) * np.cos(k * y / 2)) + np.abs(np.cos(k * x / 2) * np.sin(k * y))
    return (base_mm + relief_mm * weave / 2).astype(np.float32)


def marker_corners(profile) -> np.ndarray:
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=30, help="timed frames per case (fast backend), count")
    ap.add_argument("--gl-reps", type=int, default=3, help="timed frames per case (pyrender backend), count")
    ap.add_argument("--backends", default="fast,pyrender", help="comma-separated backends to time")
    ap.add_argument("--profile", default="vitac", help="sensor profile (960x720 for vitac)")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    profile = load_profile(args.profile)
    scenes = {"flat": None, "sphere press": sphere_depth(profile), "full-frame texture": texture_depth(profile)}
    corners = marker_corners(profile)
    usable = available_backends()
    rows = []
    for backend in args.backends.split(","):
        if backend not in usable:
            rows.append({"backend": backend, "skipped": "not available on this machine"})
            continue
        t = time.perf_counter()
        r = Renderer(profile, backend, seed=0)
        setup_ms = (time.perf_counter() - t) * 1e3
        reps = args.reps if backend == "fast" else args.gl_reps
        for scene, depth in scenes.items():
            for markers in (False, True):
                for noise in (False, True):
                    mk = corners if markers else None
                    ms, cpu = time_ms(lambda s: r.render(depth, mk, seed=s, noise=noise), reps)
                    rows.append({"backend": backend, "scene": scene, "markers": markers, "noise": noise,
                                 "ms": round(ms, 2), "cpu_ms": round(cpu, 2), "setup_ms": round(setup_ms, 1)})
        r.close()
    info = {"shape_hw": list(profile.shape), "threads": 1, "load_avg": list(os.getloadavg()),
            "cpu": platform.processor() or platform.machine(), "rows": rows}
    if args.json:
        json.dump(info, sys.stdout, indent=2)
        print()
        return 0
    h, w = profile.shape
    print(f"Optics, {w}x{h}, one core, median ms per frame (load average {info['load_avg'][0]:.2f})\n")
    print("| backend | scene | markers | noise | wall ms/frame | CPU ms/frame |")
    print("|---|---|---|---|---:|---:|")
    for row in rows:
        if "skipped" in row:
            print(f"| {row['backend']} | ({row['skipped']}) | | | | |")
        else:
            print(f"| {row['backend']} | {row['scene']} | {'yes' if row['markers'] else 'no'} | "
                  f"{'yes' if row['noise'] else 'no'} | {row['ms']:.1f} | {row['cpu_ms']:.1f} |")
    setups = {row["backend"]: row["setup_ms"] for row in rows if "setup_ms" in row}
    print("\nRenderer set-up (background, light maps, noise bank; GL context): "
          + ", ".join(f"{b} {ms:.0f} ms" for b, ms in setups.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
