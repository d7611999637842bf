"""``gelsim generate --ray``: the same bytes as the local pool, on a real two-node Ray cluster
(tests/conftest.py), through a killed worker and a resume; and its bad input.

The tests that start a cluster are marked ``cluster`` (``make test-cluster``); the others need at
most Ray importable and run in the default suite.
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from gelsim.cli import main
from gelsim.dataset import (MAX_SEQUENCES_PER_TASK, TASKS_PER_WORKER, GenerateConfig, load_manifest, plan,
                            ray_sequences, sequences_per_task, verify)
from gelsim.fabrics import load_catalog

# Long enough (about 0.3 s a sequence on one core) for a test to catch a task running.
CONFIG = ["--fabrics", "4", "--sequences-per-fabric", "3", "--resolution", "128x96", "--fidelity", "fast",
          "--frames", "24-30", "--precontact", "2-3"]
GELSIM = str(Path(sys.executable).with_name("gelsim"))


def _gen_cli(out, *extra) -> subprocess.Popen:
    """``gelsim generate`` in a process of its own; its output goes to files (a pipe nobody reads while
    the test polls could fill up and stall it). :func:`_finish` collects it."""
    files = (tempfile.TemporaryFile(), tempfile.TemporaryFile())
    proc = subprocess.Popen([GELSIM, "generate", "--out", str(out), *CONFIG, "--json", *extra],
                            stdout=files[0], stderr=files[1])
    proc.output_files = files
    return proc


def _finish(proc: subprocess.Popen, timeout: float = 300) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of a :func:`_gen_cli` process."""
    rc = proc.wait(timeout=timeout)
    text = []
    for f in proc.output_files:
        f.seek(0)
        text.append(f.read().decode(errors="replace"))
        f.close()
    return rc, text[0], text[1]


def dataset_files(root: Path) -> dict[str, bytes | dict]:
    """Every file of a dataset by relative path: bytes, except the per-sequence records, whose
    timings change from run to run (compared without them). previews/dataset_stats.json names the
    dataset's own directory, which differs between two runs: it is compared without that name."""
    out = {}
    for p in sorted(root.rglob("*")):
        if not p.is_file():
            continue
        rel = p.relative_to(root).as_posix()
        if rel.startswith("records/"):
            r = json.loads(p.read_text())
            out[rel] = {k: v for k, v in r.items() if k not in ("timings_s", "seconds")}
        elif rel == "previews/dataset_stats.json":
            out[rel] = {k: v for k, v in json.loads(p.read_text()).items() if k != "dataset"}
        else:
            out[rel] = p.read_bytes()
    return out


def assert_same_dataset(a: Path, b: Path) -> None:
    fa, fb = dataset_files(a), dataset_files(b)
    assert sorted(fa) == sorted(fb)          # no file more or less (no probe file, no partial)
    different = [k for k in fa if fa[k] != fb[k]]
    assert different == []
    assert any(k.startswith("previews/") for k in fa) and any(k.startswith("videos/") for k in fa)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The dataset made by the local pool (2 workers)."""
    out = tmp_path_factory.mktemp("local") / "ds"
    assert main(["generate", "--out", str(out), *CONFIG, "--workers", "2", "--json"]) == 0
    assert verify(out) == []
    return out


# ---------------------------------------------------------------- bad input (no cluster)

def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("gelsim: error: ")
    for n in needles:
        assert n in err
    return err


def test_ray_not_installed_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets where Ray is not installed
    out = tmp_path / "ds"
    assert main(["generate", "--out", str(out), *CONFIG, "--ray"]) == 2
    _one_line_error(capsys, "make ray", "pip install ray==2.60.0")
    assert not out.exists()


def test_unreachable_address_is_one_line_and_writes_nothing(tmp_path, capsys, free_port):
    pytest.importorskip("ray", reason="Ray is not installed (make ray)")
    out = tmp_path / "ds"
    t0 = time.monotonic()
    assert main(["generate", "--out", str(out), *CONFIG, "--ray", f"127.0.0.1:{free_port}"]) == 2
    _one_line_error(capsys, "no Ray head answers", "ray start --head")
    assert time.monotonic() - t0 < 30
    assert not out.exists()


@pytest.mark.parametrize("args, needle", [
    (["--ray", "head:port"], "is malformed"),
    (["--ray", "127.0.0.1:1", "--workers", "2"], "drop --workers"),
])
def test_bad_ray_options_one_line(tmp_path, capsys, args, needle):
    pytest.importorskip("ray", reason="Ray is not installed (make ray)")
    out = tmp_path / "ds"
    assert main(["generate", "--out", str(out), *CONFIG, *args]) == 2
    _one_line_error(capsys, needle)
    assert not out.exists()


# ---------------------------------------------------------------- the task itself (no Ray needed)

def test_sequences_per_task_is_one_for_small_runs_and_bounded():
    assert sequences_per_task(12, 2) == 1
    assert sequences_per_task(5_000, 2) == MAX_SEQUENCES_PER_TASK
    assert sequences_per_task(5_000, 1_600) == 1
    assert sequences_per_task(500_000, 1_600) == MAX_SEQUENCES_PER_TASK
    for n, cpus in ((100, 3), (10_000, 64)):
        k = sequences_per_task(n, cpus)
        assert n // k >= TASKS_PER_WORKER * cpus or k == 1


def test_a_retried_task_keeps_the_sequences_its_first_attempt_finished(reference, tmp_path):
    """What Ray reruns after a worker died half-way through a task: the finished sequences are
    read back, the others generated (the same bytes)."""
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    m = load_manifest(out)
    config = GenerateConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in m["options"].items()})
    specs = [s for s in plan(config, len(load_catalog())) if s.fabric_id == 2]
    lost = specs[1]
    (out / "records" / f"{lost.id}.json").unlink()
    (out / m["sequences"][[s["id"] for s in m["sequences"]].index(lost.id)]["video"]).unlink()
    kept = {s.id: (out / "records" / f"{s.id}.json").stat().st_mtime_ns for s in specs if s is not lost}
    records = ray_sequences(config, str(out), specs)
    assert [r["id"] for r in records] == [s.id for s in specs]
    assert {i: (out / "records" / f"{i}.json").stat().st_mtime_ns for i in kept} == kept
    assert_same_dataset(reference, out)


# ---------------------------------------------------------------- on a two-node cluster

@pytest.mark.cluster
def test_two_nodes_write_the_same_bytes_as_the_local_pool(ray_cluster, reference, tmp_path):
    out = tmp_path / "ds"
    proc = _gen_cli(out, "--ray", ray_cluster.address)
    raylets = set()
    while proc.poll() is None:  # which nodes' raylets run our tasks
        raylets |= {int(Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[1])
                    for p in ray_cluster.task_workers("ray_sequences") if Path(f"/proc/{p}").exists()}
        time.sleep(0.05)
    rc, stdout, stderr = _finish(proc)
    assert rc == 0, stderr
    summary = json.loads(stdout)
    assert summary["complete"] and summary["sequences"] == 12
    assert len(raylets) == 2          # both nodes ran sequences
    assert_same_dataset(reference, out)


@pytest.mark.cluster
def test_a_killed_worker_is_retried_and_the_run_ends_identical(ray_cluster, reference, tmp_path):
    out = tmp_path / "ds"
    proc = _gen_cli(out, "--ray", ray_cluster.address)
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and proc.poll() is None and time.monotonic() < deadline:
        running = ray_cluster.task_workers("ray_sequences")
        if running and any((out / "records").glob("*.json")):  # mid-run: some sequences done, one running
            killed = running[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    rc, stdout, stderr = _finish(proc)
    assert killed is not None, "no task was caught running"
    assert rc == 0, stderr
    assert json.loads(stdout)["complete"], stdout
    assert_same_dataset(reference, out)
    assert verify(out) == []


@pytest.mark.cluster
def test_resume_on_ray_redoes_only_what_is_missing(ray_cluster, reference, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    m = load_manifest(out)
    lost = m["sequences"][5]
    (out / lost["video"]).unlink()
    (out / "records" / f"{lost['id']}.json").unlink()
    before = {p.name: p.stat().st_mtime_ns for p in (out / "videos").rglob("*.mp4")}
    rc, stdout, stderr = _finish(_gen_cli(out, "--ray", ray_cluster.address))
    assert rc == 0, stderr
    assert_same_dataset(reference, out)
    after = {p.name: p.stat().st_mtime_ns for p in (out / "videos").rglob("*.mp4")}
    rewritten = [k for k in after if after[k] != before.get(k)]
    assert rewritten == [Path(lost["video"]).name]


@pytest.mark.cluster
@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("unshare"),
                    reason="a node with its own view of the file system needs root (unshare --mount)")
def test_a_node_that_cannot_see_the_output_is_one_line_before_any_work(tmp_path, local_ray_cluster):
    shared = tmp_path / "shared"
    shared.mkdir()
    cluster = local_ray_cluster(nodes=1, cpus=1)
    # The second node runs in its own mount namespace, with an empty tmpfs over `shared`: it sees
    # another directory at the same path, as a node without the NFS mount would.
    cluster.add_node(prefix=["unshare", "--mount", "--propagation", "private", "sh", "-c",
                             'mount -t tmpfs tmpfs "$0" && exec "$@"', str(shared)])
    out = shared / "ds"
    rc, stdout, stderr = _finish(_gen_cli(out, "--ray", cluster.address))
    cluster.stop()
    assert rc == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "is not shared by every Ray node" in lines[0], stderr
    assert lines[0].count("No such file or directory") == 1     # the one node without it, named
    assert [p.name for p in out.iterdir()] == []   # no manifest, no sequence, no probe file left
