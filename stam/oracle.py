"""The onset-aware oracle's windows: which frames of each window come before the detected contact onset.

The oracle (model ``oracle``: the CNN with the ``onset`` fusion, :mod:`stam.models`) averages the
per-frame class scores over the frames of its window from the detected onset on, and drops the frames
before it: what a perfect detector of the frames before contact could do with them, so the upper
bound for any robustness mechanism. It is told where the onset is; no model of the paper is.

The onset is the one the clean windows start at (:meth:`stam.data.TactileDataset.onset`, detected from
the images by default). For a window of ``n`` frames starting at frame ``first`` of a sequence with
onset ``o``, the frames ``first .. o - 1`` are dropped; when that is all of them (the window ends before
the onset) the last frame is kept, so every window has a prediction; when no onset was detected none
is dropped (the detector gives no frame as before contact).
"""
from __future__ import annotations

import torch
from torch.utils.data import Dataset

from .data import WindowDataset


def keep_mask(onset: int | None, first: int, n: int) -> torch.Tensor:
    """``bool (n,)``: the frames of the window ``first .. first + n - 1`` the oracle keeps: those from
    ``onset`` on; the last one alone when the window ends before the onset; all when ``onset`` is None."""
    if onset is None:
        return torch.ones(n, dtype=torch.bool)
    keep = torch.arange(first, first + n) >= onset
    if not keep.any():
        keep[-1] = True
    return keep


class OnsetWindows(Dataset):
    """A :class:`stam.data.WindowDataset`'s items with the oracle's mask: ``((window, keep), label)``,
    ``keep`` from :func:`keep_mask` with the onset of ``onset`` mode (``detected`` or ``true``) and
    ``threshold`` (DN), as the clean windows find it."""

    def __init__(self, windows: WindowDataset, onset: str = "detected", threshold: float | None = None):
        self.windows = windows
        data, size = windows.data, windows.size
        kw = {} if threshold is None else {"threshold": threshold}
        self.keep = [keep_mask(data.onset(seq, size, onset, **kw), first, windows.n) for seq, first in windows.items]

    @property
    def items(self):
        """(sequence, first frame) per window, as the wrapped WindowDataset's."""
        return self.windows.items

    @property
    def undetected(self) -> int:
        """Sequences of the wrapped windows without a detected onset."""
        return self.windows.undetected

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int):
        x, y = self.windows[i]
        return (x, self.keep[i]), y


def windows_for(model, windows: WindowDataset, onset: str, threshold: float) -> Dataset:
    """``windows`` as ``model`` reads them: with the oracle's masks when it needs them
    (``model.needs_onset``), else unchanged."""
    return OnsetWindows(windows, onset, threshold) if getattr(model, "needs_onset", False) else windows
