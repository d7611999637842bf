"""The sweep behind the paper's Tables I and II: CNN, CNN + SA and STAM (and the named variants of
stam.models.VARIANTS), n = 2..7, clean (windows from the first contact frame) and noisy (from frame 0),
over seeds; with 95% intervals on every accuracy and on the differences the paper claims. A third
setting, transfer, tests the clean setting's models on noisy windows (trained clean, tested noisy).

Output directory::

    OUT/pretrain/backbone.pt        shared starting weights of all three models
    OUT/features-<key>.pt           frozen-backbone features of every frame (cpu preset)
    OUT/cells/<setting>/n<n>/<model>/seed<k>/result.json   accuracy, and each test sequence's id,
                                    prediction and correctness (+ the run's logs and best.pt; a
                                    transfer cell holds the test of its clean cell's best.pt)
    OUT/onsets.json                 agreement of detected and true contact onsets
    OUT/table1.md, OUT/table2.md    ours (mean [95% CI]) beside the paper's figures, the paper's layout
    OUT/table2_transfer.md          the transfer setting's table
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
from .config import SETTINGS as SETTING_NAMES
from .config import PretrainConfig, TrainConfig, load_preset, resolve_pretrain, resolve_train
from .data import SPLITS, TactileDataset, backbone_features
from .errors import StamError
from .evaluate import evaluate
from .train import load_backbone, pretrain, save_atomic, train

# Where each setting's test windows start (stam.data.WindowDataset's start); a setting in TRAINED_AS is
# not trained itself but tests the models of the setting named there.
SETTINGS = {"clean": "contact", "noisy": "zero", "transfer": "zero"}
TRAINED_AS = {"transfer": "clean"}
MODEL_LABELS = {"cnn": "CNNs", "cnn_sa": "CNNs+Spatial Attention", "stam": "STAM",
                "cnn_mean_features": "CNN, features averaged over frames",
                "cnn_max_features": "CNN, features max-pooled over frames",
                "cnn_flatten": "CNN, one FC on the flattened window",
                "cnn_joint": "CNN with STAM-paper's head (per-frame head + FC on the window)",
                "stam_paper": "STAM as its 68.8 M parameters read (full q, k, v; FC on the window)",
                "oracle": "Oracle: CNN on the frames from the detected onset on"}
SHORT_LABELS = {"cnn": "CNN", "cnn_sa": "CNN+SA", "stam": "STAM",  # in the differences' row names
                "cnn_mean_features": "CNN-meanF", "cnn_max_features": "CNN-maxF", "cnn_flatten": "CNN-flat",
                "cnn_joint": "CNN-joint", "stam_paper": "STAM-paper", "oracle": "Oracle"}
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
        ev = evaluate(best, split="test", data=data, features=feats, plot=False)
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


def _check_cell_options(cell_dir: Path, base: TrainConfig, model: str) -> None:
    """Refuse to reuse a finished cell trained with other model options than ``base`` gives ``model``
    (e.g. another ``attention_at``): its config.json (written by stam.train) names them. Options the
    config predates read as their defaults."""
    wanted = resolve_train(base, {"model": model}, "the sweep").model_options()   # a variant's own options
    path = cell_dir / "config.json"
    if not (cell_dir / "result.json").is_file() or not path.is_file():
        return
    saved = json.loads(path.read_text())
    default = TrainConfig()
    for k, v in wanted.items():
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
    ev = evaluate(summary["best"], split="test", data=data, features=feats, plot=False)
    cell = {"setting": setting, "frames": n, "model": m, "seed": seed, "test_acc": ev["accuracy"],
            "val_acc": summary["best_val_acc"], "best_epoch": summary["best_epoch"],
            "test_count": ev["count"], "seconds": round(time.perf_counter() - c0, 2), **_per_sequence(ev)}
    atomic_write_json(cell_dir / "result.json", cell)
    # Checkpoints of finished cells are not needed for the tables; keep best.pt only.
    (cell_dir / "last.pt").unlink(missing_ok=True)
    return cell


def transfer_cell(out: Path, key: tuple, data: TactileDataset, feats: dict | None) -> dict:
    """Test cell ``key`` = (seed, setting, n, model) of a setting of TRAINED_AS (transfer): the best.pt of
    the cell it names (the clean one), tested on this setting's windows; returns (and writes as
    result.json) its result with the per-sequence lists."""
    seed, setting, n, m = key
    source = _cell_dir(out, (seed, TRAINED_AS[setting], n, m))
    if not (source / "best.pt").is_file():
        raise StamError(f"{source} has no best.pt to test on {setting} windows; delete its result.json to retrain it")
    trained = json.loads((source / "result.json").read_text())
    cell_dir = _cell_dir(out, key)
    c0 = time.perf_counter()
    ev = evaluate(source / "best.pt", split="test", data=data, features=feats, start=SETTINGS[setting], out=cell_dir,
                  plot=False)
    cell = {"setting": setting, "trained_as": TRAINED_AS[setting], "frames": n, "model": m, "seed": seed,
            "test_acc": ev["accuracy"], "val_acc": trained["val_acc"], "best_epoch": trained["best_epoch"],
            "test_count": ev["count"], "seconds": round(time.perf_counter() - c0, 2), **_per_sequence(ev)}
    atomic_write_json(cell_dir / "result.json", cell)
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
                   note=None, ray: str | None = None, pretrain_overrides: dict | None = None,
                   clean_extra: list[int] | None = None) -> dict:
    """Run (or resume) the sweep; returns what results.json holds: cells (without per-sequence lists),
    tables, differences, ratios, resolution, seed check, paths. ``settings``: of clean, noisy and
    transfer (which tests the clean models, so it trains them too). ``overrides``: [train] keys;
    ``pretrain_overrides``: [pretrain] keys (e.g. ``contact_only=False``: the backbone also learns the
    frames before contact). ``clean_extra``: more n for the clean setting only (e.g. each n − 1, so that
    the frames before contact can be costed against the clean window with the same contact frames when
    ``frames`` skips n). ``log``: progress lines; ``note``:
    warnings (one line each; the CLI prints them on stderr). ``ray``: train the cells as Ray tasks
    (``"local"``: on a Ray instance started here; ``"auto"`` or ``HOST:PORT``: on that cluster, whose
    nodes must see ``data_dir`` and ``out``); pretraining and the feature cache stay on this machine."""
    connection = contextlib.nullcontext(None)
    if ray is not None:
        from gelsim.cluster import connect

        connection = connect(ray)
    with connection as cluster:  # joined first: a bad address fails before any pretraining
        return _run_experiment(data_dir, out, preset, seeds, models, frames, settings, overrides, log, note,
                               cluster, pretrain_overrides, clean_extra)


def _run_experiment(data_dir, out, preset, seeds, models, frames, settings, overrides, log, note, cluster,
                    pretrain_overrides=None, clean_extra=None) -> dict:
    cfg = load_preset(preset)
    sweep = cfg.sweep
    models = list(dict.fromkeys(models or sweep.models))
    frames = list(frames or sweep.frames)
    settings = set(settings or sweep.settings)
    seeds = seeds if seeds is not None else sweep.seeds
    for s in settings:
        if s not in SETTINGS:
            raise StamError(f"unknown setting {s!r}; choose from {', '.join(SETTINGS)}")
    settings |= {TRAINED_AS[s] for s in settings if s in TRAINED_AS}   # transfer tests the clean models
    settings = [s for s in SETTING_NAMES if s in settings]
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
    clean_extra = sorted(set(clean_extra or []) - set(frames)) if "clean" in settings else []
    if max(frames + clean_extra) > shortest or min(frames + clean_extra) < 1:
        raise StamError(f"frames {sorted(set(frames + clean_extra))} outside 1..{shortest} (the shortest sequence); "
                        "choose smaller n")
    test = sorted(data.split("test"), key=lambda s: s.id)
    test_ids = [s.id for s in test]
    warning = test_size_warning(len(test))
    if warning and note:
        note(warning)

    t0 = time.perf_counter()
    pre = resolve_pretrain(cfg.pretrain or PretrainConfig(), pretrain_overrides, "the experiment's pretraining")
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
    todo += [(seed, "clean", n, m) for seed in range(seeds) for n in clean_extra for m in models]
    for key in todo:   # before the feature cache: a run that cannot reuse this --out computes nothing
        _check_cell_options(_cell_dir(out, key), base, key[3])
    feats = features_path = None
    if base.freeze_backbone:
        features_path, feats = _feature_cache(out, Path(pt["path"]), data, base.width, size, log,
                                                base.attention_at)

    finished = {key: _finished_cell(_cell_dir(out, key), out, test_ids, data, feats, log) for key in todo}
    train_keys = [key for key in todo if finished[key] is None and key[1] not in TRAINED_AS]
    for seed, setting, n, m in train_keys:   # a model trained anew is tested anew in the settings that test it
        for other, source in TRAINED_AS.items():
            if source == setting and (seed, other, n, m) in finished:
                finished[(seed, other, n, m)] = None

    def done(cell):
        finished[(cell["seed"], cell["setting"], cell["frames"], cell["model"])] = cell
        if log:
            count = sum(c is not None for c in finished.values())
            log(f"[{count}/{len(todo)}] {cell['setting']} n={cell['frames']} {cell['model']} seed {cell['seed']}: "
                f"test {cell['test_acc']:.3f} (val {cell['val_acc']:.3f}, {cell['seconds']:.0f} s)")

    for cell in _cell_results(base, out, train_keys, data, feats, features_path, cluster):
        done(cell)
    for key in todo:   # the settings that test another setting's models, once those are trained
        if finished[key] is None:
            done(transfer_cell(out, key, data, feats))
    cells = [finished[key] for key in todo]
    # the onset the clean windows start at (detected, unless the run was told to use the manifest's)
    detected = {s.id: data.onset(s, size, base.onset, base.onset_threshold) for s in test}
    analysis = analyse(cells, models, frames, settings, test_ids, detected)
    label = str(preset) if base.attention_at == "pool5" else f"{preset}` with `attention_at = {base.attention_at}"
    paths = write_tables(out, analysis, models, frames, settings, seeds, onsets, label)
    result = {"cells": [{k: v for k, v in c.items() if k not in PER_SEQUENCE_KEYS} for c in cells],
              **analysis, "test_size_warning": warning, "onsets": onsets, "pretrain": pt,
              "seconds": round(time.perf_counter() - t0, 1), **paths}
    atomic_write_json(out / "results.json", result)
    return result


def seed_correctness(cells: list[dict], test_ids: list[str]) -> np.ndarray:
    """``0/1 (S, N)``: each seed's correctness on the test sequences, in ``test_ids`` order."""
    rows = []
    for c in sorted(cells, key=lambda c: c["seed"]):
        by_id = dict(zip(c["test_ids"], c["test_correct"]))
        rows.append([by_id[i] for i in test_ids])
    return np.array(rows, float)


# Comparisons besides every model against the CNN: attention given the position-aware head (STAM-paper
# against the same head without attention), and the paper's STAM head against the default one.
EXTRA_PAIRS = (("stam_paper", "cnn_joint"), ("stam_paper", "stam"))


def short_label(model: str) -> str:
    return SHORT_LABELS.get(model, model)


def versus_cnn(models) -> list[str]:
    """The models compared with the CNN baseline (all others, when the CNN is in the sweep)."""
    return [m for m in models if m != "cnn"] if "cnn" in models else []


def difference_rows(models, settings) -> list[tuple[str, str, list[tuple[int, str, str]]]]:
    """The paper's comparisons as (label, kind, terms): the per-sequence difference at n is the sum
    of weight x (seed-averaged correctness of model in setting at n) over terms (weight, setting, model).
    Every model against the CNN in each setting; each setting with frames before contact (noisy,
    transfer) against clean, per model; and the robustness contrast (model − CNN) x (that − clean)."""
    rows = []
    others = versus_cnn(models)
    pairs = [(m, "cnn") for m in others] + [p for p in EXTRA_PAIRS if p[0] in models and p[1] in models]
    for s in settings:
        for m, base in pairs:
            rows.append((f"{short_label(m)} − {short_label(base)}, {s}", "model", [(1, s, m), (-1, s, base)]))
    for t in [t for t in ("noisy", "transfer") if t in settings and "clean" in settings]:
        for m in models:
            rows.append((f"{t} − clean, {short_label(m)}", "setting", [(1, t, m), (-1, "clean", m)]))
        # The paper's robustness claim: attention gains more with pre-contact frames in the window.
        for m in others:
            rows.append((f"({short_label(m)} − CNN), {t} − clean", "robustness",
                         [(1, t, m), (-1, t, "cnn"), (-1, "clean", m), (1, "clean", "cnn")]))
    return rows


def _paper_mean(values: list[float | None]) -> float | None:
    return None if not values or any(v is None for v in values) else float(np.mean(values))


def _paper_sum(terms: list[tuple[int, str, str]], n: int) -> float | None:
    vals = [_paper(s, m, n) for _, s, m in terms]
    return None if None in vals else sum(w * v for (w, _, _), v in zip(terms, vals))


def interval(mean: float, lo: float, hi: float, scale: float = 100.0) -> dict:
    """``{"mean", "ci95": [lo, hi]}`` of a proportion's estimate and 95% bounds, in points (x ``scale``)."""
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
    correct = {key: seed_correctness(cs, test_ids) for key, cs in grouped.items()}
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
        spreads.append(shift_spread(weighted, correct))

    # the clean setting may hold extra n (run for the matched cost of the frames before contact: n - 1)
    clean_frames = sorted({n for s, n, _ in seed_mean if s == "clean"} | set(frames))
    cell_keys = [(s, n, m) for s in settings for m in models for n in (clean_frames if s == "clean" else frames)
                 if (s, n, m) in seed_mean]
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
            **interval(*ci[(s, n, m)]), "std": float(np.std(per_seed, ddof=1)) if per_seed.size > 1 else 0.0,
            "seeds": int(per_seed.size), "values": per_seed.tolist(), "paper": _paper(s, m, n)}

    differences = []
    for label, kind, terms in rows:
        papers = {n: _paper_sum(terms, n) for n in frames}
        for n in [*frames, "mean"]:
            if (label, n) not in ci:
                continue
            paper = _paper_mean(list(papers.values())) if n == "mean" else papers[n]
            d = interval(*ci[(label, n)])
            differences.append({"difference": label, "kind": kind, "frames": n, "terms": [list(t) for t in terms], **d,
                                "resolved": d["ci95"][0] > 0 or d["ci95"][1] < 0, "paper": paper})

    ratios = {}
    if "clean" in settings and "noisy" in settings:
        for m in models:
            if all((s, n, m) in seed_mean for s in ("clean", "noisy") for n in frames):
                avg = {s: np.mean([seed_mean[(s, n, m)] for n in frames], axis=0) for s in ("clean", "noisy")}
                r = stats.ratio_ci(avg["noisy"], avg["clean"])
                if r is not None:
                    # the seeds' shift by the delta method: var(N/C) = r^2 (var N / N^2 + var C / C^2)
                    shift = {s: seed_check["shift_variance"] * shift_spread(
                        [(1 / len(frames), (s, n, m)) for n in frames], correct) for s in ("clean", "noisy")}
                    r = (r[0], *stats.widen(r[0], r[1], r[2], r[0] ** 2 * sum(
                        shift[s] / avg[s].mean() ** 2 for s in ("clean", "noisy"))))
                    paper = {s: _paper_mean([_paper(s, m, n) for n in frames]) for s in ("clean", "noisy")}
                    ratios[m] = {"ratio": r[0], "ci95": [r[1], r[2]], "resolved": r[1] > 1 or r[2] < 1,
                                 "paper": None if None in paper.values() else paper["noisy"] / paper["clean"]}

    precontact = {t: (_precontact(seed_mean, correct, models, frames, test_ids, onsets, seed_check["shift_variance"], t,
                                  clean_frames)
                      if onsets and "clean" in settings and t in settings else None) for t in ("noisy", "transfer")}
    return {"tables": tables, "differences": differences, "ratios": ratios, "precontact": precontact["noisy"],
            "precontact_transfer": precontact["transfer"],
            "resolution": resolution(differences, tables, len(test_ids), max((len(c) for c in grouped.values()), default=0)),
            "seed_check": seed_check,
            "bootstrap": {"method": "percentile bootstrap over the test sequences; each sequence's correctness "
                                    "averaged over the seeds; all statistics on the same resamples (paired); "
                                    "each interval widened in quadrature by the seeds' shared shift "
                                    "(seed_check's shift_variance over the seeds, cells' seeds independent)",
                          "resamples": stats.BOOTSTRAP_RESAMPLES, "seed": stats.BOOTSTRAP_SEED,
                          "level": stats.CI_LEVEL, "test_sequences": len(test_ids)}}


def shift_spread(weighted: list[tuple[float, tuple]], correct: dict) -> float:
    """sum of weight^2 / seeds over ``weighted`` (weight, cell key) pairs: times the seeds' shift variance,
    what that shift adds to the variance of sum(weight x the cell's seed-averaged accuracy), the cells'
    seeds taken as independent."""
    return sum(w * w / len(correct[key]) for w, key in weighted)


def _precontact(seed_mean: dict, correct: dict, models, frames, test_ids: list[str], onsets: dict,
                shift_variance: float, tested: str = "noisy", clean_frames=None) -> dict | None:
    """The cost of the frames before contact, with the contact frames held fixed.

    A noisy window of n frames starts at frame 0; with the detected onset o (1 <= o < n) it holds the
    o frames before contact and then frames o..n-1, which are exactly the clean window of k = n - o
    frames. So noisy(n) - clean(k) on such a sequence is what adding the frames before contact does,
    apart from the contact frames it brings fewer of (the rest of noisy - clean). Per model: the mean
    of that per-sequence difference (correctness averaged over the seeds) over every (sequence, n)
    with k among ``clean_frames`` (the clean setting's n: ``frames``, and any extra ones run for this, such
    as n - 1), as a ratio of means over the test sequences (bootstrap, then widened by
    the seeds' shift over the cells involved, as the other intervals). Also model - CNN of it for every
    other model: the paper's claim is that STAM gains here. ``tested``: the setting whose windows start
    at frame 0 (noisy, or transfer: the clean models on those windows). None when no sequence qualifies."""
    clean_frames = sorted(set(clean_frames or frames))
    pairs = [(i, n, n - onsets[t]) for i, t in enumerate(test_ids) for n in frames
             if onsets.get(t) is not None and 1 <= onsets[t] < n and n - onsets[t] in clean_frames]
    if not pairs:
        return None
    count = np.zeros(len(test_ids))
    np.add.at(count, [i for i, _, _ in pairs], 1.0)
    # seed shift: each side is a mixture of cells weighted by their share of the pairs
    share = {(tested, n): 0.0 for n in frames} | {("clean", k): 0.0 for k in clean_frames}
    for _, n, k in pairs:
        share[(tested, n)] += 1 / len(pairs)
        share[("clean", k)] += 1 / len(pairs)
    sums, out, diffs = {}, {}, {}
    for m in models:
        if not all((tested, n, m) in seed_mean and ("clean", k, m) in seed_mean for _, n, k in pairs):
            continue
        v = np.zeros(len(test_ids))
        for i, n, k in pairs:
            v[i] += seed_mean[(tested, n, m)][i] - seed_mean[("clean", k, m)][i]
        sums[m] = v
        cells = [(w, (s, f, m)) for (s, f), w in share.items() if w]
        out[m] = _precontact_ci(v, count, shift_spread(cells, correct) * shift_variance)
    for m in versus_cnn(models):
        if m in sums and "cnn" in sums:
            cells = [(w, (s, f, model)) for (s, f), w in share.items() if w for model in (m, "cnn")]
            diffs[m] = _precontact_ci(sums[m] - sums["cnn"], count, shift_spread(cells, correct) * shift_variance)
    onset_values = sorted({n - k for _, n, k in pairs})
    return {"tested": tested, "windows": len(pairs), "sequences": int((count > 0).sum()), "onsets": onset_values,
            "models": out, "minus_cnn": diffs}


def _precontact_ci(values: np.ndarray, count: np.ndarray, variance: float) -> dict:
    mean, lo, hi = stats.ratio_ci(values, count)
    d = interval(mean, *stats.widen(mean, lo, hi, variance))
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
    if n in PAPER_FRAMES and model in PAPER_TABLES.get(setting, {}):
        return PAPER_TABLES[setting][model][PAPER_FRAMES.index(n)]
    return None


def ci_text(d: dict, signed: bool = False) -> str:
    """An :func:`interval` as ``"mean [lo, hi]"`` to 0.1 point (with signs when ``signed``)."""
    f = "+.1f" if signed else ".1f"
    return f"{d['mean']:{f}} [{d['ci95'][0]:{f}}, {d['ci95'][1]:{f}}]"


def markdown_table(tables: dict, setting: str, models, frames, seeds: int, test_sequences: int) -> str:
    title = {"clean": "Table I (clean: windows start at the detected first contact frame)",
             "noisy": "Table II (noisy: windows start at frame 0, pre-contact frames included)",
             "transfer": "Table II, trained clean (the clean setting's models tested on windows from frame 0)"}[setting]
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
            row.append(("–" if c is None else ci_text(c)) + (f" ({p:.2f})" if p is not None else ""))
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
            text = ci_text(d, signed=True)
            text = f"**{text}**" if d["resolved"] else text
            cells.append(text + (f" ({d['paper']:+.2f})" if d["paper"] is not None else ""))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if analysis["ratios"]:
        parts = []
        for m, r in analysis["ratios"].items():
            text = f"{r['ratio']:.2f} [{r['ci95'][0]:.2f}, {r['ci95'][1]:.2f}]"
            parts.append(f"{short_label(m)} " + (f"**{text}**" if r["resolved"] else text)
                         + (f" ({r['paper']:.2f})" if r["paper"] is not None else ""))
        lines += ["", "Noisy/clean accuracy ratio (accuracies averaged over n; bold: the CI excludes 1): "
                  + ", ".join(parts) + "."]
    for pc in (analysis.get("precontact"), analysis.get("precontact_transfer")):
        if pc:
            lines += ["", precontact_text(pc)]
    lines += ["", analysis["resolution"]["statement"]]
    sc = analysis["seed_check"]
    if sc["ratio"] is not None:
        lines += ["", f"Seed check: the variance of a cell's accuracy across seeds is {sc['ratio']:.2f} times what "
                  f"independent per-sequence flips predict (pooled over {sc['cells']} cells): seeds shift whole cells, "
                  f"by {100 * math.sqrt(sc['shift_variance']):.2f} points (standard deviation per seed). The intervals "
                  "include that shift, each cell's seeds taken as independent of other cells' (one pretrained "
                  "backbone serves all cells, so its own seed is not in them)."]
    return "\n".join(lines) + "\n"


def _bold_ci(d: dict) -> str:
    text = ci_text(d, signed=True)
    return f"**{text}**" if d["resolved"] else text


def precontact_text(pc: dict) -> str:
    """One paragraph: what the frames before contact cost with the contact frames matched (:func:`_precontact`)."""
    parts = [f"{short_label(m)} {_bold_ci(d)}" for m, d in pc["models"].items()]
    gains = [f"{short_label(m)} − CNN {_bold_ci(d)}" for m, d in pc["minus_cnn"].items()]
    tested = pc.get("tested", "noisy")
    which = "noisy windows" if tested == "noisy" else "transfer: the clean models on windows from frame 0"
    return (f"Frames before contact, contact frames matched ({which}): a window of n frames from frame 0 holds "
            "the o frames before the detected onset and then the clean window of k = n − o frames, the same frames. "
            f"{tested.capitalize()}(n) − clean(k) on the same sequences, points, over {pc['windows']:,} windows of "
            f"{pc['sequences']:,} sequences (o = {', '.join(map(str, pc['onsets']))}; k among the table's n): "
            + ", ".join(parts) + (". Against the baseline on it: " + ", ".join(gains) if gains else "")
            + f". The rest of {tested} − clean is the contact frames such a window lacks.")


def write_tables(out: Path, analysis: dict, models, frames, settings, seeds: int, onsets: dict, preset: str) -> dict:
    paths = {}
    tables, n_tests = analysis["tables"], analysis["bootstrap"]["test_sequences"]
    for s, name in (("clean", "table1.md"), ("noisy", "table2.md"), ("transfer", "table2_transfer.md")):
        if s in settings:
            shown = sorted({n for cells in tables.get(s, {}).values() for n in cells} | set(frames))
            text = markdown_table(tables, s, models, shown, seeds, n_tests)
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
    colours = {"cnn": "tab:blue", "cnn_sa": "tab:orange", "stam": "tab:green", "cnn_mean_features": "tab:purple",
               "cnn_max_features": "tab:brown", "cnn_flatten": "tab:pink", "cnn_joint": "tab:gray",
               "stam_paper": "tab:olive", "oracle": "black"}
    for ax, s in zip(axes[0], settings):
        for k, m in enumerate(models):
            cells = tables.get(s, {}).get(m, {})
            ns = [n for n in frames if n in cells]
            if ns:
                mean = np.array([cells[n]["mean"] for n in ns])
                lo = np.array([cells[n]["ci95"][0] for n in ns])
                hi = np.array([cells[n]["ci95"][1] for n in ns])
                # Nudged sideways so that the models' bars do not hide each other.
                x = np.array(ns) + 0.08 * (k - (len(models) - 1) / 2)
                ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], marker="o", capsize=3, color=colours.get(m),
                            label=f"{MODEL_LABELS.get(m, m)} (ours, 95% CI)")
            pn = [n for n in frames if _paper(s, m, n) is not None]
            if pn:
                ax.plot(pn, [_paper(s, m, n) for n in pn], ls="--", marker="x", color=colours.get(m), alpha=0.6,
                        label=f"{MODEL_LABELS.get(m, m)} (paper)")
        ax.set_title({"clean": "clean (Table I)", "noisy": "noisy (Table II)",
                      "transfer": "trained clean, tested noisy"}[s])
        ax.set_xticks(frames)
        ax.set_xlabel("n (frames per window)")
        ax.set_ylabel("test accuracy (%)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    return write_figure(path, fig, dpi=100)
