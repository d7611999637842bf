import csv
import json
import math

import pytest
import torch

from stam import cli
from stam.evaluate import evaluate
from stam.config import TrainConfig, resolve_train
from stam.train import STALL_EPOCH, load_checkpoint, pretrain, stalled, train


def _cfg(synth, out, **kw):
    base = {"data": str(synth), "out": str(out), "model": "stam", "frames": 3, "image_size": 96, "width": 0.25,
            "epochs": 2, "batch_size": 8, "optimizer": "adam", "lr": 0.001, "lr_schedule": "constant",
            "progress": False}
    return resolve_train(TrainConfig(), base | kw)


def test_tiny_end_to_end_training_beats_chance(synth, tmp_path):
    # Whole pipeline (video -> cache -> windows -> AlexNet + SA + temporal attention -> head), backbone
    # trained end to end from scratch; 4 classes, chance 25 %.
    torch.manual_seed(0)
    res = train(_cfg(synth, tmp_path / "run", epochs=12, width=0.25, dropout=0.0), log=None)
    ev = evaluate(res["best"], split="test")
    val = evaluate(res["best"], split="val", out=tmp_path / "ev")
    acc = (ev["accuracy"] * ev["count"] + val["accuracy"] * val["count"]) / (ev["count"] + val["count"])
    assert acc >= 0.6, (ev["accuracy"], val["accuracy"])
    assert (tmp_path / "ev" / "confusion-val.png").stat().st_size > 1000
    assert sum(sum(r) for r in val["confusion"]) == val["count"] == 16


def _resume_matches_straight(synth, tmp_path, **kw):
    """Train 4 epochs in one run (tmp_path/a) and 2 + 2 with a resume (tmp_path/b); the last
    checkpoints' weights must agree. Returns both checkpoints."""
    straight = train(_cfg(synth, tmp_path / "a", epochs=4, **kw), log=None)
    train(_cfg(synth, tmp_path / "b", epochs=2, **kw), log=None)
    resumed = train(_cfg(synth, tmp_path / "b", epochs=4, **kw), resume=True, log=None)
    a, b = load_checkpoint(straight["last"]), load_checkpoint(resumed["last"])
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=1e-5, atol=1e-6)
    return a, b


def test_resume_continues_from_checkpoint(synth, tmp_path):
    kw = {"model": "cnn_sa", "freeze_backbone": True, "seed": 3}
    a, b = _resume_matches_straight(synth, tmp_path, **kw)
    assert a["epoch"] == b["epoch"] == 4
    with open(tmp_path / "b" / "log.csv") as f:
        assert [int(r["epoch"]) for r in csv.DictReader(f)] == [1, 2, 3, 4]
    assert json.loads((tmp_path / "b" / "config.json").read_text())["epochs"] == 4
    with pytest.raises(Exception, match="different config"):
        train(_cfg(synth, tmp_path / "b", epochs=5, lr=0.1, **kw), resume=True, log=None)


def test_resume_uses_the_checkpoints_frozen_backbone(synth, tmp_path):
    # After a resume the frozen backbone's features must come from the checkpoint's (pretrained)
    # backbone, not from the freshly built model's random one.
    from stam import models

    torch.manual_seed(123)
    backbone = models.build("cnn", 3, 4, width=0.25, image_size=96).backbone
    torch.save({"backbone": backbone.state_dict()}, tmp_path / "backbone.pt")
    _resume_matches_straight(synth, tmp_path, model="cnn", freeze_backbone=True, seed=3,
                             pretrained=str(tmp_path / "backbone.pt"))


def test_resume_with_more_epochs_follows_the_longer_cosine(synth, tmp_path):
    kw = {"model": "cnn", "freeze_backbone": True, "lr_schedule": "cosine", "lr": 0.002}
    train(_cfg(synth, tmp_path / "b", epochs=2, **kw), log=None)
    train(_cfg(synth, tmp_path / "b", epochs=4, **kw), resume=True, log=None)
    with open(tmp_path / "b" / "log.csv") as f:
        lr = [float(r["lr"]) for r in csv.DictReader(f)]
    # epochs 1-2 on the 2-epoch cosine, 3-4 where a 4-epoch cosine is: 0.002 x (1 + cos(pi t / 4)) / 2
    assert lr == pytest.approx([0.002, 0.001, 0.001, 0.002 * (1 + math.cos(3 * math.pi / 4)) / 2], rel=1e-6)


def test_config_errors_exit_2(synth, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[train]\nmodel = "stam"\nlearning_rate = 0.1\n')
    assert cli.main(["train", "--config", str(bad), "--data", str(synth), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown key 'learning_rate'" in err and "bad.toml" in err and "\n" not in err
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "o"), "--set", "epochs=two"]) == 2
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "o"), "--frames", "11",
                     "--pretrained", "none", "--set", "image_size=96", "--set", "width=0.25", "--quiet"]) == 2
    assert "outside" in capsys.readouterr().err
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "o"), "--preset", "cpu",
                     "--set", "width=0.25", "--quiet"]) == 2
    assert "pretrained at width 0.5 but trained at width 0.25" in capsys.readouterr().err
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "o2"), "--resume"]) == 2


def test_checkpoints_load_weights_only(synth, tmp_path):
    res = train(_cfg(synth, tmp_path / "r", epochs=1, freeze_backbone=True), log=None)
    for name in ("best", "last"):
        ck = torch.load(res[name], weights_only=True)
        assert ck["config"]["model"] == "stam" and "model" in ck


def test_stalled_flags_chance_level_after_the_third_epoch():
    # The cpu preset's measured runs (100 classes): 1.0-1.1% after epoch 3 stalled, 3.6-5.3% took off.
    assert stalled(0.011, 100, STALL_EPOCH) and not stalled(0.036, 100, STALL_EPOCH)
    assert not stalled(0.011, 100, STALL_EPOCH - 1) and not stalled(0.011, 100, STALL_EPOCH + 1)
    assert stalled(0.45, 4, STALL_EPOCH) and not stalled(0.55, 4, STALL_EPOCH)


def test_pretraining_that_does_not_move_is_told_to_lower_its_learning_rate(synth, tmp_path):
    # At lr 1e-12 the weights stay at their initial values, so training accuracy stays near chance (4 classes).
    lines = []
    res = pretrain(str(synth), tmp_path, width=0.25, image_size=64, epochs=STALL_EPOCH, batch_size=32,
                   lr=1e-12, frame_stride=4, progress=False, log=lines.append)
    assert res["val_acc"] < 0.5
    warned = [line for line in lines if "still at chance" in line]
    assert len(warned) == 1 and "lr 1e-12" in warned[0] and "try 3.3e-13" in warned[0], lines


def test_a_stalled_pretraining_is_told_on_stderr_without_a_log(synth, tmp_path, capsys):
    assert cli.main(["pretrain", "--data", str(synth), "--out", str(tmp_path), "--width", "0.25",
                     "--image-size", "64", "--epochs", str(STALL_EPOCH), "--batch-size", "32", "--lr", "1e-12",
                     "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["val_acc"] < 0.5 and "still at chance" in err
