"""End-to-end generation benchmark: time per frame by stage, peak memory, disk, and the full-run estimate.

Generates a sample of the default dataset (same profile, fidelity, format and frame counts as
`gelsim generate --fabrics 100`) with one worker, then extrapolates to the full 5,000-sequence
run on N workers. Usage:

    python benchmarks/bench_generate.py [--fabrics 4] [--sequences-per-fabric 5] [--workers-full 2] [--json]

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
    ap.add_argument("--workers-full", type=int, default=2, help="workers assumed for the full-run estimate")
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
        manifest = generate(cfg, out / "ds", workers=1, previews=False)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        timing = summarize_timings(out / "ds", manifest)
        frames = timing["frames"]
        nbytes = sum(p.stat().st_size for p in (out / "ds").rglob("*") if p.is_file())
    finally:
        shutil.rmtree(out, ignore_errors=True)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    full = plan(GenerateConfig(), 100)
    full_frames = sum(s.num_frames for s in full)
    ms = 1000 * wall / frames
    est_min = full_frames * ms / 1000 / args.workers_full / 60
    result = {
        "sample": {"fabrics": args.fabrics, "sequences": len(manifest["sequences"]), "frames": frames,
                   "fidelity": args.fidelity, "resolution": list(res) if res else [960, 720]},
        "ms_per_frame_one_worker": round(ms, 2), "cpu_ms_per_frame": round(1000 * cpu / frames, 2),
        "frames_per_s_one_worker": round(frames / wall, 2),
        "stages_ms_per_frame": {k: round(v, 2) for k, v in timing["stages_ms_per_frame"].items()},
        "peak_rss_mb_one_worker": round(peak_mb, 1), "bytes_per_frame": round(nbytes / frames),
        "full_run": {"sequences": len(full), "frames": full_frames, "workers": args.workers_full,
                     "estimated_minutes": round(est_min, 1),
                     "estimated_disk_gb": round(nbytes / frames * full_frames / 1e9, 2)},
        "load_avg": os.getloadavg()[0],
    }
    if args.json:
        print_json(result)
    else:
        print(f"sample: {len(manifest['sequences'])} sequences, {frames} frames, fidelity {args.fidelity}")
        print(f"one worker: {ms:.1f} ms per frame end to end ({frames / wall:.1f} frames/s), peak RSS {peak_mb:.0f} MB")
        print("| stage | ms per frame |\n|---|---|")
        for k, v in result["stages_ms_per_frame"].items():
            print(f"| {k} | {v:.1f} |")
        print(f"disk: {nbytes / frames / 1e3:.1f} kB per frame")
        print(f"full run ({len(full)} sequences, {full_frames} frames) on {args.workers_full} workers: "
              f"about {est_min:.0f} min, {result['full_run']['estimated_disk_gb']:.1f} GB")
        print(f"(load average {result['load_avg']:.2f})")
    return 0


if __name__ == "__main__":
    run_script(main)
