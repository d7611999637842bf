"""What the paper's Tables I and II say about the frames before contact (docs/nuisance.md, "The timing").

Reads the paper's figures from ``stam.experiment.PAPER_TABLES`` and prints, per model and n:

* the noisy/clean ratio;
* an upper bound on q_n, the share of test sequences whose first n frames hold no contact frame: a
  window without contact can only be guessed (1% over 100 classes), and a window with contact is
  assumed to do no better than the clean window of the same n, so
  ``noisy_n <= (1 - q_n) clean_n + q_n / 100`` and ``q_n <= (clean_n - noisy_n) / (clean_n - 1)``.
  Also a one-sided 95% bound from the test split's sampling error (Table II and Table I are single runs
  on about 504 test sequences, 10% of 5,036; the two cells treated as independent binomials, which
  errs wide) and, since q_n cannot grow with n, the tightest bound from any m <= n;
* what a given pre-contact mixture would cap accuracy at (for the old default: 0-1 frames, and 6-12 for
  one sequence in five);
* the "extra" loss: clean_{n-1} - noisy_n, what a noisy window loses beyond a whole contact frame (the
  most a window that starts one frame before the touch can lack).

Arithmetic on published figures only; nothing here is fitted to our data.

    .venv/bin/python tools/table2_timing.py [--test-sequences 504] [--json]
"""
from __future__ import annotations

import argparse
import json
import math
import sys

from stam.experiment import PAPER_FRAMES, PAPER_TABLES

CHANCE = 1.0          # % for 100 classes
Z95_ONE_SIDED = 1.645


def q_bound(clean: float, noisy: float) -> float:
    """Largest share of windows without contact that keeps ``noisy`` reachable, given ``clean`` (both %)."""
    return max(0.0, (clean - noisy) / (clean - CHANCE))


def se_points(acc: float, n_test: int) -> float:
    """Binomial standard error of an accuracy (%) on ``n_test`` sequences, in points."""
    p = acc / 100.0
    return 100.0 * math.sqrt(p * (1 - p) / n_test)


def cap(clean: float, q: float) -> float:
    """Highest noisy accuracy (%) when a share ``q`` of windows holds no contact."""
    return (1 - q) * clean + q * CHANCE


def late_start_q(n: int, early=(0, 1), late=(6, 12), late_fraction=0.2) -> float:
    """q_n for pre-contact counts drawn uniformly from ``early`` (share 1 - late_fraction) or ``late``."""
    def share(rng):
        lo, hi = rng
        k = hi - lo + 1
        return sum(1 for o in range(lo, hi + 1) if o >= n) / k
    return (1 - late_fraction) * share(early) + late_fraction * share(late)


def analyse(n_test: int) -> dict:
    out: dict = {"test_sequences": n_test, "models": {}}
    for m in ("cnn", "cnn_sa", "stam"):
        clean, noisy = PAPER_TABLES["clean"][m], PAPER_TABLES["noisy"][m]
        rows, running = [], 1.0
        for i, n in enumerate(PAPER_FRAMES):
            c, z = clean[i], noisy[i]
            b = q_bound(c, z)
            diff_up = (c - z) + Z95_ONE_SIDED * math.hypot(se_points(c, n_test), se_points(z, n_test))
            b95 = max(0.0, diff_up / (c - CHANCE))
            running = min(running, b95)
            q_old = late_start_q(n)
            rows.append({"n": n, "clean": c, "noisy": z, "ratio": z / c, "q_bound": b, "q_bound_95": b95,
                         "q_bound_95_monotone": running, "old_default_q": q_old,
                         "old_default_cap": cap(c, q_old),
                         "old_default_z": (z - cap(c, q_old)) / math.hypot(se_points(z, n_test), se_points(c, n_test)),
                         "extra_loss_beyond_one_frame": (clean[i - 1] - z) if i > 0 else None})
        extra = [r["extra_loss_beyond_one_frame"] for r in rows if r["extra_loss_beyond_one_frame"] is not None]
        out["models"][m] = {"rows": rows, "mean_extra_loss_n3to7": sum(extra) / len(extra),
                            "mean_noisy_minus_clean": sum(z - c for z, c in zip(noisy, clean)) / len(clean)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--test-sequences", type=int, default=504,
                   help="test split size behind each published cell (10%% of 5,036: 504)")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    if a.test_sequences < 10:
        print("--test-sequences must be at least 10", file=sys.stderr)
        return 2
    res = analyse(a.test_sequences)
    if a.json:
        print(json.dumps(res, indent=1))
        return 0
    for m, r in res["models"].items():
        print(f"{m}: mean noisy - clean {r['mean_noisy_minus_clean']:+.2f} points; mean loss beyond one whole "
              f"contact frame (clean n-1 - noisy n, n = 3..7) {r['mean_extra_loss_n3to7']:+.2f}")
        print("  n  clean  noisy  ratio  q<= (point, 95%, 95% over m<=n)  old default: q, cap, z  beyond-1-frame")
        for row in r["rows"]:
            ex = row["extra_loss_beyond_one_frame"]
            print(f"  {row['n']}  {row['clean']:5.2f}  {row['noisy']:5.2f}  {row['ratio']:.3f}  "
                  f"{row['q_bound']:.3f}  {row['q_bound_95']:.3f}  {row['q_bound_95_monotone']:.3f}"
                  f"      {row['old_default_q']:.2f} {row['old_default_cap']:5.1f} {row['old_default_z']:+5.1f}"
                  f"  {'' if ex is None else f'{ex:+.2f}'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
