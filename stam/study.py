"""The robustness study of issue 48, read from its `stam experiment` runs: the positive control, the
mechanism table and the report (`benchmarks/nuisance_study.py` runs the steps; docs/stam_study.md).

The question: what makes a model lose accuracy to the frames before contact, and which mechanism, if
any, gives the pattern of the paper's Table II: its CNN loses about 12 points more than the contact
frames its noisy windows lack, its STAM about 2.5 (docs/nuisance.md, section 1). Candidates: the
nuisance content of those frames (a level of `gelsim generate --nuisance`), the baseline's fusion of
the frames, the STAM head the paper's parameter count implies, and the training protocol (trained on
noisy windows, or on clean windows and tested on noisy ones).

The measure is :func:`stam.experiment._precontact`'s: on the same test sequences, a window from frame 0
against the clean window holding the same contact frames, noisy(n) − clean(n − o) for the detected
onset o, averaged over sequences and n. The paper's figure for it, under its own assumption that no
window lacks more than one contact frame, is noisy(n) − clean(n − 1) averaged over n = 3..7
(:func:`paper_cost`). Every interval is the runs' paired 95% interval (bootstrap over the test
sequences, widened by the seeds' shift).

A positive control comes first: on data whose sequences start 3-6 frames before contact, the oracle
(which drops the frames before the detected onset) must gain over the CNN, resolved. Only then is a
null result about the other models a result: the study could have seen a gain and did not.
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path

from .errors import StamError
from .experiment import PAPER_FRAMES, PAPER_TABLES, ci_text, short_label

# What a study run holds unless told otherwise: the baseline, its fusions, the position-aware head
# with and without attention, STAM as the default reads it and as the paper's count reads it, and the
# oracle. The control needs only the baseline and the oracle.
STUDY_MODELS = ("cnn", "cnn_mean_features", "cnn_max_features", "cnn_flatten", "cnn_joint", "stam", "stam_paper",
                "oracle")
CONTROL_MODELS = ("cnn", "oracle")
STUDY_SETTINGS = ("clean", "noisy", "transfer")
# The cells no cut may drop (issue 48): n = 2, 4 and 6 at every level, and the control.
REQUIRED_FRAMES = (2, 4, 6)
# The settings whose windows hold the frames before contact, and the training protocol each is.
PROTOCOLS = {"noisy": "trained noisy, tested noisy", "transfer": "trained clean, tested noisy"}


def paper_cost(model: str) -> float | None:
    """What the frames before contact cost ``model`` in the paper beyond the contact frames a noisy window
    lacks, points: noisy(n) − clean(n − 1) averaged over n = 3..7 (docs/nuisance.md, section 1: CNN −11.8,
    STAM −2.5). None for a model the paper did not run."""
    if model not in PAPER_TABLES["clean"]:
        return None
    clean, noisy = PAPER_TABLES["clean"][model], PAPER_TABLES["noisy"][model]
    diffs = [noisy[i] - clean[i - 1] for i in range(1, len(PAPER_FRAMES))]
    return sum(diffs) / len(diffs)


def paper_gap() -> float:
    """STAM's cost minus the CNN's in the paper (:func:`paper_cost`), points: what a mechanism that
    reproduces the paper's pattern gains over the CNN on the frames before contact."""
    return paper_cost("stam") - paper_cost("cnn")


def load_results(run: str | Path) -> dict:
    """A finished `stam experiment` run's ``results.json``."""
    path = Path(run) / "results.json"
    if not path.is_file():
        raise StamError(f"{path} not found; run `stam experiment --out {run}` to the end first")
    return json.loads(path.read_text())


def difference(results: dict, model: str, setting: str, base: str = "cnn", frames="mean",
               kind: str = "model", against: str = "clean") -> dict | None:
    """One paired difference of a run: ``model − base`` in ``setting`` (kind ``model``), or the
    robustness contrast (``model − base``) x (``setting − against``) (kind ``robustness``), at n =
    ``frames`` or averaged over n ("mean"); None when the run does not have it."""
    if kind == "model":
        terms = [[1, setting, model], [-1, setting, base]]
    else:
        terms = [[1, setting, model], [-1, setting, base], [-1, against, model], [1, against, base]]
    for d in results.get("differences", []):
        if d.get("kind") == kind and d.get("frames") == frames and d.get("terms") == terms:
            return d
    return None


def precontact(results: dict, setting: str) -> dict | None:
    """The run's matched cost of the frames before contact in ``setting`` (noisy or transfer)."""
    return results.get("precontact" if setting == "noisy" else f"precontact_{setting}")


def control_verdict(results: dict) -> dict:
    """The positive control's verdict from its run: oracle − CNN per protocol (noisy: trained and tested
    noisy; transfer: trained clean, tested noisy), averaged over n and per n. A protocol's ``resolved_gain``:
    the mean's 95% interval lies above 0, so the study sees what discounting the frames before contact can
    gain there. ``passed``: that holds for some protocol. Where it does not, the interval's upper end bounds
    what any such mechanism can gain at that level and protocol."""
    out = {}
    for s in PROTOCOLS:
        mean = difference(results, "oracle", s)
        if mean is None:
            continue
        frames = sorted({d["frames"] for d in results["differences"] if d["frames"] != "mean"})
        out[s] = {"mean": mean, "per_n": {n: difference(results, "oracle", s, frames=n) for n in frames},
                  "resolved_gain": mean["ci95"][0] > 0}
    if "noisy" not in out:
        raise StamError("the control run has no oracle − CNN in the noisy setting; run it with --models cnn oracle "
                        "and the noisy setting")
    return {"passed": any(v["resolved_gain"] for v in out.values()), **out}


def control_markdown(name: str, verdict: dict) -> str:
    lines = [f"Positive control ({name}): the oracle against the CNN, points [95% CI]; bold: resolved.", "",
             "| protocol | " + " | ".join(f"n={n}" for n in verdict["noisy"]["per_n"]) + " | mean over n |",
             "|---" * (len(verdict["noisy"]["per_n"]) + 2) + "|"]
    for s in PROTOCOLS:
        if s in verdict:
            cells = [_bold(d) if d else "–" for d in verdict[s]["per_n"].values()]
            lines.append(f"| {PROTOCOLS[s]} | " + " | ".join(cells) + f" | {_bold(verdict[s]['mean'])} |")
    seen = [PROTOCOLS[s] for s in PROTOCOLS if s in verdict and verdict[s]["resolved_gain"]]
    unseen = [(PROTOCOLS[s], verdict[s]["mean"]["ci95"][1]) for s in PROTOCOLS
              if s in verdict and not verdict[s]["resolved_gain"]]
    text = []
    if seen:
        text.append(f"**Control passed ({'; '.join(seen)}): the study resolves the oracle's gain over the CNN.**")
    else:
        text.append("**Control failed: the study resolves no gain of the oracle over the CNN.**")
    for name, top in unseen:
        text.append(f"{name.capitalize()}: not resolved; at this level the oracle gains at most {top:+.1f} points "
                    "(the interval's upper end), which bounds any mechanism that discounts the frames before contact; "
                    "smaller gains cannot be told from none here.")
    return "\n".join(lines + [""] + text) + "\n"


def level_markdown(level: str, results: dict) -> str:
    """A level's run in one table: per model, its difference from the CNN in each setting and the
    robustness contrasts, averaged over n (points [95% CI]; bold: resolved); the CNN's own noisy − clean."""
    models = [m for m in results["tables"].get("clean", {}) if m != "cnn"]
    settings = [s for s in ("clean", "noisy", "transfer") if s in results["tables"]]
    heads = [f"− CNN, {s}" for s in settings] + [f"(− CNN) x ({s} − clean)" for s in PROTOCOLS if s in settings]
    frames = sorted({d["frames"] for d in results.get("differences", []) if d["frames"] != "mean"})
    lines = [f"**{level}** (test sequences: {results['bootstrap']['test_sequences']:,}; averaged over n = "
             + ", ".join(map(str, frames)) + ")", "",
             "| model | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
    for m in models:
        cells = [_bold(difference(results, m, s)) for s in settings]
        cells += [_bold(difference(results, m, s, kind="robustness")) for s in PROTOCOLS if s in settings]
        lines.append(f"| {short_label(m)} | " + " | ".join(cells) + " |")
    own = [f"{s} − clean {_bold(_setting_difference(results, 'cnn', s))}" for s in PROTOCOLS if s in settings]
    if own:
        lines += ["", "CNN: " + ", ".join(own) + "."]
    return "\n".join(lines) + "\n"


def onset_line(results: dict) -> str:
    """One line: how the run's detected onsets agree with the simulator's (a nuisance can move them, and the
    clean windows and the oracle follow them)."""
    o = results.get("onsets") or {}
    if not o.get("sequences"):
        return "Onsets: none recorded."
    n = o["sequences"]
    hist = ", ".join(f"{k}: {v}" for k, v in o.get("error_histogram", {}).items())
    return (f"Detected onsets against the simulator's: exact {o['exact']}/{n}, within one frame {o['within_1']}/{n}, "
            f"not detected {o['not_detected']} (detected − true, frames: {hist}).")


def _setting_difference(results: dict, model: str, setting: str) -> dict | None:
    terms = [[1, setting, model], [-1, "clean", model]]
    return next((d for d in results.get("differences", []) if d.get("kind") == "setting"
                 and d.get("frames") == "mean" and d.get("terms") == terms), None)


def _bold(d: dict | None, signed: bool = True) -> str:
    if d is None:
        return "–"
    text = ci_text(d, signed=signed)
    return f"**{text}**" if d.get("resolved") else text


def _contains(d: dict | None, value: float | None) -> bool | None:
    if d is None or value is None:
        return None
    return d["ci95"][0] <= value <= d["ci95"][1]


def mechanism_rows(runs: dict[str, dict]) -> list[dict]:
    """One row per (level, protocol, model) of the runs (level name -> results.json): the matched cost of
    the frames before contact, its difference from the CNN's, and the robustness contrast (model − CNN) x
    (protocol − clean) averaged over n, each with its 95% interval; and whether each is consistent with
    the paper's pattern: the CNN's cost holds the paper's (:func:`paper_cost`), another model's gain over
    the CNN is resolved and holds the paper's STAM − CNN gap (:func:`paper_gap`)."""
    rows = []
    gap, cnn_cost = paper_gap(), paper_cost("cnn")
    for level, res in runs.items():
        for s in PROTOCOLS:
            pc = precontact(res, s)
            if not pc:
                continue
            for m, cost in pc["models"].items():
                gain = pc["minus_cnn"].get(m)
                row = {"level": level, "protocol": s, "model": m, "cost": cost, "gain_over_cnn": gain,
                       "contrast": difference(res, m, s, kind="robustness") if m != "cnn" else None,
                       "windows": pc["windows"]}
                if m == "cnn":
                    row["paper_pattern"] = _contains(cost, cnn_cost)
                else:
                    row["paper_pattern"] = bool(gain and gain["ci95"][0] > 0 and _contains(gain, gap))
                rows.append(row)
    return rows


def mechanism_markdown(rows: list[dict]) -> str:
    """The mechanism table as markdown, with the paper's figures it is read against."""
    gap, cnn_cost, stam_cost = paper_gap(), paper_cost("cnn"), paper_cost("stam")
    lines = [f"What the frames before contact cost, with the contact frames matched: window from frame 0 minus "
             f"the clean window with the same contact frames, points [95% CI], averaged over the test sequences and "
             f"n. The paper: CNN {cnn_cost:+.1f}, STAM {stam_cost:+.1f} (noisy(n) − clean(n − 1), n = 3..7), a "
             f"gap of {gap:+.1f}. \"Paper's pattern\": for the CNN, its cost's interval holds {cnn_cost:+.1f}; for "
             f"another model, its gain over the CNN is resolved and its interval holds {gap:+.1f}. The contrast is "
             "(model − CNN) x (that protocol − clean), averaged over n. Bold: resolved.", "",
             "| level | protocol | model | cost | − CNN's cost | contrast | paper's pattern |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        pattern = {True: "yes", False: "no", None: "–"}[r["paper_pattern"]]
        lines.append(f"| {r['level']} | {PROTOCOLS[r['protocol']]} | {short_label(r['model'])} | {_bold(r['cost'])} | "
                     f"{_bold(r['gain_over_cnn'])} | {_bold(r['contrast'])} | {pattern} |")
    return "\n".join(lines) + "\n"


def mechanism_summary(rows: list[dict]) -> list[str]:
    """One line per candidate mechanism, as the rows fall: nuisance content (the CNN's cost by level),
    fusion (the baseline's other fusions), STAM head (the position-aware head, with and without attention),
    training protocol (the CNN's cost trained noisy against trained clean)."""
    def find(level, protocol, model):
        return next((r for r in rows if (r["level"], r["protocol"], r["model"]) == (level, protocol, model)), None)

    levels = list(dict.fromkeys(r["level"] for r in rows))
    out = []
    for p in PROTOCOLS:
        costs = [(lv, find(lv, p, "cnn")) for lv in levels if find(lv, p, "cnn")]
        if costs:
            out.append(f"Nuisance content ({PROTOCOLS[p]}): the CNN's cost " + "; ".join(
                f"{lv} {ci_text(r['cost'], signed=True)}" for lv, r in costs)
                + f" (paper {paper_cost('cnn'):+.1f}).")
    groups = {"Fusion": ("cnn_mean_features", "cnn_max_features", "cnn_flatten"),
              "STAM head": ("cnn_joint", "stam", "stam_paper")}
    for name, models in groups.items():
        for p in PROTOCOLS:
            parts = []
            for lv in levels:
                for m in models:
                    r = find(lv, p, m)
                    if r and r["gain_over_cnn"]:
                        parts.append(f"{short_label(m)} at {lv} {ci_text(r['gain_over_cnn'], signed=True)}"
                                     + (" (the paper's pattern)" if r["paper_pattern"] else ""))
            if parts:
                out.append(f"{name} ({PROTOCOLS[p]}), gain over the CNN's cost: " + "; ".join(parts)
                           + f" (paper's STAM {paper_gap():+.1f}).")
    for lv in levels:
        a, b = find(lv, "noisy", "cnn"), find(lv, "transfer", "cnn")
        if a and b:
            out.append(f"Training protocol at {lv}: the CNN's cost trained noisy {ci_text(a['cost'], signed=True)}, "
                       f"trained clean {ci_text(b['cost'], signed=True)}.")
    return out


def cell_costs(run: str | Path) -> dict:
    """What a run's steps cost, seconds, from its files: pretraining (the backbone's epochs), and per trained
    cell (training and test) and per test-only cell (transfer) the median over cells, per model and in all."""
    run = Path(run)
    out: dict = {}
    from .train import load_checkpoint

    backbone = run / "pretrain" / "backbone.pt"
    if backbone.is_file():
        log = load_checkpoint(backbone).get("log") or []
        out["pretrain_s"] = round(sum(r["seconds"] for r in log), 1)
        out["pretrain_epochs"] = len(log)
    trained, tested = {}, {}
    for p in run.glob("cells/*/n*/*/seed*/result.json"):
        c = json.loads(p.read_text())
        (tested if c.get("trained_as") else trained).setdefault(c["model"], []).append(float(c["seconds"]))
    for name, group in (("trained_cell", trained), ("tested_cell", tested)):
        every = [s for v in group.values() for s in v]
        if every:
            out[f"{name}_median_s"] = round(statistics.median(every), 2)
            out[f"{name}s"] = len(every)
            out[f"{name}_total_s"] = round(sum(every), 1)
            out[f"{name}_median_s_by_model"] = {m: round(statistics.median(v), 2) for m, v in sorted(group.items())}
    return out


def check_cuts(frames, levels, control_levels) -> None:
    """Refuse a study that cuts what issue 48 keeps: n = 2, 4 and 6, two levels at least, the control."""
    missing = [n for n in REQUIRED_FRAMES if n not in frames]
    if missing:
        raise StamError(f"--frames {' '.join(map(str, frames))} leaves out n = {', '.join(map(str, missing))}; the study "
                        f"keeps n = {', '.join(map(str, REQUIRED_FRAMES))} (cut others)")
    if len(levels) < 2:
        raise StamError(f"--levels {' '.join(levels)}: the study compares at least two levels (the first is the "
                        "reference, e.g. none handheld)")
    if not control_levels:
        raise StamError("--control-levels is empty; the positive control runs first, at one level at least")
