"""gelsim.firstrun: a first run's kernel compilation is said once, in whichever process compiles first."""
from __future__ import annotations

import multiprocessing

import numba
import pytest

from gelsim import firstrun


@pytest.fixture
def fresh(monkeypatch):
    """The module's flag and notifier as before any command, restored afterwards."""
    monkeypatch.setattr(firstrun, "_announced", None)
    monkeypatch.setattr(firstrun, "_notify", None)
    yield


def _new_kernel(k: int):
    # a function numba has never seen (no cache=True): calling it compiles it
    return numba.njit(lambda x: x * k + 1)


def test_the_first_compile_is_said_once(fresh):
    lines = []
    firstrun.announce_compiles(lines.append)
    assert _new_kernel(2)(3) == 7 and _new_kernel(3)(3) == 10
    assert len(lines) == 1 and lines[0].startswith("first run on this machine: compiling the imprint and optics")
    firstrun.announce_compiles(lines.append)            # idempotent: no second listener, no second line
    assert _new_kernel(4)(3) == 13 and len(lines) == 1


def _compile_in_child():
    _new_kernel(5)(1)


def test_a_forked_worker_shares_the_flag(fresh):
    """The workers of `gelsim generate` are forked after the command announced: the one that compiles first
    says it, and the others (and the parent) stay quiet."""
    lines = []
    firstrun.announce_compiles(lines.append)
    child = multiprocessing.get_context("fork").Process(target=_compile_in_child)
    child.start()
    child.join(120)
    assert child.exitcode == 0 and firstrun._announced.value == 1
    _new_kernel(6)(1)
    assert lines == []       # said by the child (on its stderr), not again here
