"""Write gelsim/assets/johnson.toml: the texture map's tables for the 1-D and 2-D waves.

Each row solves one wave exactly (periodic Polonsky-Keer, gelsim.gel.johnson.periodic_contact)
at p / p* = s and fits the span slope that makes the two-scale imprint's pointwise map keep the
same fundamental. About a minute. Run from the repository root:

    .venv/bin/python tools/johnson_tables.py            # write the table
    .venv/bin/python tools/johnson_tables.py --check    # compare the 1-D rows with the closed forms
"""
from __future__ import annotations

import argparse

import numpy as np

from gelsim.atomic import atomic_write_text
from gelsim.cli import run_script
from gelsim.gel import johnson
from gelsim.params import dump_toml

# s grid: dense at light load, where the contact fraction changes fastest.
S_GRID = (0.005, 0.01, 0.02, 0.03, 0.05, 0.07, 0.1, 0.13, 0.16, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5,
          0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.93, 0.96, 0.98, 0.99, 1.0)
# Grid points per period: 2048 in 1-D and 128 x 128 in 2-D keep the contact fraction within
# 1/n and the fundamental within 1e-3 of a grid twice as fine (checked when written).
N = {"1d": 2048, "2d": 128}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="compare 1-D rows with the closed forms; write nothing")
    args = ap.parse_args()
    tables = {}
    for kind in ("1d", "2d"):
        rows = [johnson.fit_map_row(kind, s, N[kind]) for s in S_GRID[:-1]]
        rows.append({"s": 1.0, "contact_fraction": 1.0, "kept": 1.0, "zeta": 1.0, "lam": 1.0})
        tables[kind] = {k: [round(float(r[k]), 5) for r in rows] for k in rows[0]}
        for r in rows:
            print(f"{kind} s={r['s']:.3f} contact={r['contact_fraction']:.4f} kept={r['kept']:.4f} "
                  f"zeta={r['zeta']:.4f} lam={r['lam']:.4f}")
    s1 = np.array(tables["1d"]["s"])
    dc = np.abs(np.array(tables["1d"]["contact_fraction"]) - johnson.contact_fraction_1d(s1)).max()
    dk = np.abs(np.array(tables["1d"]["kept"]) - johnson.kept_relief_1d(s1)).max()
    print(f"1-D against the closed forms: contact fraction within {dc:.4f}, kept fundamental within {dk:.4f}")
    if args.check:
        return 0
    header = ("Texture-scale contact tables for the two-scale imprint (gelsim/gel/johnson.py, twoscale.py).\n"
              "Written by tools/johnson_tables.py: each row is the exact periodic contact (Polonsky-Keer) of\n"
              "the unit wave at p / p* = s, '1d' z = cos(2 pi x), '2d' z = cos(2 pi x) cos(2 pi y); contact_fraction\n"
              "and kept (fundamental of the gel surface over the wave's) are the solution's; zeta is the\n"
              "contact edge's depth below the crowns over the crown-to-valley depth, lam the span slope\n"
              "fitted so that the pointwise map keeps the same fundamental.\n"
              f"1-D rows against Johnson's closed forms: contact within {dc:.4f}, kept within {dk:.4f}.")
    text = dump_toml(tables, header=header)
    atomic_write_text(johnson.TABLE_FILE, text)
    print(f"wrote {johnson.TABLE_FILE}")
    return 0


if __name__ == "__main__":
    run_script(main)
