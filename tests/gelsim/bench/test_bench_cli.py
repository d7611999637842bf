"""`gelsim bench` (gelsim/cli/bench_cmd.py)."""
from __future__ import annotations

import json

import pytest

from gelsim import bench
from gelsim.cli import main

from test_bench_levels import KEYS


def test_cli_json(tmp_path, capsys):
    rc = main(["bench", "--json", "--resolution", "64x48,80x60", "--frames", "4", "--precontact", "1", "--fabrics",
               "", "--levels", "fast", "--reference", "balanced", "--no-shortcut-study", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["settings"]["resolution"] for r in doc["runs"]] == [[64, 48], [80, 60]]
    for r in doc["runs"]:
        assert [lv["name"] for lv in r["levels"]] == ["fast", "balanced"]
        assert KEYS <= set(r["levels"][0])
        assert r["levels"][0]["kept_relief"] is None          # the sphere alone: no texture
    assert (tmp_path / "bench.md").exists() and (tmp_path / "bench_pareto.png").exists()
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2  # the reference's sphere, at each size

def test_cli_quick(tmp_path, capsys):
    rc = main(["bench", "--quick", "--json", "--levels", "fast", "--reference", "balanced", "--no-cache",
               "--out", str(tmp_path)])
    assert rc == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    assert run["settings"]["resolution"] == list(bench.QUICK["resolution"])
    assert run["settings"]["scenes"] == ["fabric50-press", "fabric50-slip"] and "shortcuts" not in run
    fast = run["levels"][0]
    assert 0 < fast["kept_relief"] < 1 and fast["contact_area_err"] > 0 and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("argv, msg", [
    (["--frames", "3", "--precontact", "2"], "frames"),
    (["--fabrics", "1,x"], "--fabrics"),
    (["--fabrics", "999"], "unknown fabric"),
    (["--resolution", "10x10"], "out of range for vitac"),
    (["--convergence", "--knobs", "colour"], "--knobs"),
    (["--resolution", ","], "--resolution"),
    (["--quick", "--levels", "ultra"], "unknown fidelity"),
])
def test_cli_bad_input(argv, msg, capsys, tmp_path):
    assert main(["bench", "--out", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gelsim: error:") and msg in err and err.count("\n") == 1
