"""The README's quick path timed on a machine's first run (cold) and on a later one (warm).

The path: ``gelsim generate --preset quick``, ``gelsim show`` of one sequence, ``stam train --config quick``
and ``stam evaluate``. Cold: numba's kernel cache (``NUMBA_CACHE_DIR``) and gelsim's user cache
(``GELSIM_CACHE``: the first look) start empty, as on a new machine (Python's own bytecode may be
compiled already). Warm: the same commands again into new folders with those caches filled (the dataset's
frame cache and the run's pretrained backbone belong to them, so they are made again).

Prints one JSON document: per run and step the wall time (s), the CPU time of the command (user + system,
s, all its processes), and the load average before and after. On a shared machine the wall time grows with
the load and the CPU time much less: say both (docs/quickstart.md).

    python benchmarks/bench_quickstart.py [--out out/bench_quickstart] [--no-train]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from gelsim.cli import run_script
from gelsim.errors import GelsimError


#: The file that marks --out as this script's scratch folder.
MARK = ".bench_quickstart"


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _step(name: str, cmd: list[str], env: dict) -> dict:
    load = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), _cpu()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    if r.returncode != 0:
        raise GelsimError(f"{name} failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-1:]}; run it by hand")
    return {"step": name, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "load_before": round(load, 2),
            "load_after": round(os.getloadavg()[0], 2), "stderr_first_line": (r.stderr.strip().splitlines() or [""])[0],
            "stdout_last_line": (r.stdout.strip().splitlines() or [""])[-1]}


def run_path(root: Path, env: dict, train: bool) -> list[dict]:
    bindir = Path(sys.executable).parent
    data, run = root / "demo", root / "demo-run"
    steps = [_step("generate", [str(bindir / "gelsim"), "generate", "--preset", "quick", "--out", str(data)], env),
             _step("show", [str(bindir / "gelsim"), "show", str(data), "--video"], env)]
    if train:
        steps.append(_step("train", [str(bindir / "stam"), "train", "--config", "quick", "--data", str(data),
                                     "--out", str(run), "--quiet"], env))
        steps.append(_step("evaluate", [str(bindir / "stam"), "evaluate", "--checkpoint", str(run / "best.pt")], env))
    return steps


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/bench_quickstart", help="scratch folder (made anew; its caches go inside it)")
    ap.add_argument("--no-train", action="store_true", help="time the dataset steps only")
    args = ap.parse_args()
    out = Path(args.out)
    if out.exists():
        if not (out / MARK).is_file():   # only a folder this script made is emptied
            raise GelsimError(f"--out {out} exists and was not made by this script; give a new folder")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARK).write_text("scratch folder of benchmarks/bench_quickstart.py\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(out / "numba-cache"), "GELSIM_CACHE": str(out / "gelsim-cache")}
    result = {"cores": os.cpu_count(), "cold": run_path(out / "cold", env, not args.no_train)}
    result["warm"] = run_path(out / "warm", env, not args.no_train)
    for key in ("cold", "warm"):
        result[f"{key}_total_wall_s"] = round(sum(s["wall_s"] for s in result[key]), 1)
        result[f"{key}_total_cpu_s"] = round(sum(s["cpu_s"] for s in result[key]), 1)
    json.dump(result, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    run_script(main)
