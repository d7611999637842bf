"""How much the attention modules of a `stam experiment` run change the frozen backbone's features.

    python benchmarks/attention_use.py OUT [--settings clean,noisy] [--json]

OUT: the --out of `stam experiment` with a frozen backbone (the cpu preset), whose OUT/features-*.pt
holds every frame's backbone map. For each CNN+SA and STAM cell and seed, on the test split's windows
exactly as the cell was evaluated (stam.data.WindowDataset): the spatial module's relative change
||SA(F) - F|| / ||F|| over all windows, and for STAM the temporal modules' (their mean, as STAM
combines them) ||T(G) - G|| / ||G|| on the spatially attended G, with the mean |gain| of its temporal
modules (a learned residual gain, 0 at the start of training). A module at 0 is an identity: it
cannot matter. A module that changes the features by a fifth while the model's accuracy stays at the
CNN's transforms them without adding anything the head can use.
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

from gelsim.cli import print_json, run_script
from stam.data import TactileDataset, WindowDataset
from stam.errors import StamError
from stam.experiment import feature_cache_path
from stam.train import model_from_checkpoint


def _relative(after: torch.Tensor, before: torch.Tensor) -> float:
    return float((after - before).norm() / before.norm())


def cell_use(checkpoint: Path, data: TactileDataset, features: dict) -> dict:
    """The relative changes (and STAM's mean |gain|) of one cell's modules on its test windows."""
    model, cfg, _ = model_from_checkpoint(checkpoint)
    model.eval()
    ds = WindowDataset(data, "test", cfg.frames, cfg.start, cfg.image_size, cfg.onset, cfg.onset_threshold, features)
    x = torch.stack([ds[i][0] for i in range(len(ds))])  # windows x n x C x h x w
    out = {"setting": "clean" if cfg.start == "contact" else "noisy", "model": cfg.model, "frames": cfg.frames,
           "seed": cfg.seed, "windows": len(ds)}
    with torch.no_grad():
        g = model.spatial(x.flatten(0, 1)).view_as(x)
        out["spatial"] = _relative(g, x)
        if model.temporal is not None:
            out["temporal"] = _relative(model.attend(x), g)
            gains = [abs(float(m.gamma)) for m in model.temporal if m.gamma is not None]
            out["gain"] = statistics.fmean(gains) if gains else None
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", help="the --out directory of a `stam experiment` run with a frozen backbone")
    ap.add_argument("--settings", default="clean,noisy", help="comma-separated settings")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    out = Path(args.out)
    checkpoints = sorted(p for s in args.settings.split(",") for m in ("cnn_sa", "stam")
                         for p in out.glob(f"cells/{s}/n*/{m}/seed*/best.pt"))
    if not checkpoints:
        raise StamError(f"{out} has no finished CNN+SA or STAM cells (cells/SETTING/nN/MODEL/seedS/best.pt); "
                        "run the sweep first")
    # The features the cells were trained on: the file the sweep keyed by their backbone, input size,
    # crop and cut (a run directory may hold several, e.g. after a rerun with --attention-at).
    _, cfg, _ = model_from_checkpoint(checkpoints[0])
    if not cfg.freeze_backbone or not cfg.pretrained:
        raise StamError(f"{checkpoints[0]} was trained with the backbone unfrozen; give the --out of a `stam "
                        "experiment` run whose preset freezes it (the cpu preset)")
    if not Path(cfg.pretrained).is_file():
        raise StamError(f"the cells' backbone {cfg.pretrained} is missing; run this where the sweep ran, or put "
                        "the backbone back")
    feature_file = feature_cache_path(out, Path(cfg.pretrained), cfg.image_size, cfg.crop, cfg.attention_at)
    if not feature_file.is_file():
        raise StamError(f"{feature_file} is missing; rerun the `stam experiment` command that made {out} (it "
                        "recomputes the features and skips finished cells)")
    features = torch.load(feature_file, map_location="cpu", weights_only=True)
    data = TactileDataset(cfg.data, cfg.cache_dir or None, crop=cfg.crop)
    cells = [cell_use(p, data, features) for p in checkpoints]
    groups: dict = {}
    for c in cells:
        groups.setdefault((c["setting"], c["model"], c["frames"]), []).append(c)
    rows = []
    for (s, m, n), cs in sorted(groups.items()):
        row = {"setting": s, "model": m, "frames": n, "seeds": len(cs),
               "spatial": statistics.fmean(c["spatial"] for c in cs)}
        if m == "stam":
            row["temporal"] = statistics.fmean(c["temporal"] for c in cs)
            row["gain"] = statistics.fmean(c["gain"] for c in cs)
        rows.append(row)
    if args.json:
        print_json({"run": str(out), "features": feature_file.name, "cells": cells, "rows": rows})
        return 0
    print(f"{out}: relative change of the features by each module, mean over seeds, on the test windows")
    print("| setting | model | n | spatial | temporal | mean temporal gain |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        t = f"{r['temporal']:.3f}" if "temporal" in r else ""
        g = f"{r['gain']:.3f}" if r.get("gain") is not None else ""
        print(f"| {r['setting']} | {r['model']} | {r['frames']} | {r['spatial']:.3f} | {t} | {g} |")
    return 0


if __name__ == "__main__":
    run_script(main)
