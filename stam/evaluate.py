"""Evaluation of a trained run: accuracy, per-class accuracy, confusion matrix (JSON and PNG)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from gelsim.atomic import atomic_write_text, write_figure

from .data import TactileDataset, WindowDataset
from .oracle import windows_for
from .train import apply, batch_to, model_from_checkpoint, resolve_device


@torch.no_grad()
def predict(model, loader, device, forward=None) -> tuple[np.ndarray, np.ndarray]:
    """(labels, predictions), both ``int64 (N,)``."""
    model.eval()
    forward = forward or model
    ys, ps = [], []
    for x, y in loader:
        ps.append(apply(forward, batch_to(x, device)).argmax(1).cpu())
        ys.append(y)
    return torch.cat(ys).numpy(), torch.cat(ps).numpy()


def metrics(labels: np.ndarray, preds: np.ndarray, num_classes: int) -> dict:
    """Accuracy, per-class accuracy (None for classes absent from the split), confusion
    matrix ``int (K, K)`` with rows = true class, columns = predicted class."""
    cm = np.zeros((num_classes, num_classes), np.int64)
    np.add.at(cm, (labels, preds), 1)
    support = cm.sum(1)
    per_class = [float(cm[i, i] / support[i]) if support[i] else None for i in range(num_classes)]
    present = [a for a in per_class if a is not None]
    return {"accuracy": float((labels == preds).mean()) if labels.size else 0.0,
            "mean_class_accuracy": float(np.mean(present)) if present else 0.0,
            "per_class_accuracy": per_class, "confusion": cm.tolist(), "count": int(labels.size)}


#: Up to this many classes, each cell of the confusion plot shows its count of windows.
MAX_ANNOTATED_CLASSES = 30


def plot_confusion(cm, class_names: list[str], path: str | Path, title: str = "") -> Path:
    """Write the row-normalised confusion matrix as a PNG (atomically): colour the fraction of each true
    class, and the number of windows in each non-empty cell up to MAX_ANNOTATED_CLASSES classes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cm = np.asarray(cm, float)
    norm = cm / np.maximum(cm.sum(1, keepdims=True), 1)
    k = len(class_names)
    side = min(12, 3 + 0.25 * k)
    fig, ax = plt.subplots(figsize=(side, side))
    im = ax.imshow(norm, vmin=0, vmax=1, cmap="viridis")
    if k <= 30:
        ax.set_xticks(range(k), class_names, rotation=90, fontsize=7)
        ax.set_yticks(range(k), class_names, fontsize=7)
    if k <= MAX_ANNOTATED_CLASSES:   # the counts themselves, where a small split leaves fractions ambiguous
        for i, j in zip(*np.nonzero(cm)):
            ax.text(j, i, f"{int(cm[i, j])}", ha="center", va="center", fontsize=7,
                    color="black" if norm[i, j] > 0.5 else "white")
    ax.set_xlabel("predicted fabric")
    ax.set_ylabel("true fabric")
    ax.set_title(title)
    fig.colorbar(im, ax=ax, fraction=0.046, label="fraction of true class")
    fig.tight_layout()
    return write_figure(path, fig, dpi=100)


def evaluate(checkpoint: str | Path, data_dir: str | None = None, split: str = "test", *,
             out: str | Path | None = None, batch_size: int = 32, device: str = "auto",
             data: TactileDataset | None = None, features: dict | None = None, start: str | None = None,
             plot: bool = True) -> dict:
    """Evaluate a ``best.pt``/``last.pt`` on a split of the dataset it was trained on (or
    ``data_dir``). Writes ``eval-<split>.json`` and ``confusion-<split>.png`` to ``out``
    (default: the checkpoint's directory). ``features`` as in :func:`stam.train.train`. ``start``:
    where the windows start (``contact`` or ``zero``; default the run's own), e.g. a model trained on
    clean windows tested on noisy ones. ``plot=False`` leaves the PNG out (``confusion_png`` None): a
    sweep's cells skip it, as it costs more than testing a cell (1-5 s each for 20 classes on 2 shared
    cores). Besides :func:`metrics`, the result lists each window's sequence id, label and prediction."""
    model, cfg, ck = model_from_checkpoint(checkpoint)
    dev = resolve_device(device)
    model.to(dev)
    data = data or TactileDataset(data_dir or cfg.data, cfg.cache_dir or None, crop=cfg.crop)
    use_feats = cfg.freeze_backbone and features is not None
    start = start or cfg.start
    ds = windows_for(model, WindowDataset(data, split, cfg.frames, start, cfg.image_size, cfg.onset,
                                          cfg.onset_threshold, features if use_feats else None),
                     cfg.onset, cfg.onset_threshold)
    loader = DataLoader(ds, batch_size=batch_size, shuffle=False)
    labels, preds = predict(model, loader, dev, model.forward_features if use_feats else None)
    res = metrics(labels, preds, data.num_classes)
    res.update({"checkpoint": str(checkpoint), "split": split, "model": cfg.model, "frames": cfg.frames,
                "start": start, "trained_start": cfg.start, "epoch": int(ck.get("epoch", 0)), "class_names": data.class_names,
                # Per sequence, in the split's order, so that runs on the same split can be paired.
                "sequences": [seq.id for seq, _ in ds.items], "labels": labels.tolist(),
                "predictions": preds.tolist()})
    out = Path(out) if out else Path(checkpoint).parent
    out.mkdir(parents=True, exist_ok=True)
    res["confusion_png"] = None
    if plot:
        png = plot_confusion(res["confusion"], data.class_names, out / f"confusion-{split}.png",
                             f"{cfg.model}, n={cfg.frames}, {start}: {split} accuracy {res['accuracy']:.3f}\n"
                             f"({res['count']} windows; chance {1 / max(data.num_classes, 1):.3f})")
        res["confusion_png"] = str(png)
    atomic_write_text(out / f"eval-{split}.json", json.dumps(res, indent=1))
    return res
