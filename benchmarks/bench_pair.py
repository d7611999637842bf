"""Two versions of the code timed side by side, on a VM whose speed drifts.

    python benchmarks/bench_pair.py --base REV [--new DIR] [--rounds 2] [--json] [-- BENCH_ARGS...]

On a shared VM the same code runs 5-25% faster or slower from one minute to the next, so two versions
timed one after the other differ by the drift as much as by the code (docs/speed.md). Here each version
runs `benchmarks/bench_generate.py` (its own copy, on its own sample of the default dataset) pinned to its
own core, both at once, so both see the same moment's VM; then they swap cores, and the pair repeats
``--rounds`` times. The ratio new / base of the steady ms per frame (the whole call's where the base's
benchmark predates the steady figure) and of each stage is reported per run and as the median. Both
versions share the memory bus and the last-level cache, as the two workers of a dataset run do.

``--base REV``: a commit (checked out into a temporary git worktree; numba's kernels are compiled there in a
warm-up run first); ``--new DIR``: the tree to time against it (default: this checkout, as it is on disk).
Arguments after ``--`` go to both benchmarks (e.g. ``-- --fabrics 8``). Needs at least 2 cores and git.
About 2 minutes per round with the default sample.

Its own spread, from the same commit on both sides (2026-11-27, 2-core VM): runs at 1.005 and 1.007, and
one at 0.89, where every stage of one side ran 10% slower for the whole run (a neighbour on that core).
So take the median of 3 or more rounds, and trust a stage's ratio that holds in every run more than the
whole frame's.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from gelsim.cli import print_json, run_script
from gelsim.errors import GelsimError

ROOT = Path(__file__).resolve().parents[1]


def _run_pair(trees: dict[str, Path], cores: dict[str, int], bench_args: list[str], quiet: bool) -> dict[str, dict]:
    """Both trees' benchmarks at once, each on its core; their JSON results."""
    procs = {}
    for name, tree in trees.items():
        env = dict(os.environ, PYTHONPATH=str(tree))
        cmd = [sys.executable, str(tree / "benchmarks" / "bench_generate.py"), "--json", *bench_args]
        procs[name] = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE,
                                       stderr=subprocess.DEVNULL if quiet else None, text=True,
                                       preexec_fn=lambda c=cores[name]: os.sched_setaffinity(0, {c}))
    stdouts = {name: p.communicate()[0] for name, p in procs.items()}   # both finished before any is judged
    for name, p in procs.items():
        if p.returncode != 0:
            raise GelsimError(f"the benchmark in {trees[name]} failed (exit {p.returncode}); run it there alone "
                              "to see why")
    return {name: json.loads(out) for name, out in stdouts.items()}


def _key(base: dict, new: dict) -> str:
    """The figure both results have: the steady ms per frame, or the whole call's where the base's
    benchmark predates it (a ratio of one to the other would count the start-up on one side only)."""
    return "steady_ms_per_frame" if "steady_ms_per_frame" in base and "steady_ms_per_frame" in new \
        else "ms_per_frame_one_worker"


def main() -> int:
    argv = sys.argv[1:]
    bench_args = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="the commit to compare against (any git revision)")
    ap.add_argument("--new", default=str(ROOT), help="the tree to time (default: this checkout)")
    ap.add_argument("--rounds", type=int, default=2, help="pairs of runs, each version once on each core")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        raise GelsimError(f"--rounds {args.rounds}: give 1 or more")
    new = Path(args.new).resolve()
    if not (new / "benchmarks" / "bench_generate.py").is_file():
        raise GelsimError(f"--new {args.new} has no benchmarks/bench_generate.py; give a gelsim checkout")
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", args.base + "^{commit}"],
                         capture_output=True, text=True)
    if rev.returncode != 0:
        raise GelsimError(f"--base {args.base} is not a commit of this repository; give a hash, tag or branch")
    commit = rev.stdout.strip()
    if not hasattr(os, "sched_setaffinity"):
        raise GelsimError("bench_pair pins each version to a core with Linux's CPU affinity, which this system "
                          "lacks; time the versions one after the other with bench_generate.py instead")
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        raise GelsimError("bench_pair needs 2 cores (one per version); this process may use only "
                          f"{len(cores)}; time the versions one after the other with bench_generate.py instead")
    tmp = Path(tempfile.mkdtemp(prefix="gelsim-pair-"))
    base = tmp / "base"
    try:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(base), commit],
                       check=True, capture_output=True)
        trees = {"base": base, "new": new}
        quiet = args.json
        # Warm-up: numba compiles each tree's kernels into that tree's cache on first use, and which
        # kernels run depends on the fabrics: one sequence of each of the sample's fabrics (a
        # one-sequence warm-up left a kernel to compile in the first timed run: 0.65x on the imprint).
        _run_pair(trees, {"base": cores[0], "new": cores[1]}, [*bench_args, "--sequences-per-fabric", "1"], quiet)
        runs = []
        for r in range(args.rounds):
            for swap in (False, True):
                placed = {"base": cores[1 if swap else 0], "new": cores[0 if swap else 1]}
                res = _run_pair(trees, placed, bench_args, quiet)
                b, n = res["base"], res["new"]
                stages = {s: n["stages_ms_per_frame"][s] / b["stages_ms_per_frame"][s]
                          for s in n["stages_ms_per_frame"] if b["stages_ms_per_frame"].get(s)}
                k = _key(b, n)
                bm, nm = float(b[k]), float(n[k])
                runs.append({"round": r + 1, "base_core": placed["base"], "figure": k, "base_ms": bm, "new_ms": nm,
                             "ratio": nm / bm, "stage_ratios": stages, "base": b, "new": n})
                if not quiet:
                    print(f"round {r + 1}, base on core {placed['base']}: base {bm:.1f} ms, new {nm:.1f} ms per "
                          f"frame, new / base {nm / bm:.3f}", flush=True)
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)], capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)
    summary = {"base": args.base, "base_commit": commit, "new": str(new), "runs": len(runs),
               "ratio_median": statistics.median(r["ratio"] for r in runs),
               "ratio_range": [min(r["ratio"] for r in runs), max(r["ratio"] for r in runs)],
               "stage_ratio_medians": {s: statistics.median(r["stage_ratios"][s] for r in runs)
                                       for s in runs[0]["stage_ratios"]}}
    if args.json:
        print_json({**summary, "detail": runs})
        return 0
    print(f"new / base, {runs[0]['figure']}: median {summary['ratio_median']:.3f} "
          f"(runs {summary['ratio_range'][0]:.3f}-{summary['ratio_range'][1]:.3f})")
    print("by stage: " + ", ".join(f"{s} {v:.3f}" for s, v in summary["stage_ratio_medians"].items()))
    return 0


if __name__ == "__main__":
    run_script(main)
