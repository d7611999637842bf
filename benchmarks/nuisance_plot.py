"""Accuracy against nuisance severity per model (docs/nuisance.md, "Robustness benchmark").

Reads the ``results.json`` of `stam experiment` runs, one per severity (each labelled SEVERITY=DIR), and plots
each model's accuracy, averaged over the runs' n, against severity, one panel per setting the runs hold (clean,
noisy, and transfer: trained clean, tested noisy), with the mean of the cells' 95% intervals as error bars (a
display aid: the paired comparisons are `stam compare`'s).

    .venv/bin/python benchmarks/nuisance_plot.py 0=OUT/none 0.5=OUT/h05 1=OUT/handheld 2=OUT/h2 --out plot.png
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", metavar="SEVERITY=DIR")
    p.add_argument("--out", required=True)
    p.add_argument("--title", default="accuracy against nuisance severity")
    a = p.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gelsim.atomic import write_figure

    pts: dict = {}
    for item in a.runs:
        sev, _, d = item.partition("=")
        tables = json.loads((Path(d) / "results.json").read_text())["tables"]
        # the n every setting has (the clean setting may hold extra n, run for the matched cost)
        shared = set.intersection(*(set(cells) for models in tables.values() for cells in models.values()))
        for setting, models in tables.items():
            for model, cells in models.items():
                kept = [c for n, c in cells.items() if n in shared]
                means = [c["mean"] for c in kept]
                half = [(c["ci95"][1] - c["ci95"][0]) / 2 for c in kept]
                pts.setdefault((setting, model), []).append((float(sev), np.mean(means), np.mean(half)))
    settings = [s for s in ("clean", "noisy", "transfer") if any(k[0] == s for k in pts)]
    fig, axes = plt.subplots(1, len(settings), figsize=(4.5 * len(settings), 3.6), sharey=True, squeeze=False)
    axes = axes[0]
    titles = {"clean": "clean windows", "noisy": "noisy windows", "transfer": "trained clean, tested noisy"}
    for ax, setting in zip(axes, settings):
        for (s, model), rows in sorted(pts.items()):
            if s != setting:
                continue
            rows.sort()
            x, y, e = (np.array(v) for v in zip(*rows))
            ax.errorbar(x, y, yerr=e, marker="o", capsize=3, label=model)
        ax.set_title(titles[setting])
        ax.set_xlabel("severity")
    axes[0].set_ylabel("test accuracy, % (mean over n)")
    axes[0].legend(fontsize=7)
    fig.suptitle(a.title)
    # Each point is its own run, with its own pretrained backbone: the bars are the heads' seeds and the test
    # sequences, not the backbone's own spread, which a difference between points also holds.
    fig.text(0.5, 0.01, "each point: its own dataset and backbone; bars: 95% CI over test sequences and head seeds, "
             "without the backbone's own spread", ha="center", fontsize=7)
    fig.tight_layout(rect=(0, 0.04, 1, 0.93))
    write_figure(a.out, fig)
    return 0


if __name__ == "__main__":
    sys.exit(main())
