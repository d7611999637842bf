"""What a first run on a machine does before its first frame, said in one line.

The imprint's and the optics' per-pixel kernels are compiled by numba the first time they run on a machine
(10-25 s of one core for a fast frame, with the machine's load; docs/quickstart.md) and cached on disk, next to the installed
package (``__pycache__``) or, where that is read only, in numba's user cache; later runs load them in about
half a second. Until then a first ``gelsim render`` looked hung. :func:`announce_compiles` says it on
stderr once, when the first compile starts, in whichever process that is: the command's own or one of
the workers of ``gelsim generate``, which are forked from it and share its flag.
"""
from __future__ import annotations

import multiprocessing
from typing import Callable

_announced = None   # a shared flag (multiprocessing.Value), made before any worker is forked
_notify: Callable[[str], None] | None = None


class _FirstCompile:
    """A numba event listener that calls the notifier once, on the first compile of any process sharing
    the flag."""

    def on_start(self, event) -> None:
        if _notify is None or _announced is None:
            return
        with _announced.get_lock():
            if _announced.value:
                return
            _announced.value = 1
        _notify("first run on this machine: compiling the imprint and optics kernels (10-30 s on 2 cores; "
                "numba keeps them on disk for the next runs) ...")

    def on_end(self, event) -> None:
        pass


def announce_compiles(notify: Callable[[str], None]) -> None:
    """Call ``notify(line)`` once, when a numba kernel of this process (or of a worker forked from it later)
    is first compiled rather than loaded from the disk cache. Idempotent; the last ``notify`` given is used."""
    global _announced, _notify
    _notify = notify
    if _announced is not None:
        return
    from numba.core import event

    class Listener(_FirstCompile, event.Listener):
        pass

    _announced = multiprocessing.Value("b", 0)
    event.register("numba:compile", Listener())
