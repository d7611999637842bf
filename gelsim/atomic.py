"""Writing files so that no half-written file ever looks complete: one implementation for gelsim.

Each writer puts the data under a hidden temporary name in the target's folder (same file system),
flushes it to disk and renames it over the target: a reader sees the old file or the new one, never
a torn one, and an interrupted run leaves only a ``.NAME.partial-PID`` file behind.
"""
from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import GelsimError


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` (folders created) atomically; unwritable places are a GelsimError."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise GelsimError(f"{path}: cannot write there ({e.strerror}); choose a writable place") from None
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=False) + "\n").encode())


def atomic_write_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """A compressed .npz of ``arrays``."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def write_png(path: str | Path, img: np.ndarray, *, rgb: bool = True) -> Path:
    """An 8-bit image as PNG: (H, W) grey or (H, W, 3) RGB (``rgb=False``: already BGR, OpenCV's order)."""
    import cv2

    a = np.asarray(img)
    if a.ndim == 3 and rgb:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", a)
    if not ok:
        raise GelsimError(f"{path}: could not encode the image as PNG (shape {a.shape}, dtype {a.dtype})")
    return atomic_write_bytes(path, buf.tobytes())
