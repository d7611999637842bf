import json
import subprocess
import sys

import pytest

from stam import cli
from stam.experiment import PAPER_TABLES, markdown_table, run_experiment


def test_info_json(capsys):
    assert cli.main(["info", "--model", "cnn", "--frames", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["params"] == 57_413_540 and out["paper_params_m"] == 57.4
    assert cli.main(["info", "--model", "stam", "--frames", "3", "--width", "0.5", "--image-size", "128", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["paper_params_m"] is None and 0 < out["params"] < 57_413_540


def test_experiment_tables_and_resume(tiny_experiment):
    out, res = tiny_experiment["out"], tiny_experiment["result"]
    assert len(res["cells"]) == 12  # 3 models x n in {2, 3} x clean/noisy x 1 seed
    t1 = (out / "table1.md").read_text()
    assert "| STAM |" in t1 and "(76.50)" in t1 and "(67.23)" in t1
    assert "(72.00)" in (out / "table2.md").read_text()
    assert (out / "tables.png").stat().st_size > 1000
    for c in res["cells"]:
        assert 0.0 <= c["test_acc"] <= 1.0 and c["test_count"] == 8
    # Resumable: a second run recomputes nothing (every cell is read back from result.json).
    marker = out / "cells" / "clean" / "n2" / "cnn" / "seed0" / "result.json"
    cell = json.loads(marker.read_text())
    cell["test_acc"] = 0.123  # a recomputation would overwrite this
    marker.write_text(json.dumps(cell))
    again = run_experiment(str(tiny_experiment["data"]), out, str(tiny_experiment["preset"]), log=None)
    assert any(c["test_acc"] == 0.123 for c in again["cells"])
    assert "12.3" in (out / "table1.md").read_text()


def test_markdown_table_layout():
    tables = {"clean": {m: {n: {"mean": 50.0, "std": 1.5, "seeds": 3, "values": []} for n in range(2, 8)}
                        for m in PAPER_TABLES["clean"]}}
    text = markdown_table(tables, "clean", ["cnn", "cnn_sa", "stam"], list(range(2, 8)), 3)
    lines = [l for l in text.splitlines() if l.startswith("|")]
    assert lines[0] == "| Models | n=2 | n=3 | n=4 | n=5 | n=6 | n=7 |"
    assert lines[2].startswith("| CNNs | 50.0 ± 1.5 (67.23) |") and lines[4].endswith("(81.93) |")


def test_explain_writes_maps(tiny_experiment, tmp_path, capsys):
    cells = tiny_experiment["out"] / "cells" / "clean" / "n3"
    args = ["explain", "--out", str(tmp_path), "--json"]
    for m in ("cnn", "cnn_sa", "stam"):
        args += ["--checkpoint", str(cells / m / "seed0" / "best.pt")]
    assert cli.main(args) == 0
    res = json.loads(capsys.readouterr().out)
    assert (tmp_path / "gradcam.png").stat().st_size > 1000 and (tmp_path / "temporal.png").stat().st_size > 1000
    assert len(res["temporal_top3"]) == 3 and set(res["predictions"]) == {"cnn", "cnn_sa", "stam"}


def test_experiment_bad_input(synth, tmp_path, capsys):
    assert cli.main(["experiment", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert cli.main(["experiment", "--data", str(synth), "--out", str(tmp_path / "o"), "--preset", "gpu9"]) == 2
    assert cli.main(["experiment", "--data", str(synth), "--out", str(tmp_path / "o"), "--frames", "12"]) == 2
    errs = capsys.readouterr().err.strip().splitlines()
    assert len(errs) == 3 and all(e.startswith("stam: error:") for e in errs)


def test_stam_error_is_a_gelsim_error_and_one_line(tmp_path, capsys):
    from gelsim.errors import GelsimError
    from stam.data import load_manifest
    from stam.errors import StamError

    assert issubclass(StamError, GelsimError)
    with pytest.raises(StamError, match="does not exist"):
        load_manifest(tmp_path / "missing")
    assert cli.main(["onsets", "--data", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("stam: error:") and err.count("\n") == 1


def test_closed_pipe_ends_quietly():
    # `stam ... | head`: the reader is gone before the command writes. Closing our end at once
    # makes the first write fail (the interpreter takes a second or more to start).
    argv = ["-m", "stam", "info", "--model", "stam", "--readings", "--json"]
    proc = subprocess.Popen([sys.executable, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    _, err = proc.communicate(timeout=120)
    assert err.decode() == "" and proc.returncode == 141
