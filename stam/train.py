"""Training: a TOML config plus overrides, seeds, `last`/`best` checkpoints, resume, CSV logs.

One run trains one model on one setting (n frames, clean or noisy windows) and writes to
its output directory:

* ``config.json``   the resolved configuration;
* ``log.csv``       one row per epoch (losses, accuracies, learning rate, seconds);
* ``last.pt``       model, optimiser, scheduler, epoch and RNG state, for ``--resume``;
* ``best.pt``       the weights with the best validation accuracy.

Checkpoints hold only tensors and plain Python values and are loaded with
``weights_only=True``. With ``freeze_backbone`` the AlexNet features of every frame are
computed once and only the attention modules and the head are trained (the ``cpu``
preset's way of fitting the sweep on two cores).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
import random
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Subset

from gelsim.atomic import atomic_open, atomic_write_text

from . import distributed, models
from .backbone import AlexNet, feature_size, fold_batchnorm
from .config import TrainConfig, default_preset, describe_run, load_preset, parse_sets, resolve_train
from .data import DEFAULT_ONSET_THRESHOLD, FrameDataset, TactileDataset, WindowDataset, backbone_features
from .distributed import make_loader
from .errors import StamError
from .oracle import windows_for


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise StamError("device cuda requested but no GPU is available; use --set device=cpu")
    return torch.device(name)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def load_checkpoint(path: str | Path) -> dict:
    """Load a stam checkpoint safely (``weights_only=True``)."""
    p = Path(path)
    if not p.is_file():
        raise StamError(f"checkpoint {p} not found; train first or check the path")
    try:
        return torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # a truncated or foreign file: one line, not a traceback
        raise StamError(f"cannot load checkpoint {p} ({type(e).__name__}); retrain or check the file") from None


def save_atomic(obj, path: Path) -> None:
    """``torch.save(obj)`` to ``path`` through gelsim's atomic writer (a killed run leaves the old file)."""
    with atomic_open(path) as f:
        torch.save(obj, f)


def load_backbone(model_backbone: torch.nn.Module, path: str) -> None:
    ck = load_checkpoint(path)
    state = ck.get("backbone", ck)
    try:
        model_backbone.load_state_dict(state)
    except RuntimeError:
        raise StamError(f"backbone weights in {path} do not fit this model (different width?); "
                          "pretrain with the same width") from None


def batch_to(x, device):
    """A batch's input on ``device``: a tensor, or a list of them (a window and the oracle's keep mask,
    :mod:`stam.oracle`)."""
    return [t.to(device) for t in x] if isinstance(x, (list, tuple)) else x.to(device)


def apply(forward, x):
    """``forward`` on a batch's input as :func:`batch_to` gives it (a list: its items are the arguments)."""
    return forward(*x) if isinstance(x, list) else forward(x)


def run_epoch(model, loader, device, forward, optimizer=None, progress=False, desc="", shares=None,
              dist=None) -> tuple[float, float]:
    """One pass; trains when ``optimizer`` is given. Returns (mean loss, accuracy in [0, 1]).

    Under torchrun (``dist``, a :class:`stam.distributed.Dist`) the means are over every rank's
    items; ``shares`` (training) lists per batch (global batch size, items of this rank's part that
    count), and each rank's loss is scaled so that DDP's average of the gradients is the gradient of
    the global batch's mean loss (:mod:`stam.distributed`)."""
    train = optimizer is not None
    model.train(train)
    total_loss, correct, count = 0.0, 0, 0
    it = loader
    if progress:
        from tqdm import tqdm

        it = tqdm(loader, desc=desc, leave=False, file=sys.stderr, dynamic_ncols=True)
    with torch.set_grad_enabled(train):
        for k, (x, y) in enumerate(it):
            x, y = batch_to(x, device), y.to(device)
            logits = apply(forward, x)
            if shares is None:
                loss = F.cross_entropy(logits, y)
                n, loss_sum = y.shape[0], loss.item() * y.shape[0]
            else:
                size, n = shares[k]
                per = F.cross_entropy(logits, y, reduction="none")[:n]
                loss = per.sum() * (dist.world / size)
                loss_sum = per.sum().item()
                logits, y = logits[:n], y[:n]
            if train:
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
            total_loss += loss_sum
            correct += (logits.argmax(1) == y).sum().item()
            count += n
    if dist is not None:
        total_loss, correct, count = distributed.all_sum([total_loss, correct, count], device)
    return total_loss / max(count, 1), correct / max(count, 1)


def make_optimizer(cfg: TrainConfig, params) -> torch.optim.Optimizer:
    params = [p for p in params if p.requires_grad]
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay)


def make_scheduler(cfg: TrainConfig, opt):
    if cfg.lr_schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs)
    return torch.optim.lr_scheduler.LambdaLR(opt, lambda e: 1.0)


class CsvLog:
    """Per-epoch CSV log; on resume, rows after the checkpoint's epoch are dropped."""

    COLUMNS = ["epoch", "train_loss", "train_acc", "val_loss", "val_acc", "lr", "seconds"]

    def __init__(self, path: Path, keep_epochs: int):
        self.path = path
        rows = []
        if path.is_file() and keep_epochs > 0:
            with open(path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["epoch"]) <= keep_epochs]
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, self.COLUMNS)
            w.writeheader()
            w.writerows(rows)
        self.tb = None
        try:  # TensorBoard is optional: used when installed
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(path.parent / "tb"))
        except Exception:
            self.tb = None

    def write(self, row: dict) -> None:
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.COLUMNS).writerow(row)
        if self.tb is not None:
            for k, v in row.items():
                if k != "epoch":
                    self.tb.add_scalar(k, v, row["epoch"])
            self.tb.flush()


def train(cfg: TrainConfig, *, resume: bool = False, features: dict | None = None,
          data: TactileDataset | None = None, log=print, dist=None) -> dict:
    """Train one run into ``cfg.out``. ``features`` (seq id -> T x C x h x w) skips the backbone
    pass when the backbone is frozen. ``dist`` (a :class:`stam.distributed.Dist`): this process is one
    rank of a torchrun job (DDP; rank 0 writes the files). Returns a summary dict (best validation
    accuracy, epoch, paths)."""
    if not cfg.data or not cfg.out:
        raise StamError("both data and out are required; pass --data DIR --out DIR")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    main = dist is None or dist.main
    if dist is None:
        device = resolve_device(cfg.device)
    else:
        device = distributed.init(dist, cfg.device)
    data = data or TactileDataset(cfg.data, cfg.cache_dir or None, crop=cfg.crop)
    seed_everything(cfg.seed)
    model = models.build(cfg.model, cfg.frames, data.num_classes, **cfg.model_options())

    start_epoch, best_acc, best_epoch = 1, -1.0, 0
    last_path, best_path = out / "last.pt", out / "best.pt"
    ck = None
    if resume:
        if not last_path.is_file():
            raise StamError(f"nothing to resume in {out} (no last.pt); run without --resume")
        ck = load_checkpoint(last_path)
        saved = dict(ck["config"])
        mine = dataclasses.asdict(cfg)
        diff = [k for k in mine if k not in ("epochs", "progress", "threads", "workers", "device")
                and saved.get(k) != mine[k]]
        if diff:
            raise StamError(f"--resume with a different config ({', '.join(diff)}); "
                            "use the saved config or a new --out")
        # Before the frozen backbone's features are computed below: they must come from the
        # checkpoint's backbone, not from this freshly initialised one.
        model.load_state_dict(ck["model"])
    else:
        if cfg.pretrained:
            load_backbone(model.backbone, cfg.pretrained)
    if cfg.freeze_backbone:
        model.backbone.requires_grad_(False)
    model.to(device)

    if cfg.freeze_backbone and features is None:
        seqs = data.split("train") + data.split("val")
        features = backbone_features(model.backbone, data, seqs, cfg.image_size)
    feats = features if cfg.freeze_backbone else None
    train_ds, val_ds = (windows_for(model, WindowDataset(data, split, cfg.frames, cfg.start, cfg.image_size,
                                                         cfg.onset, cfg.onset_threshold, feats),
                                    cfg.onset, cfg.onset_threshold) for split in ("train", "val"))
    forward = model.forward_features if cfg.freeze_backbone else model
    train_forward = forward if dist is None else distributed.wrap(model, cfg.freeze_backbone, device)

    opt = make_optimizer(cfg, model.parameters())
    sched = make_scheduler(cfg, opt)
    if dist is not None and not dist.main:
        # Dropout masks of their own on the other ranks (rank 0 draws as one process would).
        torch.manual_seed(cfg.seed * 1_000_003 + dist.rank)
    if ck is not None:
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        rngs = ck.get("rng_ranks") or []
        torch.set_rng_state(rngs[dist.rank] if dist is not None and len(rngs) == dist.world else ck["rng"])
        start_epoch, best_acc, best_epoch = ck["epoch"] + 1, ck["best_acc"], ck["best_epoch"]
        if hasattr(sched, "T_max") and sched.T_max != cfg.epochs:
            # More (or fewer) epochs on resume: the cosine over the new length, from where the run is.
            # PyTorch's cosine steps recursively from the current rate, which is 0 at the old end, so
            # the rate is set to the new curve's value here (as a run of cfg.epochs would have it).
            sched.T_max = cfg.epochs
            for group, base in zip(opt.param_groups, sched.base_lrs):
                group["lr"] = sched.eta_min + (base - sched.eta_min) * (
                    1 + math.cos(math.pi * sched.last_epoch / cfg.epochs)) / 2
    config = dataclasses.asdict(cfg)
    if main:
        atomic_write_text(out / "config.json", json.dumps(config, indent=2))
        logger = CsvLog(out / "log.csv", start_epoch - 1)
    else:
        log = None

    for epoch in range(start_epoch, cfg.epochs + 1):
        t0 = time.perf_counter()
        lr = opt.param_groups[0]["lr"]
        if dist is None:
            tl, ta = run_epoch(model, make_loader(train_ds, cfg.batch_size, True, cfg.seed, epoch, cfg.workers),
                               device, forward, opt, cfg.progress, f"epoch {epoch}/{cfg.epochs}")
            vl, va = run_epoch(model, make_loader(val_ds, cfg.batch_size, False, cfg.seed, epoch, cfg.workers),
                               device, forward)
        else:
            batches = distributed.RankBatches(len(train_ds), cfg.batch_size, cfg.seed, epoch, dist)
            tl, ta = run_epoch(model, DataLoader(train_ds, batch_sampler=batches, num_workers=cfg.workers), device,
                               train_forward, opt, cfg.progress and main, f"epoch {epoch}/{cfg.epochs}",
                               shares=batches.weights(), dist=dist)
            shard = Subset(val_ds, range(dist.rank, len(val_ds), dist.world))
            vl, va = run_epoch(model, DataLoader(shard, batch_size=cfg.batch_size, num_workers=cfg.workers), device,
                               forward, dist=dist)
        sched.step()
        row = {"epoch": epoch, "train_loss": round(tl, 5), "train_acc": round(ta, 5), "val_loss": round(vl, 5),
               "val_acc": round(va, 5), "lr": lr, "seconds": round(time.perf_counter() - t0, 3)}
        improved = va > best_acc  # the same on every rank: va is summed over them
        if improved:
            best_acc, best_epoch = va, epoch
        rngs = None if dist is None else distributed.gather_rng(dist)
        if not main:
            continue
        logger.write(row)
        if improved:
            save_atomic({"model": model.state_dict(), "config": config, "epoch": epoch, "val_acc": va,
                         "num_classes": data.num_classes, "class_names": data.class_names}, best_path)
        save_atomic({"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                     "epoch": epoch, "best_acc": best_acc, "best_epoch": best_epoch, "config": config,
                     "rng": torch.get_rng_state(), "num_classes": data.num_classes,
                     "class_names": data.class_names, **({"rng_ranks": rngs} if rngs else {})}, last_path)
        if log:
            left = cfg.epochs - epoch
            eta = f"; about {left * row['seconds'] / 60:.1f} min for the {left} epochs left" if epoch == start_epoch and left else ""
            log(f"epoch {epoch}: train loss {tl:.3f} acc {ta:.3f}, val loss {vl:.3f} acc {va:.3f} "
                f"({row['seconds']:.1f} s{eta})")
    if dist is not None:
        distributed.barrier()  # rank 0's checkpoints are written when any rank returns
    return {"out": str(out), "best_val_acc": best_acc, "best_epoch": best_epoch, "epochs": cfg.epochs,
            "train_windows": len(train_ds), "val_windows": len(val_ds),
            "undetected_onsets_train": train_ds.undetected, "best": str(best_path), "last": str(last_path)}


def model_from_checkpoint(path: str | Path) -> tuple[models.SequenceModel, TrainConfig, dict]:
    """Rebuild the model stored in a ``best.pt``/``last.pt``; returns (model in eval mode, config, checkpoint)."""
    ck = load_checkpoint(path)
    if "model" not in ck or "config" not in ck:
        raise StamError(f"{path} is not a stam training checkpoint; pass best.pt or last.pt of a run")
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = resolve_train(TrainConfig(), {k: v for k, v in ck["config"].items() if k in known}, str(path))
    model = models.build(cfg.model, cfg.frames, int(ck["num_classes"]), **cfg.model_options())
    model.load_state_dict(ck["model"])
    return model.eval(), cfg, ck


# From scratch, the un-normalised AlexNet can sit at chance for many epochs. On the cpu preset's data
# (100 fabrics) at Adam 1e-3, seeds 1 and 2 had 1.0-1.1% training accuracy after epoch 3 and did not leave
# chance in 8 and 5 epochs, while seed 0 had 5.3% and took off; at 3e-4 all three seeds had 3.6-5.3%. A
# run still under twice chance after STALL_EPOCH epochs is told so (and goes on: the user decides; at 64 px
# and 3e-4 the cpu preset's backbone was told so and then left chance at epochs 4-5).
STALL_EPOCH = 3
STALL_FACTOR = 2.0


def stalled(train_acc: float, num_classes: int, epoch: int) -> bool:
    """Whether a pretraining run looks stuck at chance: epoch :data:`STALL_EPOCH` ended with a training
    accuracy (fraction) under ``STALL_FACTOR / num_classes``."""
    return epoch == STALL_EPOCH and train_acc < STALL_FACTOR / num_classes


def pretrain(data_dir: str, out: str | Path, *, width: float = 1.0, image_size: int = 224, epochs: int = 10,
             batch_size: int = 64, lr: float = 0.001, optimizer: str = "adam", seed: int = 0, contact_only: bool = True, frame_stride: int = 1,
             onset_threshold: float = DEFAULT_ONSET_THRESHOLD, device: str = "auto", cache_dir: str = "",
             progress: bool = True, data: TactileDataset | None = None, crop: float = 1.0,
             batchnorm: bool = False, log=print) -> dict:
    """Train a single-frame AlexNet on the training split's frames (every ``frame_stride``-th) (the stand-in for ImageNet
    pretraining) and save its backbone as ``out/backbone.pt`` (``{"backbone": state_dict, ...}``).
    Resumable: an existing ``backbone.pt`` with the same settings is returned as is."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "backbone.pt"
    settings = {"width": width, "image_size": image_size, "epochs": epochs, "batch_size": batch_size, "lr": lr,
                "optimizer": optimizer, "seed": seed, "contact_only": contact_only, "onset_threshold": onset_threshold,
                "frame_stride": frame_stride, "crop": crop, "batchnorm": batchnorm}
    if path.is_file():
        ck = load_checkpoint(path)
        if ck.get("settings") == settings:
            return {"path": str(path), "val_acc": ck["val_acc"], "reused": True}
    dev = resolve_device(device)
    data = data or TactileDataset(data_dir, cache_dir or None, crop=crop)
    if data.crop != crop:
        raise StamError(f"pretrain crop {crop} differs from the dataset reader's crop {data.crop}")
    seed_everything(seed)
    # Optional BatchNorm while pretraining from scratch, folded away before saving. Measured on
    # `gelsim generate --preset cpu` (100 fabrics, width 0.5, 128 px, crop 0.5, Adam 1e-3, 3 epochs):
    # val frame accuracy 0.21 without it, 0.11 with it, so it is off by default.
    net = AlexNet(data.num_classes, width, pool=feature_size(image_size), batchnorm=batchnorm).to(dev)
    train_ds = FrameDataset(data, "train", image_size, contact_only, onset_threshold, frame_stride)
    val_ds = FrameDataset(data, "val", image_size, contact_only, onset_threshold, frame_stride)
    # Adam by default: from scratch, an un-normalised AlexNet under SGD (lr 0.01, momentum 0.9) stayed
    # at chance for the first epochs on a 20-fabric gelsim dataset. Adam too can stall (see `stalled`).
    opt = (torch.optim.Adam(net.parameters(), lr=lr) if optimizer == "adam" else
           torch.optim.SGD(net.parameters(), lr=lr, momentum=0.9, weight_decay=5e-4))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs)
    best, rows = -1.0, []
    for epoch in range(1, epochs + 1):
        t0 = time.perf_counter()
        tl, ta = run_epoch(net, make_loader(train_ds, batch_size, True, seed, epoch, 0), dev, net, opt,
                           progress, f"pretrain {epoch}/{epochs}")
        vl, va = run_epoch(net, make_loader(val_ds, batch_size, False, seed, epoch, 0), dev, net)
        sched.step()
        rows.append({"epoch": epoch, "train_loss": tl, "train_acc": ta, "val_loss": vl, "val_acc": va,
                     "seconds": time.perf_counter() - t0})
        if log:
            left, sec = epochs - epoch, rows[-1]["seconds"]
            eta = f"; about {left * sec / 60:.1f} min for the {left} epochs left" if epoch == 1 and left else ""
            log(f"pretrain epoch {epoch}: train acc {ta:.3f}, val frame acc {va:.3f} ({sec:.1f} s{eta})")
        if stalled(ta, data.num_classes, epoch):
            # said even without a log (--quiet, --json): on stderr then, so that JSON output stays clean
            (log or (lambda m: print(m, file=sys.stderr)))(
                f"pretrain: training accuracy {ta:.1%} after {epoch} epochs is still at chance "
                f"({1 / data.num_classes:.1%} for {data.num_classes} classes); from scratch this AlexNet can "
                f"stay there for many epochs. If it has not left chance in a few more, stop it and rerun with a "
                f"lower learning rate (lr {lr:g} now; try {lr / 3:.2g}: --lr for `stam pretrain`, [pretrain] lr "
                "in a preset)")
        if va > best:
            best = va
            plain = fold_batchnorm(net.backbone.cpu().eval())
            net.backbone.to(dev)
            state = {k: v.detach().clone() for k, v in plain.state_dict().items()}
    save_atomic({"backbone": state, "settings": settings, "val_acc": best, "log": rows}, path)
    return {"path": str(path), "val_acc": best, "reused": False, "train_frames": len(train_ds)}


def cuda_available() -> bool:
    """Whether torch sees a CUDA device (what ``stam train`` picks its default preset by)."""
    return torch.cuda.is_available()


def run_train(data: str, out: str, *, preset: str | None = None, overrides: dict | None = None,
              sets: list[str] | None = None, pretrained: str | None = None, resume: bool = False,
              dry_run: bool = False, log=print, note=print) -> dict:
    """What ``stam train`` does: resolve the config (preset, then ``overrides``, then ``sets``
    "key=value"), pretrain the backbone as the preset's ``[pretrain]`` says (into ``OUT/pretrain/``,
    reused when its settings match) unless ``pretrained`` names a backbone (``"none"``: random
    weights), then train. With ``preset=None`` the preset is the one ``--resume`` finds in
    ``OUT/config.json``, else :func:`stam.config.default_preset` (cpu without a CUDA device), and
    ``note`` says so in one line. ``dry_run``: resolve and check only. Returns a summary dict."""
    if not data or not out:
        raise StamError("both data and out are required; pass --data DIR --out DIR")
    out_dir = Path(out)
    if resume and not (out_dir / "last.pt").is_file():
        raise StamError(f"nothing to resume in {out_dir} (no last.pt); run without --resume")
    extra = parse_sets(sets or [])
    chosen = None
    if preset is None and resume and (out_dir / "config.json").is_file():
        preset = json.loads((out_dir / "config.json").read_text()).get("preset") or None
    if preset is None:
        device = str(extra.get("device") or (overrides or {}).get("device") or "auto")
        preset = chosen = default_preset(device, cuda_available())
    p = load_preset(preset)
    cfg = resolve_train(p.train, {**(overrides or {}), "data": str(data), "out": str(out), "preset": p.name})
    cfg = resolve_train(cfg, extra, "--set")
    if pretrained == "none":
        cfg, plan = dataclasses.replace(cfg, pretrained=""), None
    elif pretrained:
        cfg, plan = dataclasses.replace(cfg, pretrained=str(pretrained)), None
    elif not cfg.pretrained and p.pretrain is not None:
        plan = p.pretrain
        cfg = dataclasses.replace(cfg, pretrained=str(out_dir / "pretrain" / "backbone.pt"))
    else:
        plan = None
    if plan is not None and plan.width != cfg.width:
        raise StamError(f"the backbone would be pretrained at width {plan.width:g} but trained at width "
                          f"{cfg.width:g}; give [pretrain] and [train] the same width in a preset file, "
                          "or pass --pretrained PATH|none")
    dist = distributed.from_env()
    if dist is not None:
        # Before anything is read or written: every rank must be about to run the same thing.
        distributed.init(dist, cfg.device)
        distributed.check_same_config(dist, {**dataclasses.asdict(cfg), "resume": resume, "dry_run": dry_run,
                                             "pretrain": None if plan is None else dataclasses.asdict(plan)})
        if not dist.main:
            log = note = None
    if chosen is not None and note:
        why = "no CUDA device" if chosen != "paper" else "a CUDA device is available"
        note(f"stam train: no --config given and {why}: using the {chosen} config: {describe_run(cfg, plan)}; "
             "see `stam train --help`")
    dataset = TactileDataset(cfg.data, cfg.cache_dir or None, crop=cfg.crop)
    shortest = min(s.num_frames for s in dataset.sequences)
    if cfg.frames > shortest:
        raise StamError(f"n_frames={cfg.frames} is outside 1..{shortest} (the shortest sequence); choose a smaller n")
    summary = {"preset": p.name, "preset_chosen_by_default": chosen is not None,
               "pretrain": None if plan is None else dataclasses.asdict(plan), "config": dataclasses.asdict(cfg)}
    if dry_run:
        if dist is not None:
            summary.update(rank=dist.rank, ranks=dist.world)
            distributed.close()
        return summary
    if plan is not None:
        # Under torchrun, rank 0 pretrains while the others wait, then they find its backbone.pt.
        if dist is not None and not dist.main:
            distributed.barrier()
        pt = pretrain(cfg.data, out_dir / "pretrain", data=dataset, crop=cfg.crop, onset_threshold=cfg.onset_threshold,
                      device=cfg.device, progress=cfg.progress and (dist is None or dist.main), log=log,
                      **dataclasses.asdict(plan))
        if dist is not None and dist.main:
            distributed.barrier()
        summary["pretrain_result"] = pt
    summary.update(train(cfg, resume=resume, data=dataset, log=log, dist=dist))
    if dist is not None:
        summary.update(rank=dist.rank, ranks=dist.world)
        distributed.close()
    return summary
