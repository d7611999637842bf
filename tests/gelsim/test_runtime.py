"""Process settings for one-core workers (gelsim.runtime)."""
import time

import numpy as np

from gelsim.runtime import configure_worker, single_thread_blas


def test_blas_products_leave_no_threads_spinning():
    """After configure_worker, a mid-sized product followed by other work costs the process no more
    CPU than the thread itself uses (OpenBLAS threads left spinning doubled a worker's CPU time)."""
    configure_worker()
    assert single_thread_blas() >= 1          # numpy's OpenBLAS at least (the wheels bundle one)
    a, b = np.random.default_rng(0).random((240, 55)), np.random.default_rng(1).random((55, 280))
    x = np.random.default_rng(2).random((400, 400))
    p0, t0 = time.process_time(), time.thread_time()
    for _ in range(30):
        a @ b
        np.sort(x, axis=None)
    proc, thread = time.process_time() - p0, time.thread_time() - t0
    assert proc < 1.3 * thread + 0.02, (proc, thread)
