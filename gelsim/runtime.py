"""Process settings for frame-by-frame work on one core (generation workers, benchmarks).

Three settings, applied by :func:`configure_worker`:

* **OpenCV on one thread.** One process per core: OpenCV's own threads would oversubscribe.
* **BLAS on one thread.** numpy and OpenCV each bundle an OpenBLAS whose threads, once started by a
  mid-sized product (a 240x55 by 55x280 one is enough), spin between calls: measured, a worker
  whose frame ran two such products used 76 ms of CPU for 37 ms of its own work. Both are set to
  one thread through threadpoolctl.
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

from .errors import GelsimError

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


def single_thread_blas() -> int:
    """Set every BLAS loaded in this process to one thread, for good; returns how many were set."""
    from threadpoolctl import threadpool_limits

    return len(threadpool_limits(limits=1, user_api="blas").get_original_num_threads())


class ThreadLimit:
    """A block run on at most ``threads`` threads of OpenCV and of every BLAS/OpenMP pool threadpoolctl
    finds, the caller's own settings given back after it (``None``: nothing changed).

    Why (issue 42): numpy's OpenBLAS starts a second thread on a mid-sized product and it spins between
    calls; a GelSight sensor at 320x240 used 14.5 ms of CPU for 6.6 ms of work, and twice the wall time
    with two sensors side by side. The limit is process-wide while the block runs (OpenCV's and
    OpenBLAS's settings are global), so sensors rendered from several Python threads at once share it.
    Entering costs about 25 us (threadpoolctl's controller is built once, at the first use, when the
    libraries a render needs are loaded)."""

    def __init__(self, threads: int | None):
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise GelsimError(f"threads {threads!r} is not a thread count; give an integer >= 1, or None to leave "
                              "numpy's and OpenCV's threading as the process has it")
        self.threads = threads
        self._controller = None
        self._saved: list = []

    def __enter__(self) -> "ThreadLimit":
        if self.threads is None:
            return self
        import cv2
        from threadpoolctl import ThreadpoolController

        if self._controller is None:
            self._controller = ThreadpoolController()
        limit = self._controller.limit(limits=self.threads)
        self._saved.append((cv2.getNumThreads(), limit))
        cv2.setNumThreads(self.threads)
        return self

    def __exit__(self, *exc) -> None:
        if self.threads is None:
            return
        import cv2

        cv_threads, limit = self._saved.pop()
        limit.restore_original_limits()
        cv2.setNumThreads(cv_threads)


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
