"""The sweep behind the paper's Tables I and II: CNN, CNN + SA and STAM, n = 2..7,
clean (windows from the first contact frame) and noisy (from frame 0), over seeds.

Output directory::

    OUT/pretrain/backbone.pt        shared starting weights of all three models
    OUT/features-<key>.pt           frozen-backbone features of every frame (cpu preset)
    OUT/cells/<setting>/n<n>/<model>/seed<k>/result.json (+ the run's logs and checkpoints)
    OUT/onsets.json                 agreement of detected and true contact onsets
    OUT/table1.md, OUT/table2.md    ours beside the paper's figures, the paper's layout
    OUT/tables.png                  accuracy against n, both settings
    OUT/results.json                every cell

Resumable: a cell whose ``result.json`` exists is not recomputed.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from .backbone import AlexNetFeatures
from .config import PretrainConfig, load_preset, resolve_train
from .data import SPLITS, TactileDataset, backbone_features
from .errors import StamError
from .evaluate import evaluate
from .train import load_backbone, pretrain, save_atomic, train

SETTINGS = {"clean": "contact", "noisy": "zero"}
MODEL_LABELS = {"cnn": "CNNs", "cnn_sa": "CNNs+Spatial Attention", "stam": "STAM"}
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


def _feature_cache(out: Path, backbone_path: Path, data: TactileDataset, width: float, image_size: int,
                   log) -> dict:
    digest = hashlib.sha256(backbone_path.read_bytes()).hexdigest()[:12]
    path = out / f"features-{digest}-{image_size}px-crop{data.crop:g}.pt"
    if path.is_file():
        return torch.load(path, map_location="cpu", weights_only=True)
    t0 = time.perf_counter()
    net = AlexNetFeatures(width)
    load_backbone(net, str(backbone_path))
    feats = backbone_features(net, data, data.sequences, image_size)
    save_atomic(feats, path)
    if log:
        log(f"features of {len(feats)} sequences in {time.perf_counter() - t0:.1f} s -> {path.name}")
    return feats


def run_experiment(data_dir: str, out: str | Path, preset: str = "cpu", seeds: int | None = None,
                   models: list[str] | None = None, frames: list[int] | None = None,
                   settings: list[str] | None = None, overrides: dict | None = None, log=print) -> dict:
    """Run (or resume) the sweep; returns {"cells": [...], "tables": {...}, paths}."""
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
    crop = cfg.train.crop
    data = TactileDataset(data_dir, crop=crop)
    for split in SPLITS:
        if not data.split(split):
            raise StamError(f"dataset {data_dir} has no {split!r} sequences; generate at least 10 sequences "
                              "per fabric for the 7:2:1 split")
    shortest = min(s.num_frames for s in data.sequences)
    if max(frames) > shortest or min(frames) < 1:
        raise StamError(f"frames {frames} outside 1..{shortest} (the shortest sequence); choose smaller n")

    t0 = time.perf_counter()
    pre = cfg.pretrain or PretrainConfig()
    size = cfg.train.image_size
    onsets = data.onset_agreement(size, cfg.train.onset_threshold)
    (out / "onsets.json").write_text(json.dumps(onsets, indent=1))
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
    feats = None
    if base.freeze_backbone:
        feats = _feature_cache(out, Path(pt["path"]), data, base.width, size, log)

    cells = []
    todo = [(seed, setting, n, m) for seed in range(seeds) for setting in settings for n in frames for m in models]
    for i, (seed, setting, n, m) in enumerate(todo, 1):
        cell_dir = out / "cells" / setting / f"n{n}" / m / f"seed{seed}"
        res_path = cell_dir / "result.json"
        if res_path.is_file():
            cells.append(json.loads(res_path.read_text()))
            continue
        c0 = time.perf_counter()
        run_cfg = resolve_train(base, {"out": str(cell_dir), "model": m, "frames": n,
                                       "start": SETTINGS[setting], "seed": seed}, "the sweep")
        summary = train(run_cfg, features=feats, data=data, log=None)
        ev = evaluate(summary["best"], split="test", data=data, features=feats)
        cell = {"setting": setting, "frames": n, "model": m, "seed": seed, "test_acc": ev["accuracy"],
                "val_acc": summary["best_val_acc"], "best_epoch": summary["best_epoch"],
                "test_count": ev["count"], "seconds": round(time.perf_counter() - c0, 2)}
        res_path.write_text(json.dumps(cell, indent=1))
        # Checkpoints of finished cells are not needed for the tables; keep best.pt only.
        (cell_dir / "last.pt").unlink(missing_ok=True)
        cells.append(cell)
        if log:
            log(f"[{i}/{len(todo)}] {setting} n={n} {m} seed {seed}: test {ev['accuracy']:.3f} "
                f"(val {summary['best_val_acc']:.3f}, {cell['seconds']:.0f} s)")
    tables = summarise(cells, models, frames, settings)
    paths = write_tables(out, tables, models, frames, settings, seeds, onsets, preset)
    result = {"cells": cells, "tables": tables, "onsets": onsets, "pretrain": pt,
              "seconds": round(time.perf_counter() - t0, 1), **paths}
    tmp = out / f".results.json.partial-{os.getpid()}"
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, out / "results.json")
    return result


def summarise(cells: list[dict], models, frames, settings) -> dict:
    """{setting: {model: {n: {"mean", "std", "seeds", "values"}}}}, accuracies in %."""
    tables: dict = {}
    for s in settings:
        for m in models:
            for n in frames:
                vals = [100 * c["test_acc"] for c in cells if c["setting"] == s and c["model"] == m and c["frames"] == n]
                if vals:
                    tables.setdefault(s, {}).setdefault(m, {})[n] = {
                        "mean": float(np.mean(vals)), "std": float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0,
                        "seeds": len(vals), "values": vals}
    return tables


def _paper(setting: str, model: str, n: int) -> float | None:
    if n in PAPER_FRAMES and model in PAPER_TABLES[setting]:
        return PAPER_TABLES[setting][model][PAPER_FRAMES.index(n)]
    return None


def markdown_table(tables: dict, setting: str, models, frames, seeds: int) -> str:
    title = {"clean": "Table I (clean: windows start at the detected first contact frame)",
             "noisy": "Table II (noisy: windows start at frame 0, pre-contact frames included)"}[setting]
    spread = f"mean ± sample std over {seeds} seeds" if seeds > 1 else "one seed"
    lines = [f"### {title}", "",
             f"Test accuracy in %, ours ({spread}) with the paper's figure in brackets.", "",
             "| Models | " + " | ".join(f"n={n}" for n in frames) + " |",
             "|---" * (len(frames) + 1) + "|"]
    for m in models:
        row = []
        for n in frames:
            c = tables.get(setting, {}).get(m, {}).get(n)
            p = _paper(setting, m, n)
            ours = "–" if c is None else (f"{c['mean']:.1f} ± {c['std']:.1f}" if c["seeds"] > 1 else f"{c['mean']:.1f}")
            row.append(ours + (f" ({p:.2f})" if p is not None else ""))
        lines.append(f"| {MODEL_LABELS.get(m, m)} | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def write_tables(out: Path, tables: dict, models, frames, settings, seeds: int, onsets: dict, preset: str) -> dict:
    paths = {}
    for s, name in (("clean", "table1.md"), ("noisy", "table2.md")):
        if s in settings:
            text = markdown_table(tables, s, models, frames, seeds)
            text += (f"\nPreset `{preset}`. Onset detection agreed exactly with the simulator's contact onset on "
                     f"{onsets['exact']}/{onsets['sequences']} sequences ({onsets['within_1']} within one frame).\n")
            (out / name).write_text(text)
            paths[name.replace(".md", "")] = str(out / name)
    paths["plot"] = str(plot_tables(out / "tables.png", tables, models, frames, settings))
    return paths


def plot_tables(path: Path, tables: dict, models, frames, settings) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(settings), figsize=(5.5 * len(settings), 4), squeeze=False)
    colours = {"cnn": "tab:blue", "cnn_sa": "tab:orange", "stam": "tab:green"}
    for ax, s in zip(axes[0], settings):
        for m in models:
            cells = tables.get(s, {}).get(m, {})
            ns = [n for n in frames if n in cells]
            if ns:
                mean = np.array([cells[n]["mean"] for n in ns])
                std = np.array([cells[n]["std"] for n in ns])
                ax.errorbar(ns, mean, yerr=std, marker="o", capsize=3, color=colours.get(m), label=f"{MODEL_LABELS[m]} (ours)")
            pn = [n for n in frames if _paper(s, m, n) is not None]
            ax.plot(pn, [_paper(s, m, n) for n in pn], ls="--", marker="x", color=colours.get(m), alpha=0.6,
                    label=f"{MODEL_LABELS[m]} (paper)")
        ax.set_title({"clean": "clean (Table I)", "noisy": "noisy (Table II)"}[s])
        ax.set_xlabel("n (frames per window)")
        ax.set_ylabel("test accuracy (%)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
    return path
