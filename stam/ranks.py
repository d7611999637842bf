"""One line on every rank when a torchrun job stops on an error.

Under ``torchrun --nproc-per-node N -m stam train``, a rank that meets bad input (a truncated video, a
missing file) raises a StamError and prints its one line. The other ranks are then waiting in a
collective step (rank 0 pretrains while the others wait at a barrier) whose peer has gone: gloo raises
"Connection closed by peer" and each of them printed a 30-line traceback (issue 42), or torchrun's
agent ended them with SIGTERM. :func:`one_line_per_rank` turns both into the CLI's one line and status 2:

* the failing rank also leaves its message in the job's key-value store (torchrun's agent keeps it
  while the job lives), under :data:`ERROR_KEY`;
* a rank whose collective step fails, or that torchrun stops, says ``rank R of N stopped: rank Q
  failed: <its message>`` when the store still holds it, else that another rank failed and its own
  line says why.
"""
from __future__ import annotations

import contextlib
import signal

from gelsim.errors import GelsimError

from .errors import StamError

#: Where the first failing rank leaves its one line in the job's store.
ERROR_KEY = "stam/first-error"


def _group():
    """(rank, world, store) of the process group this process has joined, or None."""
    try:
        import torch.distributed as td

        if not (td.is_available() and td.is_initialized()):
            return None
        # torch has no public accessor for the default group's store (tests/test_private_names.py: THIRD_PARTY)
        from torch.distributed.distributed_c10d import _get_default_store

        return td.get_rank(), td.get_world_size(), _get_default_store()
    except (ImportError, RuntimeError, ValueError):
        return None


def _publish(group, message: str) -> None:
    rank, _, store = group
    try:
        if not store.check([ERROR_KEY]):
            store.set(ERROR_KEY, f"rank {rank} failed: {message}")
    except Exception:  # noqa: BLE001 - the store may be gone with its host; the rank's own line stands
        pass


def _peer_message(group) -> str | None:
    try:
        store = group[2]
        return store.get(ERROR_KEY).decode() if store.check([ERROR_KEY]) else None
    except Exception:  # noqa: BLE001 - the store lived in the failed rank (no torchrun agent)
        return None


class _Stopped(Exception):
    """torchrun's agent ended this rank (SIGTERM) after another rank failed."""


def _stopped_line(group, how: str) -> StamError:
    rank, world, _ = group
    peer = _peer_message(group)
    why = peer if peer else "another rank failed (its own line says why); fix that and rerun every rank"
    return StamError(f"rank {rank} of {world} {how}: {why}")


@contextlib.contextmanager
def one_line_per_rank():
    """Run a torchrun rank's work so that any stop is one line (see the module docstring); a process
    outside a torchrun job runs it unchanged."""
    previous = None
    try:
        previous = signal.getsignal(signal.SIGTERM)

        def stop(signum, frame):
            raise _Stopped()

        signal.signal(signal.SIGTERM, stop)
    except ValueError:  # not the main thread: leave the signal alone
        previous = None
    try:
        yield
    except GelsimError as e:  # (StamError is one) this rank's own bad input: said here, left for the others
        group = _group()
        if group is not None:
            _publish(group, str(e))
        raise
    except _Stopped:
        group = _group()
        if group is None:
            raise SystemExit(128 + signal.SIGTERM) from None
        raise _stopped_line(group, "was stopped by torchrun") from None
    except RuntimeError:
        # a collective step whose peer has gone (gloo: "Connection closed by peer"; NCCL: a watchdog abort)
        group = _group()
        if group is None:
            raise
        raise _stopped_line(group, "stopped") from None
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
