"""benchmarks/bench_resolution.py end to end on the tiny synthetic dataset: subset, presets, table, resume."""
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from stam.config import load_preset
from stam.data import TactileDataset

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_resolution.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_resolution", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_subset_keeps_the_first_sequences_of_each_fabric_and_split(bench, synth, tmp_path):
    sub = bench.subset(Path(synth), tmp_path / "sub", {"train": 3, "val": 1, "test": 2})
    data = TactileDataset(sub)
    fabrics = data.num_classes
    assert [len(data.split(s)) for s in ("train", "val", "test")] == [3 * fabrics, fabrics, 2 * fabrics]
    full = json.loads((Path(synth) / "manifest.json").read_text())["sequences"]
    first_train = [s["id"] for s in full if s["split"] == "train" and s["fabric_id"] == full[0]["fabric_id"]][:3]
    assert [s.id for s in data.split("train")][:3] == first_train
    assert data.frames(data.split("test")[0], 64).shape[1:] == (64, 64, 3)   # the videos are reachable


def test_point_preset_is_the_cpu_preset_at_another_size(bench, tmp_path):
    cfg = load_preset(str(bench.point_preset(tmp_path, 256, 0.25, 3)))
    cpu = load_preset("cpu")
    assert (cfg.pretrain.image_size, cfg.train.image_size, cfg.train.crop, cfg.pretrain.epochs) == (256, 256, 0.25, 3)
    assert cfg.train.hidden == cpu.train.hidden and cfg.pretrain.width == cpu.pretrain.width
    assert cfg.sweep == cpu.sweep


def test_two_points_with_paired_differences_and_resume(bench, synth, tmp_path, monkeypatch, capsys):
    argv = ["bench_resolution.py", "--data", str(synth), "--out", str(tmp_path / "out"), "--points", "64:1,64:0.5",
            "--base", "64:1", "--per-fabric", "4,2,2", "--pretrain-epochs", "1", "--models", "cnn",
            "--frames", "2", "--json"]
    monkeypatch.setattr(sys, "argv", argv)
    assert bench.main() == 0
    first = json.loads(capsys.readouterr().out)
    rows = first["points"]
    assert [(r["px"], r["crop"]) for r in rows] == [(64, 1.0), (64, 0.5)]
    assert rows[1]["view_mm"] == pytest.approx(rows[0]["view_mm"] / 2, rel=0.02)
    for r in rows:
        mean, lo, hi = r["cnn_n2"]
        assert 0 <= lo <= mean <= hi <= 100
    assert "cnn_n2_minus_base" not in rows[0]
    d, dlo, dhi = rows[1]["cnn_n2_minus_base"]
    assert dlo <= d <= dhi and d == pytest.approx(rows[1]["cnn_n2"][0] - rows[0]["cnn_n2"][0], abs=0.11)
    assert (tmp_path / "out" / "resolution.png").stat().st_size > 0
    # A second run reads the points back: the same table, nothing retrained.
    stamp = (tmp_path / "out" / "s64-c1.json").stat().st_mtime_ns
    assert bench.main() == 0
    assert json.loads(capsys.readouterr().out)["points"] == rows
    assert (tmp_path / "out" / "s64-c1.json").stat().st_mtime_ns == stamp


def test_spectrum_bands_see_only_what_the_resolution_resolves(bench):
    coarse = bench.SpectrumBands(32, 32, 0.1, 0.1)     # Nyquist 5 cycles/mm
    fine = bench.SpectrumBands(128, 128, 0.025, 0.025)  # Nyquist 20 cycles/mm
    assert coarse.size < fine.size
    edges = bench.PROBE_BANDS_CPMM
    top = lambda b: edges[b.keep.max() // bench.PROBE_ORIENTATIONS + 1]  # noqa: E731  (upper edge of its last band)
    assert top(coarse) <= 5.0 < top(fine) <= 20.0
    # A grating of 8 cycles/mm along x puts its power in the band holding 8 cycles/mm, orientation 0.
    yy, xx = np.mgrid[0:128, 0:128]
    img = np.repeat((128 + 60 * np.cos(2 * np.pi * 8.0 * xx * 0.025))[..., None], 3, axis=2).astype(np.uint8)
    f = fine.features(img)
    per_channel = (fine.size - 3) // 3
    loudest = fine.keep[int(np.argmax(f[:per_channel]))]
    radial, angle = divmod(loudest, bench.PROBE_ORIENTATIONS)
    assert edges[radial] <= 8.0 < edges[radial + 1] and angle == 0
    assert f[-3:] == pytest.approx([img[..., c].mean() / 255 for c in range(3)], rel=1e-5)


def test_probe_ranks_resolutions_on_the_tiny_dataset(bench, synth, tmp_path, monkeypatch, capsys):
    out = tmp_path / "probe"
    argv = ["bench_resolution.py", "--method", "probe", "--data", str(synth), "--out", str(out),
            "--points", "32:1,64:1", "--base", "64:1", "--per-fabric", "all", "--json"]
    monkeypatch.setattr(sys, "argv", argv)
    assert bench.main() == 0
    rows = json.loads(capsys.readouterr().out)["points"]
    assert rows[0]["features"] < rows[1]["features"]
    for r in rows:
        mean, lo, hi = r["probe"]
        assert 0 <= lo <= mean <= hi <= 100
        assert r["probe_val_acc"] > 25   # 4 fabrics: chance is 25%; the synthetic textures differ plainly
    assert rows[0]["probe_minus_base"][0] == pytest.approx(rows[0]["probe"][0] - rows[1]["probe"][0], abs=0.11)
    cached = (out / "probe_features.npz").stat().st_mtime_ns
    assert bench.main() == 0 and json.loads(capsys.readouterr().out)["points"] == rows
    assert (out / "probe_features.npz").stat().st_mtime_ns == cached
