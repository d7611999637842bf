import json
import shutil

import numpy as np
import pytest

from gelsim.errors import GelsimError
from stam import cli
from stam.data import TactileDataset, WindowDataset, detect_onset, load_manifest


def _copy_manifest(src, dst, **changes):
    dst.mkdir(parents=True, exist_ok=True)
    m = json.loads((src / "manifest.json").read_text())
    m.update(changes)
    (dst / "manifest.json").write_text(json.dumps(m))
    return dst


def test_bad_dataset_directories(synth, tmp_path, capsys):
    with pytest.raises(GelsimError, match="does not exist"):
        load_manifest(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(GelsimError, match="no manifest"):
        load_manifest(tmp_path / "empty")
    with pytest.raises(GelsimError, match="incomplete"):
        load_manifest(_copy_manifest(synth, tmp_path / "partial", complete=False))
    with pytest.raises(GelsimError, match="not a gelsim dataset"):
        load_manifest(_copy_manifest(synth, tmp_path / "foreign", format="coco"))
    capsys.readouterr()
    assert cli.main(["onsets", "--data", str(tmp_path / "partial")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stam: error:") and "\n" not in err


def test_detect_onset():
    assert detect_onset(np.array([0, 1, 2, 9, 12], np.float32), 6.0) == 3
    assert detect_onset(np.array([0, 1, 2], np.float32), 6.0) is None


def test_onset_detection_agrees_with_manifest(synth):
    agree = TactileDataset(synth).onset_agreement(96)
    assert agree["sequences"] == 80
    assert agree["within_1"] >= 0.8 * agree["sequences"], agree


def test_windows_clean_noisy_and_split(synth):
    data = TactileDataset(synth)
    splits = {s: {q.id for q in data.split(s)} for s in ("train", "val", "test")}
    assert [len(splits[s]) for s in ("train", "val", "test")] == [56, 16, 8]
    assert not (splits["train"] & splits["val"]) and not (splits["train"] & splits["test"])
    noisy = WindowDataset(data, "train", 4, "zero", 96)
    clean = WindowDataset(data, "train", 4, "contact", 96)
    assert all(first == 0 for _, first in noisy.items)
    for seq, first in clean.items:
        det = data.onset(seq, 96)
        assert first == (min(det, seq.num_frames - 4) if det is not None else seq.num_frames - 4)
    x, y = clean[0]
    assert x.shape == (4, 3, 96, 96) and x.dtype.is_floating_point and 0 <= y < 4
    truth = WindowDataset(data, "train", 4, "contact", 96, onset="true")
    assert all(first == min(seq.true_onset, seq.num_frames - 4) for seq, first in truth.items)


def test_n_outside_sequence_length(synth):
    data = TactileDataset(synth)
    for n in (0, 11):
        with pytest.raises(GelsimError, match="outside"):
            WindowDataset(data, "train", n, "zero", 96)


def test_cache_means_no_second_decode(synth, tmp_path, monkeypatch):
    data = TactileDataset(synth, cache_dir=tmp_path / "cache")
    seq = data.sequences[0]
    first = np.array(data.frames(seq, 64))
    assert first.shape == (10, 64, 64, 3) and first.dtype == np.uint8
    assert (tmp_path / "cache" / "64px" / f"{seq.id}.npy").is_file()

    def no_decode(path):
        raise AssertionError("video decoded twice")

    import gelsim.video

    monkeypatch.setattr(gelsim.video, "read_video", no_decode)
    np.testing.assert_array_equal(np.array(TactileDataset(synth, cache_dir=tmp_path / "cache").frames(seq, 64)), first)
    assert not list((tmp_path / "cache" / "64px").glob(".*partial*"))


def test_crop_keeps_the_centre_at_higher_resolution(synth, tmp_path):
    from gelsim.video import read_video
    from stam.data import TactileDataset

    full = TactileDataset(synth, cache_dir=tmp_path / "full")
    half = TactileDataset(synth, cache_dir=tmp_path / "half", crop=0.5)
    seq = full.sequences[0]
    raw = read_video(seq.video)[-1].astype(np.float32)          # (72, 96, 3)
    a = np.asarray(half.frames(half.sequences[0], 36))[-1].astype(np.float32)
    # crop 0.5 of the 72-px side = the central 36 x 36 px, at its native resolution
    centre = raw[18:54, 30:66]
    assert np.abs(a - centre).mean() < 1.0
    b = np.asarray(full.frames(seq, 36))[-1].astype(np.float32)
    assert np.abs(b - centre).mean() > np.abs(a - centre).mean()
    with pytest.raises(GelsimError, match="crop"):
        TactileDataset(synth, crop=0.0)
