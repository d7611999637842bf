import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stam import cli
from stam.data import TactileDataset
from stam.errors import StamError
from stam.experiment import PAPER_TABLES, PER_SEQUENCE_KEYS, markdown_table, run_experiment


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
    assert "| STAM |" in t1 and "(76.50)" in t1 and "(67.23)" in t1 and "95% CI" in t1
    assert "(72.00)" in (out / "table2.md").read_text()
    assert (out / "tables.png").stat().st_size > 1000
    assert res["resolution"]["test_sequences"] == 8 and "Resolution: on 8 test sequences" in (
        out / "differences.md").read_text()
    assert res["test_size_warning"].startswith("stam experiment: warning: the test split has 8 sequences")
    test_ids = sorted(s.id for s in TactileDataset(tiny_experiment["data"]).split("test"))
    # n in {2, 3}: a noisy window of 3 frames after a detected onset at 1 holds the clean window of 2
    reader = TactileDataset(tiny_experiment["data"])
    onset_1 = sum(reader.onset(s, 96) == 1 for s in reader.split("test"))
    assert onset_1 > 0 and res["precontact"]["windows"] == res["precontact"]["sequences"] == onset_1
    assert "Frames before contact, contact frames matched" in (out / "differences.md").read_text()
    for c in res["cells"]:
        assert 0.0 <= c["test_acc"] <= 1.0 and c["test_count"] == 8
        assert "test_correct" not in c  # results.json leaves the per-sequence lists in the cells' files
        full = json.loads((out / "cells" / c["setting"] / f"n{c['frames']}" / c["model"] / "seed0"
                           / "result.json").read_text())
        assert sorted(full["test_ids"]) == test_ids and len(full["test_predictions"]) == 8
        assert np.mean(full["test_correct"]) == pytest.approx(c["test_acc"])
        assert res["tables"][c["setting"]][c["model"]][c["frames"]]["mean"] == pytest.approx(100 * c["test_acc"])

    def again(**kw):
        return run_experiment(str(tiny_experiment["data"]), out, str(tiny_experiment["preset"]), log=None, **kw)

    def cell_path(m):
        return out / "cells" / "clean" / "n2" / m / "seed0" / "result.json"

    # Resumable: a second run retrains nothing; every cell is read back from result.json.
    cell = json.loads(cell_path("cnn").read_text())
    cell["test_correct"] = [1 - v for v in cell["test_correct"]]  # a retrained cell would overwrite this
    cell_path("cnn").write_text(json.dumps(cell))
    flipped = 100 * np.mean(cell["test_correct"])
    assert again()["tables"]["clean"]["cnn"][2]["mean"] == pytest.approx(flipped)
    assert f"| CNNs | {flipped:.1f} [" in (out / "table1.md").read_text()

    # A result.json from before per-sequence results were kept: completed from its best.pt.
    old = json.loads(cell_path("stam").read_text())
    stripped = {k: v for k, v in old.items() if k not in PER_SEQUENCE_KEYS}
    cell_path("stam").write_text(json.dumps(stripped))
    again()
    assert json.loads(cell_path("stam").read_text()) == old
    # ... unless its best.pt disagrees with the recorded accuracy: tested on another dataset.
    cell_path("stam").write_text(json.dumps(stripped | {"test_acc": old["test_acc"] + 0.25}))
    with pytest.raises(StamError, match="another dataset"):
        again()
    # ... and without best.pt it is retrained.
    cell_path("stam").write_text(json.dumps(stripped))
    (cell_path("stam").parent / "best.pt").unlink()
    again()
    assert "test_correct" in json.loads(cell_path("stam").read_text())
    assert (cell_path("stam").parent / "best.pt").is_file()
    # A cell tested on other sequences is refused.
    cell = json.loads(cell_path("cnn_sa").read_text())
    cell_path("cnn_sa").write_text(json.dumps(cell | {"test_ids": ["f009-s0000"] + cell["test_ids"][1:]}))
    with pytest.raises(StamError, match="other sequences"):
        again()
    cell_path("cnn_sa").write_text(json.dumps(cell))

    # A second seed of one cell: its sequences pair with the first seed's.
    two = again(seeds=2, models=["cnn"], frames=[2], settings=["clean"])
    row = two["tables"]["clean"]["cnn"][2]
    assert row["seeds"] == 2 and row["mean"] == pytest.approx(np.mean(row["values"]))
    assert two["seed_check"]["cells"] == 1 and two["differences"] == []


def test_experiment_attention_at_conv5(tiny_experiment, tmp_path, capsys):
    import shutil

    import torch

    out = tmp_path / "conv5"
    out.mkdir()
    shutil.copytree(tiny_experiment["out"] / "pretrain", out / "pretrain")   # reused: same settings
    args = ["experiment", "--data", str(tiny_experiment["data"]), "--out", str(out), "--preset",
            str(tiny_experiment["preset"]), "--models", "cnn", "cnn_sa", "--frames", "2", "--settings", "clean",
            "--attention-at", "conv5", "--json"]
    assert cli.main(args) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["cells"] == 2 and res["pretrain"]["reused"]
    # Features at conv5 (96 px: 5 x 5, pool5 2 x 2), in a file of their own.
    (path,) = out.glob("features-*.pt")
    assert path.name.endswith("-conv5.pt")
    feats = torch.load(path, weights_only=True)
    assert next(iter(feats.values())).shape[-2:] == (5, 5)
    cell = out / "cells" / "clean" / "n2" / "cnn_sa" / "seed0"
    assert json.loads((cell / "config.json").read_text())["attention_at"] == "conv5"
    assert "with `attention_at = conv5`" in (out / "table1.md").read_text()   # the tables say so
    # The same --out at pool5 would mix the two settings' cells: refused in one line, exit 2.
    assert cli.main(args[:-3]) == 2
    err = capsys.readouterr().err.strip().splitlines()   # (the small-split warning, then the error)
    assert err[-1].startswith("stam: error:") and "attention_at = 'conv5'" in err[-1]
    assert not any(e.startswith("Traceback") for e in err)
    # benchmarks/attention_use.py reads the features the cells were trained on, not the newest file:
    # a pool5 file from the first run, written later, is passed over.
    import runpy

    decoy = next((tiny_experiment["out"]).glob("features-*px-crop*[0-9].pt"))
    shutil.copy(decoy, out / decoy.name)
    script = Path(__file__).resolve().parents[2] / "benchmarks" / "attention_use.py"
    old_argv = sys.argv
    sys.argv = [str(script), str(out), "--settings", "clean", "--json"]
    try:
        with pytest.raises(SystemExit) as done:
            runpy.run_path(str(script), run_name="__main__")
    finally:
        sys.argv = old_argv
    assert done.value.code in (0, None)
    use = json.loads(capsys.readouterr().out)
    assert use["features"] == path.name
    (row,) = use["rows"]
    assert row["model"] == "cnn_sa" and row["frames"] == 2 and row["spatial"] > 0


def test_markdown_table_layout():
    tables = {"clean": {m: {n: {"mean": 50.0, "ci95": [47.25, 52.75], "std": 1.5, "seeds": 3, "values": []}
                            for n in range(2, 8)} for m in PAPER_TABLES["clean"]}}
    text = markdown_table(tables, "clean", ["cnn", "cnn_sa", "stam"], list(range(2, 8)), 3, 1100)
    lines = [l for l in text.splitlines() if l.startswith("|")]
    assert lines[0] == "| Models | n=2 | n=3 | n=4 | n=5 | n=6 | n=7 |"
    assert lines[2].startswith("| CNNs | 50.0 [47.2, 52.8] (67.23) |") and lines[4].endswith("(81.93) |")
    assert "mean over 3 seeds [95% CI: bootstrap over the 1,100 test sequences" in text


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


def test_experiment_cli_warns_on_a_small_test_split_and_prints_the_resolution(tiny_experiment, capsys):
    # Every cell is done: this only reads them back and rewrites the tables.
    args = ["experiment", "--data", str(tiny_experiment["data"]), "--out", str(tiny_experiment["out"]),
            "--preset", str(tiny_experiment["preset"])]
    assert cli.main(args) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("stam experiment: warning: the test split has 8 sequences (under 500)")
    assert "### Paired differences" in captured.out and "Resolution: on 8 test sequences and 1 seed" in captured.out


def test_help_says_how_big_the_test_split_must_be(capsys):
    from stam.stats import required_test_size

    for argv in (["--help"], ["experiment", "--help"]):
        with pytest.raises(SystemExit) as exit_:
            cli.main(argv)
        assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert "95% CIs" in text  # the command list, where argparse %-formats the help
    assert f"3 points: {required_test_size(0.03):,}" in text and "With fewer than 500 test sequences it warns" in text
