"""Process settings for one-core workers (gelsim.runtime)."""
import json
import subprocess
import sys

# Run in a fresh process: in the test session other libraries' threads (torch's, a writer thread)
# would count in this process's CPU time.
_PROBE = """
import json, time
import numpy as np
from gelsim.runtime import configure_worker, single_thread_blas
if {configure}:
    configure_worker()
a, b = np.random.default_rng(0).random((240, 55)), np.random.default_rng(1).random((55, 280))
x = np.random.default_rng(2).random((400, 400))
# OpenCV 5's import starts a thread that works for about 0.1 s CPU once, in the background: wait until
# the other threads are still (at most 5 s), so that only what the products leave running is counted.
import os
def others():
    ticks = []
    for t in sorted(os.listdir("/proc/self/task")):
        if int(t) != os.getpid():
            f = open(f"/proc/self/task/{{t}}/stat").read().rsplit(")", 1)[1].split()
            ticks.append(int(f[11]) + int(f[12]))
    return ticks
for _ in range(25):
    before = others()
    time.sleep(0.2)
    if others() == before:
        break
p0, t0 = time.process_time(), time.thread_time()
for _ in range(30):
    a @ b
    np.sort(x, axis=None)
print(json.dumps({{"proc": time.process_time() - p0, "thread": time.thread_time() - t0,
                  "set": single_thread_blas()}}))
"""


def _probe(configure: bool) -> dict:
    out = subprocess.run([sys.executable, "-c", _PROBE.format(configure=configure)], capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout)


def test_blas_products_leave_no_threads_spinning():
    """After configure_worker, mid-sized products between other work cost the process no more CPU than
    its own thread uses (OpenBLAS threads left spinning doubled a worker's CPU time)."""
    r = _probe(True)
    assert r["set"] >= 1                       # numpy's OpenBLAS at least (the wheels bundle one)
    assert r["proc"] < 1.3 * r["thread"] + 0.02, r
