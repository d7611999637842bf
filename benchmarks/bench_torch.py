"""Frames per second of the torch optics backend at 640x480 and 960x720, beside the fast backend's.

The frame is the dataset's: the ``vitac`` profile (calibrated table, LED shadows, depth and halo terms)
over a catalog fabric pressed across the whole pad, with markers and camera noise, rendered to uint8.
The imprint is computed once (it is an input of the optics); its own CPU time per frame (the
``balanced`` two-scale model, which stays in numpy in every backend: its outputs are labels) is
reported beside, since it bounds what a GPU can do for ``gelsim generate``.

* ``fast``: one frame per call, CPU time on one core (OpenCV on one thread).
* ``torch`` on the CPU: ``BatchRenderer.render`` of ``--batch`` frames (each its own noise draw),
  CPU time on one core (one torch thread), per frame.
* ``torch`` on CUDA, when this machine has a GPU: wall time per frame (synchronised), at each batch
  size of ``--cuda-batches``; otherwise the rows say plainly that no GPU was measured.

    .venv/bin/python benchmarks/bench_torch.py [--reps 3] [--batch 8] [--json] [--out FILE.json]

Issue #16's goal: 1,000 frames/s at 960x720 on one H100 for imprint plus optics.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")   # before numpy, OpenCV and torch load their thread pools

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_optics import fabric_depth, marker_corners  # noqa: E402

from gelsim.cli import print_result, run_script  # noqa: E402
from gelsim.optics import Renderer  # noqa: E402
from gelsim.runtime import configure_worker  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402

RESOLUTIONS = ((640, 480), (960, 720))
GOAL_FPS_960 = 1000.0   # issue #16, imprint plus optics on one H100


def _per_frame(fn, frames: int, reps: int, clock) -> float:
    """Median seconds per frame of ``fn(i)`` (which renders ``frames`` frames), after one warm-up call."""
    fn(0)
    times = []
    for i in range(reps):
        t = clock()
        fn(i + 1)
        times.append((clock() - t) / frames)
    return float(np.median(times))


def _imprint_ms(profile, fabric_id: int, force_n: float, reps: int) -> float:
    """CPU ms of the balanced two-scale imprint of the fabric press (protrusion given), one core."""
    from gelsim.fabrics import load_catalog
    from gelsim.frame import press_object
    from gelsim.scene import FabricObject, field_heights

    obj = FabricObject(load_catalog()[fabric_id])
    prot = field_heights(obj, profile, seed=1)
    return 1e3 * _per_frame(lambda i: press_object(obj, profile, "balanced", force_n=force_n, seed=1,
                                                   protrusion_mm=prot), 1, reps, time.process_time)


def run(reps: int = 3, batch: int = 8, cuda_batches=(1, 16, 64), fabric_id: int = 12, force_n: float = 3.0) -> dict:
    import torch

    from gelsim.optics.torch_backend import BatchRenderer

    configure_worker()
    torch.set_num_threads(1)
    cuda = torch.cuda.is_available()
    rows = []
    for w, h in RESOLUTIONS:
        profile = load_profile("vitac").with_resolution(w, h)
        depth = fabric_depth(profile, fabric_id, force_n)
        corners = marker_corners(profile)
        fast = Renderer(profile, "fast", seed=0)
        s = _per_frame(lambda i: fast.render(depth, corners, seed=i), 1, max(reps, 10), time.process_time)
        rows.append({"resolution": f"{w}x{h}", "backend": "fast", "device": "cpu", "batch": 1,
                     "ms_per_frame": round(s * 1e3, 2), "fps": round(1 / s, 1), "clock": "CPU, one core"})
        br = BatchRenderer(Renderer(profile, "torch", seed=0, device="cpu"))
        s = _per_frame(lambda i: br.render([depth] * batch, [corners] * batch, list(range(i, i + batch))),
                       batch, reps, time.process_time)
        rows.append({"resolution": f"{w}x{h}", "backend": "torch", "device": "cpu", "batch": batch,
                     "ms_per_frame": round(s * 1e3, 2), "fps": round(1 / s, 1), "clock": "CPU, one torch thread"})
        if not cuda:
            rows.append({"resolution": f"{w}x{h}", "backend": "torch", "device": "cuda",
                         "skipped": "no CUDA device on this machine: GPU not measured"})
        else:  # pragma: no cover - needs a GPU
            gpu = BatchRenderer(Renderer(profile, "torch", seed=0, device="cuda"))

            def on_gpu(i, b):
                gpu.render([depth] * b, [corners] * b, list(range(i, i + b)))
                torch.cuda.synchronize()

            for b in cuda_batches:
                s = _per_frame(lambda i: on_gpu(i, b), b, reps, time.perf_counter)
                rows.append({"resolution": f"{w}x{h}", "backend": "torch", "device": "cuda", "batch": b,
                             "ms_per_frame": round(s * 1e3, 3), "fps": round(1 / s, 1),
                             "clock": f"wall, {torch.cuda.get_device_name()}", "includes": "host to device and back"})
        rows.append({"resolution": f"{w}x{h}", "stage": "imprint (balanced two-scale, numpy, every backend)",
                     "ms_per_frame": round(_imprint_ms(profile, fabric_id, force_n, reps), 2), "clock": "CPU, one core"})
    return {"profile": "vitac", "scene": f"fabric {fabric_id} pressed at {force_n:g} N over the whole pad, markers, noise",
            "goal_fps_960x720": GOAL_FPS_960, "cuda": cuda, "torch": torch.__version__,
            "load_avg": [round(v, 2) for v in os.getloadavg()], "cpus": os.cpu_count(),
            "cpu": platform.processor() or platform.machine(), "rows": rows}


def markdown(info: dict) -> str:
    la = info["load_avg"]
    lines = [f"Optics of one dataset frame ({info['scene']}), {info['profile']}; {info['cpus']} CPUs, "
             f"load average {la[0]:.2f} / {la[1]:.2f} / {la[2]:.2f}, torch {info['torch']}", "",
             "| resolution | what | device | batch | ms/frame | frames/s | clock |", "|---|---|---|---:|---:|---:|---|"]
    for r in info["rows"]:
        what = r.get("backend", r.get("stage"))
        if "skipped" in r:
            lines.append(f"| {r['resolution']} | {what} | {r['device']} | | | | {r['skipped']} |")
        elif "stage" in r:
            lines.append(f"| {r['resolution']} | {what} | cpu | | {r['ms_per_frame']} | {1e3 / r['ms_per_frame']:.1f} "
                         f"| {r['clock']} |")
        else:
            lines.append(f"| {r['resolution']} | {what} optics | {r['device']} | {r['batch']} | {r['ms_per_frame']} | "
                         f"{r['fps']} | {r['clock']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3, help="timed batches per case, count; default 3")
    ap.add_argument("--batch", type=int, default=8, help="frames per batch for torch on the CPU; default 8")
    ap.add_argument("--cuda-batches", default="1,16,64", help="batch sizes timed on a GPU; default 1,16,64")
    ap.add_argument("--fabric", type=int, default=12, help="catalog fabric id of the press; default 12")
    ap.add_argument("--force", type=float, default=3.0, help="normal force of the press, N; default 3")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    ap.add_argument("--out", metavar="FILE.json", help="also write the JSON document there")
    args = ap.parse_args(argv)
    info = run(args.reps, args.batch, tuple(int(b) for b in args.cuda_batches.split(",")), args.fabric, args.force)
    if args.out:
        from gelsim.atomic import atomic_write_json

        atomic_write_json(args.out, info)
    return print_result(args.json, info, markdown(info))


if __name__ == "__main__":
    run_script(main)
