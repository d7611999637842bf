"""The onset-aware oracle: which frames it drops, its windows, and that it is the CNN where it drops none."""
import dataclasses

import pytest
import torch

from stam.config import TrainConfig, resolve_train
from stam.data import TactileDataset, WindowDataset
from stam.oracle import OnsetWindows, keep_mask, windows_for


def test_keep_mask_drops_the_frames_before_the_onset():
    assert keep_mask(2, 0, 4).tolist() == [False, False, True, True]
    assert keep_mask(0, 0, 3).tolist() == [True, True, True]
    assert keep_mask(3, 5, 2).tolist() == [True, True]            # a window after the onset keeps everything
    assert keep_mask(6, 4, 3).tolist() == [False, False, True]    # frames 4, 5 before the onset, 6 kept
    assert keep_mask(9, 0, 4).tolist() == [False, False, False, True]   # none left: the last frame
    assert keep_mask(None, 0, 4).tolist() == [True] * 4          # no onset detected: nothing dropped


@pytest.mark.parametrize("start", ["zero", "contact"])
def test_onset_windows_drop_exactly_the_frames_before_the_detected_onset(synth, start):
    data = TactileDataset(synth)
    windows = WindowDataset(data, "train", 4, start, 96)
    ds = OnsetWindows(windows, "detected", 5.0)
    assert len(ds) == len(windows) and ds.items == windows.items and ds.undetected == windows.undetected
    dropped_some = 0
    for i, (seq, first) in enumerate(windows.items):
        (x, keep), y = ds[i]
        x0, y0 = windows[i]
        assert torch.equal(x, x0) and y == y0
        onset = data.onset(seq, 96, "detected", 5.0)
        frames = list(range(first, first + 4))
        expected = [t >= onset for t in frames] if onset is not None else [True] * 4
        if not any(expected):
            expected[-1] = True
        assert keep.tolist() == expected, (seq.id, first, onset)
        dropped_some += not all(expected)
    if start == "zero":   # the synthetic sequences touch at frame 1 or later: every noisy window drops some
        assert dropped_some == len(ds)
    # the true onset instead of the detected one, when asked
    true = OnsetWindows(windows, "true", 5.0)
    for i, (seq, first) in enumerate(windows.items):
        assert true.keep[i].tolist() == keep_mask(seq.true_onset, first, 4).tolist()


def test_windows_for_wraps_only_the_oracles(synth):
    from stam.models import build

    windows = WindowDataset(TactileDataset(synth), "val", 2, "zero", 96)
    cnn = build("cnn", 2, 4, width=0.125, image_size=96)
    oracle = build("oracle", 2, 4, width=0.125, image_size=96)
    assert windows_for(cnn, windows, "detected", 5.0) is windows
    assert isinstance(windows_for(oracle, windows, "detected", 5.0), OnsetWindows)


def test_oracle_trained_where_it_drops_nothing_is_the_cnn(synth, tmp_path):
    """On clean windows of 2 frames (no window starts before its onset here) the oracle keeps every frame:
    trained with the CNN's seed on the same frozen (random) backbone, it is the CNN, to the prediction."""
    from stam.evaluate import evaluate
    from stam.train import train

    base = resolve_train(TrainConfig(), {"data": str(synth), "image_size": 96, "width": 0.25, "frames": 2,
                                         "epochs": 2, "batch_size": 16, "optimizer": "adam", "lr": 0.002,
                                         "freeze_backbone": True, "progress": False})
    data = TactileDataset(synth)
    clean = WindowDataset(data, "test", 2, "contact", 96)
    assert all(keep_mask(data.onset(s, 96), first, 2).all() for s, first in clean.items)
    preds = {}
    for model in ("cnn", "oracle"):
        cfg = resolve_train(base, {"model": model, "out": str(tmp_path / model), "start": "contact"})
        best = train(cfg, data=data, log=None)["best"]
        preds[model] = evaluate(best, split="test", data=data)["predictions"]
    assert preds["oracle"] == preds["cnn"]
    assert dataclasses.asdict(cfg)["fusion"] == "onset"
