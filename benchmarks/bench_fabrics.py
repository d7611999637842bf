"""Time and memory of gelsim.fabrics.heightfield, one line per family (the family's first catalog fabric).

Cases (all 40 x 40 mm patches, the size the issue asks for, plus the dataset generator's call):

* ``fine``:      0.01 mm/px   -> 4000 x 4000 px, rotation 0
* ``sensor``:    0.0197 mm/px -> 2030 x 2030 px, rotation 0
* ``sensor30``:  0.0197 mm/px, rotated 30 degrees (the rotated path renders tiles and resamples)
* ``gen30``:     30 x 30 mm at 0.0197 mm/px (1523 x 1523 px), rotated 30 degrees: one dataset sequence

Times are the best of ``--repeat`` runs on one thread (OpenCV limited to 1 thread), in ms: wall
clock, and process CPU time (steadier when other jobs share the machine). Peak memory is
tracemalloc's peak of Python/numpy allocations during one call, in MB (OpenCV's own buffers, such as
the resampled output of a rotated patch, are not counted). ``--all`` times every catalog fabric in
one case instead and reports the slowest ones.

    .venv/bin/python benchmarks/bench_fabrics.py [--repeat 3] [--cases fine,sensor,sensor30,gen30] [--json]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc

import cv2

from gelsim.cli import print_json, run_script
from gelsim.fabrics import FAMILY_KEYS, heightfield, load_catalog

CASES = {
    "fine": dict(size_mm=40.0, mm_per_px=0.01, rotation_deg=0.0),
    "sensor": dict(size_mm=40.0, mm_per_px=0.0197, rotation_deg=0.0),
    "sensor30": dict(size_mm=40.0, mm_per_px=0.0197, rotation_deg=30.0),
    "gen30": dict(size_mm=30.0, mm_per_px=0.0197, rotation_deg=30.0),
}


def measure(fabric, size_mm: float, mm_per_px: float, rotation_deg: float, repeat: int
            ) -> tuple[float, float, float]:
    n = int(round(size_mm / mm_per_px))
    kw = dict(x0_mm=-size_mm / 2, y0_mm=-size_mm / 2, width_px=n, height_px=n, mm_per_px=mm_per_px, seed=0,
              rotation_deg=rotation_deg)
    tracemalloc.start()
    heightfield(fabric, **kw)
    peak = tracemalloc.get_traced_memory()[1] / 2 ** 20
    tracemalloc.stop()
    best, best_cpu = float("inf"), float("inf")
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        heightfield(fabric, **kw)
        best = min(best, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c)
    return best * 1000.0, best_cpu * 1000.0, peak


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3, help="runs per case, best kept (default 3)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--families", default="", help="comma-separated subset of families (default: all)")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    ap.add_argument("--all", metavar="CASE", default="",
                    help="time every catalog fabric in this one case and list the 10 slowest (CPU ms)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cases = [c for c in args.cases.split(",") if c]
    for c in cases:
        if c not in CASES:
            ap.error(f"unknown case {c!r}; choose from {', '.join(CASES)}")
    cat = load_catalog()
    if args.all:
        if args.all not in CASES:
            ap.error(f"unknown case {args.all!r}; choose from {', '.join(CASES)}")
        times = []
        for fab in cat:
            ms, cpu, mb = measure(fab, repeat=args.repeat, **CASES[args.all])
            times.append({"id": fab.id, "fabric": fab.name, "family": fab.family, "ms": round(ms, 1),
                          "cpu_ms": round(cpu, 1), "peak_mb": round(mb, 1)})
        times.sort(key=lambda r: -r["cpu_ms"])
        if args.json:
            print_json({"case": CASES[args.all], "loadavg_1min": round(os.getloadavg()[0], 2), "rows": times})
            return 0
        cpus = sorted(r["cpu_ms"] for r in times)
        print(f"{args.all}: median {cpus[len(cpus) // 2]:.0f} ms CPU, max {cpus[-1]:.0f} ms CPU over {len(cpus)} fabrics")
        for r in times[:10]:
            print(f"  {r['id']:3d} {r['fabric']:28s} {r['family']:12s} {r['cpu_ms']:6.0f} ms CPU {r['ms']:6.0f} ms wall")
        return 0
    fams = [f for f in FAMILY_KEYS if not args.families or f in args.families.split(",")]
    rows = []
    for fam in fams:
        fab = next(f for f in cat if f.family == fam)
        row = {"family": fam, "fabric_id": fab.id, "fabric": fab.name}
        for c in cases:
            ms, cpu, mb = measure(fab, repeat=args.repeat, **CASES[c])
            row[f"{c}_ms"] = round(ms, 1)
            row[f"{c}_cpu_ms"] = round(cpu, 1)
            row[f"{c}_peak_mb"] = round(mb, 1)
        rows.append(row)
        if not args.json:
            print(f"# {fam}: " + ", ".join(f"{c} {row[c + '_cpu_ms']:.0f} ms CPU / {row[c + '_peak_mb']:.0f} MB"
                                          for c in cases), file=sys.stderr, flush=True)
    load = os.getloadavg()
    meta = {"cases": {c: CASES[c] for c in cases}, "repeat": args.repeat, "threads": 1,
            "loadavg_1min": round(load[0], 2), "cpus": os.cpu_count()}
    if args.json:
        print_json({"meta": meta, "rows": rows})
        return 0
    head = ["family", "fabric"] + [f"{c} ms (CPU)" for c in cases] + [f"{c} MB" for c in cases]
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join(["---"] * len(head)) + "|")
    for r in rows:
        vals = [r["family"], f"{r['fabric_id']} {r['fabric']}"] \
            + [f"{r[c + '_ms']:.0f} ({r[c + '_cpu_ms']:.0f})" for c in cases] \
            + [f"{r[c + '_peak_mb']:.0f}" for c in cases]
        print("| " + " | ".join(vals) + " |")
    print(f"\nbest of {args.repeat}, 1 thread, load average {load[0]:.2f} on {os.cpu_count()} CPUs; "
          "sizes: " + "; ".join(f"{c} = {CASES[c]['size_mm']:g} mm at {CASES[c]['mm_per_px']} mm/px, "
                                f"{CASES[c]['rotation_deg']:g} deg" for c in cases))
    return 0


if __name__ == "__main__":
    run_script(main)
