"""Ray, for running independent units of work on a cluster: the sequences of ``gelsim generate --ray``
and the cells of ``stam experiment --ray``.

Ray is an optional extra (``make ray``, or ``pip install ray==2.60.0``); nothing here imports it
until :func:`connect` is called. Ray does the scheduling, the retries of tasks whose worker
died and the placement on nodes; this module only

* joins or starts a cluster (:func:`connect`), with one-line errors for an address that does not
  answer or Ray not installed;
* checks that a directory is shared by every node before any work is sent (:func:`check_shared_dir`):
  each node writes a file there that the driver reads back, and reads one the driver wrote;
* runs a function over items as Ray tasks and yields the results as they finish
  (:func:`run_unordered`), with a task's own error (a GelsimError) passed on as one line and a
  task whose worker died more than ``max_retries`` times reported by its item's name.

Output is written by the tasks to the shared directory, never sent back through Ray; what a task
returns is its small record.
"""
from __future__ import annotations

import contextlib
import os
import secrets
import socket
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from .errors import GelsimError

#: ``--ray`` without an address: start a Ray instance on this machine for the run.
LOCAL = "local"
#: Ray's default port of the head node's GCS (``ray start --head``), for an address without a port.
DEFAULT_PORT = 6379
#: Seconds to wait for a TCP answer from the head before calling an address unreachable (Ray itself
#: retries for a minute or more before it gives up).
CONNECT_TIMEOUT_S = 5.0
#: Seconds for every node's shared-directory probe: it starts one worker process per node (1-3 s
#: each on an idle node), so a minute means a node is stuck, not slow.
PROBE_TIMEOUT_S = 60.0
#: Retries of a task whose worker process or node died (Ray's ``max_retries``): a sequence or cell
#: that kills its worker four times is a bug to report, not bad luck.
MAX_RETRIES = 3
#: Tasks in flight per cluster CPU: enough queued that a freed CPU never waits for the driver, few
#: enough that a 100-node cluster's driver does not hold hundreds of thousands of task references.
IN_FLIGHT_PER_CPU = 2
INSTALL_HINT = "run `make ray` in the clone, or `pip install ray==2.60.0`"


def import_ray():
    """The ``ray`` module, or a one-line GelsimError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise GelsimError(f"--ray needs Ray, which is not installed; {INSTALL_HINT}") from None
    return ray


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``host[:port]`` or ``ray://host:port`` address; None when it names no
    host to try (``auto``)."""
    if address == "auto":
        return None
    rest = address.split("://", 1)[-1].rstrip("/")
    host, _, port = rest.rpartition(":") if ":" in rest else (rest, "", "")
    try:
        return host.strip("[]"), int(port) if port else DEFAULT_PORT
    except ValueError:
        raise GelsimError(f"--ray {address!r} is malformed; give HOST:PORT of the head node (e.g. 10.0.0.1:6379), "
                          "'auto' or nothing") from None


def _check_reachable(address: str) -> None:
    hp = _host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as e:
        raise GelsimError(f"--ray {address}: no Ray head answers at {hp[0]}:{hp[1]} ({e.strerror or e}); start one "
                          "with `ray start --head` there, or check the address and the firewall") from None


def _token_available() -> bool:
    """Whether a Ray authentication token is at hand: ``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or
    Ray's default file ``~/.ray/auth_token`` (where ``ray start --head`` puts the one it generates)."""
    path = os.environ.get("RAY_AUTH_TOKEN_PATH") or os.path.expanduser("~/.ray/auth_token")
    return bool(os.environ.get("RAY_AUTH_TOKEN")) or os.path.isfile(path)


@contextlib.contextmanager
def connect(address: str, *, num_cpus: int | None = None) -> Iterator[Any]:
    """``with connect(address) as ray:`` a connected ``ray`` module.

    ``address``: :data:`LOCAL` starts a Ray instance on this machine with ``num_cpus`` CPUs (all by
    default) for the duration of the block; ``auto`` joins the cluster ``ray start`` made on this
    machine (or ``RAY_ADDRESS``); ``HOST:PORT`` joins that head node. If Ray is already initialised in
    this process (a notebook, a test), that connection is used as is and left open."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    if address != LOCAL:
        if num_cpus is not None:
            raise GelsimError(f"--workers goes with the local pool or a local Ray cluster (--ray alone); the "
                              f"cluster at {address} has its own CPUs; drop --workers")
        _check_reachable(address)
    # log_to_driver off: Ray would print its workers' and raylets' lines (a worker that died, say) on
    # this process's stdout, which --json keeps for one JSON document. They stay in Ray's session logs.
    kwargs: dict[str, Any] = dict(include_dashboard=False, configure_logging=False, log_to_driver=False)
    if (address == LOCAL or _token_available()) and "RAY_AUTH_MODE" not in os.environ:
        # Token authentication: Ray 2.60's default for an instance it starts (said explicitly, it prints
        # no line about it), and what a cluster `ray start --head` made expects from its drivers, which
        # Ray does not turn on by itself when joining. Ray reads the mode into its config when imported:
        # refreshed here as Ray itself does when it turns token mode on. An explicit RAY_AUTH_MODE is kept.
        os.environ["RAY_AUTH_MODE"] = "token"
        from ray._raylet import Config

        Config.initialize("")
    try:
        if address == LOCAL:
            ray.init(address="local", num_cpus=num_cpus, **kwargs)
        else:
            ray.init(address=address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        where = "a local Ray instance" if address == LOCAL else f"the Ray cluster at {address!r}"
        fix = ("start one with `ray start --head`, or give its address (--ray HOST:6379)" if address == "auto"
               else "check that the Ray versions of this machine and the cluster match (`ray --version`)")
        raise GelsimError(f"cannot join {where} ({first}); {fix}") from None
    try:
        # Ray prints the errors its raylets report (a worker that died) on sys.stdout, which --json keeps
        # for one JSON document: they go to stderr while connected.
        with contextlib.redirect_stdout(sys.stderr):
            yield ray
    finally:
        ray.shutdown()


def worker_nodes(ray) -> list[dict]:
    """The alive nodes that can run a task (at least one CPU), as ``ray.nodes()`` lists them."""
    return [n for n in ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) > 0]


def cluster_cpus(ray) -> int:
    return int(ray.cluster_resources().get("CPU", 0))


def _probe(root: str, token: str, node_id: str) -> dict:
    """On one node: read the driver's probe file in ``root``, write this node's; report what was seen."""
    import gelsim

    root_p = Path(root)
    seen = None
    try:
        seen = (root_p / f".ray-probe-{token}").read_text()
    except OSError as e:
        seen = f"<{e.strerror or e}>"
    error = None
    try:
        (root_p / f".ray-probe-{token}-{node_id}").write_text(token)
    except OSError as e:
        error = e.strerror or str(e)
    return {"host": socket.gethostname(), "saw": seen, "write_error": error, "version": gelsim.__version__}


def check_shared_dir(ray, root: str | Path, option: str = "--out") -> int:
    """Check that ``root`` is the same directory on every node that can run a task: each node reads a
    file the driver wrote there and writes one the driver reads back. Returns the number of nodes
    checked; raises a GelsimError naming the nodes that cannot see it, or whose gelsim version differs
    (a node with another version would write other bytes)."""
    import gelsim

    root = Path(root)
    token = secrets.token_hex(8)
    mine = root / f".ray-probe-{token}"
    mine.write_text(token)
    nodes = worker_nodes(ray)
    if not nodes:
        mine.unlink(missing_ok=True)
        raise GelsimError("the Ray cluster has no node with a CPU to run tasks on; add a worker node "
                          "(`ray start --address HEAD:6379`)")
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    probe = ray.remote(_probe)
    # num_cpus=0: the probe must run even on a node whose CPUs are busy with another job.
    refs = {n["NodeID"]: probe.options(num_cpus=0, max_retries=0, scheduling_strategy=NodeAffinitySchedulingStrategy(
        n["NodeID"], soft=False)).remote(str(root), token, n["NodeID"]) for n in nodes}
    bad, versions = [], set()
    try:
        try:
            answers = dict(zip(refs, ray.get(list(refs.values()), timeout=PROBE_TIMEOUT_S)))
        except ray.exceptions.GetTimeoutError:
            raise GelsimError(f"a Ray node did not answer the shared-directory check within {PROBE_TIMEOUT_S:.0f} s; "
                              "check the cluster (`ray status`)") from None
        for n in nodes:
            a = answers[n["NodeID"]]
            name = f"{n.get('NodeManagerAddress', '?')} ({a['host']})"
            back = root / f".ray-probe-{token}-{n['NodeID']}"
            if a["saw"] != token or a["write_error"] or not back.is_file() or back.read_text() != token:
                why = a["write_error"] or ("it sees no such file" if a["saw"] != token else "its file is not here")
                bad.append(f"{name}: {why}")
            if a["version"] != gelsim.__version__:
                versions.add(f"{name} has gelsim {a['version']}")
    finally:
        for p in root.glob(f".ray-probe-{token}*"):
            p.unlink(missing_ok=True)
    if bad:
        raise GelsimError(f"{option} {root} is not shared by every Ray node ({'; '.join(bad)}); put it on storage "
                          "every node mounts at the same path (NFS, Lustre, a cloud file system)")
    if versions:
        raise GelsimError(f"the Ray nodes run another gelsim than this machine's {gelsim.__version__} "
                          f"({'; '.join(sorted(versions))}); install the same version everywhere")
    return len(nodes)


def _task_error(ray, e: Exception, label: str) -> Exception:
    """The exception to raise for a task that failed: its own GelsimError as one line, a worker or
    node that kept dying as one line naming the item, anything else as Ray raised it."""
    if isinstance(e, ray.exceptions.RayTaskError):
        cause = e.cause
        if isinstance(cause, GelsimError):
            return type(cause)(str(cause))
        return e
    if isinstance(e, (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                      ray.exceptions.LocalRayletDiedError, ray.exceptions.ObjectLostError)):
        return GelsimError(f"{label}: its Ray worker died {MAX_RETRIES + 1} times ({type(e).__name__}); see the "
                           "Ray logs (/tmp/ray/session_latest/logs) and rerun the same command to resume")
    return e


def run_unordered(ray, fn: Callable, items: Iterable, *, args: tuple = (), label: Callable[[Any], str] = str,
                  num_cpus: float = 1, num_gpus: float = 0, max_retries: int = MAX_RETRIES) -> Iterator[Any]:
    """``fn(*args, item)`` for every item as a Ray task (``num_cpus``/``num_gpus`` each); yields the
    results as they finish. A task whose worker dies is rerun by Ray up to ``max_retries`` times; a task
    that raises is not retried (the same input would raise again) and its error ends the run."""
    remote = ray.remote(fn).options(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=max_retries,
                                    retry_exceptions=False)
    shared = [ray.put(a) for a in args]  # sent to the object store once, not with every task
    todo = iter(items)
    pending: dict = {}
    limit, checked = 0, 0.0

    def fill() -> None:
        nonlocal limit, checked
        if time.monotonic() - checked > 10:  # nodes come and go: follow the cluster's size
            limit, checked = max(2, IN_FLIGHT_PER_CPU * cluster_cpus(ray)), time.monotonic()
        while len(pending) < limit:
            item = next(todo, None)
            if item is None:
                return
            pending[remote.remote(*shared, item)] = item

    fill()
    try:
        while pending:
            refs = list(pending)
            ray.wait(refs, num_returns=1)  # blocks until one is done; then take all that are
            ready, _ = ray.wait(refs, num_returns=len(refs), timeout=0)
            for ref in ready:
                item = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as e:  # Ray's task, worker and node errors, sorted by _task_error
                    raise _task_error(ray, e, label(item)) from None
                yield result
            fill()
    finally:
        for ref in pending:  # an error or Ctrl-C: do not leave the cluster busy with this run's tasks
            ray.cancel(ref, force=True)


def node_description() -> str:
    """``host (pid)`` of the process this runs in, for errors raised inside a task."""
    return f"{socket.gethostname()} (pid {os.getpid()})"
