"""``stam experiment --ray``: the sweep's cells as Ray tasks on a two-node cluster (tests/conftest.py)
give the local sweep's results, and finished cells are kept on a rerun."""
import json

import pytest

from stam.cli import main
from stam.experiment import run_experiment

COMPARED = ("test_acc", "val_acc", "best_epoch", "test_count", "test_ids", "test_predictions", "test_correct")


def _cells(out):
    return {p.parent.relative_to(out).as_posix(): json.loads(p.read_text())
            for p in sorted((out / "cells").rglob("result.json"))}


@pytest.mark.cluster
def test_cells_on_ray_give_the_local_results_and_are_kept(ray_cluster, tiny_experiment, tmp_path):
    out = tmp_path / "ray"
    res = run_experiment(str(tiny_experiment["data"]), out, str(tiny_experiment["preset"]), log=None,
                         ray=ray_cluster.address)
    local, remote = _cells(tiny_experiment["out"]), _cells(out)
    assert sorted(remote) == sorted(local) and len(local) == 12
    for key in local:
        assert {k: remote[key][k] for k in COMPARED} == {k: local[key][k] for k in COMPARED}, key
    for name in ("table1.md", "table2.md", "differences.md"):
        assert (out / name).read_text() == (tiny_experiment["out"] / name).read_text()
    assert len(res["cells"]) == 12

    # A rerun on Ray trains nothing: every cell's result.json is kept as it is.
    stamps = {p: p.stat().st_mtime_ns for p in (out / "cells").rglob("result.json")}
    run_experiment(str(tiny_experiment["data"]), out, str(tiny_experiment["preset"]), log=None,
                   ray=ray_cluster.address)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps


def test_unreachable_ray_address_is_one_line_before_any_training(tiny_experiment, tmp_path, capsys, free_port):
    pytest.importorskip("ray", reason="Ray is not installed (make ray)")
    out = tmp_path / "never"
    assert main(["experiment", "--data", str(tiny_experiment["data"]), "--out", str(out),
                 "--preset", str(tiny_experiment["preset"]), "--ray", f"127.0.0.1:{free_port}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("stam: error: ") and "no Ray head answers" in err[0]
    assert not out.exists()
