"""A real Ray cluster on this machine for the ``cluster`` tests: a head node on 127.0.0.1 and worker
nodes joined with ``ray start --address``, one CPU each, under a temporary directory of its own.

It is stopped by killing the processes whose command line names that directory (the GCS, raylets
and agents of this cluster only; their workers exit with their raylet): never ``ray stop``, which
would stop every Ray instance on the machine.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

RAY = str(Path(sys.executable).with_name("ray"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _parent(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def _pids() -> list[int]:
    return [int(p) for p in os.listdir("/proc") if p.isdigit()]


class LocalRayCluster:
    """``ray start --head`` plus ``nodes - 1`` nodes joined to it, ``cpus`` CPUs each."""

    def __init__(self, nodes: int = 2, cpus: int = 1):
        # Short: Ray's Unix socket paths live under it and must stay under 108 bytes.
        self.temp = Path(tempfile.mkdtemp(prefix="gsray", dir="/tmp"))
        self.port = _free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.cpus = cpus
        self._blocking: list[subprocess.Popen] = []
        self._joined = 0
        self._start(["--head", f"--port={self.port}", f"--temp-dir={self.temp}", "--include-dashboard=false"])
        for _ in range(nodes - 1):
            self.add_node()

    def _start(self, args: list[str], prefix: list[str] | None = None, block: bool = False) -> None:
        cmd = [*(prefix or []), RAY, "start", *args, "--node-ip-address=127.0.0.1", f"--num-cpus={self.cpus}",
               "--object-store-memory=100000000", "--disable-usage-stats"]
        # Token authentication, as Ray's default for a new cluster; said explicitly, since a node joined
        # with `ray start --address` does not turn it on by itself.
        env = self.env()
        if block:  # stays in the foreground (a node in another mount namespace: see add_node)
            self._blocking.append(subprocess.Popen(cmd + ["--block"], env=env, stdout=subprocess.DEVNULL,
                                                   stderr=subprocess.DEVNULL))
            return
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=180)
        if r.returncode != 0:
            self.stop()
            pytest.fail(f"ray start failed: {r.stderr[-2000:]}")

    @staticmethod
    def env() -> dict:
        """The environment of this cluster's processes and of the test's drivers."""
        return {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token"}

    def add_node(self, prefix: list[str] | None = None) -> None:
        """Join one more node; ``prefix`` runs ``ray start`` under another command (``unshare ...``)."""
        before = self.alive_nodes()
        self._joined += 1
        # Its own temporary directory (inside the cluster's): two raylets on one machine, two sessions.
        node_temp = self.temp / f"n{self._joined}"
        self._start([f"--address={self.address}", f"--temp-dir={node_temp}"], prefix, block=prefix is not None)
        deadline = time.monotonic() + 120
        while self.alive_nodes() <= before:
            if time.monotonic() > deadline:
                self.stop()
                pytest.fail("a Ray node did not join within 120 s")
            time.sleep(1)

    def alive_nodes(self) -> int:
        """Nodes the head counts as alive (``ray list nodes`` would need the dashboard)."""
        code = ("import ray, sys; ray.init(address=sys.argv[1], configure_logging=False, log_to_driver=False); "
                "print(sum(n['Alive'] for n in ray.nodes()))")
        r = subprocess.run([sys.executable, "-c", code, self.address], capture_output=True, text=True, timeout=120,
                           env=self.env())
        return int(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 and r.stdout.strip() else 0

    def own_processes(self) -> list[int]:
        """Pids of this cluster's daemons (their command lines name its temporary directory) and of
        their children (agents and workers, which retitle themselves ``ray::...``)."""
        me = str(self.temp)
        pids = _pids()
        own = {p for p in pids if me in _cmdline(p) and p != os.getpid()}
        parents = {p: _parent(p) for p in pids}
        grown = True
        while grown:
            children = {p for p, parent in parents.items() if parent in own} - own
            own |= children
            grown = bool(children)
        return sorted(own)

    def task_workers(self, function: str) -> list[int]:
        """Pids of this cluster's worker processes now running a task of ``function``: Ray titles a
        worker ``ray::<function>`` while it runs one."""
        return [p for p in self.own_processes() if _cmdline(p).startswith(f"ray::{function}")]

    def stop(self) -> None:
        for p in self._blocking:
            p.terminate()
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid in self.own_processes():
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + 10
            while self.own_processes() and time.monotonic() < deadline:
                time.sleep(0.2)
        for p in self._blocking:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(self.temp, ignore_errors=True)


@pytest.fixture
def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (just now)."""
    return _free_port()


@pytest.fixture
def local_ray_cluster():
    """The :class:`LocalRayCluster` class, for a test that needs a cluster of its own; stops what it made."""
    pytest.importorskip("ray", reason="Ray is not installed (make ray)")
    made = []

    def make(**kwargs) -> LocalRayCluster:
        made.append(LocalRayCluster(**kwargs))
        return made[-1]

    yield make
    for c in made:
        c.stop()


@pytest.fixture(scope="session")
def ray_cluster():
    """A two-node Ray cluster (head + one joined node, one CPU each) on 127.0.0.1, shared by the
    session's cluster tests and stopped at its end."""
    pytest.importorskip("ray", reason="Ray is not installed (make ray)")
    cluster = LocalRayCluster(nodes=2, cpus=1)
    yield cluster
    cluster.stop()


@pytest.fixture(scope="session")
def synth(tmp_path_factory):
    """A tiny stam dataset: 4 fabrics x 20 sequences x 10 frames at 96 x 72 px, H.264 (splits 14/4/2
    per fabric). Shared by tests/stam and tests/benchmarks."""
    from stam.synthetic import make_synthetic_dataset

    return make_synthetic_dataset(tmp_path_factory.mktemp("synth"), num_fabrics=4, seqs_per_fabric=20,
                                  num_frames=10, size=(96, 72), seed=1)
