"""Planning logic of the dataset (no simulation): counts, splits, seeds, parsing."""
from collections import Counter

import pytest

from gelsim.dataset import (GenerateConfig, apportion, parse_range, parse_ratio, parse_resolution, plan,
                            sequence_seed)
from gelsim.errors import GelsimError


def test_apportion_sums_and_ratios():
    assert apportion(50, (7, 1, 2)) == [35, 5, 10]
    assert apportion(10, (7, 2, 1)) == [7, 2, 1]
    assert sum(apportion(13, (7, 1, 2))) == 13
    assert apportion(3, (1, 0, 0)) == [3, 0, 0]


def test_plan_actions_splits_and_ids():
    cfg = GenerateConfig(fabrics=4, sequences_per_fabric=20, frames=(25, 36))
    specs = plan(cfg, catalog_size=100)
    assert len(specs) == 80
    assert len({s.id for s in specs}) == 80
    for fid in range(1, 5):
        mine = [s for s in specs if s.fabric_id == fid]
        assert Counter(s.action for s in mine) == {"press": 14, "slip": 2, "twist": 4}
        # 7:2:1 split stratified by fabric
        assert Counter(s.split for s in mine) == {"train": 14, "val": 4, "test": 2}
    assert all(25 <= s.num_frames <= 36 for s in specs)
    assert len({s.seed for s in specs}) == 80


def test_plan_is_deterministic_and_seed_dependent():
    a = plan(GenerateConfig(fabrics=3, sequences_per_fabric=5), 100)
    b = plan(GenerateConfig(fabrics=3, sequences_per_fabric=5), 100)
    c = plan(GenerateConfig(fabrics=3, sequences_per_fabric=5, seed=1), 100)
    assert a == b
    assert [s.seed for s in a] != [s.seed for s in c]
    # a sequence's seed does not depend on how many fabrics or sequences are planned
    assert sequence_seed(0, 2, 3) == next(s.seed for s in a if s.fabric_id == 2 and s.index == 3)


def test_plan_rejects_bad_fabric_count():
    with pytest.raises(GelsimError, match="1-100"):
        plan(GenerateConfig(fabrics=101), 100)
    with pytest.raises(GelsimError, match="1-100"):
        plan(GenerateConfig(fabrics=0), 100)


def test_plan_precontact_must_leave_contact_frames():
    with pytest.raises(GelsimError, match="precontact"):
        plan(GenerateConfig(fabrics=1, sequences_per_fabric=3, frames=(5, 5), precontact=(5, 5)), 100)


@pytest.mark.parametrize("text", ["7:1", "a:b:c", "7:-1:2", "0:0:0", "7:1:2:3", "nan:1:1"])
def test_parse_ratio_rejects(text):
    with pytest.raises(GelsimError, match="--actions"):
        parse_ratio(text)


def test_parse_ratio_and_range_accept():
    assert parse_ratio("7:1:2") == (7.0, 1.0, 2.0)
    assert parse_range("25-36", "--frames") == (25, 36)
    assert parse_range("4", "--precontact") == (4, 4)
    assert parse_resolution("320x240") == (320, 240)


@pytest.mark.parametrize("text,msg", [("36-25", "inverted"), ("x-3", "malformed"), ("1-2-3", "malformed"),
                                      ("-3-4", "malformed")])
def test_parse_range_rejects(text, msg):
    with pytest.raises(GelsimError, match=msg):
        parse_range(text, "--frames")


@pytest.mark.parametrize("text", ["320", "axb", "0x0", "-5x10"])
def test_parse_resolution_rejects(text):
    with pytest.raises(GelsimError, match="--resolution"):
        parse_resolution(text)


def test_a_resolution_too_small_names_the_smallest_that_works():
    """`--resolution 0x0` said "use at least 16x16", and 16x16 was then refused for its pixel size (#50): the
    profile names its own range, and the smallest size in it works."""
    from gelsim.sensor import load_profile

    vitac = load_profile("vitac")
    (w, h), _ = vitac.resolution_range()
    for size in ((16, 16), (w - 1, h), (w, h - 1)):
        with pytest.raises(GelsimError, match=rf"out of range for vitac; give {w}x{h} to 8192x8192 px"):
            vitac.with_resolution(*size)
    small = vitac.with_resolution(w, h)
    assert small.shape == (h, w) and small.image.mm_per_px <= 1.0


def test_small_datasets_still_contain_every_action():
    specs = plan(GenerateConfig(fabrics=10, sequences_per_fabric=3), 100)
    counts = Counter(s.action for s in specs)
    assert counts == {"press": 21, "slip": 3, "twist": 6}


def test_interleave_blocks_hold_the_exact_ratio():
    from gelsim.dataset import interleave

    seq = interleave(100, (7, 1, 2))
    for b in range(10):
        assert Counter(seq[10 * b: 10 * b + 10]) == {0: 7, 1: 1, 2: 2}


def test_split_weights_apportion_per_fabric():
    specs = plan(GenerateConfig(fabrics=4, sequences_per_fabric=20, split=(7.0, 2.0, 11.0)), 100)
    for fid in range(1, 5):
        c = Counter(s.split for s in specs if s.fabric_id == fid)
        assert c == {"train": 7, "val": 2, "test": 11}
    # the default is the paper's 7:2:1, and float weights plan as the old integer ones did
    d = plan(GenerateConfig(fabrics=3, sequences_per_fabric=10), 100)
    assert Counter(s.split for s in d) == {"train": 21, "val": 6, "test": 3}
    with pytest.raises(GelsimError, match="--split '7:2' is malformed; give three non-negative train:val:test"):
        parse_ratio("7:2", "--split", "train:val:test", "7:2:1")


def test_frames_too_short_for_the_precontact_mixture_fail_before_anything_is_written(tmp_path, monkeypatch):
    """--frames whose shortest sequence could keep fewer than MIN_CONTACT_FRAMES in contact after the
    pre-contact frames (given, or the default mixture: its early range, and its late starts only when
    their fraction is above 0) is refused up front, not mid-run."""
    import dataclasses
    import subprocess
    import sys

    import gelsim.motion
    from gelsim.dataset import GenerateConfig, check_frames
    from gelsim.errors import GelsimError

    with pytest.raises(GelsimError, match="fewer than 3 frames in contact"):
        check_frames(GenerateConfig(frames=(3, 4)))               # the default's 0-1 frames leave 2
    check_frames(GenerateConfig(frames=(8, 10)))                  # no late starts by default
    with pytest.raises(GelsimError, match="at most 5"):
        check_frames(GenerateConfig(frames=(8, 10), precontact=(2, 6)))
    check_frames(GenerateConfig(frames=(8, 10), precontact=(0, 5)))
    check_frames(GenerateConfig())
    ranges = gelsim.motion.load_motion_ranges()
    late = dataclasses.replace(ranges, timing=dataclasses.replace(ranges.timing, late_start_fraction=0.2))
    monkeypatch.setattr(gelsim.motion, "load_motion_ranges", lambda path=None: late)
    with pytest.raises(GelsimError, match="fewer than 3 frames in contact"):
        check_frames(GenerateConfig(frames=(8, 10)))              # late starts take up to 12
    monkeypatch.undo()
    out = tmp_path / "ds"
    r = subprocess.run([sys.executable, "-m", "gelsim", "generate", "--frames", "3-4", "--out", str(out),
                        "--fabrics", "1"], capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not out.exists()
