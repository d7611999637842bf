import json
import shutil

import numpy as np
import pytest

from gelsim.errors import GelsimError
from stam import cli
from stam.data import (DEFAULT_ONSET_THRESHOLD, ONSET_DRIFT_FACTOR, SCORE_PERCENTILE, TactileDataset,
                       WindowDataset, change_score, contact_scores, detect_onset, load_manifest, model_input,
                       thumbnails)
from stam.errors import StamError


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


def _touch_sequence(w, h, onset, frames=14, seed=0, step=None, noise=1.0):
    """A still gel (smooth background, Gaussian sensor noise of ``noise`` DN) touched at ``onset`` by a disk whose
    shading changes the channels in opposite directions (three LEDs 120 degrees apart): red up,
    blue down, grey almost unchanged. ``step``: per-frame growth of a slow contact instead."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    bg = (110 + 40 * xx / w + 20 * yy / h)[..., None] * np.array([1.0, 0.95, 1.05], np.float32)
    disk = (np.hypot(xx - 0.5 * w, yy - 0.5 * h) < 0.08 * w).astype(np.float32)[..., None]
    shade = np.array([12.0, -3.0, -15.0], np.float32)       # 0.299 * 12 - 0.587 * 3 - 0.114 * 15 = 0.0
    out = []
    for t in range(frames):
        amp = 0.0 if t < onset else (1.0 if step is None else min(1.0, step * (t - onset + 1)))
        out.append(np.clip(bg + amp * disk * shade + rng.normal(0, noise, bg.shape), 0, 255).astype(np.uint8))
    return np.stack(out)


@pytest.mark.parametrize("size", [(320, 240), (960, 720)])
def test_detect_onset_noise_then_a_touch(size):
    for onset in (1, 3, 9):
        scores, noise = contact_scores(_touch_sequence(*size, onset, seed=onset))
        assert scores.shape == (14, 2) and scores.dtype == np.float32
        assert scores[1:onset, 1].max(initial=0) < 0.8 * DEFAULT_ONSET_THRESHOLD   # noise alone
        # 1 DN per channel, averaged over 2 x 2 (320x240) or 6 x 6 px (960x720), differenced: sqrt(2) / 2 or / 6
        assert noise == pytest.approx(np.sqrt(2) * 1.0 / (size[0] // 160), rel=0.25)
        assert detect_onset(scores, noise_dn=noise) == onset
    scores, noise = contact_scores(_touch_sequence(*size, onset=99))
    assert detect_onset(scores, noise_dn=noise) is None


def test_noisy_camera_raises_the_bar():
    # 5 DN of noise: pure-noise changes reach ~13 DN at 320x240, above the 5 DN floor; the bar
    # follows the sequence's noise level, and the touch (19 DN) still shows.
    scores, noise = contact_scores(_touch_sequence(320, 240, onset=6, noise=5.0, seed=1))
    assert scores[1:6, 1].max() > DEFAULT_ONSET_THRESHOLD                 # a fixed 5 DN bar would fire on noise
    assert detect_onset(scores, noise_dn=0.0) < 6
    assert noise == pytest.approx(5.0 * np.sqrt(2) / 2, rel=0.25)
    assert detect_onset(scores, noise_dn=noise) == 6


def test_per_channel_score_sees_a_touch_that_grey_cancels():
    th = thumbnails(_touch_sequence(320, 240, onset=4))
    assert th.shape == (14, 120, 160, 3)
    grey = th @ np.array([0.299, 0.587, 0.114], np.float32)
    assert np.percentile(np.abs(grey[4] - grey[3]), SCORE_PERCENTILE) < 2.0
    assert change_score(th[4], th[3]) > 3 * DEFAULT_ONSET_THRESHOLD


def test_slow_contact_is_caught_by_the_change_from_frame_0():
    # Each step adds a quarter of the shading (about 5 DN): below the frame-to-frame bar at
    # first, so the change from frame 0 must cross ONSET_DRIFT_FACTOR x the threshold.
    scores, _ = contact_scores(_touch_sequence(320, 240, onset=5, step=0.25))
    d = detect_onset(scores)
    assert d is not None and 5 <= d <= 8
    first = np.flatnonzero(scores[:, 0] > ONSET_DRIFT_FACTOR * DEFAULT_ONSET_THRESHOLD)[0]
    jump = np.flatnonzero(scores[:, 1] > DEFAULT_ONSET_THRESHOLD)
    assert d == min(first, jump[0] if jump.size else first)


def test_detect_onset_rules():
    s = np.zeros((6, 2), np.float32)
    assert detect_onset(s, 5.0) is None
    s[3, 1] = 5.5                          # a jump from frame 2
    assert detect_onset(s, 5.0) == 3
    s[2, 0] = 10.5                         # drift from frame 0 past 2 x threshold comes first
    assert detect_onset(s, 5.0) == 2
    s[0] = 99.0                            # frame 0 is the reference, never the onset
    assert detect_onset(s, 5.0) == 2
    assert detect_onset(s, 5.0, noise_dn=1.0) is None  # bar 6 DN: neither the jump of 5.5 nor the drift of 10.5 counts
    s[4, 1] = 6.5
    assert detect_onset(s, 5.0, noise_dn=1.0) == 4
    with pytest.raises(GelsimError, match="shape"):
        detect_onset(np.zeros(5, np.float32))


def test_onset_detection_agrees_with_manifest(synth):
    agree = TactileDataset(synth).onset_agreement(96)
    assert agree["sequences"] == 80
    assert agree["within_1"] >= 0.95 * agree["sequences"], agree
    assert sum(agree["error_histogram"].values()) + agree["not_detected"] == 80
    assert sum(sum(row.values()) for row in agree["confusion"].values()) == 80
    lo, hi = agree["within_1_ci95"]
    assert lo <= agree["within_1_rate"] <= hi


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A tiny `gelsim generate` dataset: 4 fabrics x 3 sequences at 320x240, fast level,
    0-5 pre-contact frames (a contact at frame 0 included)."""
    from gelsim.cli import main as gelsim_main

    out = tmp_path_factory.mktemp("gen") / "ds"
    assert gelsim_main(["generate", "--out", str(out), "--workers", "1", "--fabrics", "4",
                        "--sequences-per-fabric", "3", "--resolution", "320x240", "--fidelity", "fast",
                        "--frames", "10-12", "--precontact", "0-5", "--seed", "3", "--no-previews",
                        "--json"]) == 0
    return out


def test_onsets_on_a_generated_dataset(generated, capsys):
    assert cli.main(["onsets", "--data", str(generated), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["sequences"] == 12 and res["not_detected"] == 0
    assert res["within_1"] >= 11, res
    m = load_manifest(generated)
    assert sorted(int(t) for t in res["confusion"]) == sorted({s["contact_onset"] for s in m["sequences"]})
    assert cli.main(["onsets", "--data", str(generated)]) == 0
    text = capsys.readouterr().out
    assert "within 1 frame" in text and "95% CI" in text and "confusion" in text


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
    assert (tmp_path / "cache" / "64px" / f"{seq.id}-{data.cache_key(seq)}.npy").is_file()

    def no_decode(path):
        raise AssertionError("video decoded twice")

    import gelsim.video

    monkeypatch.setattr(gelsim.video, "read_video", no_decode)
    np.testing.assert_array_equal(np.array(TactileDataset(synth, cache_dir=tmp_path / "cache").frames(seq, 64)), first)
    assert not list((tmp_path / "cache" / "64px").glob(".*partial*"))


def test_a_video_changed_since_is_not_read_from_the_cache(synth, tmp_path):
    """The frame cache was keyed by the sequence id alone: a video copied over afterwards (another
    sequence's here) kept being read from its stale cache (#42)."""
    from gelsim.video import read_video

    root = tmp_path / "data"
    shutil.copytree(synth, root)
    data = TactileDataset(root, cache_dir=tmp_path / "cache")
    a, b = data.sequences[0], data.sequences[-1]
    old = np.array(data.frames(a, 64))
    shutil.copyfile(b.video, a.video)                   # a new file: another size or modification time
    _record_checksum(root, a.id)                        # as a dataset rewritten with it says
    fresh = TactileDataset(root, cache_dir=tmp_path / "cache")
    new = np.array(fresh.frames(fresh.sequences[0], 64))
    assert not np.array_equal(new, old)
    np.testing.assert_array_equal(new, np.array(fresh.frames(fresh.sequences[-1], 64)))
    assert np.array_equal(new, np.stack([model_input(f, 64) for f in read_video(b.video)]))


def _record_checksum(root, seq_id):
    """Put the checksum of ``seq_id``'s video as it is now into ``root``'s manifest."""
    from gelsim.schema import sha256_of

    path = root / "manifest.json"
    m = json.loads(path.read_text())
    for s in m["sequences"]:
        if s["id"] == seq_id:
            s["sha256"]["video"] = sha256_of(root / s["video"])
    path.write_text(json.dumps(m))


def test_a_video_that_fails_its_checksum_is_named_before_it_is_read(synth, tmp_path):
    """`stam train` on a dataset with a changed video trained on it without a word (#50): the first read of
    a video checks it against the manifest, and a mismatch is one line naming the file and the fix."""
    root = tmp_path / "data"
    shutil.copytree(synth, root)
    data = TactileDataset(root, cache_dir=tmp_path / "cache")
    a, b = data.sequences[0], data.sequences[-1]
    shutil.copyfile(b.video, a.video)              # decodes fine, but is not the video the manifest lists
    with pytest.raises(StamError, match=rf"video {a.video} does not match the manifest's checksum.*gelsim verify"):
        data.frames(a, 64)
    assert not any((tmp_path / "cache").rglob(f"{a.id}-*.npy"))     # nothing of it cached
    np.asarray(data.frames(b, 64))                                   # the others read as before


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
