"""benchmarks/bench_pair.py: two versions timed at once on their own cores; bad input in one line."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "bench_pair.py"


def run(*args, timeout=60):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT)


@pytest.mark.parametrize("args, says", [(["--base", "no-such-revision-42"], "--base no-such-revision-42"),
                                        (["--base", "HEAD", "--rounds", "0"], "--rounds 0"),
                                        (["--base", "HEAD", "--new", "/"], "--new /")])
def test_bad_input_is_one_line_and_exit_2(args, says):
    proc = run(*args)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0] and "Traceback" not in proc.stderr


def _worktrees() -> set[str]:
    out = subprocess.run(["git", "-C", str(ROOT), "worktree", "list", "--porcelain"], capture_output=True,
                         text=True).stdout
    return {line.split(" ", 1)[1] for line in out.splitlines() if line.startswith("worktree ")}


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux's CPU affinity and 2 cores")
def test_a_version_against_itself_and_the_worktree_is_removed():
    """The same commit on both sides (one fabric, one sequence: about a minute): every run gives a ratio
    per stage, the summary is their median, and the temporary worktree is gone afterwards."""
    before = _worktrees()
    proc = run("--base", "HEAD", "--rounds", "1", "--json", "--", "--fabrics", "1", "--sequences-per-fabric", "1",
               timeout=900)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["runs"] == 2 and len(doc["detail"]) == 2
    assert {r["base_core"] for r in doc["detail"]} == set(sorted(os.sched_getaffinity(0))[:2])
    for r in doc["detail"]:
        assert r["ratio"] == pytest.approx(r["new_ms"] / r["base_ms"])
        assert set(r["stage_ratios"]) >= {"imprint", "optics", "encode"}
    assert min(doc["ratio_range"]) <= doc["ratio_median"] <= max(doc["ratio_range"])
    assert 0.5 < doc["ratio_median"] < 2.0   # the same code: far from any real difference's scale
    assert _worktrees() == before
