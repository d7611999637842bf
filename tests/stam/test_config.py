"""stam's presets and `stam train`'s choice of one (the CUDA check is mocked)."""
import json

import pytest

import stam.train

from gelsim.errors import GelsimError
from stam import cli
from stam.config import (CPU_PRESET, GPU_PRESET, TrainConfig, default_preset, load_preset, parse_sets,
                         preset_names, resolve_train)

TINY_TRAIN_PRESET = """
[pretrain]
width = 0.25
image_size = 64
epochs = 1
batch_size = 32
frame_stride = 3
[train]
image_size = 64
width = 0.25
freeze_backbone = true
hidden = 64
epochs = 2
batch_size = 16
optimizer = "adam"
lr = 0.002
progress = false
"""


def test_shipped_presets_load_and_validate():
    assert {"cpu", "paper"} <= set(preset_names())
    cpu, paper = load_preset("cpu"), load_preset("paper")
    assert cpu.name == "cpu" and cpu.train.freeze_backbone and cpu.train.width == cpu.pretrain.width == 0.5
    assert cpu.train.image_size == 128 and cpu.train.crop == 0.5 and cpu.sweep.seeds == 3
    assert paper.train.width == 1.0 and paper.train.image_size == 224 and not paper.train.freeze_backbone
    assert paper.sweep.frames == (2, 3, 4, 5, 6, 7)
    with pytest.raises(Exception):
        cpu.train.lr = 1.0                                     # frozen
    assert cpu.pretrain.seed == 0 and cpu.pretrain.lr == 3e-4   # one backbone for every cell; lr: docs/stam.md


def test_preset_file_errors(tmp_path):
    cases = {
        "flat.toml": ("lr = 0.1\n", "outside a section"),
        "section.toml": ("[training]\nlr = 0.1\n", "unknown key 'training'"),
        "range.toml": ("[train]\nwidth = 0\n", "width: 0 is out of range"),
        "choice.toml": ('[train]\noptimizer = "rmsprop"\n', "'rmsprop' is not one of"),
        "model.toml": ('[train]\nmodel = "vgg"\n', "model 'vgg' unknown"),
        "sweep.toml": ('[sweep]\nsettings = ["dirty"]\n', "'dirty' unknown"),
        "type.toml": ('[pretrain]\nepochs = "ten"\n', "expected an integer"),
        "seed.toml": ('[pretrain]\nseed = -1\n', "seed: -1 is out of range"),
    }
    for name, (text, match) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(GelsimError, match=match):
            load_preset(str(tmp_path / name))
    with pytest.raises(GelsimError, match="unknown config 'gpu9'"):
        load_preset("gpu9")


def test_overrides_and_sets_are_validated_like_files():
    assert parse_sets(["lr=1e-3", "model=cnn", "freeze_backbone=true", "epochs=4"]) == {
        "lr": 0.001, "model": "cnn", "freeze_backbone": True, "epochs": 4}
    cfg = resolve_train(load_preset("cpu").train, {"lr": 1, "epochs": None})
    assert cfg.lr == 1.0 and isinstance(cfg.lr, float) and cfg.epochs == 12
    for bad, match in (({"epochs": "two"}, "expected an integer"), ({"frames": 0}, "out of range"),
                       ({"learning_rate": 1}, "unknown key")):
        with pytest.raises(GelsimError, match=match):
            resolve_train(TrainConfig(), bad)
    with pytest.raises(GelsimError, match="key=value"):
        parse_sets(["lr"])


def test_default_preset_follows_cuda():
    assert default_preset("auto", False) == CPU_PRESET == "cpu"
    assert default_preset("auto", True) == GPU_PRESET == "paper"
    assert default_preset("cuda", True) == "paper"
    assert default_preset("cpu", True) == "cpu"          # a GPU machine told to train on the CPU


@pytest.mark.parametrize("cuda, expected", [(False, "cpu"), (True, "paper")])
def test_train_without_preset_picks_by_cuda_and_says_so(synth, tmp_path, capsys, monkeypatch, cuda, expected):
    monkeypatch.setattr(stam.train, "cuda_available", lambda: cuda)
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "r"), "--dry-run", "--json"]) == 0
    cap = capsys.readouterr()
    res = json.loads(cap.out)
    assert res["preset"] == expected and res["preset_chosen_by_default"] is True
    assert res["config"] == {**res["config"], **{k: v for k, v in vars(load_preset(expected).train).items()
                                                 if k not in ("data", "out", "preset", "pretrained", "progress")}}
    assert res["config"]["pretrained"] == str(tmp_path / "r" / "pretrain" / "backbone.pt")
    note = cap.err.strip().splitlines()
    assert len(note) == 1 and f"using the {expected} config" in note[0]
    # An explicit preset is used as given, silently.
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "r"), "--dry-run", "--json",
                     "--preset", "paper" if expected == "cpu" else "cpu"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["preset_chosen_by_default"] is False and cap.err == ""


def test_set_device_cpu_on_a_gpu_machine_gets_the_cpu_preset(synth, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(stam.train, "cuda_available", lambda: True)
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "r"), "--dry-run", "--json",
                     "--set", "device=cpu"]) == 0
    assert json.loads(capsys.readouterr().out)["preset"] == "cpu"


def test_train_pretrains_saves_config_and_resumes(synth, tmp_path, capsys, monkeypatch):
    preset = tmp_path / "tiny.toml"
    preset.write_text(TINY_TRAIN_PRESET.replace("[train]", "seed = 1\n[train]"))   # the backbone's seed
    out = tmp_path / "run"
    base = ["train", "--data", str(synth), "--out", str(out), "--frames", "3", "--quiet", "--json"]
    assert cli.main(base + ["--preset", str(preset)]) == 0
    first = json.loads(capsys.readouterr().out)
    assert (out / "pretrain" / "backbone.pt").is_file() and first["pretrain_result"]["reused"] is False
    assert stam.train.load_checkpoint(out / "pretrain" / "backbone.pt")["settings"]["seed"] == 1
    saved = json.loads((out / "config.json").read_text())
    assert saved["preset"] == str(preset) and saved["pretrained"] == str(out / "pretrain" / "backbone.pt")
    assert saved["epochs"] == 2 and saved["frames"] == 3 and saved["width"] == 0.25 and saved["freeze_backbone"]
    # --resume without --preset takes the preset from config.json, even where the default would differ.
    monkeypatch.setattr(stam.train, "cuda_available", lambda: True)
    assert cli.main(base + ["--resume", "--epochs", "3"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["preset"] == str(preset) and again["pretrain_result"]["reused"] is True
    assert load_checkpoint_epoch(out / "last.pt") == 3
    assert json.loads((out / "config.json").read_text())["epochs"] == 3
    with open(out / "log.csv") as f:
        assert [int(line.split(",")[0]) for line in f.read().splitlines()[1:]] == [1, 2, 3]


def load_checkpoint_epoch(path):
    from stam.train import load_checkpoint

    return load_checkpoint(path)["epoch"]


@pytest.mark.slow
def test_paper_preset_commands_run_on_a_tiny_dataset(tmp_path, capsys):
    """The GPU run's commands (docs/performance.md, "Rendering in batches, on a GPU"), at toy size on the CPU: the dataset rendered by
    the torch backend in batches, then one epoch of the paper preset's model (full AlexNet at 224 px,
    fine-tuned end to end) on it. About 20 s on 2 cores, mostly the 58 M-parameter model."""
    from gelsim.cli import main as gelsim_main

    data, run = tmp_path / "data", tmp_path / "run"
    assert gelsim_main(["generate", "--out", str(data), "--fabrics", "2", "--sequences-per-fabric", "3",
                        "--split", "1:1:1", "--resolution", "96x72", "--frames", "8-10", "--precontact", "1-2",
                        "--backend", "torch", "--device", "cpu", "--batch", "4", "--workers", "1",
                        "--no-previews", "--json"]) == 0
    capsys.readouterr()
    assert cli.main(["train", "--preset", "paper", "--data", str(data), "--out", str(run), "--epochs", "1",
                     "--pretrained", "none", "--set", "workers=0", "--quiet", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    paper = load_preset("paper").train
    assert res["config"]["image_size"] == paper.image_size == 224 and res["config"]["width"] == paper.width == 1.0
    assert res["epochs"] == 1 and res["train_windows"] > 0 and (run / "best.pt").is_file()


def test_the_first_line_describes_the_run_not_the_preset(synth, tmp_path, capsys, monkeypatch):
    """`--pretrained none --epochs 1` was announced as the preset's 16 pretraining epochs and 12 of
    training (#42)."""
    monkeypatch.setattr(stam.train, "cuda_available", lambda: False)
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "r"), "--dry-run", "--json",
                     "--pretrained", "none", "--epochs", "1", "--model", "cnn", "--frames", "3"]) == 0
    first = capsys.readouterr().err.splitlines()[0]
    assert "using the cpu config" in first
    assert "cnn, windows of 3 frames" in first and "backbone from random weights" in first
    assert "trained for 1 epoch " in first and "pretrained on single frames" not in first
    assert cli.main(["train", "--data", str(synth), "--out", str(tmp_path / "r"), "--dry-run", "--json",
                     "--pretrained", str(tmp_path / "b.pt"), "--set", "start=zero"]) == 0
    first = capsys.readouterr().err.splitlines()[0]
    assert f"backbone from {tmp_path / 'b.pt'}" in first and "from frame 0" in first
