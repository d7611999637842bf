"""The study of issue 48: the protocols of `stam experiment` (trained noisy, trained clean and tested noisy,
the backbone pretrained on all frames), stam.study's readings of a run, and benchmarks/nuisance_study.py
end to end on tiny synthetic datasets."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gelsim.errors import GelsimError
from stam import study
from stam.experiment import analyse, run_experiment

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "nuisance_study.py"


def test_paper_pattern_from_the_tables():
    # docs/nuisance.md, section 1: the CNN loses 11.8 points beyond the missing contact frame, STAM 2.5
    assert round(study.paper_cost("cnn"), 1) == -11.8 and round(study.paper_cost("stam"), 1) == -2.5
    assert study.paper_gap() == pytest.approx(study.paper_cost("stam") - study.paper_cost("cnn"))
    assert round(study.paper_gap(), 1) == 9.3
    assert study.paper_cost("oracle") is None


def test_the_cuts_keep_what_the_issue_keeps():
    study.check_cuts([2, 4, 6], ["none", "handheld"], ["handheld"])
    for frames, levels, control, match in (([2, 3, 4], ["none", "x"], ["x"], "n = 6"),
                                           ([2, 4, 6], ["none"], ["x"], "two levels"),
                                           ([2, 4, 6], ["none", "x"], [], "control")):
        with pytest.raises(GelsimError, match=match):
            study.check_cuts(frames, levels, control)


def _cells(gain_noisy: float, gain_transfer: float, n_seq=300, frames=(2, 4, 6)):
    """Made-up cells of cnn and oracle in the three settings, one seed: the CNN right on 40% of the
    sequences clean and 30% from frame 0; the oracle as the CNN, plus right on a further share of the
    sequences from frame 0 (``gain_noisy`` trained noisy, ``gain_transfer`` trained clean)."""
    ids = [f"f{i % 20:03d}-s{i:04d}" for i in range(n_seq)]
    u = np.random.default_rng(0).permutation((np.arange(n_seq) + 0.5) / n_seq)   # exact shares
    cells = []
    for n in frames:
        for setting, p, gain in (("clean", 0.4, 0), ("noisy", 0.3, gain_noisy), ("transfer", 0.3, gain_transfer)):
            cnn = (u < p).astype(int)
            oracle = ((u < p) | ((u >= p) & (u < p + gain))).astype(int)
            for model, c in (("cnn", cnn), ("oracle", oracle)):
                cells.append({"setting": setting, "frames": n, "model": model, "seed": 0, "test_ids": ids,
                              "test_correct": c.tolist()})
    onsets = {t: 2 for t in ids}   # noisy n = 4, 6 hold the clean windows of 2, 4 frames
    return analyse(cells, ["cnn", "oracle"], list(frames), ["clean", "noisy", "transfer"], ids, onsets)


def test_control_verdict_and_mechanism_rows():
    passed = study.control_verdict(_cells(0.10, 0.2))
    assert passed["passed"] and passed["noisy"]["mean"]["mean"] == pytest.approx(10.0)
    assert passed["transfer"]["mean"]["mean"] == pytest.approx(20.0) and set(passed["noisy"]["per_n"]) == {2, 4, 6}
    text = study.control_markdown("x", passed)
    assert "Control passed (trained noisy, tested noisy; trained clean, tested noisy)" in text
    assert "| trained noisy, tested noisy |" in text
    failed = study.control_verdict(_cells(0.0, 0.0))
    text = study.control_markdown("x", failed)
    assert not failed["passed"] and "Control failed" in text and "gains at most" in text
    # the mechanism table: the CNN's cost (noisy(n) − clean(n − 1): 30% against 40%) and the oracle's gain
    rows = study.mechanism_rows({"none": _cells(0.093, 0.0)})
    cnn = next(r for r in rows if (r["protocol"], r["model"]) == ("noisy", "cnn"))
    oracle = next(r for r in rows if (r["protocol"], r["model"]) == ("noisy", "oracle"))
    assert cnn["cost"]["mean"] == pytest.approx(-10.0) and cnn["paper_pattern"] is True   # holds -11.8
    assert oracle["gain_over_cnn"]["mean"] == pytest.approx(100 * 28 / 300)   # (k + 0.5) / 300 in [0.3, 0.393)
    assert oracle["paper_pattern"] is True and oracle["contrast"]["mean"] == pytest.approx(oracle["gain_over_cnn"]["mean"])
    transfer = next(r for r in rows if (r["protocol"], r["model"]) == ("transfer", "oracle"))
    assert transfer["gain_over_cnn"]["mean"] == 0 and transfer["paper_pattern"] is False
    md = study.mechanism_markdown(rows)
    assert md.count("\n| none |") == 4 and "-11.8" in md and "+9.3" in md
    assert any(s.startswith("Training protocol at none") for s in study.mechanism_summary(rows))


def test_protocols_of_the_sweep(synth, tiny_preset, tmp_path):
    """noisy trains and tests from frame 0; transfer tests the clean models from frame 0 (and trains them
    when not asked for); the backbone is pretrained on all frames when told; a clean model trained anew
    is tested anew."""
    from stam.data import TactileDataset
    from stam.evaluate import evaluate

    out = tmp_path / "run"
    kw = dict(models=["cnn", "oracle"], frames=[2, 3], seeds=1, log=None)
    res = run_experiment(str(synth), out, str(tiny_preset), settings=["noisy", "transfer"],
                         pretrain_overrides={"contact_only": False}, **kw)
    assert sorted({(c["setting"], c["model"]) for c in res["cells"]}) == [
        (s, m) for s in ("clean", "noisy", "transfer") for m in ("cnn", "oracle")]
    for setting, start in (("clean", "contact"), ("noisy", "zero")):
        config = json.loads((out / "cells" / setting / "n2" / "oracle" / "seed0" / "config.json").read_text())
        assert config["start"] == start and config["fusion"] == "onset" and config["model"] == "oracle"
    assert not (out / "cells" / "transfer" / "n2" / "cnn" / "seed0" / "config.json").exists()   # not trained
    transfer = json.loads((out / "cells" / "transfer" / "n2" / "cnn" / "seed0" / "result.json").read_text())
    assert transfer["trained_as"] == "clean"
    ev = evaluate(out / "cells" / "clean" / "n2" / "cnn" / "seed0" / "best.pt", split="test", start="zero",
                  out=tmp_path / "ev")
    assert transfer["test_correct"] == [int(p == y) for p, y in zip(ev["predictions"], ev["labels"])]
    assert ev["start"] == "zero" and ev["trained_start"] == "contact"
    # pretrained on every training frame, the frames before contact included
    data = TactileDataset(synth)
    assert res["pretrain"]["train_frames"] == sum(s.num_frames for s in data.split("train"))
    assert res["precontact_transfer"]["tested"] == "transfer" and "transfer − clean, CNN" in open(
        out / "differences.md").read()
    assert (out / "table2_transfer.md").is_file()
    # a rerun reuses every cell; a clean cell trained anew is tested anew in transfer
    def stamps():
        return {p: p.stat().st_mtime_ns for p in (out / "cells").glob("*/n*/*/seed0/result.json")}

    before = stamps()
    os.remove(out / "cells" / "clean" / "n2" / "cnn" / "seed0" / "result.json")
    run_experiment(str(synth), out, str(tiny_preset), settings=["clean", "transfer"],
                   pretrain_overrides={"contact_only": False}, **kw)
    changed = {str(p.relative_to(out / "cells")) for p, t in stamps().items() if before[p] != t}
    assert changed == {"clean/n2/cnn/seed0/result.json", "transfer/n2/cnn/seed0/result.json"}


MICRO_PRESET = """
[pretrain]
width = 0.125
image_size = 64
epochs = 1
batch_size = 32
lr = 0.002
[train]
image_size = 64
width = 0.125
freeze_backbone = true
hidden = 32
window_hidden = 16
epochs = 1
batch_size = 16
optimizer = "adam"
lr = 0.002
threads = 1
progress = false
"""


def test_nuisance_study_end_to_end(tmp_path):
    """The driver on a micro synthetic dataset (3 fabrics x 10 sequences of 9 frames, 64 x 48 px; onsets at frame 1 or 2) linked in as
    every level, so that the levels hold the same sequences as gelsim generate's do: the control first, each
    level, the comparison, the mechanism table, the costs; the cuts it refuses."""
    from stam.synthetic import make_synthetic_dataset

    # seed 2: two of the three test sequences touch at frame 2 (detected there too), so noisy n = 4 and 6 hold
    # the clean windows of 2 and 4 frames and the matched cost of the frames before contact exists
    micro = make_synthetic_dataset(tmp_path / "micro", num_fabrics=3, seqs_per_fabric=10, num_frames=9, size=(64, 48),
                                   seed=2)
    preset = tmp_path / "micro.toml"
    preset.write_text(MICRO_PRESET)
    data = tmp_path / "data"
    data.mkdir()
    for name in ("control-x", "none", "x"):
        (data / name).symlink_to(micro)
    out = tmp_path / "out"
    args = [sys.executable, str(SCRIPT), "--data", str(data), "--out", str(out), "--preset", str(preset),
            "--levels", "none", "x", "--control-levels", "x", "--control-onset", "detected", "true",
            "--models", "cnn", "oracle",
            "--frames", "2", "4", "6", "--control-frames", "2", "4", "6", "--seeds", "1"]
    plan = subprocess.run(args + ["--plan"], capture_output=True, text=True)
    assert plan.returncode == 0, plan.stderr
    assert "control-x" in plan.stdout and "18 cells trained, 6 tested only" in plan.stdout and not out.exists()
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.index("Positive control") < r.stdout.index("level none done")   # the control comes first
    report = (out / "report.md").read_text()
    assert report.index("## 1. Positive control") < report.index("## 2. Each level") < report.index("## 3. Mechanism")
    assert "| Oracle |" in report and "x_vs_none.md" in report and (out / "x_vs_none.md").is_file()
    rows = json.loads((out / "mechanism.json").read_text())
    assert {(r["level"], r["protocol"]) for r in rows} == {(lv, p) for lv in ("none", "x") for p in ("noisy", "transfer")}
    costs = json.loads((out / "costs.json").read_text())
    assert set(costs) == {"control-x", "control-x-true-onset", "none", "x"}
    # the true-onset control: the same all-frames backbone (copied, not pretrained again), its own windows
    assert ((out / "control-x" / "pretrain" / "backbone.pt").read_bytes()
            == (out / "control-x-true-onset" / "pretrain" / "backbone.pt").read_bytes())
    assert "true onsets" in (out / "control.md").read_text()
    config = json.loads((out / "control-x-true-onset" / "cells" / "clean" / "n2" / "oracle" / "seed0" / "config.json")
                        .read_text())
    assert config["onset"] == "true"
    assert costs["none"]["trained_cells"] == 18 and costs["none"]["tested_cells"] == 6 and costs["none"]["pretrain_s"] > 0
    # each level pretrains its own backbone, on all of its training frames
    for name in ("none", "x"):
        pretrain = json.loads((out / name / "results.json").read_text())["pretrain"]
        assert pretrain["path"] == str(out / name / "pretrain" / "backbone.pt") and pretrain["train_frames"] == 21 * 9
    bad = subprocess.run(args + ["--frames", "2", "3"], capture_output=True, text=True)   # the last --frames counts
    assert bad.returncode == 2 and "n = 4, 6" in bad.stderr and "Traceback" not in bad.stderr


def test_the_small_study_preset_is_the_cpu_preset_with_half_its_pretraining():
    import dataclasses

    from stam.config import load_preset

    small, cpu = load_preset("study-small"), load_preset("cpu")
    assert small.train == cpu.train
    assert small.pretrain == dataclasses.replace(cpu.pretrain, epochs=cpu.pretrain.epochs // 2)
    assert set(small.sweep.models) <= set(study.STUDY_MODELS) and set(study.REQUIRED_FRAMES) <= set(small.sweep.frames)
