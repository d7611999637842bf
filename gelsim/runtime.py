"""Process settings for frame-by-frame work on one core (generation workers, benchmarks).

Three settings, applied by :func:`configure_worker`:

* **OpenCV on one thread.** One process per core: OpenCV's own threads would oversubscribe.
* **BLAS on one thread.** numpy and OpenCV each bundle an OpenBLAS whose threads, once started by a
  mid-sized product (a 240x55 by 55x280 one is enough), spin between calls: measured, a worker
  whose frame ran two such products used 76 ms of CPU for 37 ms of its own work. Both are set to
  one thread through OpenBLAS's ``*_set_num_threads`` (as threadpoolctl does; no new dependency).
* **Keep freed arrays on the heap (glibc).** A frame allocates dozens of short-lived arrays of a
  few MB. glibc serves allocations above its mmap threshold with fresh ``mmap`` pages, which the
  kernel zeroes and faults in on first touch: measured on a 960x720 fabric press, that overhead
  made the two-scale imprint 2.5x slower (16.5 vs 6.5 ms CPU for its texture stage) than with the
  same arrays reused from the heap. ``mallopt`` raises the mmap threshold and the trim threshold
  so that freed blocks are reused. The process keeps its peak heap (a few hundred MB for a worker,
  see benchmarks/bench_generate.py) instead of returning it between frames. Elsewhere than glibc
  this is a no-op.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

# glibc's mallopt parameters (malloc.h): M_TRIM_THRESHOLD = -1, M_MMAP_THRESHOLD = -3.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# Arrays up to 256 MB come from the heap (a 960x720 float64 frame is 5.5 MB; 256 MB is glibc's
# largest allowed threshold on 64-bit, HEAP_MAX/2 = 32 MB on some builds clamps it lower, which
# still covers a frame); the heap is trimmed only past 512 MB of free top.
MMAP_THRESHOLD_BYTES = 256 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 512 * 1024 * 1024

_configured = False


def keep_heap() -> bool:
    """Apply the glibc allocator setting above; True if it took effect."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
        ok &= libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
        return bool(ok)
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False


# OpenBLAS builds name their thread setter differently (64-bit-index builds of scipy-openblas add a
# prefix and a suffix).
_BLAS_SETTERS = ("openblas_set_num_threads", "scipy_openblas_set_num_threads64_", "openblas_set_num_threads64_",
                 "scipy_openblas_set_num_threads")


def single_thread_blas() -> int:
    """Set every OpenBLAS loaded in this process to one thread; returns how many were set (0 where
    none is loaded or the platform has no /proc/self/maps)."""
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower() and "/" in line}
    except OSError:
        return 0
    done = 0
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _BLAS_SETTERS:
            fn = getattr(lib, name, None)
            if fn is not None:
                fn(ctypes.c_int(1))
                done += 1
                break
    return done


def configure_worker() -> None:
    """One-core frame work: OpenCV and BLAS on one thread, freed arrays kept on the heap. Idempotent."""
    global _configured
    import cv2
    import numpy  # noqa: F401  (loads numpy's OpenBLAS, so that it is found below)

    cv2.setNumThreads(1)
    if not _configured:
        keep_heap()
        single_thread_blas()
        _configured = True
