"""The sweep behind the paper's Tables I and II: CNN, CNN + SA and STAM, n = 2..7,
clean (windows from the first contact frame) and noisy (from frame 0), over seeds; with 95%
intervals on every accuracy and on the differences the paper claims.

Output directory::

    OUT/pretrain/backbone.pt        shared starting weights of all three models
    OUT/features-<key>.pt           frozen-backbone features of every frame (cpu preset)
    OUT/cells/<setting>/n<n>/<model>/seed<k>/result.json   accuracy, and each test sequence's id,
                                    prediction and correctness (+ the run's logs and best.pt)
    OUT/onsets.json                 agreement of detected and true contact onsets
    OUT/table1.md, OUT/table2.md    ours (mean [95% CI]) beside the paper's figures, the paper's layout
    OUT/differences.md              the paper's comparisons as paired differences with 95% CIs, the
                                    noisy/clean ratios, what the frames before contact cost with the
                                    contact frames matched, and the resolution at this test size
    OUT/tables.png                  accuracy against n with 95% CIs, both settings
    OUT/results.json                all of it (cells without their per-sequence lists)

Intervals (stam.stats): every model, n, setting and seed is tested on the same test sequences.
Each sequence's correctness is averaged over the seeds, and the test sequences are resampled
(10,000 times, fixed seed); every statistic is computed on the same resamples,
so differences between models, n and settings are paired. Each interval is then widened by the
seeds' shared shift of a cell's accuracy, measured across the seeds (the seed check).

Resumable: a cell whose ``result.json`` exists is not retrained. A ``result.json`` written before
per-sequence results were kept is completed by re-evaluating the cell's ``best.pt`` (it must give
the recorded accuracy, else the cell was tested on another dataset and the run stops); without
``best.pt`` the cell is retrained.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from gelsim.atomic import atomic_write_json, atomic_write_text, write_figure

from . import stats
from .backbone import AlexNetFeatures
from .config import PretrainConfig, TrainConfig, load_preset, resolve_train
from .data import SPLITS, TactileDataset, backbone_features
from .errors import StamError
from .evaluate import evaluate
from .train import load_backbone, pretrain, save_atomic, train

SETTINGS = {"clean": "contact", "noisy": "zero"}
MODEL_LABELS = {"cnn": "CNNs", "cnn_sa": "CNNs+Spatial Attention", "stam": "STAM"}
SHORT_LABELS = {"cnn": "CNN", "cnn_sa": "CNN+SA", "stam": "STAM"}  # in the differences' row names
# Tables I and II of Cao et al. (IROS 2020), accuracy in %, n = 2..7.
PAPER_TABLES = {
    "clean": {"cnn": [67.23, 72.04, 75.26, 78.06, 79.56, 81.29],
              "cnn_sa": [72.12, 73.97, 78.60, 80.43, 80.43, 80.86],
              "stam": [76.50, 79.35, 80.00, 80.64, 81.72, 81.93]},
    "noisy": {"cnn": [53.20, 58.20, 59.60, 61.23, 64.60, 69.40],
              "cnn_sa": [55.40, 60.80, 62.60, 62.80, 65.40, 71.00],
              "stam": [72.00, 72.20, 75.80, 76.61, 80.80, 80.20]},
}
PAPER_FRAMES = [2, 3, 4, 5, 6, 7]


def feature_cache_path(out: Path, backbone_path: Path, image_size: int, crop: float, cut: str = "pool5") -> Path:
    """Where a sweep into ``out`` keeps the frozen backbone's features: one file per backbone (by the
    digest of its checkpoint), input size, crop and ``cut`` (where the backbone stops)."""
    digest = hashlib.sha256(backbone_path.read_bytes()).hexdigest()[:12]
    tag = "" if cut == "pool5" else f"-{cut}"   # (pool5 files keep the names they had)
    return out / f"features-{digest}-{image_size}px-crop{crop:g}{tag}.pt"


def _feature_cache(out: Path, backbone_path: Path, data: TactileDataset, width: float, image_size: int,
                   log, cut: str = "pool5") -> tuple[Path, dict]:
    """(path, features): the frozen backbone's features of every frame, computed once into ``out``
    (``cut``: where the backbone stops, see stam.backbone.AlexNetFeatures)."""
    path = feature_cache_path(out, backbone_path, image_size, data.crop, cut)
    if path.is_file():
        return path, torch.load(path, map_location="cpu", weights_only=True)
    t0 = time.perf_counter()
    net = AlexNetFeatures(width, cut=cut)
    load_backbone(net, str(backbone_path))
    feats = backbone_features(net, data, data.sequences, image_size)
    save_atomic(feats, path)
    if log:
        log(f"features of {len(feats)} sequences in {time.perf_counter() - t0:.1f} s -> {path.name}")
    return path, feats


PER_SEQUENCE_KEYS = ("test_ids", "test_predictions", "test_correct")


def test_size_warning(n: int) -> str | None:
    """One line when a test split of ``n`` sequences is too small to resolve the paper's attention
    gains (1-5 points), else None."""
    if n >= stats.MIN_TEST_SEQUENCES:
        return None
    half = 100 * stats.paired_halfwidth(n)
    return (f"stam experiment: warning: the test split has {n} sequences (under {stats.MIN_TEST_SEQUENCES}): a "
            f"difference between two models gets a 95% CI of about ±{half:.1f} points, too wide for the paper's "
            "1-5 point attention gains; generate more test sequences (gelsim generate --preset cpu has 1,100)")


def _per_sequence(ev: dict) -> dict:
    return {"test_ids": ev["sequences"], "test_predictions": ev["predictions"],
            "test_correct": [int(p == y) for p, y in zip(ev["predictions"], ev["labels"])]}


def _finished_cell(cell_dir: Path, out: Path, test_ids: list[str], data: TactileDataset, feats: dict | None,
                   log) -> dict | None:
    """The cell's result, or None when it has to be (re)trained. A result.json without per-sequence
    results (written before they were kept) gets them from its best.pt, re-evaluated on the test split."""
    path = cell_dir / "result.json"
    if not path.is_file():
        return None
    cell = json.loads(path.read_text())
    rerun = f"use a new --out (or delete {out / 'cells'}) to rerun the sweep on this dataset"
    if "test_correct" not in cell:
        best = cell_dir / "best.pt"
        if not best.is_file():
            if log:
                log(f"{path} has no per-sequence results and no best.pt to recompute them: retraining the cell")
            return None
        ev = evaluate(best, split="test", data=data, features=feats)
        if (ev["count"] != cell["test_count"]
                or round(ev["accuracy"] * ev["count"]) != round(cell["test_acc"] * cell["test_count"])):
            raise StamError(f"{path} recorded test accuracy {cell['test_acc']:.4f} on {cell['test_count']} sequences, "
                            f"its best.pt now gives {ev['accuracy']:.4f} on {ev['count']}: it was tested on another "
                            f"dataset; {rerun}")
        cell.update(_per_sequence(ev))
        atomic_write_json(path, cell)
        if log:
            log(f"{path}: per-sequence results recomputed from best.pt (same accuracy)")
    if sorted(cell["test_ids"]) != test_ids:
        raise StamError(f"{path} was tested on other sequences than this dataset's test split; {rerun}")
    return cell


def _check_cell_options(cell_dir: Path, base: TrainConfig) -> None:
    """Refuse to reuse a finished cell trained with other model options than ``base`` (e.g. another
    ``attention_at``): its config.json (written by stam.train) names them. Options the config predates
    read as their defaults."""
    path = cell_dir / "config.json"
    if not (cell_dir / "result.json").is_file() or not path.is_file():
        return
    saved = json.loads(path.read_text())
    default = TrainConfig()
    for k, v in base.model_options().items():
        had = saved.get(k, getattr(default, k))
        if had != v:
            raise StamError(f"{cell_dir} was trained with {k} = {had!r}, this run asks for {v!r}; use a new --out "
                            "for another model setting")


def _cell_dir(out: Path, key: tuple) -> Path:
    seed, setting, n, m = key
    return out / "cells" / setting / f"n{n}" / m / f"seed{seed}"


def train_cell(base: TrainConfig, out: Path, key: tuple, data: TactileDataset, feats: dict | None) -> dict:
    """Train and test one cell ``key`` = (seed, setting, n, model) of the sweep into its directory;
    returns (and writes as result.json) its result with the per-sequence lists."""
    seed, setting, n, m = key
    cell_dir = _cell_dir(out, key)
    c0 = time.perf_counter()
    run_cfg = resolve_train(base, {"out": str(cell_dir), "model": m, "frames": n, "start": SETTINGS[setting],
                                   "seed": seed}, "the sweep")
    summary = train(run_cfg, features=feats, data=data, log=None)
    ev = evaluate(summary["best"], split="test", data=data, features=feats)
    cell = {"setting": setting, "frames": n, "model": m, "seed": seed, "test_acc": ev["accuracy"],
            "val_acc": summary["best_val_acc"], "best_epoch": summary["best_epoch"],
            "test_count": ev["count"], "seconds": round(time.perf_counter() - c0, 2), **_per_sequence(ev)}
    atomic_write_json(cell_dir / "result.json", cell)
    # Checkpoints of finished cells are not needed for the tables; keep best.pt only.
    (cell_dir / "last.pt").unlink(missing_ok=True)
    return cell


_RAY_WORKER: dict = {}


def ray_cell(base: TrainConfig, out: str, features: str | None, key: tuple) -> dict:
    """:func:`train_cell` as a Ray task. The dataset reader and the frozen backbone's features (from
    the driver's cache file in OUT) are loaded once per worker process and kept for its next cells.
    Torch runs on the task's CPUs (``threads``, else 1), as a local run with that many threads would."""
    torch.set_num_threads(base.threads or 1)
    which = (base.data, base.crop, base.cache_dir, features)
    if _RAY_WORKER.get("which") != which:
        _RAY_WORKER.clear()
        _RAY_WORKER.update(which=which, data=TactileDataset(base.data, base.cache_dir or None, crop=base.crop),
                           feats=None if features is None else
                           torch.load(features, map_location="cpu", weights_only=True))
    return train_cell(base, Path(out), key, _RAY_WORKER["data"], _RAY_WORKER["feats"])


def _cell_results(base: TrainConfig, out: Path, keys: list[tuple], data, feats, features_path, cluster):
    """The results of training ``keys``, as they finish: here one after another, or as Ray tasks."""
    if cluster is None:
        return (train_cell(base, out, key, data, feats) for key in keys)
    from gelsim.cluster import run_unordered

    gpus = 1 if base.device == "cuda" or (base.device == "auto" and cluster.cluster_resources().get("GPU")) else 0
    return run_unordered(cluster, ray_cell, keys, args=(base, str(out), features_path and str(features_path)),
                         label=lambda key: f"cell {_cell_dir(out, key).relative_to(out)}",
                         num_cpus=base.threads or 1, num_gpus=gpus)


def run_experiment(data_dir: str, out: str | Path, preset: str = "cpu", seeds: int | None = None,
                   models: list[str] | None = None, frames: list[int] | None = None,
                   settings: list[str] | None = None, overrides: dict | None = None, log=print,
                   note=None, ray: str | None = None) -> dict:
    """Run (or resume) the sweep; returns what results.json holds: cells (without per-sequence lists),
    tables, differences, ratios, resolution, seed check, paths. ``log``: progress lines; ``note``:
    warnings (one line each; the CLI prints them on stderr). ``ray``: train the cells as Ray tasks
    (``"local"``: on a Ray instance started here; ``"auto"`` or ``HOST:PORT``: on that cluster, whose
    nodes must see ``data_dir`` and ``out``); pretraining and the feature cache stay on this machine."""
    connection = contextlib.nullcontext(None)
    if ray is not None:
        from gelsim.cluster import connect

        connection = connect(ray)
    with connection as cluster:  # joined first: a bad address fails before any pretraining
        return _run_experiment(data_dir, out, preset, seeds, models, frames, settings, overrides, log, note,
                               cluster)


def _run_experiment(data_dir, out, preset, seeds, models, frames, settings, overrides, log, note, cluster) -> dict:
    cfg = load_preset(preset)
    sweep = cfg.sweep
    models = list(models or sweep.models)
    frames = list(frames or sweep.frames)
    settings = list(settings or sweep.settings)
    seeds = seeds if seeds is not None else sweep.seeds
    for s in settings:
        if s not in SETTINGS:
            raise StamError(f"unknown setting {s!r}; choose clean or noisy")
    if seeds < 1:
        raise StamError(f"--seeds must be at least 1, got {seeds}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if cluster is not None:
        from gelsim.cluster import check_shared_dir

        # Ray's workers do not start in this directory: they get absolute paths.
        out, data_dir = Path(os.path.abspath(out)), os.path.abspath(data_dir)
        check_shared_dir(cluster, out)
        check_shared_dir(cluster, data_dir, "--data")
    crop = cfg.train.crop
    data = TactileDataset(data_dir, crop=crop)
    for split in SPLITS:
        if not data.split(split):
            raise StamError(f"dataset {data_dir} has no {split!r} sequences; generate more sequences per fabric "
                            "(or another gelsim generate --split)")
    shortest = min(s.num_frames for s in data.sequences)
    if max(frames) > shortest or min(frames) < 1:
        raise StamError(f"frames {frames} outside 1..{shortest} (the shortest sequence); choose smaller n")
    test = sorted(data.split("test"), key=lambda s: s.id)
    test_ids = [s.id for s in test]
    warning = test_size_warning(len(test))
    if warning and note:
        note(warning)

    t0 = time.perf_counter()
    pre = cfg.pretrain or PretrainConfig()
    size = cfg.train.image_size
    onsets = data.onset_agreement(size, cfg.train.onset_threshold)
    atomic_write_json(out / "onsets.json", onsets)
    if log:
        log(f"onset detection: exact {onsets['exact']}/{onsets['sequences']}, within 1 frame "
            f"{onsets['within_1']}, not detected {onsets['not_detected']}")
    pt = pretrain(data_dir, out / "pretrain", data=data, progress=False, log=log, crop=crop,
                  onset_threshold=cfg.train.onset_threshold, **dataclasses.asdict(pre))
    t_pre = time.perf_counter() - t0
    if log:
        log(f"pretrained backbone: val frame accuracy {pt['val_acc']:.3f} ({t_pre:.0f} s)")
    base = resolve_train(cfg.train, {**(overrides or {}), "data": str(data_dir), "pretrained": pt["path"],
                                     "preset": cfg.name}, "the experiment's overrides")
    todo = [(seed, setting, n, m) for seed in range(seeds) for setting in settings for n in frames for m in models]
    for key in todo:   # before the feature cache: a run that cannot reuse this --out computes nothing
        _check_cell_options(_cell_dir(out, key), base)
    feats = features_path = None
    if base.freeze_backbone:
        features_path, feats = _feature_cache(out, Path(pt["path"]), data, base.width, size, log,
                                                base.attention_at)

    finished = {key: _finished_cell(_cell_dir(out, key), out, test_ids, data, feats, log) for key in todo}
    train_keys = [key for key in todo if finished[key] is None]
    for cell in _cell_results(base, out, train_keys, data, feats, features_path, cluster):
        finished[(cell["seed"], cell["setting"], cell["frames"], cell["model"])] = cell
        if log:
            done = sum(c is not None for c in finished.values())
            log(f"[{done}/{len(todo)}] {cell['setting']} n={cell['frames']} {cell['model']} seed {cell['seed']}: "
                f"test {cell['test_acc']:.3f} (val {cell['val_acc']:.3f}, {cell['seconds']:.0f} s)")
    cells = [finished[key] for key in todo]
    detected = {s.id: data.onset(s, size, "detected", cfg.train.onset_threshold) for s in test}
    analysis = analyse(cells, models, frames, settings, test_ids, detected)
    label = str(preset) if base.attention_at == "pool5" else f"{preset}` with `attention_at = {base.attention_at}"
    paths = write_tables(out, analysis, models, frames, settings, seeds, onsets, label)
    result = {"cells": [{k: v for k, v in c.items() if k not in PER_SEQUENCE_KEYS} for c in cells],
              **analysis, "test_size_warning": warning, "onsets": onsets, "pretrain": pt,
              "seconds": round(time.perf_counter() - t0, 1), **paths}
    atomic_write_json(out / "results.json", result)
    return result


def _correct(cells: list[dict], test_ids: list[str]) -> np.ndarray:
    """``0/1 (S, N)``: each seed's correctness on the test sequences, in ``test_ids`` order."""
    rows = []
    for c in sorted(cells, key=lambda c: c["seed"]):
        by_id = dict(zip(c["test_ids"], c["test_correct"]))
        rows.append([by_id[i] for i in test_ids])
    return np.array(rows, float)


def difference_rows(models, settings) -> list[tuple[str, str, list[tuple[int, str, str]]]]:
    """The paper's comparisons as (label, kind, terms): the per-sequence difference at n is the sum
    of weight x (seed-averaged correctness of model in setting at n) over terms (weight, setting, model)."""
    rows = []
    attention = [m for m in ("stam", "cnn_sa") if m in models and "cnn" in models]
    for s in settings:
        for m in attention:
            rows.append((f"{SHORT_LABELS[m]} − CNN, {s}", "model", [(1, s, m), (-1, s, "cnn")]))
    if "clean" in settings and "noisy" in settings:
        for m in models:
            rows.append((f"noisy − clean, {SHORT_LABELS[m]}", "setting", [(1, "noisy", m), (-1, "clean", m)]))
        # The paper's robustness claim: attention gains more with pre-contact frames in the window.
        for m in attention:
            rows.append((f"({SHORT_LABELS[m]} − CNN), noisy − clean", "robustness",
                         [(1, "noisy", m), (-1, "noisy", "cnn"), (-1, "clean", m), (1, "clean", "cnn")]))
    return rows


def _paper_mean(values: list[float | None]) -> float | None:
    return None if not values or any(v is None for v in values) else float(np.mean(values))


def _paper_sum(terms: list[tuple[int, str, str]], n: int) -> float | None:
    vals = [_paper(s, m, n) for _, s, m in terms]
    return None if None in vals else sum(w * v for (w, _, _), v in zip(terms, vals))


def _interval(mean: float, lo: float, hi: float, scale: float = 100.0) -> dict:
    return {"mean": float(scale * mean), "ci95": [float(scale * lo), float(scale * hi)]}


def analyse(cells: list[dict], models, frames, settings, test_ids: list[str],
            onsets: dict[str, int | None] | None = None) -> dict:
    """Accuracies with 95% CIs, the paper's paired differences with 95% CIs, noisy/clean ratios, the
    resolution at this test size and the seed check; with ``onsets`` (test sequence id -> detected
    contact onset, the frame the clean windows start at, or None), what the frames before contact
    cost once the contact frames are matched (:func:`_precontact`). Percent and percentage points.

    ``cells``: results with per-sequence correctness; ``test_ids``: the test split, sorted."""
    grouped: dict = {}
    for c in cells:
        grouped.setdefault((c["setting"], c["frames"], c["model"]), []).append(c)
    correct = {key: _correct(cs, test_ids) for key, cs in grouped.items()}
    seed_mean = {key: m.mean(0) for key, m in correct.items()}

    # Every statistic below is a mean over the test sequences of one per-sequence column, a weighted
    # sum of cells' seed-averaged correctness; all are resampled together. Each also carries the
    # seeds' shared shift: sum over its cells of weight^2 / seeds, times the pooled shift variance
    # (cells' seeds taken as independent; same-seed cells of two models were correlated +0.33 in the
    # cpu preset's run, so a difference's interval errs on the wide side).
    seed_check = stats.seed_variance_ratio(list(correct.values()))
    names, columns, spreads = [], [], []

    def column(name, weighted):
        names.append(name)
        columns.append(sum(w * seed_mean[key] for w, key in weighted))
        spreads.append(_shift_spread(weighted, correct))

    cell_keys = [(s, n, m) for s in settings for m in models for n in frames if (s, n, m) in seed_mean]
    for key in cell_keys:
        column(key, [(1, key)])
    rows = difference_rows(models, settings)
    for label, _, terms in rows:
        per_n = {}
        for n in frames:
            if all((s, n, m) in seed_mean for _, s, m in terms):
                per_n[n] = [(w, (s, n, m)) for w, s, m in terms]
                column((label, n), per_n[n])
        if len(per_n) == len(frames) > 1:
            column((label, "mean"), [(w / len(frames), key) for n in frames for w, key in per_n[n]])
    ci = {}
    if columns:
        for name, (mean, lo, hi), spread in zip(names, stats.bootstrap_intervals(np.stack(columns, axis=1)), spreads):
            ci[name] = (mean, *stats.widen(mean, lo, hi, spread * seed_check["shift_variance"]))

    tables: dict = {}
    for s, n, m in cell_keys:
        per_seed = 100 * correct[(s, n, m)].mean(1)
        tables.setdefault(s, {}).setdefault(m, {})[n] = {
            **_interval(*ci[(s, n, m)]), "std": float(np.std(per_seed, ddof=1)) if per_seed.size > 1 else 0.0,
            "seeds": int(per_seed.size), "values": per_seed.tolist(), "paper": _paper(s, m, n)}

    differences = []
    for label, kind, terms in rows:
        papers = {n: _paper_sum(terms, n) for n in frames}
        for n in [*frames, "mean"]:
            if (label, n) not in ci:
                continue
            paper = _paper_mean(list(papers.values())) if n == "mean" else papers[n]
            d = _interval(*ci[(label, n)])
            differences.append({"difference": label, "kind": kind, "frames": n, **d,
                                "resolved": d["ci95"][0] > 0 or d["ci95"][1] < 0, "paper": paper})

    ratios = {}
    if "clean" in settings and "noisy" in settings:
        for m in models:
            if all((s, n, m) in seed_mean for s in ("clean", "noisy") for n in frames):
                avg = {s: np.mean([seed_mean[(s, n, m)] for n in frames], axis=0) for s in ("clean", "noisy")}
                r = stats.ratio_ci(avg["noisy"], avg["clean"])
                if r is not None:
                    # the seeds' shift by the delta method: var(N/C) = r^2 (var N / N^2 + var C / C^2)
                    shift = {s: seed_check["shift_variance"] * _shift_spread(
                        [(1 / len(frames), (s, n, m)) for n in frames], correct) for s in ("clean", "noisy")}
                    r = (r[0], *stats.widen(r[0], r[1], r[2], r[0] ** 2 * sum(
                        shift[s] / avg[s].mean() ** 2 for s in ("clean", "noisy"))))
                    paper = {s: _paper_mean([_paper(s, m, n) for n in frames]) for s in ("clean", "noisy")}
                    ratios[m] = {"ratio": r[0], "ci95": [r[1], r[2]], "resolved": r[1] > 1 or r[2] < 1,
                                 "paper": None if None in paper.values() else paper["noisy"] / paper["clean"]}

    precontact = (_precontact(seed_mean, correct, models, frames, test_ids, onsets, seed_check["shift_variance"])
                  if onsets and "clean" in settings and "noisy" in settings else None)
    return {"tables": tables, "differences": differences, "ratios": ratios, "precontact": precontact,
            "resolution": resolution(differences, tables, len(test_ids), max((len(c) for c in grouped.values()), default=0)),
            "seed_check": seed_check,
            "bootstrap": {"method": "percentile bootstrap over the test sequences; each sequence's correctness "
                                    "averaged over the seeds; all statistics on the same resamples (paired); "
                                    "each interval widened in quadrature by the seeds' shared shift "
                                    "(seed_check's shift_variance over the seeds, cells' seeds independent)",
                          "resamples": stats.BOOTSTRAP_RESAMPLES, "seed": stats.BOOTSTRAP_SEED,
                          "level": stats.CI_LEVEL, "test_sequences": len(test_ids)}}


def _shift_spread(weighted: list[tuple[float, tuple]], correct: dict) -> float:
    """sum of weight^2 / seeds over ``weighted`` (weight, cell key) pairs: times the seeds' shift variance,
    what that shift adds to the variance of sum(weight x the cell's seed-averaged accuracy), the cells'
    seeds taken as independent."""
    return sum(w * w / len(correct[key]) for w, key in weighted)


def _precontact(seed_mean: dict, correct: dict, models, frames, test_ids: list[str], onsets: dict,
                shift_variance: float) -> dict | None:
    """The cost of the frames before contact, with the contact frames held fixed.

    A noisy window of n frames starts at frame 0; with the detected onset o (1 <= o < n) it holds the
    o frames before contact and then frames o..n-1, which are exactly the clean window of k = n - o
    frames. So noisy(n) - clean(k) on such a sequence is what adding the frames before contact does,
    apart from the contact frames it brings fewer of (the rest of noisy - clean). Per model: the mean
    of that per-sequence difference (correctness averaged over the seeds) over every (sequence, n)
    with k among ``frames``, as a ratio of means over the test sequences (bootstrap, then widened by
    the seeds' shift over the cells involved, as the other intervals). Also attention - CNN of it: the
    paper's claim is that STAM gains here. None when no sequence qualifies."""
    pairs = [(i, n, n - onsets[t]) for i, t in enumerate(test_ids) for n in frames
             if onsets.get(t) is not None and 1 <= onsets[t] < n and n - onsets[t] in frames]
    if not pairs:
        return None
    count = np.zeros(len(test_ids))
    np.add.at(count, [i for i, _, _ in pairs], 1.0)
    # seed shift: each side is a mixture of cells weighted by their share of the pairs
    share = {("noisy", n): 0.0 for n in frames} | {("clean", k): 0.0 for k in frames}
    for _, n, k in pairs:
        share[("noisy", n)] += 1 / len(pairs)
        share[("clean", k)] += 1 / len(pairs)
    sums, out, diffs = {}, {}, {}
    for m in models:
        if not all(("noisy", n, m) in seed_mean and ("clean", k, m) in seed_mean for _, n, k in pairs):
            continue
        v = np.zeros(len(test_ids))
        for i, n, k in pairs:
            v[i] += seed_mean[("noisy", n, m)][i] - seed_mean[("clean", k, m)][i]
        sums[m] = v
        cells = [(w, (s, f, m)) for (s, f), w in share.items() if w]
        out[m] = _precontact_ci(v, count, _shift_spread(cells, correct) * shift_variance)
    for m in ("stam", "cnn_sa"):
        if m in sums and "cnn" in sums:
            cells = [(w, (s, f, model)) for (s, f), w in share.items() if w for model in (m, "cnn")]
            diffs[m] = _precontact_ci(sums[m] - sums["cnn"], count, _shift_spread(cells, correct) * shift_variance)
    onset_values = sorted({n - k for _, n, k in pairs})
    return {"windows": len(pairs), "sequences": int((count > 0).sum()), "onsets": onset_values,
            "models": out, "minus_cnn": diffs}


def _precontact_ci(values: np.ndarray, count: np.ndarray, variance: float) -> dict:
    mean, lo, hi = stats.ratio_ci(values, count)
    d = _interval(mean, *stats.widen(mean, lo, hi, variance))
    return {**d, "resolved": d["ci95"][0] > 0 or d["ci95"][1] < 0}


def resolution(differences: list[dict], tables: dict, test_sequences: int, seeds: int) -> dict:
    """The half-widths of the 95% CIs this run achieved (medians), and one sentence saying so."""
    def half(d):
        return (d["ci95"][1] - d["ci95"][0]) / 2

    models_n = [half(d) for d in differences if d["kind"] == "model" and d["frames"] != "mean"]
    models_mean = [half(d) for d in differences if d["kind"] == "model" and d["frames"] == "mean"]
    accuracy = [half(c) for t in tables.values() for row in t.values() for c in row.values()]
    res = {"test_sequences": test_sequences, "seeds": seeds,
           "paired_halfwidth_points": float(np.median(models_n)) if models_n else None,
           "paired_halfwidth_mean_over_n_points": float(np.median(models_mean)) if models_mean else None,
           "accuracy_halfwidth_points": float(np.median(accuracy)) if accuracy else None,
           "planning_paired_halfwidth_points": 100 * stats.paired_halfwidth(test_sequences),
           "resolved": sum(d["resolved"] for d in differences), "differences": len(differences)}
    if models_n:
        text = (f"a difference between two models has a 95% CI half-width of {res['paired_halfwidth_points']:.1f} "
                f"points at one n (median of {len(models_n)})")
        if models_mean:
            text += f", {res['paired_halfwidth_mean_over_n_points']:.1f} averaged over n"
    else:
        text = (f"a difference between two models would have a 95% CI half-width of about "
                f"{res['planning_paired_halfwidth_points']:.1f} points (planning figure; no two models were run)")
    if accuracy:
        text += f"; one accuracy ±{res['accuracy_halfwidth_points']:.1f}"
    kinds = {"model": "model − CNN", "setting": "noisy − clean", "robustness": "(model − CNN) noisy − clean"}
    counts = [f"{sum(d['resolved'] for d in differences if d['kind'] == k)} of "
              f"{sum(d['kind'] == k for d in differences)} {name}" for k, name in kinds.items()
              if any(d["kind"] == k for d in differences)]
    res["statement"] = (f"Resolution: on {test_sequences:,} test sequences and {seeds} seed{'s' * (seeds != 1)}, {text}. "
                        "Resolved (CI excludes 0): " + (", ".join(counts) if counts else "no differences") + ".")
    return res


def _paper(setting: str, model: str, n: int) -> float | None:
    if n in PAPER_FRAMES and model in PAPER_TABLES[setting]:
        return PAPER_TABLES[setting][model][PAPER_FRAMES.index(n)]
    return None


def _ci_text(d: dict, signed: bool = False) -> str:
    f = "+.1f" if signed else ".1f"
    return f"{d['mean']:{f}} [{d['ci95'][0]:{f}}, {d['ci95'][1]:{f}}]"


def markdown_table(tables: dict, setting: str, models, frames, seeds: int, test_sequences: int) -> str:
    title = {"clean": "Table I (clean: windows start at the detected first contact frame)",
             "noisy": "Table II (noisy: windows start at frame 0, pre-contact frames included)"}[setting]
    over = f"mean over {seeds} seeds" if seeds > 1 else "one seed"
    lines = [f"### {title}", "",
             f"Test accuracy in %: ours, {over} [95% CI: bootstrap over the {test_sequences:,} test sequences, "
             "each sequence's correctness averaged over the seeds, widened by the seeds' shift of a whole cell], and "
             "the paper's figure in parentheses.", "",
             "| Models | " + " | ".join(f"n={n}" for n in frames) + " |",
             "|---" * (len(frames) + 1) + "|"]
    for m in models:
        row = []
        for n in frames:
            c = tables.get(setting, {}).get(m, {}).get(n)
            p = _paper(setting, m, n)
            row.append(("–" if c is None else _ci_text(c)) + (f" ({p:.2f})" if p is not None else ""))
        lines.append(f"| {MODEL_LABELS.get(m, m)} | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def markdown_differences(analysis: dict, frames) -> str:
    """The paired differences (rows) by n and averaged over n, the noisy/clean ratios, the
    resolution and the seed check, as markdown."""
    n_tests = analysis["bootstrap"]["test_sequences"]
    lines = ["### Paired differences (percentage points)", "",
             f"Ours: mean [95% CI, paired bootstrap over the {n_tests:,} test sequences: the same resamples for every "
             "model, n and setting, each sequence's correctness averaged over the seeds; widened by the seeds' shift "
             "of a whole cell, see the seed check], and the paper's figure "
             "in parentheses. **Bold**: resolved (the CI excludes 0).", "",
             "| Difference | " + " | ".join(f"n={n}" for n in frames) + " | mean over n |",
             "|---" * (len(frames) + 2) + "|"]
    by_row: dict = {}
    for d in analysis["differences"]:
        by_row.setdefault(d["difference"], {})[d["frames"]] = d
    for label, row in by_row.items():
        cells = []
        for n in [*frames, "mean"]:
            d = row.get(n)
            if d is None:
                cells.append("–")
                continue
            text = _ci_text(d, signed=True)
            text = f"**{text}**" if d["resolved"] else text
            cells.append(text + (f" ({d['paper']:+.2f})" if d["paper"] is not None else ""))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if analysis["ratios"]:
        parts = []
        for m, r in analysis["ratios"].items():
            text = f"{r['ratio']:.2f} [{r['ci95'][0]:.2f}, {r['ci95'][1]:.2f}]"
            parts.append(f"{SHORT_LABELS.get(m, m)} " + (f"**{text}**" if r["resolved"] else text)
                         + (f" ({r['paper']:.2f})" if r["paper"] is not None else ""))
        lines += ["", "Noisy/clean accuracy ratio (accuracies averaged over n; bold: the CI excludes 1): "
                  + ", ".join(parts) + "."]
    pc = analysis.get("precontact")
    if pc:
        def fmt(d):
            text = _ci_text(d, signed=True)
            return f"**{text}**" if d["resolved"] else text
        parts = [f"{SHORT_LABELS.get(m, m)} {fmt(d)}" for m, d in pc["models"].items()]
        gains = [f"{SHORT_LABELS.get(m, m)} − CNN {fmt(d)}" for m, d in pc["minus_cnn"].items()]
        lines += ["", "Frames before contact, contact frames matched: a noisy window of n frames holds the o frames "
                  "before the detected onset and then the clean window of k = n − o frames, the same frames. "
                  f"Noisy(n) − clean(k) on the same sequences, points, over {pc['windows']:,} windows of "
                  f"{pc['sequences']:,} sequences (o = {', '.join(map(str, pc['onsets']))}; k among the table's n): "
                  + ", ".join(parts) + (". Attention against the baseline on it: " + ", ".join(gains) if gains else "")
                  + ". The rest of noisy − clean is the contact frames such a window lacks."]
    lines += ["", analysis["resolution"]["statement"]]
    sc = analysis["seed_check"]
    if sc["ratio"] is not None:
        lines += ["", f"Seed check: the variance of a cell's accuracy across seeds is {sc['ratio']:.2f} times what "
                  f"independent per-sequence flips predict (pooled over {sc['cells']} cells): seeds shift whole cells, "
                  f"by {100 * math.sqrt(sc['shift_variance']):.2f} points (standard deviation per seed). The intervals "
                  "include that shift, each cell's seeds taken as independent of other cells' (one pretrained "
                  "backbone serves all cells, so its own seed is not in them)."]
    return "\n".join(lines) + "\n"


def write_tables(out: Path, analysis: dict, models, frames, settings, seeds: int, onsets: dict, preset: str) -> dict:
    paths = {}
    tables, n_tests = analysis["tables"], analysis["bootstrap"]["test_sequences"]
    for s, name in (("clean", "table1.md"), ("noisy", "table2.md")):
        if s in settings:
            text = markdown_table(tables, s, models, frames, seeds, n_tests)
            text += (f"\nPreset `{preset}`. Onset detection agreed exactly with the simulator's contact onset on "
                     f"{onsets['exact']}/{onsets['sequences']} sequences ({onsets['within_1']} within one frame).\n")
            atomic_write_text(out / name, text)
            paths[name.replace(".md", "")] = str(out / name)
    atomic_write_text(out / "differences.md", markdown_differences(analysis, frames))
    paths["differences_table"] = str(out / "differences.md")
    paths["plot"] = str(plot_tables(out / "tables.png", tables, models, frames, settings))
    return paths


def plot_tables(path: Path, tables: dict, models, frames, settings) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(settings), figsize=(5.5 * len(settings), 4), squeeze=False)
    colours = {"cnn": "tab:blue", "cnn_sa": "tab:orange", "stam": "tab:green"}
    for ax, s in zip(axes[0], settings):
        for k, m in enumerate(models):
            cells = tables.get(s, {}).get(m, {})
            ns = [n for n in frames if n in cells]
            if ns:
                mean = np.array([cells[n]["mean"] for n in ns])
                lo = np.array([cells[n]["ci95"][0] for n in ns])
                hi = np.array([cells[n]["ci95"][1] for n in ns])
                # Nudged sideways so that the three models' bars do not hide each other.
                x = np.array(ns) + 0.08 * (k - (len(models) - 1) / 2)
                ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], marker="o", capsize=3, color=colours.get(m),
                            label=f"{MODEL_LABELS[m]} (ours, 95% CI)")
            pn = [n for n in frames if _paper(s, m, n) is not None]
            ax.plot(pn, [_paper(s, m, n) for n in pn], ls="--", marker="x", color=colours.get(m), alpha=0.6,
                    label=f"{MODEL_LABELS[m]} (paper)")
        ax.set_title({"clean": "clean (Table I)", "noisy": "noisy (Table II)"}[s])
        ax.set_xticks(frames)
        ax.set_xlabel("n (frames per window)")
        ax.set_ylabel("test accuracy (%)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    return write_figure(path, fig, dpi=100)
