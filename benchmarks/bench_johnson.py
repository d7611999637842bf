"""Johnson's sinusoidal contact: every imprint model against the theory on 1-D and 2-D waves.

A wave of steepness 0.15 is pressed over a whole flat pad (no membrane smoothing: the imprint alone) at
mean pressures s = p / p* from 0.05 to 3, wavelengths 0.1-2 mm at 24 px per period; the contact fraction
and the kept fundamental are measured over the central half and set against the theory at the local
pressure there (gelsim/gel/johnson.py, tests/gelsim/test_johnson.py). The pyramid model (gelsim's default
before the two-scale model) is included for comparison. A few minutes (the elastic reference dominates).

    .venv/bin/python benchmarks/bench_johnson.py [--json] [--markdown]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time

from gelsim.cli import run_script
from gelsim.fidelity import get_fidelity
from gelsim.gel import johnson, wave_check
from gelsim.runtime import configure_worker
from gelsim.sensor import load_profile

MODELS = {
    "reference (elastic)": dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0),
    "balanced (two-scale)": get_fidelity("balanced"),
    "fast (two-scale, 0.5)": get_fidelity("fast"),
    "pyramid (old default)": dataclasses.replace(get_fidelity("balanced"), imprint_model="pyramid"),
}
WAVELENGTHS = (0.1, 0.2, 0.5, 1.0, 2.0)
PRESSURES = (0.05, 0.2, 0.5, 1.0, 3.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    ap.add_argument("--markdown", action="store_true", help="print the summary as a Markdown table")
    ap.add_argument("--wavelengths", default=",".join(map(str, WAVELENGTHS)), help="mm, comma-separated")
    args = ap.parse_args()
    configure_worker()
    base = load_profile("vitac")
    rows = []
    t0 = time.perf_counter()
    for name, fid in MODELS.items():
        for kind in ("1d", "2d"):
            for L in (float(v) for v in args.wavelengths.split(",")):
                for s in PRESSURES:
                    r = wave_check.press_wave(base, fid, kind, L, s)
                    r["model"] = name
                    rows.append(r)
    summary = []
    for name in MODELS:
        rs = [r for r in rows if r["model"] == name]

        def err(key, th):
            return [abs(r[key] - r[th]) for r in rs]

        within = sum(abs(r["contact_fraction"] - r["theory_contact_fraction"]) <= 0.1 * r["theory_contact_fraction"]
                     + 2.0 / r["work_px_per_period"] and abs(r["kept"] - r["theory_kept"]) <= 0.1 * r["theory_kept"] + 0.02
                     for r in rs)
        summary.append({"model": name, "cases": len(rs), "within_tolerance": within,
                        "contact_error_median": sorted(err("contact_fraction", "theory_contact_fraction"))[len(rs) // 2],
                        "contact_error_max": max(err("contact_fraction", "theory_contact_fraction")),
                        "kept_error_median": sorted(err("kept", "theory_kept"))[len(rs) // 2],
                        "kept_error_max": max(err("kept", "theory_kept"))})
    doc = {"seconds": round(time.perf_counter() - t0, 1), "summary": summary, "rows": rows}
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        print()
        return 0
    print("| model | within tolerance | contact error, median / max | kept error, median / max |")
    print("|---|---|---|---|")
    for r in summary:
        print(f"| {r['model']} | {r['within_tolerance']}/{r['cases']} | {r['contact_error_median']:.3f} / "
              f"{r['contact_error_max']:.3f} | {r['kept_error_median']:.3f} / {r['kept_error_max']:.3f} |")
    if args.markdown:
        print("\n| model | wave | L mm | s | contact (theory) | kept (theory) |\n|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['model']} | {r['kind']} | {r['wavelength_mm']:g} | {r['s']:.2f} | {r['contact_fraction']:.2f} "
                  f"({r['theory_contact_fraction']:.2f}) | {r['kept']:.2f} ({r['theory_kept']:.2f}) |")
    print(f"\n{len(rows)} presses in {doc['seconds']} s")
    return 0


if __name__ == "__main__":
    run_script(main)
