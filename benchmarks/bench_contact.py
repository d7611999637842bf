"""Time of the contact simulation (gelsim.contact.simulate) per sequence, per action and fidelity level.

Usage: .venv/bin/python benchmarks/bench_contact.py [--repeats N] [--json]

Each run samples a motion (seeded), builds a synthetic woven-like coarse heightfield (0.2 mm cells)
covering its travel and simulates it; reports the median and max wall time per sequence in ms,
the simulated physics steps, and the machine load (timings on a shared machine are noisy).
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import numpy as np

from gelsim.cli import print_json, run_script
from gelsim.contact import Surface, simulate
from gelsim.fidelity import fidelity_levels
from gelsim.motion import ACTIONS, sample_motion
from gelsim.sensor import load_profile

CELL_MM = 0.2  # the physics cell size the pipeline uses


def synthetic_surface(motion, profile, seed: int) -> Surface:
    """A plain-weave-like relief (0.5 mm pitch, 0.06 mm deep) plus fuzz, covering the travel."""
    xmin, ymin, xmax, ymax = motion.travel_bounds_mm()
    r = 0.5 * math.hypot(*profile.field_mm) + 1.0
    x0, y0 = xmin - r, ymin - r
    w = int(math.ceil((xmax - xmin + 2 * r) / CELL_MM)) + 1
    h = int(math.ceil((ymax - ymin + 2 * r) / CELL_MM)) + 1
    yy, xx = np.mgrid[0:h, 0:w] * CELL_MM
    rng = np.random.default_rng(seed)
    z = 0.03 * (np.sin(2 * np.pi * (xx + x0) / 0.5) * np.sin(2 * np.pi * (yy + y0) / 0.5) + 1)
    z += 0.01 * rng.random((h, w))
    return Surface(z.astype(np.float32), CELL_MM, (x0, y0), 0.7)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="sequences per action and level (default 5)")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    profile = load_profile("vitac")
    rows = []
    for level, fid in fidelity_levels().items():
        for action in ACTIONS:
            times, steps = [], []
            for rep in range(args.repeats):
                motion = sample_motion(action, 1000 + rep)
                surface = synthetic_surface(motion, profile, rep)
                t0 = time.perf_counter()
                frames = simulate(motion, surface, profile, fid)
                times.append((time.perf_counter() - t0) * 1e3)
                steps.append(int(round((frames.time_s[-1] + frames.contact_time_s) / fid.physics_dt_s)))
            rows.append({"level": level, "action": action, "physics_dt_s": fid.physics_dt_s,
                         "median_ms": statistics.median(times), "max_ms": max(times),
                         "mean_steps": statistics.mean(steps), "repeats": args.repeats})
    result = {"benchmark": "contact", "load_avg_1min": os.getloadavg()[0], "cpus": os.cpu_count(), "rows": rows}
    if args.json:
        print_json(result)
    else:
        print(f"load average {result['load_avg_1min']:.2f} on {result['cpus']} CPUs")
        print(f"{'level':10s} {'action':6s} {'dt s':>8s} {'median ms':>10s} {'max ms':>8s} {'steps':>7s}")
        for r in rows:
            print(f"{r['level']:10s} {r['action']:6s} {r['physics_dt_s']:8.5f} {r['median_ms']:10.1f} "
                  f"{r['max_ms']:8.1f} {r['mean_steps']:7.0f}")
    return 0


if __name__ == "__main__":
    run_script(main)
