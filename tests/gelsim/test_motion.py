"""Hand-held motion sampling: ratios, ranges, determinism, travel bounds."""
from __future__ import annotations

import dataclasses
import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gelsim.errors import GelsimError
from gelsim.motion import ACTIONS, Motion, load_motion_ranges, sample_motion

RANGES = load_motion_ranges()


def test_ranges_load_with_sources():
    r = RANGES
    assert (r.actions.press, r.actions.slip, r.actions.twist) == (7.0, 1.0, 2.0)
    assert r.timing.precontact_frames[0] <= r.timing.precontact_frames[1]
    assert r.force.peak_force_n[1] <= 5.0  # a few newtons at most by hand
    assert 8.0 <= r.tremor.frequency_hz[0] and r.tremor.frequency_hz[1] <= 12.0


def test_action_ratios_follow_vitac():
    rng = np.random.default_rng(0)
    n = 3000
    counts = Counter(sample_motion("random", rng, ranges=RANGES).action for _ in range(n))
    for action, share in (("press", 0.7), ("slip", 0.1), ("twist", 0.2)):
        assert counts[action] / n == pytest.approx(share, abs=0.03), action


def check_in_range(m: Motion, frames=(25, 36), pre=None) -> None:
    r = RANGES
    assert frames[0] <= m.num_frames <= frames[1]
    if pre is None:  # the default mixture: early starts, or a late start for some sequences
        t = r.timing
        assert (t.precontact_frames[0] <= m.precontact_frames <= t.precontact_frames[1]
                or t.late_start_frames[0] <= m.precontact_frames <= t.late_start_frames[1])
    else:
        assert pre[0] <= m.precontact_frames <= pre[1]
    assert math.hypot(*m.start_xy_mm) <= r.approach.start_offset_mm + 1e-9
    assert 0 <= m.fabric_rotation_deg < 360
    assert r.approach.speed_mm_s[0] <= m.approach_speed_mm_s <= r.approach.speed_mm_s[1]
    lo, hi = r.force.peak_force_n
    if m.action != "press":
        lo *= r.force.slip_force_scale[0]
        hi *= r.force.slip_force_scale[1]
    assert lo - 1e-9 <= m.peak_force_n <= hi + 1e-9
    assert all(abs(t) <= r.tilt.max_tilt_deg for t in m.tilt_deg)
    assert r.tremor.amplitude_mm[0] <= m.tremor_amplitude_mm <= r.tremor.amplitude_mm[1]
    assert r.tremor.frequency_hz[0] <= m.tremor_frequency_hz <= r.tremor.frequency_hz[1]
    assert r.timing.contact_phase[0] <= m.contact_phase <= r.timing.contact_phase[1]
    if m.action == "slip":
        assert r.slip.distance_mm[0] <= m.slip_distance_mm <= r.slip.distance_mm[1]
        assert m.twist_deg == 0
    elif m.action == "twist":
        assert r.twist.angle_deg[0] <= abs(m.twist_deg) <= r.twist.angle_deg[1]
        assert m.slip_distance_mm == 0
    else:
        assert m.slip_distance_mm == 0 and m.twist_deg == 0
    assert m.release_fraction >= 0 and m.rise_fraction + m.hold_fraction + m.release_fraction <= 1.0
    for v in dataclasses.astuple(m)[1:]:
        for x in (v if isinstance(v, tuple) else (v,)):
            assert math.isfinite(x)


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), action=st.sampled_from(ACTIONS + ("random",)))
def test_hypothesis_motions_finite_in_range(seed, action):
    m = sample_motion(action, seed, ranges=RANGES)
    if action != "random":
        assert m.action == action
    check_in_range(m)
    xmin, ymin, xmax, ymax = m.travel_bounds_mm()
    x0, y0 = m.start_xy_mm
    dx, dy = m.slip_vector_mm()
    for x, y in ((x0, y0), (x0 + dx, y0 + dy)):
        assert xmin + 0.5 <= x <= xmax - 0.5 and ymin + 0.5 <= y <= ymax - 0.5


def test_options_frames_and_precontact():
    for seed in range(50):
        m = sample_motion("press", seed, frames=(30, 30), precontact=(0, 1), ranges=RANGES)
        check_in_range(m, frames=(30, 30), pre=(0, 1))
        assert m.num_frames == 30
    seen = {sample_motion("press", s, precontact=(3, 5)).precontact_frames for s in range(60)}
    assert seen == {3, 4, 5}


def test_same_seed_same_motion_and_generator_advances():
    assert sample_motion("twist", 5) == sample_motion("twist", 5)
    assert sample_motion("twist", 5) != sample_motion("twist", 6)
    rng = np.random.default_rng(1)
    a, b = sample_motion("slip", rng), sample_motion("slip", rng)
    assert a != b


def test_slip_direction_and_vector():
    m = dataclasses.replace(sample_motion("slip", 2), slip_direction_deg=90.0, slip_distance_mm=4.0)
    dx, dy = m.slip_vector_mm()
    assert dx == pytest.approx(0.0, abs=1e-12) and dy == pytest.approx(4.0)
    xmin, ymin, xmax, ymax = m.travel_bounds_mm()
    assert ymax - ymin == pytest.approx(4.0 + 2 * (2 * m.tremor_amplitude_mm + 0.5))


def test_bad_inputs_raise():
    with pytest.raises(GelsimError, match="unknown action"):
        sample_motion("poke", 0)
    with pytest.raises(GelsimError):
        sample_motion("press", 0, frames=(5, 5), precontact=(4, 4))
    with pytest.raises(GelsimError):
        dataclasses.replace(sample_motion("press", 0), precontact_frames=40)


def test_bad_ranges_file(tmp_path):
    text = (RANGES_FILE := __import__("gelsim.motion", fromlist=["MOTIONS_FILE"]).MOTIONS_FILE).read_text()
    bad = tmp_path / "m.toml"
    bad.write_text(text.replace("speed_mm_s = [5.0, 20.0]", "speed_mm_s = [20.0, 5.0]"))
    with pytest.raises(GelsimError, match="speed_mm_s"):
        load_motion_ranges(bad)
    bad.write_text(text.replace("[tremor]", "[tremor]\nbogus_hz = 3.0"))
    with pytest.raises(GelsimError, match="bogus_hz"):
        load_motion_ranges(bad)
    assert RANGES_FILE.exists()


def test_default_precontact_mixture_shares():
    from collections import Counter as C

    t = RANGES.timing
    n = 2000
    pre = C(sample_motion("press", s, ranges=RANGES).precontact_frames for s in range(n))
    late = sum(v for k, v in pre.items() if k >= t.late_start_frames[0]) / n
    assert late == pytest.approx(t.late_start_fraction, abs=0.03)
    assert set(pre) <= set(range(t.precontact_frames[0], t.precontact_frames[1] + 1)) | \
        set(range(t.late_start_frames[0], t.late_start_frames[1] + 1))
