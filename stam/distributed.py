"""``torchrun --nproc-per-node N -m stam train ...``: one run on N processes with DistributedDataParallel.

torchrun starts the processes and sets ``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` and
``MASTER_PORT``; with ``WORLD_SIZE`` above 1, ``stam train`` joins a process group (NCCL on GPUs, one
per local rank; gloo on CPUs) and:

* checks that every rank resolved the same configuration (a node started with other arguments or
  another preset file): rank 0 reports the keys that differ, in one line, and every rank exits 2;
* draws the same global batches as one process would (:func:`global_batches`: the order of
  ``make_loader``) and gives each rank its share of every batch (:class:`RankBatches`).
  Each rank's summed loss is scaled by ``world / global batch``, so DDP's gradient average is the
  gradient of the global batch's mean loss, as in one process; a rank whose share of a short last
  batch is empty gets one sample with weight 0 (DDP needs every rank in every step);
* validates on a strided shard of the validation split and sums losses and counts over the
  ranks, so the logged metrics are those of the whole split;
* lets rank 0 alone pretrain the backbone, write config.json, log.csv and the checkpoints.

What still differs from one process: dropout draws other masks on each rank, BatchNorm (when a
model has it) sees per-rank batches, and the all-reduce sums the gradients in another order. With
dropout off the runs agree to float rounding (tests/stam/test_distributed.py states the tolerance).
"""
from __future__ import annotations

import dataclasses
import datetime
import os

import numpy as np
import torch
import torch.distributed as td
from torch import nn
from torch.utils.data import DataLoader, Sampler

from .errors import StamError

#: How long a rank waits for the others at a collective step. Rank 0 pretrains the backbone alone
#: while the others wait (the cpu preset's pretraining takes about half an hour on 2 cores).
TIMEOUT = datetime.timedelta(hours=2)
#: Keys that may differ between ranks: how each process runs, not what it computes.
LOCAL_KEYS = ("progress", "workers", "threads", "device", "cache_dir")


@dataclasses.dataclass(frozen=True)
class Dist:
    """This process's place in a torchrun job."""

    rank: int
    world: int
    local_rank: int

    @property
    def main(self) -> bool:
        return self.rank == 0


def from_env() -> Dist | None:
    """The torchrun job this process belongs to, or None when it runs alone (no ``WORLD_SIZE`` > 1)."""
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return None
        return Dist(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")))
    except (KeyError, ValueError):
        raise StamError("WORLD_SIZE is set but RANK is missing or not a number; start the processes with "
                        "torchrun --nproc-per-node N -m stam train ...") from None


def init(dist: Dist, device: str) -> torch.device:
    """Join the process group; returns this rank's device (``cuda:LOCAL_RANK`` on GPUs)."""
    cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if cuda and not torch.cuda.is_available():
        raise StamError("device cuda requested but no GPU is available; use --set device=cpu")
    if cuda:
        torch.cuda.set_device(dist.local_rank)
    if not td.is_initialized():
        td.init_process_group("nccl" if cuda else "gloo", timeout=TIMEOUT)
    return torch.device(f"cuda:{dist.local_rank}") if cuda else torch.device("cpu")


def check_same_config(dist: Dist, config: dict, what: str = "the config") -> None:
    """Every rank must run the same ``config`` (less :data:`LOCAL_KEYS`): otherwise rank 0 raises a
    StamError naming the keys and ranks that differ, and the other ranks exit 2 quietly (rank 0's
    line is the job's one error)."""
    mine = {k: v for k, v in config.items() if k not in LOCAL_KEYS}
    every: list = [None] * dist.world
    td.all_gather_object(every, mine)
    diff = sorted({k for other in every for k in set(mine) | set(other) if other.get(k) != every[0].get(k)})
    if not diff:
        return
    # Leave the group together before exiting: a rank whose peer is gone aborts in gloo's destructor.
    td.barrier()
    td.destroy_process_group()
    if dist.main:
        ranks = [r for r, other in enumerate(every) if any(other.get(k) != every[0].get(k) for k in diff)]
        shown = ", ".join(f"{k}: {every[0].get(k)!r} on rank 0, {every[ranks[0]].get(k)!r} on rank {ranks[0]}"
                          for k in diff[:3])
        raise StamError(f"the torchrun ranks disagree on {what} ({shown}{', ...' if len(diff) > 3 else ''}; ranks "
                        f"{', '.join(map(str, ranks))} differ from rank 0); start every rank with the same "
                        "arguments and preset file")
    raise SystemExit(2)


def barrier() -> None:
    td.barrier()


def make_loader(ds, batch_size: int, shuffle: bool, seed: int, epoch: int, workers: int) -> DataLoader:
    """The loader of one epoch of ``ds`` (:mod:`stam.train`'s, one process or all ranks together): its
    order is drawn from a generator per (seed, epoch), so a resumed run draws the same batches."""
    g = torch.Generator().manual_seed(seed * 100003 + epoch)
    return DataLoader(ds, batch_size=batch_size, shuffle=shuffle, generator=g, num_workers=workers,
                      drop_last=False)


def global_batches(n: int, batch_size: int, seed: int, epoch: int) -> list[list[int]]:
    """The batches of indices (into a dataset of ``n`` items) that one process trains on in
    ``epoch``: those of :func:`make_loader`, drawn from the same generator."""
    return [b.tolist() for b in make_loader(range(n), batch_size, True, seed, epoch, 0)]


def share(batch: list[int], rank: int, world: int) -> tuple[list[int], int]:
    """This rank's part of one global batch and how many of its items count: contiguous parts whose
    sizes differ by at most one; an empty part becomes the batch's first item, counted 0 times."""
    parts = np.array_split(np.asarray(batch), world)
    mine = parts[rank].tolist()
    return (mine, len(mine)) if mine else ([batch[0]], 0)


class RankBatches(Sampler):
    """A batch sampler: this rank's part of each global batch of :func:`global_batches`."""

    def __init__(self, n: int, batch_size: int, seed: int, epoch: int, dist: Dist):
        batches = global_batches(n, batch_size, seed, epoch)
        self.parts = [share(b, dist.rank, dist.world) for b in batches]
        self.sizes = [len(b) for b in batches]

    def __iter__(self):
        return iter(part for part, _ in self.parts)

    def __len__(self) -> int:
        return len(self.parts)

    def weights(self):
        """Per batch: (global batch size, items of this rank's part that count)."""
        return [(size, counted) for size, (_, counted) in zip(self.sizes, self.parts)]


class Forward(nn.Module):
    """The function a run trains, as a module DDP can wrap: the model, or its head on frozen features."""

    def __init__(self, model: nn.Module, features: bool):
        super().__init__()
        self.model, self.features = model, features

    def forward(self, x: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        return self.model.forward_features(x, keep) if self.features else self.model(x, keep)


def wrap(model: nn.Module, features: bool, device: torch.device) -> nn.Module:
    from torch.nn.parallel import DistributedDataParallel

    return DistributedDataParallel(Forward(model, features),
                                   device_ids=[device.index] if device.type == "cuda" else None)


def all_sum(values: list[float], device: torch.device) -> list[float]:
    """``values`` summed over the ranks (float64)."""
    t = torch.tensor(values, dtype=torch.float64, device=device)
    td.all_reduce(t)
    return t.tolist()


def gather_rng(dist: Dist) -> list[torch.Tensor]:
    """Every rank's torch RNG state (on every rank), for rank 0's checkpoint."""
    every: list = [None] * dist.world
    td.all_gather_object(every, torch.get_rng_state())
    return every


def close() -> None:
    """Leave the process group at the end of a run, every rank together (called by every rank on the
    paths that end normally)."""
    if td.is_initialized():
        # A rank that tears gloo down while a peer still holds its connections can abort in gloo's
        # destructor ("terminate called without an active exception", exit -6: seen once in a
        # two-rank test run on 2026-11-28); the barrier lets every rank finish its last collective first.
        td.barrier()
        td.destroy_process_group()
