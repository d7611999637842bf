"""End-to-end generation benchmark: time per frame by stage, peak memory, disk, and the full-run estimate.

Generates a sample of the default dataset (same profile, fidelity, format and frame counts as
`gelsim generate --fabrics 100`), then extrapolates to the full 5,000-sequence run. Usage:

    python benchmarks/bench_generate.py [--fabrics 4] [--sequences-per-fabric 5] [--workers 1] [--workers-full 2] [--json]

With ``--workers 1`` (the default) the per-stage CPU times are one worker's alone, and the full run is
extrapolated as if --workers-full workers each ran that fast; they do not on this 2-core machine (two
workers run each other's stages about 1.3x slower: memory bandwidth and cache), so ``--workers 2``
measures the sample's throughput with both and extrapolates from that instead.

Time per frame is given two ways. ``steady_ms_per_frame`` is the sequences' own wall time (each
record's ``seconds``: simulate, render, encode and write it) over their frames: what every further
frame costs. ``ms_per_frame_one_worker`` divides the whole call's wall time instead, so it also holds
the run's start-up (``startup_s``: worker start, compiled kernels loaded from numba's cache, the
renderer's tables, the check render, the manifest), about 2-3 s once per run, which a 20-sequence
sample spreads over its 600 frames (3-5 ms each) and the full run over 152,000. The full-run
estimate is the start-up once plus the steady cost per frame.

Peak memory is the largest resident set of the generating process (one worker; each extra
worker adds about the same again).
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

from gelsim.cli import print_json, run_script
from gelsim.dataset import GenerateConfig, generate, plan, summarize_timings


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fabrics", type=int, default=4, help="fabrics in the sample (spread over the catalog)")
    ap.add_argument("--sequences-per-fabric", type=int, default=5)
    ap.add_argument("--fidelity", default="balanced")
    ap.add_argument("--resolution", default=None, help="WxH (default: the profile's 960x720)")
    ap.add_argument("--workers", type=int, default=1,
                    help="workers for the sample (>1: the estimate is the sample's measured throughput)")
    ap.add_argument("--workers-full", type=int, default=2,
                    help="with --workers 1: workers assumed for the full-run estimate")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from gelsim.runtime import configure_worker

    configure_worker()
    res = tuple(int(v) for v in args.resolution.split("x")) if args.resolution else None
    cfg = GenerateConfig(fabrics=args.fabrics, sequences_per_fabric=args.sequences_per_fabric,
                         fidelity=args.fidelity, resolution=res)
    out = Path(tempfile.mkdtemp(prefix="gelsim-bench-gen-"))
    try:
        t0 = time.perf_counter()
        c0 = time.process_time()
        manifest = generate(cfg, out / "ds", workers=args.workers, previews=False)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        timing = summarize_timings(out / "ds", manifest)
        frames = timing["frames"]
        nbytes = sum(p.stat().st_size for p in (out / "ds").rglob("*") if p.is_file())
    finally:
        shutil.rmtree(out, ignore_errors=True)
    # The workers' peak when they are child processes (--workers > 1), else this process's.
    who = resource.RUSAGE_CHILDREN if args.workers > 1 else resource.RUSAGE_SELF
    peak_mb = resource.getrusage(who).ru_maxrss / 1024
    full = plan(GenerateConfig(), 100)
    full_frames = sum(s.num_frames for s in full)
    ms = 1000 * wall / frames
    workers_full = args.workers if args.workers > 1 else args.workers_full
    if args.workers == 1:
        # The sequences' own wall time; the rest of the call is the run's start-up, paid once.
        steady_ms = timing["ms_per_frame"]
        startup_s = max(0.0, wall - steady_ms * frames / 1000)
        est_min = (startup_s + full_frames * steady_ms / 1000 / args.workers_full) / 60
    else:
        # Several workers' sequences overlap: the sample's throughput, start-up included (an overestimate).
        steady_ms, startup_s = None, None
        est_min = full_frames * ms / 1000 / 60
    result = {
        "sample": {"fabrics": args.fabrics, "sequences": len(manifest["sequences"]), "frames": frames,
                   "fidelity": args.fidelity, "resolution": list(res) if res else [960, 720]},
        "workers": args.workers,
        "ms_per_frame_one_worker" if args.workers == 1 else "wall_ms_per_frame_all_workers": round(ms, 2),
        **({"steady_ms_per_frame": round(steady_ms, 2), "startup_s": round(startup_s, 2)} if args.workers == 1 else {}),
        # This process's CPU time: the worker's own with --workers 1 (children's are not counted).
        **({"cpu_ms_per_frame": round(1000 * cpu / frames, 2)} if args.workers == 1 else {}),
        "frames_per_s": round(frames / wall, 2),
        "stages_ms_per_frame": {k: round(v, 2) for k, v in timing["stages_ms_per_frame"].items()},
        "peak_rss_mb_per_worker": round(peak_mb, 1), "bytes_per_frame": round(nbytes / frames),
        "full_run": {"sequences": len(full), "frames": full_frames, "workers": workers_full,
                     "basis": ("measured throughput, start-up included" if args.workers > 1 else
                               "start-up once + steady cost per frame, one worker x workers (linear)"),
                     "estimated_minutes": round(est_min, 1),
                     "estimated_disk_gb": round(nbytes / frames * full_frames / 1e9, 2)},
        "load_avg": os.getloadavg()[0],
    }
    if args.json:
        print_json(result)
    else:
        print(f"sample: {len(manifest['sequences'])} sequences, {frames} frames, fidelity {args.fidelity}")
        if args.workers == 1:
            print(f"1 worker: {steady_ms:.1f} ms of wall time per frame end to end, steady; {ms:.1f} ms with the "
                  f"run's {startup_s:.1f} s start-up spread over the sample; peak RSS {peak_mb:.0f} MB")
        else:
            print(f"{args.workers} workers: {ms:.1f} ms of wall time per frame end to end, start-up included "
                  f"({frames / wall:.1f} frames/s), peak RSS {peak_mb:.0f} MB per worker")
        print("| stage | CPU ms per frame (per worker) |\n|---|---|")
        for k, v in result["stages_ms_per_frame"].items():
            print(f"| {k} | {v:.1f} |")
        print(f"disk: {nbytes / frames / 1e3:.1f} kB per frame")
        print(f"full run ({len(full)} sequences, {full_frames} frames) on {workers_full} workers "
              f"({result['full_run']['basis']}): "
              f"about {est_min:.0f} min, {result['full_run']['estimated_disk_gb']:.1f} GB")
        print(f"(load average {result['load_avg']:.2f})")
    return 0


if __name__ == "__main__":
    run_script(main)
