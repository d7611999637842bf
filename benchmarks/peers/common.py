"""Timing, PNG output and result records shared by the runners (stdlib + numpy: runs in every venv).

The one place outside the package that writes a file on its own: run_taxim.py and run_tacto.py import
this module inside the peers' venvs, which have neither gelsim nor OpenCV, so :func:`write_png` cannot
use gelsim.atomic.write_png (run_ours.py, in the project's venv, does). It follows the same rule:
a temporary ``.NAME.partial-PID`` beside the target, then a rename.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

RESOLUTIONS = ((960, 720), (640, 480))


def time_frames(fn, warmup: int, frames: int) -> dict:
    """Call ``fn()`` ``warmup`` times untimed (JIT, GL state, caches), then ``frames`` times timed.

    Returns ms per frame: median, 10th and 90th percentile, min, and every sample."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(frames):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    s = np.asarray(samples)
    return {"ms_median": float(np.median(s)), "ms_p10": float(np.percentile(s, 10)),
            "ms_p90": float(np.percentile(s, 90)), "ms_min": float(s.min()),
            "frames": int(frames), "warmup": int(warmup), "samples_ms": [round(float(v), 3) for v in s]}


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write uint8 ``(H, W, 3)`` RGB as PNG (zlib only; every venv can), atomically (peers' venvs only)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, c = rgb.shape
    raw = b"".join(b"\x00" + rgb[r].tobytes() for r in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 1)) + chunk(b"IEND", b""))
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    tmp.write_bytes(png)
    os.replace(tmp, path)


def image_stats(rgb: np.ndarray, ref: np.ndarray | None = None) -> dict:
    """Mean colour and, against a flat reference frame, the fraction of pixels changed by > 8 DN."""
    rgb = np.asarray(rgb, dtype=np.float32)
    out = {"mean_rgb": [round(float(v), 1) for v in rgb.reshape(-1, 3).mean(axis=0)]}
    if ref is not None:
        diff = np.abs(rgb - np.asarray(ref, dtype=np.float32)).max(axis=-1)
        out["changed_frac"] = round(float((diff > 8).mean()), 4)
        out["max_diff_dn"] = round(float(diff.max()), 1)
    return out


def runner_args(description: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--frames", type=int, default=10, help="timed frames per case (default 10)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed frames before timing (default 3)")
    ap.add_argument("--png-dir", default=os.environ.get("TMPDIR", "/tmp"),
                    help="where one PNG per case goes (default $TMPDIR or /tmp)")
    ap.add_argument("--only", default="", help="comma-separated case filter, substring match (default all)")
    return ap.parse_args()


def wanted(args, *parts: str) -> bool:
    if not args.only:
        return True
    key = "/".join(parts)
    return any(tok.strip() and tok.strip() in key for tok in args.only.split(","))


def emit(results: list[dict], versions: dict) -> None:
    """Print the runner's one JSON document on stdout (the compare script parses it)."""
    doc = {"python": sys.version.split()[0], "machine": platform.machine(),
           "affinity": sorted(os.sched_getaffinity(0)),
           "threads_env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                                          "OPENBLAS_NUM_THREADS", "XLA_FLAGS",
                                                          "LP_NUM_THREADS", "PYOPENGL_PLATFORM")},
           "versions": versions, "results": results}
    sys.stdout.write(json.dumps(doc) + "\n")
    sys.stdout.flush()
