"""Ray generation benchmark: scaling from 1 to 2 Ray workers, and Ray's overhead per sequence
against the local worker pool, on this machine.

Generates the same small dataset (default: 60 sequences of 25-36 frames at 160x120, fast fidelity,
no previews) four times: in the local pool with 1 and 2 workers, and as Ray tasks on a Ray instance
started here with 1 and 2 CPUs. Each timing is of ``gelsim.dataset.generate`` alone (the Ray instance
is started before and counted apart: it is paid once per run, not per sequence); it includes the
shared-directory check and the start of the worker processes, as a user's run does. Every run must
give the same videos and labels as the first. Usage:

    python benchmarks/bench_ray.py [--fabrics 10] [--sequences-per-fabric 6] [--resolution 160x120] [--json]

Needs Ray (`make ray`); without it, it says so and exits 0 (`make bench` runs every benchmark).
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from gelsim.cli import print_json, run_script
from gelsim.cluster import import_ray, ray_available
from gelsim.dataset import GenerateConfig, generate, parse_resolution


def _checksums(manifest: dict) -> list:
    return [(s["id"], s["sha256"]) for s in manifest["sequences"]]


def _run(cfg: GenerateConfig, root: Path, name: str, **kwargs) -> tuple[float, dict]:
    t0 = time.perf_counter()
    manifest = generate(cfg, root / name, previews=False, **kwargs)
    return time.perf_counter() - t0, manifest


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fabrics", type=int, default=10)
    ap.add_argument("--sequences-per-fabric", type=int, default=6)
    ap.add_argument("--resolution", default="160x120", help="WxH")
    ap.add_argument("--fidelity", default="fast")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if not ray_available():  # `make bench` runs every benchmark; this one is for those who installed Ray
        print("bench_ray.py: Ray is not installed; skipped (make ray)")
        return 0
    ray = import_ray()
    cfg = GenerateConfig(fabrics=args.fabrics, sequences_per_fabric=args.sequences_per_fabric,
                         resolution=parse_resolution(args.resolution), fidelity=args.fidelity)
    root = Path(tempfile.mkdtemp(prefix="gelsim-bench-ray-"))
    walls: dict[str, float] = {}
    startup: dict[str, float] = {}
    try:
        ref = None
        for workers in (1, 2):
            walls[f"local_{workers}"], m = _run(cfg, root, f"local{workers}", workers=workers)
            ref = ref or _checksums(m)
            if _checksums(m) != ref:
                raise AssertionError("the local pool's runs differ")
        for cpus in (1, 2):
            t0 = time.perf_counter()
            ray.init(address="local", num_cpus=cpus, include_dashboard=False, configure_logging=False)
            startup[f"ray_{cpus}"] = time.perf_counter() - t0
            try:
                walls[f"ray_{cpus}"], m = _run(cfg, root, f"ray{cpus}", ray="local")
            finally:
                ray.shutdown()
            if _checksums(m) != ref:
                raise AssertionError(f"the run on {cpus} Ray CPU(s) differs from the local pool's")
        frames = sum(s["num_frames"] for s in m["sequences"])
    finally:
        shutil.rmtree(root, ignore_errors=True)
    n = args.fabrics * args.sequences_per_fabric
    result = {
        "sample": {"sequences": n, "frames": frames, "resolution": args.resolution, "fidelity": args.fidelity},
        "wall_s": {k: round(v, 2) for k, v in walls.items()},
        "ray_start_s": {k: round(v, 2) for k, v in startup.items()},
        "scaling_ray_1_to_2": round(walls["ray_1"] / walls["ray_2"], 2),
        "scaling_local_1_to_2": round(walls["local_1"] / walls["local_2"], 2),
        "ray_overhead_ms_per_sequence": {w: round(1000 * (walls[f"ray_{w}"] - walls[f"local_{w}"]) / n, 1)
                                         for w in (1, 2)},
        "identical_output": True,
    }
    if args.json:
        print_json(result)
    else:
        print(f"{n} sequences, {frames} frames at {args.resolution} ({args.fidelity}); wall s: "
              + ", ".join(f"{k} {v:.2f}" for k, v in result["wall_s"].items()))
        print(f"Ray 1 -> 2 workers: {result['scaling_ray_1_to_2']:.2f}x (local pool {result['scaling_local_1_to_2']:.2f}x)")
        print("Ray overhead per sequence against the local pool: "
              + ", ".join(f"{w} worker(s) {v:+.1f} ms" for w, v in result["ray_overhead_ms_per_sequence"].items())
              + f"; starting Ray: {', '.join(f'{v:.1f} s' for v in startup.values())} (once per run)")
        print("output identical in every run: yes")
    return 0


if __name__ == "__main__":
    run_script(main)
