"""Attention maps of trained models (the paper's Fig. 6 and 7).

* :func:`gradcam`: Grad-CAM (Selvaraju et al. 2017) per frame, on the backbone's last map
  for the CNN baseline and on the spatially attended map ``F^S`` for CNN + SA and STAM.
* :func:`temporal_map`: STAM's attention map averaged over its parallel modules (as the
  paper does for Fig. 7), the row of one query position in the first frame, reshaped to
  ``n x h x w``: how much each region of each frame contributes to updating the query.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from gelsim.atomic import write_figure

from .data import TactileDataset, WindowDataset
from .errors import StamError
from .train import model_from_checkpoint


def gradcam(model, x: torch.Tensor, target: int | None = None) -> tuple[np.ndarray, int]:
    """Grad-CAM of one window ``x`` (``1 x n x 3 x S x S``) for class ``target`` (default:
    the predicted class). Returns (``float32 (n, S, S)`` maps scaled to [0, 1] by their
    common maximum, the class)."""
    model.eval()
    f = model.frame_features(x).detach().requires_grad_(True)
    b, n = f.shape[:2]
    a = f
    if model.spatial is not None:
        a = model.spatial(f.flatten(0, 1)).view_as(f)
    a.retain_grad()
    g = a
    if model.temporal is not None:
        outs = [m(a) for m in model.temporal]
        g = torch.stack(outs).mean(0) if model.project is None else \
            model.project(torch.cat(outs, 2).permute(0, 2, 1, 3, 4)).permute(0, 2, 1, 3, 4)
    logits = model.classify(g)
    cls = int(logits.argmax(1)[0]) if target is None else int(target)
    model.zero_grad(set_to_none=True)
    logits[0, cls].backward()
    weights = a.grad.mean(dim=(3, 4), keepdim=True)  # 1 x n x C x 1 x 1
    cam = F.relu((weights * a).sum(2)).detach()[0]  # n x h x w
    cam = F.interpolate(cam[:, None], size=x.shape[-2:], mode="bilinear", align_corners=False)[:, 0]
    cam = cam / cam.max().clamp_min(1e-12)
    return cam.numpy().astype(np.float32), cls


@torch.no_grad()
def temporal_map(model, x: torch.Tensor, query: tuple[int, int] | None = None) -> dict:
    """STAM's module-averaged attention for one window ``x`` (``1 x n x 3 x S x S``).

    ``query`` is a (row, col) cell of the first frame's ``h x w`` feature map; default the cell
    with the largest attended feature norm. Returns {"map": ``float32 (n, h, w)`` attention
    weights of that query (they sum to 1 over all n*h*w), "query": (row, col), "top3": per
    frame the 3 most attended cells (row, col)}.
    """
    if model.temporal is None:
        raise StamError(f"model {model.name} has no temporal attention; pass a stam checkpoint")
    model.eval()
    f = model.frame_features(x)
    if model.spatial is not None:
        f = model.spatial(f.flatten(0, 1)).view_as(f)
    _, n, _, h, w = f.shape
    maps = torch.stack([m(f, return_map=True)[1][0] for m in model.temporal]).mean(0)  # m x m
    if query is None:
        norms = f[0, 0].norm(dim=0)
        r, c = divmod(int(norms.argmax()), w)
    else:
        r, c = query
        if not (0 <= r < h and 0 <= c < w):
            raise StamError(f"query {query} outside the {h}x{w} feature map; choose row < {h}, col < {w}")
    row = maps[r * w + c].view(n, h, w).numpy().astype(np.float32)
    top3 = [[divmod(int(i), w) for i in np.argsort(fr.ravel())[::-1][:3]] for fr in row]
    return {"map": row, "query": (r, c), "top3": top3}




def explain(checkpoints: list[str], sequence: str | None = None, out: str | Path = ".",
            data_dir: str | None = None, split: str = "test") -> dict:
    """Write ``gradcam.png`` (one row per checkpoint with a Grad-CAM, frames as columns) and,
    for a STAM checkpoint, ``temporal.png`` for one window of ``sequence`` (default: the
    split's first). All checkpoints must share n, the start setting and the image size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not checkpoints:
        raise StamError("no checkpoint given; pass --checkpoint RUN/best.pt (repeatable)")
    loaded = [model_from_checkpoint(c) for c in checkpoints]
    cfg0 = loaded[0][1]
    for _, cfg, _ in loaded[1:]:
        if (cfg.frames, cfg.start, cfg.image_size) != (cfg0.frames, cfg0.start, cfg0.image_size):
            raise StamError("checkpoints differ in frames, start or image_size; explain runs of one setting")
    data = TactileDataset(data_dir or cfg0.data, cfg0.cache_dir or None, crop=cfg0.crop)
    ds = WindowDataset(data, split, cfg0.frames, cfg0.start, cfg0.image_size, cfg0.onset, cfg0.onset_threshold)
    ids = [s.id for s, _ in ds.items]
    if sequence is None:
        idx = 0
    elif sequence in ids:
        idx = ids.index(sequence)
    else:
        raise StamError(f"sequence {sequence!r} is not in the {split} split; pick one of {', '.join(ids[:5])}, ...")
    x, label = ds[idx]
    seq, first = ds.items[idx]
    x = x[None]
    frames = np.asarray(data.frames(seq, cfg0.image_size)[first:first + cfg0.frames])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = cfg0.frames
    result = {"sequence": seq.id, "first_frame": first, "label": data.class_names[label], "files": []}

    fig, axes = plt.subplots(len(loaded), n, figsize=(2.2 * n, 2.4 * len(loaded)), squeeze=False)
    for row, (model, cfg, _) in enumerate(loaded):
        cam, cls = gradcam(model, x)
        for j in range(n):
            ax = axes[row][j]
            ax.imshow(frames[j])
            ax.imshow(cam[j], cmap="jet", alpha=0.45, vmin=0, vmax=1)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"frame {first + j}", fontsize=8)
        axes[row][0].set_ylabel(f"{cfg.model}\npred {data.class_names[cls]}", fontsize=8)
        result.setdefault("predictions", {})[cfg.model] = data.class_names[cls]
    fig.suptitle(f"Grad-CAM, {seq.id} ({data.class_names[label]})", fontsize=9)
    fig.tight_layout()
    result["files"].append(str(write_figure(out / "gradcam.png", fig, dpi=100)))

    for model, cfg, _ in loaded:
        if model.temporal is None:
            continue
        tm = temporal_map(model, x)
        h, w = tm["map"].shape[1:]
        s = cfg0.image_size
        fig, axes = plt.subplots(2, n, figsize=(2.2 * n, 4.6), squeeze=False)
        vmin, vmax = float(tm["map"].min()), float(tm["map"].max())
        for j in range(n):
            axes[0][j].imshow(frames[j])
            axes[0][j].set_title(f"frame {first + j}", fontsize=8)
            up = cv2_resize_nearest(tm["map"][j], s)
            axes[1][j].imshow(frames[j])
            axes[1][j].imshow(up, cmap="magma", alpha=0.55, vmin=vmin, vmax=max(vmax, vmin + 1e-9))
            for (r, c) in tm["top3"][j]:
                axes[1][j].annotate("", xy=((c + 0.5) * s / w, (r + 0.5) * s / h),
                                    xytext=((c + 0.5) * s / w + s * 0.15, (r + 0.5) * s / h - s * 0.15),
                                    arrowprops={"arrowstyle": "->", "color": "black", "lw": 1.2})
            for ax in (axes[0][j], axes[1][j]):
                ax.set_xticks([])
                ax.set_yticks([])
        qr, qc = tm["query"]
        axes[1][0].plot((qc + 0.5) * s / w, (qr + 0.5) * s / h, "o", color="lime", ms=8, mec="black")
        fig.suptitle(f"STAM temporal attention (mean of {len(model.temporal)} modules), query cell "
                     f"{tm['query']} of frame {first}", fontsize=9)
        fig.tight_layout()
        result["files"].append(str(write_figure(out / "temporal.png", fig, dpi=100)))
        result["temporal_query"] = tm["query"]
        result["temporal_top3"] = tm["top3"]
        break
    return result


def cv2_resize_nearest(a: np.ndarray, size: int) -> np.ndarray:
    """Blow a small ``h x w`` map up to ``size x size`` px with square cells (no smoothing)."""
    import cv2

    return cv2.resize(a, (size, size), interpolation=cv2.INTER_NEAREST)
