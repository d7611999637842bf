"""Video files for tactile sequences: H.264 (default), lossless FFV1, or PNG frames.

OpenCV's wheel has no H.264 encoder, so encoding goes through PyAV, whose wheels
carry libx264. Every writer writes to a temporary name and renames on close, so
an interrupted write never leaves a file that looks complete.

Formats and their files:

* ``h264``: ``NAME.mp4``, libx264, single-threaded (the dataset parallelises across
  sequences instead), ``preset`` and ``crf`` selectable.
* ``ffv1``: ``NAME.mkv``, lossless, large (about 10-20 MB per 30 frames at 960x720).
* ``png``:  ``NAME/`` directory of ``000000.png``...; lossless, simple, slowest.

All readers return ``uint8 (T, H, W, 3)`` RGB.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Literal

import numpy as np

from .atomic import partial_path
from .errors import GelsimError, check_choice

VideoFormat = Literal["h264", "ffv1", "png"]
EXTENSIONS: dict[str, str] = {"h264": ".mp4", "ffv1": ".mkv", "png": ""}
# Quality defaults: CRF 18 keeps sensor noise and marker edges (CRF 23 visibly smooths
# them away, REFERENCES.md); ultrafast costs about 4 ms per 960x720 frame on one core.
DEFAULT_CRF = 18
DEFAULT_PRESET = "ultrafast"


def video_path(stem: str | Path, fmt: VideoFormat) -> Path:
    """The file (or directory, for PNG) a sequence named ``stem`` is stored under."""
    check_choice("video format", fmt, EXTENSIONS)
    return Path(str(stem) + EXTENSIONS[fmt])


def _tmp_name(path: Path) -> Path:
    # The suffix keeps the container type visible to libav (it picks the muxer by name).
    return partial_path(path, suffix=path.suffix)


@dataclass(frozen=True)
class I420:
    """A frame already converted to the encoder's 4:2:0 planes: ``planes`` uint8 ``(3 H / 2, W)``, OpenCV's I420
    layout (``cv2.COLOR_RGB2YUV_I420``'s; :func:`gelsim.video_torch.rgb_to_i420` makes it on a device).
    :meth:`VideoWriter.write` takes it for an H.264 video of even size, skipping its own conversion."""
    planes: np.ndarray

    @property
    def size(self) -> tuple[int, int]:
        """The frame's (H, W), px."""
        return self.planes.shape[0] * 2 // 3, self.planes.shape[1]


# Why VideoWriter keeps its own rename instead of gelsim.atomic.atomic_open: libav opens and muxes
# the file itself, by name (the container chosen by the suffix), over the whole sequence, and the
# png format is a directory, which no file object can stand for. It uses the same temporary names
# (gelsim.atomic.partial_path), so `gelsim generate` sweeps its leftovers like any other.


class VideoWriter:
    """Streams RGB frames to a video file; ``close()`` makes it appear, ``abort()`` discards.

    Use as a context manager: an exception inside the block discards the partial file.
    """

    def __init__(self, path: str | Path, *, fmt: VideoFormat = "h264", fps: float = 30.0,
                 crf: int = DEFAULT_CRF, preset: str = DEFAULT_PRESET):
        self.path = Path(path)
        self.fmt = fmt
        check_choice("video format", fmt, EXTENSIONS)
        self.fps = fps
        self.crf = crf
        self.preset = preset
        self.tmp = _tmp_name(self.path)
        self.count = 0
        self._container = None
        self._stream = None
        self._shape: tuple[int, int] | None = None
        self._frame = None      # the reused yuv420p frame (see _yuv_frame)
        self._planes: list[np.ndarray] | None = []   # None: rows are padded, no reuse

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _open(self, h: int, w: int) -> None:
        import av

        self._shape = (h, w)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.fmt == "png":
            if self.tmp.exists():
                shutil.rmtree(self.tmp)
            self.tmp.mkdir()
            return
        self._container = av.open(str(self.tmp), mode="w")
        from fractions import Fraction

        rate = Fraction(self.fps).limit_denominator(1000)
        if self.fmt == "h264":
            stream = self._container.add_stream("libx264", rate=rate)
            # 4:2:0 needs even sizes; odd test-sized frames fall back to 4:4:4.
            stream.pix_fmt = "yuv420p" if h % 2 == 0 and w % 2 == 0 else "yuv444p"
            stream.options = {"crf": str(self.crf), "preset": self.preset}
            stream.thread_count = 1
        else:
            stream = self._container.add_stream("ffv1", rate=rate)
            stream.pix_fmt = "bgr0"
            stream.thread_count = 1
        stream.width, stream.height = w, h
        self._stream = stream

    def _yuv_frame(self, i420: np.ndarray):
        """An ``av.VideoFrame`` holding ``i420`` (uint8 ``(3 H / 2, W)``, OpenCV's I420 layout). One frame
        object is refilled for the whole video: PyAV's ``from_ndarray`` allocated and filled a new one per
        frame (0.7 ms at 960x720, against 0.1 ms for three plane copies; the same file, byte for byte).
        Safe because libx264 copies its input picture before ``encode`` returns (the writer is
        single-threaded). Planes with padded rows (widths that are not a multiple of the alignment)
        take ``from_ndarray``."""
        import av

        if self._frame is None and self._planes is not None:
            vf = av.VideoFrame(self._shape[1], self._shape[0], "yuv420p")
            if any(p.line_size != p.width for p in vf.planes):
                self._planes = None
            else:
                self._frame, self._planes = vf, [np.frombuffer(p, np.uint8) for p in vf.planes]
        if self._planes is None:
            return av.VideoFrame.from_ndarray(i420, format="yuv420p")
        flat, start = i420.reshape(-1), 0
        for plane in self._planes:
            plane[:] = flat[start:start + plane.size]
            start += plane.size
        self._frame.pts = None   # PyAV numbers a frame without pts itself, as it does a new one
        return self._frame

    def write(self, frame: np.ndarray | I420) -> None:
        """Append one ``uint8 (H, W, 3)`` RGB frame, or one already in I420 (:class:`I420`: an H.264 video of even
        size only, whose encoder takes those planes as they are)."""
        import av

        if isinstance(frame, I420):
            h, w = frame.size
            if self.fmt != "h264" or h % 2 or w % 2:   # (what _open encodes as yuv420p)
                raise GelsimError(f"an I420 frame goes to an H.264 video of even size, not {self.fmt} at {h} x {w}; "
                                  "give the frame as RGB")
            self._check_size(frame.size)
            self._encode(self._yuv_frame(frame.planes))
            return
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise GelsimError(f"video frames must be uint8 (H, W, 3), got {frame.dtype} {frame.shape}")
        self._check_size(frame.shape[:2])
        if self.fmt == "png":
            import cv2

            # Not gelsim.atomic.write_png: a frame inside the temporary directory needs no rename of
            # its own, and compression level 1 (not OpenCV's default 3) keeps encoding fast; the
            # bytes are the png format's, so they must not change.
            ok = cv2.imwrite(str(self.tmp / f"{self.count:06d}.png"), frame[:, :, ::-1],
                             [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise GelsimError(f"could not write PNG frames under {self.tmp}; check the disk")
        else:
            if self._stream.pix_fmt == "yuv420p":
                # OpenCV's BT.601 4:2:0 conversion: 0.9 ms at 960x720 against libswscale's 2.6 ms
                # (same round-trip error: 1.7-2.1 DN mean absolute, measured on rendered frames).
                import cv2

                vf = self._yuv_frame(cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2YUV_I420))
            else:
                vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            self._encode(vf)
            return
        self.count += 1

    def _check_size(self, size: tuple[int, int]) -> None:
        """Open the video at the first frame's ``size`` (H, W); a later frame of another size is an error."""
        if self._shape is None:
            self._open(*size)
        elif tuple(size) != self._shape:
            raise GelsimError(f"frame size changed from {self._shape} to {tuple(size)} within one video")

    def _encode(self, vf) -> None:
        for packet in self._stream.encode(vf):
            self._container.mux(packet)
        self.count += 1

    def close(self) -> Path:
        """Finish encoding and move the file to its final name. Returns the final path."""
        if self._shape is None:
            raise GelsimError(f"no frames were written to {self.path}")
        if self._container is not None:
            for packet in self._stream.encode(None):
                self._container.mux(packet)
            self._container.close()
            self._container = None
        if self.path.exists():
            if self.path.is_dir():
                shutil.rmtree(self.path)
            else:
                self.path.unlink()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Discard the partial output."""
        if self._container is not None:
            try:
                self._container.close()
            except Exception:  # the file is being thrown away; a broken muxer must not mask the real error
                pass
            self._container = None
        if self.tmp.is_dir():
            shutil.rmtree(self.tmp, ignore_errors=True)
        elif self.tmp.exists():
            self.tmp.unlink()


def write_video(path: str | Path, frames: Iterable[np.ndarray], *, fps: float = 30.0,
                fmt: VideoFormat = "h264", crf: int = DEFAULT_CRF, preset: str = DEFAULT_PRESET) -> Path:
    """Write ``uint8 (H, W, 3)`` RGB frames to ``path`` atomically; returns the path."""
    with VideoWriter(path, fmt=fmt, fps=fps, crf=crf, preset=preset) as w:
        for f in frames:
            w.write(f)
    return Path(path)


def read_video(path: str | Path) -> np.ndarray:
    """Decode a whole video (``.mp4``, ``.mkv`` or a PNG directory) to ``uint8 (T, H, W, 3)`` RGB."""
    frames = list(iter_video(path))
    if not frames:
        raise GelsimError(f"{path}: no frames could be decoded; the file is empty or corrupt, regenerate it")
    return np.stack(frames)


def iter_video(path: str | Path):
    """Yield ``uint8 (H, W, 3)`` RGB frames one at a time (constant memory)."""
    path = Path(path)
    if not path.exists():
        raise GelsimError(f"{path}: video not found; check the path or regenerate the dataset")
    if path.is_dir():
        import cv2

        for p in sorted(path.glob("*.png")):
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                raise GelsimError(f"{p}: not a readable PNG; regenerate the sequence")
            yield img[:, :, ::-1].copy()
        return
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in container.decode(stream):
                yield frame.to_ndarray(format="rgb24")
    except (av.error.FFmpegError, IndexError) as e:
        raise GelsimError(f"{path}: cannot decode video ({e}); the file is corrupt, regenerate it") from None


def count_frames(path: str | Path) -> int:
    """Number of frames that decode (decodes everything: a truncated file shows up as fewer frames)."""
    return sum(1 for _ in iter_video(path))
