"""The per-frame nuisance record: what each stage did to each frame, kept apart from the labels.

A dataset holds one ``nuisance/<stem>.npz`` per sequence (every dataset, ``--nuisance none`` included, so a
reader never has to ask whether it exists), with one row per frame of each key of :data:`RECORD`. The labels
(``labels/``) never change with the level; this file says what the level added. Rows come from each frame's
:class:`gelsim.nuisance.sequence.FrameNuisance` (None: nothing applied) by :func:`frame_row`;
:class:`NuisanceLog` is the sink that writes a sequence's file.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..atomic import atomic_write_npz


class RecordKey(NamedTuple):
    name: str
    dtype: str
    shape: tuple            # per frame
    doc: str


#: The record's keys (each an array with one row per frame, T first).
RECORD = (
    RecordKey("gains", "float32", (3,), "per-channel camera gains of the frame (R, G, B; exposure x white balance); 1: none"),
    RecordKey("stream_age_frames", "int32", (), "frames since the camera's stream started (startup stage); -1: a settled stream"),
    RecordKey("fibres_touching", "int32", (), "loose fibres denting the gel in this frame (fibres stage)"),
    RecordKey("fibre_dent_max_mm", "float32", (), "deepest fibre dent in this frame, mm; 0: none"),
)
RECORD_KEYS = tuple(k.name for k in RECORD)


def frame_row(nuisance) -> dict[str, np.ndarray]:
    """One frame's record row from its FrameNuisance (None: nothing applied)."""
    if nuisance is None:
        return {"gains": np.ones(3, np.float32), "stream_age_frames": np.int32(-1),
                "fibres_touching": np.int32(0), "fibre_dent_max_mm": np.float32(0.0)}
    return {"gains": (np.ones(3) if nuisance.gains is None else np.asarray(nuisance.gains)).astype(np.float32),
            "stream_age_frames": np.int32(nuisance.stream_age_frames),
            "fibres_touching": np.int32(nuisance.fibres_touching),
            "fibre_dent_max_mm": np.float32(nuisance.fibre_dent_max_mm)}


def stack_rows(rows: list[dict]) -> dict[str, np.ndarray]:
    """A sequence's record from its frames' rows, in :data:`RECORD` order and dtypes."""
    return {k.name: np.stack([r[k.name] for r in rows]).astype(k.dtype) if rows
            else np.zeros((0,) + k.shape, k.dtype) for k in RECORD}


def record_problems(z, num_frames: int) -> list[str]:
    """What is wrong with a loaded record ``z`` (a mapping of arrays) of a ``num_frames``-frame sequence."""
    out = []
    for k in RECORD:
        if k.name not in z:
            out.append(f"nuisance record lacks {k.name!r}")
        elif z[k.name].shape != (num_frames,) + k.shape or str(z[k.name].dtype) != k.dtype:
            out.append(f"nuisance record {k.name!r} is {z[k.name].dtype} {z[k.name].shape}, "
                       f"expected {k.dtype} {(num_frames,) + k.shape}")
    return out


class NuisanceLog:
    """A sink (:mod:`gelsim.sinks`) that writes a sequence's per-frame nuisance record to ``path`` (npz) at
    :meth:`close`, written to a temporary name and renamed."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.rows: list[dict] = []
        self.seconds: dict[str, float] = {}
        self._closed = False

    def write(self, record) -> None:
        self.rows.append(frame_row(record.nuisance))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        atomic_write_npz(self.path, **stack_rows(self.rows))
