"""Writing files so that no half-written file ever looks complete: one implementation for gelsim and stam.

Each writer puts the data under a hidden temporary name in the target's folder (same file system, so
the rename is atomic), flushes it to disk and renames it over the target: a reader sees the old file
or the new one, never a torn one, and an interrupted run leaves only a ``.NAME.partial-PID`` file
behind (:func:`partial_path`; ``gelsim generate`` sweeps such leftovers on resume).

* :func:`atomic_open`: a binary file object for writers that stream (``np.save``, ``torch.save``,
  matplotlib's ``savefig``), renamed into place when the ``with`` block ends without error;
* :func:`atomic_write_bytes`, ``_text``, ``_json``, ``_npz``: whole documents (:func:`json_default`:
  how JSON writers here and ``gelsim.cli.print_json`` store numpy values and paths);
* :func:`write_png`: the one PNG writer (8-bit grey or colour arrays, OpenCV's encoder);
* :func:`write_figure`: a matplotlib figure as PNG, the figure closed afterwards;
* :func:`out_folder`: a command's output folder, removed again when its first run fails before writing.

Unwritable places are a one-line :class:`GelsimError` naming the path.
"""
from __future__ import annotations

import io
import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from .errors import GelsimError

#: The infix of temporary names (``.NAME.partial-PID``); leftovers of a killed run carry it.
PARTIAL = ".partial-"


def partial_path(path: str | Path, suffix: str = "") -> Path:
    """The temporary name :func:`atomic_open` writes ``path`` under: ``.NAME.partial-PID`` beside it
    (``suffix`` appended, for writers that pick the format from the file name)."""
    path = Path(path)
    return path.with_name(f".{path.name}{PARTIAL}{os.getpid()}{suffix}")


def _unlink_quietly(p: Path) -> None:
    try:
        p.unlink()
    except OSError:
        pass


@contextmanager
def atomic_open(path: str | Path) -> Iterator[BinaryIO]:
    """``with atomic_open(path) as f: ...`` writes ``f`` (binary) to ``path`` atomically, folders
    created. If the block raises, the temporary file is removed and ``path`` is left as it was; an
    OSError (full disk, no permission) becomes a GelsimError naming ``path``."""
    path = Path(path)
    tmp = partial_path(path)

    def fail(e: OSError) -> GelsimError:
        return GelsimError(f"{path}: cannot write there ({e.strerror or e}); choose a writable --out")

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(tmp, "wb")
    except OSError as e:
        raise fail(e) from None
    try:
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())   # the data is on disk before the name points at it
        os.replace(tmp, path)
    except OSError as e:
        _unlink_quietly(tmp)
        raise fail(e) from None
    except BaseException:
        _unlink_quietly(tmp)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` (folders created) atomically; unwritable places are a GelsimError."""
    with atomic_open(path) as f:
        f.write(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """``text`` as UTF-8."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def json_default(o):
    """``json.dump``'s ``default=``: numpy scalars as numbers, arrays as lists, paths as strings."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "__fspath__"):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    """``obj`` as JSON, indented by one space, with a final newline (numpy values and paths as
    :func:`json_default` stores them)."""
    return atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=False, default=json_default)
                                     + "\n").encode())


def atomic_write_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """A compressed .npz of ``arrays``."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def png_bytes(img: np.ndarray, *, rgb: bool = True) -> bytes:
    """An 8-bit image encoded as PNG: ``uint8 (H, W)`` grey or ``(H, W, 3)`` colour, RGB order
    (``rgb=False``: already BGR, OpenCV's order). Encoding failures are a GelsimError."""
    import cv2

    a = np.asarray(img)
    # OpenCV would quietly convert other dtypes (float images to 8 bits, wrapping) and fail on
    # other channel counts with a long message: both are a caller's mistake, said in one line.
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)) or a.size == 0:
        raise GelsimError(f"cannot encode an image of shape {a.shape} and dtype {a.dtype} as PNG; "
                          "give uint8 (H, W) or (H, W, 3)")
    if a.ndim == 3 and rgb:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", a)
    if not ok:
        raise GelsimError(f"OpenCV could not encode the image of shape {a.shape} as PNG; check the image")
    return buf.tobytes()


def write_png(path: str | Path, img: np.ndarray, *, rgb: bool = True) -> Path:
    """An 8-bit image as PNG at ``path`` (atomically): ``(H, W)`` grey or ``(H, W, 3)`` RGB
    (``rgb=False``: already BGR, OpenCV's order)."""
    try:
        data = png_bytes(img, rgb=rgb)
    except GelsimError as e:
        raise GelsimError(f"{path}: {e}") from None
    return atomic_write_bytes(path, data)


def write_figure(path: str | Path, fig, **savefig_kw) -> Path:
    """A matplotlib figure as PNG at ``path`` (atomically), then closed; ``savefig_kw`` go to
    ``fig.savefig`` (e.g. ``dpi``)."""
    import matplotlib.pyplot as plt

    try:
        with atomic_open(path) as f:
            fig.savefig(f, format="png", **savefig_kw)
    finally:
        plt.close(fig)
    return Path(path)


def not_a_folder(path: str | Path) -> str | None:
    """Why ``path`` is no folder to read or write in (``"folder X does not exist"``, ``"X is a file, not a
    folder"``), or None when it is one."""
    path = Path(path)
    if path.is_dir():
        return None
    if path.exists():
        return f"{path} is a file, not a folder"
    return f"folder {path} does not exist"


@contextmanager
def out_folder(path: str | Path, option: str = "--out") -> Iterator[Path]:
    """``with out_folder(out):`` around a command that writes into folder ``path`` (new, or one it resumes):
    a file of that name is a GelsimError before the block runs, and when the block fails (bad input found
    late, Ctrl-C) on a ``path`` that did not exist before, the folders it made that hold no file are removed
    again: a failed first run leaves nothing behind, and one that wrote files keeps them for the next."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise GelsimError(f"{option} {path} is a file, not a folder; give a new folder or one this command "
                          "wrote before")
    above = next((p for p in path.parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise GelsimError(f"{option} {path}: {above} is a file, not a folder; choose another {option}")
    existed = path.exists()
    try:
        yield path
    except BaseException:
        if not existed and path.is_dir():
            for folder, _, _ in sorted(os.walk(path), key=lambda entry: -len(entry[0])):  # deepest first
                try:
                    os.rmdir(folder)   # only empty folders go; one with a file in it stays
                except OSError:
                    pass
        raise


def check_out_file(path: str | Path, suffix: str = ".png") -> Path:
    """Fail early (before any work) on an output file name that cannot be written: a wrong suffix
    (``suffix``, case-insensitive), a folder that does not exist, or a place that is not writable."""
    path = Path(path)
    if path.suffix.lower() != suffix:
        raise GelsimError(f"{path}: output must be a {suffix} file; give a name ending in {suffix}")
    parent = path.parent if str(path.parent) else Path(".")
    problem = not_a_folder(parent)
    if problem:
        raise GelsimError(f"{path}: {problem}; create the folder or choose another --out")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise GelsimError(f"{path}: not writable; choose a writable --out")
    return path
