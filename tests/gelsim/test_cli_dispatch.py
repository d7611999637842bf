"""The shared command-line dispatcher (gelsim/cli/__init__.py)."""
import subprocess
import sys


def test_closed_pipe_ends_quietly():
    # `gelsim fabrics list --json | head`: the reader is gone before the command writes (closing our
    # end at once makes the first write fail: the interpreter takes a moment to start). No traceback.
    proc = subprocess.Popen([sys.executable, "-m", "gelsim", "fabrics", "list", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    _, err = proc.communicate(timeout=120)
    assert err.decode() == "" and proc.returncode == 141
