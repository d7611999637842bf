"""Two runs of the Tables I/II sweep (``stam experiment``) compared cell by cell on the same test sequences.

The question it answers: did a change between the runs (the data rendered at another resolution, a
physics fix, another preset) move the tables, and did it move the attention models' gain over the
CNN? Both runs must have tested the same sequences: the same ``gelsim generate`` plan, so that only
what was changed differs. For each cell (setting, n, model) in both runs the per-sequence difference
in correctness (each run's seeds averaged) is resampled as ``stam experiment`` resamples its own
differences (:mod:`stam.stats`: the same resamples for every statistic, so all are paired), and each
interval is widened by both runs' seed shifts. A shift of the frozen backbone between the two runs
is part of what a difference measures, not of its interval: it moves every cell of a run together,
which the run-wide row (every cell, averaged) shows.

Fractions inside, percentage points out.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import stats
from .errors import StamError
from .config import SETTINGS as SETTING_ORDER
from .experiment import ci_text, seed_correctness, interval, shift_spread, short_label, versus_cnn
from .models import MODELS as MODEL_ORDER


def load_cells(run: str | Path) -> dict[tuple[str, int, str], list[dict]]:
    """A sweep's finished cells by (setting, n, model): their ``result.json`` under
    ``RUN/cells/SETTING/nN/MODEL/seedS/``, with per-sequence results (``test_ids``, ``test_correct``)."""
    run = Path(run)
    paths = sorted(run.glob("cells/*/n*/*/seed*/result.json"))
    if not paths:
        raise StamError(f"{run} has no finished cells (cells/SETTING/nN/MODEL/seedS/result.json); "
                        "give the --out directory of a `stam experiment` run")
    cells: dict[tuple[str, int, str], list[dict]] = {}
    for p in paths:
        c = json.loads(p.read_text())
        if "test_correct" not in c:
            raise StamError(f"{p} has no per-sequence results; rerun `stam experiment` with the same --out "
                            "to add them")
        cells.setdefault((c["setting"], int(c["frames"]), c["model"]), []).append(c)
    return cells


def _test_ids(cells: dict, run) -> list[str]:
    ids = {tuple(sorted(c["test_ids"])) for cs in cells.values() for c in cs}
    if len(ids) != 1:
        raise StamError(f"the cells of {run} were tested on different sequences; rerun its sweep into a new --out")
    return list(ids.pop())


def compare_runs(a: str | Path, b: str | Path) -> dict:
    """Run ``b`` against run ``a``: for every cell both have, the accuracies (%, mean over seeds) and the
    paired difference b - a in points with its 95% CI; the same averaged over n per (setting, model);
    the attention models' gain over the CNN in each run and its change, per setting averaged over n;
    and every shared cell averaged (the run-wide shift)."""
    cells_a, cells_b = load_cells(a), load_cells(b)
    ids = _test_ids(cells_a, a)
    ids_b = _test_ids(cells_b, b)
    if ids != ids_b:
        shared = len(set(ids) & set(ids_b))
        raise StamError(f"{a} and {b} were tested on different sequences ({len(ids)} and {len(ids_b)}, {shared} "
                        "shared); compare runs on datasets made with the same gelsim generate plan")
    keys = sorted(set(cells_a) & set(cells_b),
                  key=lambda k: (SETTING_ORDER.index(k[0]) if k[0] in SETTING_ORDER else 9, k[1],
                                 MODEL_ORDER.index(k[2]) if k[2] in MODEL_ORDER else 9))
    if not keys:
        raise StamError(f"{a} and {b} have no cell (setting, n, model) in common; run the same sweep in both")
    correct = {}
    for run, cells in (("a", cells_a), ("b", cells_b)):
        for k in keys:
            correct[(run, k)] = seed_correctness(cells[k], ids)
    shift = {run: stats.seed_variance_ratio([correct[(run, k)] for k in keys])["shift_variance"] for run in "ab"}

    names, columns, spreads = [], [], []

    def column(name, weighted):
        """A statistic sum(weight x seed-averaged correctness of (run, cell)) and what the seeds' shift adds
        to its variance (each run's own shift, its cells' seeds independent)."""
        names.append(name)
        columns.append(sum(w * correct[rk].mean(0) for w, rk in weighted))
        spreads.append(sum(shift[run] * shift_spread([(w, rk) for w, rk in weighted if rk[0] == run], correct)
                           for run in "ab"))

    def change(k, w=1.0):  # b - a of one cell, weighted
        return [(w, ("b", k)), (-w, ("a", k))]

    for k in keys:
        column(("cell", k), change(k))
    groups: dict = {}
    for s, n, m in keys:
        groups.setdefault((s, m), []).append(n)
    for (s, m), ns in groups.items():
        column(("mean", s, m), [t for n in ns for t in change((s, n, m), 1 / len(ns))])
    gains = []
    for s in SETTING_ORDER:
        for m in versus_cnn(MODEL_ORDER):
            ns = [n for n in groups.get((s, m), []) if n in groups.get((s, "cnn"), [])]
            if not ns:
                continue
            gains.append((s, m))
            for run in "ab":
                column(("gain", s, m, run), [(sign / len(ns), (run, (s, n, mm))) for n in ns
                                             for sign, mm in ((1, m), (-1, "cnn"))])
            column(("gain change", s, m), [t for n in ns for sign, mm in ((1, m), (-1, "cnn"))
                                           for t in change((s, n, mm), sign / len(ns))])
    column(("all",), [t for k in keys for t in change(k, 1 / len(keys))])

    ci = {}
    for name, (mean, lo, hi), spread in zip(names, stats.bootstrap_intervals(np.stack(columns, axis=1)), spreads):
        lo, hi = stats.widen(mean, lo, hi, spread)
        ci[name] = {**interval(mean, lo, hi), "resolved": bool(lo > 0 or hi < 0)}

    def acc(run, k):
        return 100 * float(correct[(run, k)].mean())

    cells = [{"setting": s, "frames": n, "model": m, "a": acc("a", (s, n, m)), "b": acc("b", (s, n, m)),
              "difference": ci[("cell", (s, n, m))]} for s, n, m in keys]
    means = [{"setting": s, "model": m, "frames": ns,
              "a": float(np.mean([acc("a", (s, n, m)) for n in ns])),
              "b": float(np.mean([acc("b", (s, n, m)) for n in ns])),
              "difference": ci[("mean", s, m)]} for (s, m), ns in groups.items()]
    gain_rows = [{"setting": s, "model": m, "a": ci[("gain", s, m, "a")], "b": ci[("gain", s, m, "b")],
                  "difference": ci[("gain change", s, m)]} for s, m in gains]
    return {"a": str(a), "b": str(b), "test_sequences": len(ids),
            "seeds": {"a": max(len(cells_a[k]) for k in keys), "b": max(len(cells_b[k]) for k in keys)},
            "shift_variance": shift, "cells": cells, "means": means, "gains": gain_rows,
            "all_cells": {"cells": len(keys), "difference": ci[("all",)]}}


def _ci(d: dict) -> str:
    text = ci_text(d, signed=True)
    return f"**{text}**" if d["resolved"] else text


def markdown(result: dict) -> str:
    """The comparison as markdown: per setting a table of b - a per model and n (and averaged over n),
    then the attention models' gains over the CNN in both runs."""
    a, b = Path(result["a"]).name or result["a"], Path(result["b"]).name or result["b"]
    lines = [f"Run B ({b}) against run A ({a}), on the same {result['test_sequences']:,} test sequences "
             f"({result['seeds']['a']} and {result['seeds']['b']} seeds per cell). B − A in points [95% CI]; "
             "bold: the CI excludes 0.", ""]
    frames = sorted({c["frames"] for c in result["cells"]})
    for s in [s for s in SETTING_ORDER if any(c["setting"] == s for c in result["cells"])]:
        lines += [f"**{s}**", "", "| model | " + " | ".join(f"n={n}" for n in frames) + " | mean over n: A, B, B − A |",
                  "|---" * (len(frames) + 2) + "|"]
        for mean in [r for r in result["means"] if r["setting"] == s]:
            by_n = {c["frames"]: c for c in result["cells"] if c["setting"] == s and c["model"] == mean["model"]}
            row = [_ci(by_n[n]["difference"]) if n in by_n else "" for n in frames]
            lines.append(f"| {short_label(mean['model'])} | " + " | ".join(row)
                         + f" | {mean['a']:.1f}, {mean['b']:.1f}, {_ci(mean['difference'])} |")
        lines.append("")
    if result["gains"]:
        lines += ["Each model over the CNN, averaged over n:", "", "| gain | A | B | B − A |", "|---|---|---|---|"]
        for g in result["gains"]:
            lines.append(f"| {short_label(g['model'])} − CNN, {g['setting']} | {_ci(g['a'])} | "
                         f"{_ci(g['b'])} | {_ci(g['difference'])} |")
        lines.append("")
    d = result["all_cells"]
    lines.append(f"All {d['cells']} shared cells averaged: B − A {_ci(d['difference'])} points (a run-wide shift, "
                 "such as another backbone's, moves every cell together).")
    return "\n".join(lines) + "\n"
