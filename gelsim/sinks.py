"""The consumers of a sequence's frame records (:class:`gelsim.stream.FrameRecord`), one interface for all.

A sink has ``write(record)`` (called once per frame, in order), ``close()`` (after the last frame:
finish what is pending, raise what went wrong; a second call does nothing) and ``seconds`` (CPU
seconds per stage that it spent, read after ``close``). :func:`drain` runs a stream of records into
its sinks and returns the sequence's labels and stage times; a sink that holds a resource (a file, a
thread) is also a context manager that releases it when the caller's block fails.

* :class:`VideoSink`: the frames into a video file (``encode``): the dataset's writer, the bench's;
* :class:`DeviceFrames`: renders the records' frames (their optics inputs, :attr:`FrameRecord.optics`) on a
  torch device, ``batch`` at a time, and passes the completed records to its own sinks on a writer thread
  (``gelsim generate --backend torch``);
* :class:`KeepFrames`: keeps the frames in memory (the bench compares them);
* :class:`ImprintCapture`: keeps each pressed frame's depth map and contact mask (the bench's texture
  metrics).

The dataset's previews (:mod:`gelsim.previews`) are drawn from the written videos once the dataset is
complete (they pick frames across workers and resumed runs), not from a stream.
"""
from __future__ import annotations

import dataclasses
import queue
import threading
from pathlib import Path
from typing import Iterable, Protocol, Sequence

import numpy as np

from .errors import GelsimError
from .stream import FrameRecord, sequence_labels, stage_clock


class Sink(Protocol):
    """A consumer of frame records (see the module docstring)."""
    seconds: dict[str, float]

    def write(self, record: FrameRecord) -> None: ...

    def close(self) -> None: ...


def _add(into: dict[str, float], seconds) -> None:
    for k, v in seconds.items():
        into[k] = into.get(k, 0.0) + v


def drain(records: Iterable[FrameRecord], sinks: Sequence[Sink] = ()) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Every record of ``records`` to each of ``sinks`` in turn, then the sinks closed: returns the sequence's
    labels (:func:`gelsim.stream.sequence_labels`) and CPU seconds per stage, the stream's and the sinks'
    together. Only the labels of the records are kept here (constant memory)."""
    return drain_each(((0, rec) for rec in records), [sinks])[0]


def drain_each(records: Iterable[tuple[int, FrameRecord]], sinks: Sequence[Sequence[Sink]]) \
        -> list[tuple[dict[str, np.ndarray], dict[str, float]]]:
    """:func:`drain` of several sequences whose records come interleaved (``(k, record)``: sequence ``k``'s, in its
    frame order; :func:`gelsim.sequence.render_sequences`), sequence ``k``'s into ``sinks[k]``: each sequence's
    labels and seconds, in order."""
    rows: list[list] = [[] for _ in sinks]
    seconds: list[dict[str, float]] = [{} for _ in sinks]
    for k, rec in records:
        for s in sinks[k]:
            s.write(rec)
        rows[k].append(rec.labels)
        _add(seconds[k], rec.seconds)
    for k, group in enumerate(sinks):
        for s in group:
            s.close()
            _add(seconds[k], s.seconds)
    return [(sequence_labels(r), sec) for r, sec in zip(rows, seconds)]


class VideoSink:
    """The records' frames into the video ``path`` (:class:`gelsim.video.VideoWriter`: ``fmt``, ``fps``); the
    file appears at :meth:`close`, and leaving the ``with`` block by an error discards it. ``encode``:
    CPU seconds of writing and closing (on the thread that writes)."""

    def __init__(self, path: str | Path, *, fmt: str, fps: float):
        from .video import VideoWriter

        self.writer = VideoWriter(path, fmt=fmt, fps=fps)
        self.seconds = {"encode": 0.0}
        self._closed = False

    def write(self, record: FrameRecord) -> None:
        if record.frame is None:
            raise GelsimError(f"frame {record.index} was not rendered; ask the sequence for frames "
                              "(outputs with 'frames') or render them in a sink before the video")
        t = stage_clock()
        self.writer.write(record.frame)
        self.seconds["encode"] += stage_clock() - t

    def close(self) -> None:
        if self._closed:
            return
        t = stage_clock()
        self.writer.close()
        self._closed = True
        self.seconds["encode"] += stage_clock() - t

    def __enter__(self) -> "VideoSink":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:
            self._closed = True
            self.writer.abort()


class KeepFrames:
    """The records' frames, in order (``frames``: uint8 (H, W, 3) each)."""

    def __init__(self):
        self.frames: list[np.ndarray] = []
        self.seconds: dict[str, float] = {}

    def write(self, record: FrameRecord) -> None:
        self.frames.append(record.frame)

    def close(self) -> None:
        pass


class ImprintCapture:
    """The imprint of every frame that pressed the gel: ``imprints`` = ``{frame index: (depth mm float32
    (H, W), contact mask bool (H, W))}``."""

    def __init__(self):
        self.imprints: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.seconds: dict[str, float] = {}

    def write(self, record: FrameRecord) -> None:
        if record.imprint is not None:
            self.imprints[record.index] = (record.imprint.depth_mm, record.imprint.contact_mask)

    def close(self) -> None:
        pass


class DeviceFrames:
    """Renders the frames of records that carry none (a sequence run without ``"frames"``), ``batch`` at a time,
    through ``renderer`` (a :class:`gelsim.optics.torch_backend.BatchRenderer`) on its device, from each record's
    inputs to the optics (:attr:`gelsim.stream.FrameRecord.optics`: the depth to render, the markers, the gains,
    its noise seed), and passes each record, its frame filled in, in order to ``sinks`` on a writer thread, which
    works while the next batch is simulated and rendered. On a CUDA device a batch's rendering and its copy back
    run while the CPU prepares the next.

    Each frame's noise offsets are drawn from its seed (the sequence's :func:`gelsim.stream.noise_generator`)
    when its record arrives, in the order the numpy renderer draws them, so the frames are the same bytes for
    any ``batch``. ``seconds``: ``optics`` (CPU seconds on the caller's thread: the draws, the copies, the
    batches' rendering) and the sinks' (on the writer thread). Use as a context manager: leaving it by an error
    stops the writer without rendering what is queued; :meth:`close` renders what is queued, waits for the
    writer and re-raises its error.
    """

    def __init__(self, renderer, batch: int, sinks: Sequence[Sink]):
        if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
            raise GelsimError(f"--batch {batch!r} is invalid; give a whole number of frames >= 1")
        self.br = renderer
        self.batch = batch
        self.sinks = list(sinks)
        self.seconds: dict[str, float] = {"optics": 0.0}
        self._records: list[FrameRecord] = []    # the batch being filled (frozen: read at its launch)
        self._offsets: list = []
        self._inflight = None
        self._queue: queue.Queue = queue.Queue(maxsize=2)
        self._error: BaseException | None = None
        self._closed = False
        self._writer = threading.Thread(target=self._write, name="gelsim-frame-writer", daemon=True)
        self._writer.start()

    def _write(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            if self._error is not None:
                continue                      # drain after a failure, so the producer never blocks
            try:
                records, frames = job
                for rec, f in zip(records, frames):
                    rec = dataclasses.replace(rec, frame=f)
                    for s in self.sinks:
                        s.write(rec)
            except BaseException as e:  # handed to the producer's thread, raised at close
                self._error = e

    def write(self, record: FrameRecord) -> None:
        """Queue ``record``'s frame; renders a batch when one is full."""
        if self._error is not None:
            raise self._error
        t = stage_clock()
        self._offsets.append(self.br.draw(record.optics.seed, record.optics.noise))
        self._records.append(record)
        if len(self._records) >= self.batch:
            self._launch()
        self.seconds["optics"] += stage_clock() - t

    def _launch(self) -> None:
        """Render the queued frames (asynchronously on a GPU) and pass the previous batch to the writer."""
        if not self._records:
            return
        inputs = [r.optics for r in self._records]
        depth, corners = self.br.stage([i.depth_mm for i in inputs], [i.markers for i in inputs])
        gains = [i.gains for i in inputs]
        out = self.br.quantise(self.br.compose(depth, corners, self._offsets,
                                               None if all(g is None for g in gains) else gains, inputs), self._offsets)
        if out.device.type == "cuda":
            import torch

            host = torch.empty(out.shape, dtype=out.dtype, pin_memory=True)
            host.copy_(out, non_blocking=True)
            done = torch.cuda.Event()
            done.record()
            job = (self._records, host, done)
        else:
            job = (self._records, out, None)
        self._records, self._offsets = [], []
        self._collect()
        self._inflight = job

    def _collect(self) -> None:
        if self._inflight is None:
            return
        records, frames, done = self._inflight
        self._inflight = None
        if done is not None:
            done.synchronize()
        self._queue.put((records, frames.numpy()))

    def close(self) -> None:
        """Render what is queued, hand every record to the writer, wait for it and close the sinks (once;
        again: nothing)."""
        if self._closed:
            return
        self._closed = True
        t = stage_clock()
        try:
            if self._error is None:
                self._launch()
                self._collect()
        finally:
            self._queue.put(None)
            self.seconds["optics"] += stage_clock() - t
            self._writer.join()
        if self._error is not None:
            raise self._error
        for s in self.sinks:
            s.close()
            _add(self.seconds, s.seconds)

    def __enter__(self) -> "DeviceFrames":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:                # the caller's error wins; stop the writer quietly
            self._closed = True
            self._records = []
            self._inflight = None
            self._queue.put(None)
            self._writer.join()
