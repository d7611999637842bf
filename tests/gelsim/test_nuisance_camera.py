"""gelsim.nuisance.camera: the webcam's auto-exposure and auto white balance, and their gain kernels."""
import math

import numpy as np
import pytest
import torch

from gelsim.errors import GelsimError
from gelsim.nuisance import (camera_start, camera_step, draw_exposure_start, draw_white_balance_start,
                             exposure_gains, exposure_start, exposure_step, load_nuisance, metered_ratios, stage_rng,
                             white_balance_gains)
from gelsim.optics.composite import BatchInput, CameraGains, FrameInput, check_gains

M = load_nuisance()
EXP, WB = M.stages.exposure, M.stages.white_balance


def test_flat_scene_stays_dark_for_the_exposure_delay_then_settles():
    """Docstring: frame 0's exposure applies until the first metered exposure lands delay_frames later;
    with the flat gel the start-up jump brings it to the settled exposure (within stable_region) from then on."""
    g = exposure_gains(np.ones(30), 0.07, EXP)
    assert np.all(g[:EXP.delay_frames] == 0.07)
    assert np.all(np.abs(g[EXP.delay_frames:] - 1.0) <= EXP.stable_region)


def test_after_start_up_a_scene_change_is_corrected_at_the_stated_speeds():
    s = EXP.startup_frames + 3                      # the scene darkens once start-up is over
    near = exposure_gains([1.0] * s + [0.9] * 12, 1.0, EXP)
    far = exposure_gains([1.0] * s + [0.5] * 20, 1.0, EXP)
    d = EXP.delay_frames
    assert np.all(near[:s + d] == 1.0) and np.all(far[:s + d] == 1.0)      # the change lands delay frames later
    t_near, t_far = 1 / 0.9, 2.0
    k = math.sqrt(EXP.speed)                                              # within near_band of the target
    assert near[s + d] == pytest.approx(k * t_near + (1 - k) * 1.0, rel=1e-12)
    assert far[s + d] == pytest.approx(EXP.speed * t_far + (1 - EXP.speed), rel=1e-12)   # outside it
    assert abs(near[-1] / t_near - 1) <= EXP.stable_region and abs(far[-1] / t_far - 1) <= EXP.stable_region
    assert np.all(np.diff(far[s:]) >= 0)                                 # approaches without overshoot


def test_no_change_inside_the_stable_region():
    g = exposure_gains([1.0] * 15 + [1 / 1.015] * 10, 1.0, EXP)
    assert np.all(g == 1.0)


def test_stepping_equals_the_whole_sequence():
    rng = np.random.default_rng(3)
    lumas = rng.uniform(0.7, 1.3, 40)
    state, out = exposure_start(0.3, EXP), []
    for v in lumas:
        gain, state = exposure_step(state, float(v), EXP)
        out.append(gain)
    assert np.array_equal(np.array(out), exposure_gains(lumas, 0.3, EXP))


def test_exposure_start_error_grows_with_severity_and_is_off_at_zero():
    starts = [draw_exposure_start(stage_rng(11, "exposure"), EXP, s) for s in (0.0, 0.5, 1.0, 2.0, 4.0)]
    assert starts[0] == 1.0
    assert all(a > b for a, b in zip(starts, starts[1:-1]))
    assert starts[-1] >= 0.0 and starts[-1] <= starts[-2]
    r = draw_exposure_start(stage_rng(11, "exposure"), EXP, 1.0)
    assert EXP.start_ratio[0] <= r <= EXP.start_ratio[1]


def test_white_balance_start_is_bounded_and_settles_then_follows_the_slow_rule():
    for seed in range(50):
        g = draw_white_balance_start(stage_rng(seed, "white_balance"), WB, 1.0)
        assert g[1] == 1.0 and np.all(np.abs(g - 1) <= WB.start_offset_max)
    assert np.all(draw_white_balance_start(stage_rng(0, "white_balance"), WB, 0.0) == 1.0)
    start = np.array([1.1, 1.0, 0.9])
    T, shift = 40, 15                                      # the scene turns redder after start-up
    ratios = np.ones((T, 3))
    ratios[shift:, 0] = 1.2
    g = white_balance_gains(ratios, start, WB)
    d = WB.delay_frames
    assert np.all(g[:d] == start)
    assert np.allclose(g[d:shift + d], 1.0)                # start-up frames jump to the flat gel's balance
    first = WB.startup_frames + WB.period_frames * math.ceil((shift - WB.startup_frames) / WB.period_frames)
    assert np.allclose(g[shift + d:first + d], 1.0)        # nothing until the next update
    assert g[first + d, 0] == pytest.approx(WB.speed * (1 / 1.2) + (1 - WB.speed), rel=1e-12)
    assert g[first + d + WB.period_frames, 0] < g[first + d, 0]
    assert np.all(g[:, 1] == 1.0)


def test_the_gain_kernels_numpy_and_torch_give_the_same_bits_for_any_batch():
    """composite.CameraGains, the stage that applies these gains: its numpy kernel (on bands of rows) and
    its torch kernel (on a batch) multiply by the same float32 gains."""
    st = CameraGains(None)
    rng = np.random.default_rng(0)
    frames = rng.uniform(-5, 260, (3, 24, 32, 3)).astype(np.float32)
    gains = list(rng.uniform(0.0, 2.0, (3, 3)))
    ref = []
    for f, g in zip(frames, gains):
        state, out = st.prepare(FrameInput(None, None, f.shape, g)), f.copy()
        st.apply(out[:10], 0, state)
        st.apply(out[10:], 10, state)
        ref.append(out)
    ref = np.stack(ref)
    t = torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()
    whole = st.apply_torch(t, BatchInput(None, None, gains)).permute(0, 2, 3, 1).numpy()
    one = np.concatenate([st.apply_torch(t[i:i + 1], BatchInput(None, None, gains[i:i + 1]))
                          .permute(0, 2, 3, 1).numpy() for i in range(3)])
    assert np.array_equal(whole, ref) and np.array_equal(one, ref)
    assert not np.array_equal(ref[0], frames[0])
    assert st.prepare(FrameInput(None, None, frames[0].shape)) is None                 # no gains: nothing
    assert st.apply_torch(t, BatchInput(None, None, None)) is t


@pytest.mark.parametrize("call", [
    lambda: check_gains([1, -1, 1]),
    lambda: check_gains([1, 1]),
    lambda: CameraGains(None).apply_torch(torch.zeros(2, 3, 4, 4), BatchInput(None, None, [[1, 1, 1], [1, 1]])),
    lambda: exposure_gains([1.0, 0.0], 0.5, EXP),
    lambda: exposure_gains([1.0, float("nan")], 0.5, EXP),
    lambda: exposure_start(-0.1, EXP),
    lambda: white_balance_gains(np.ones((3, 2)), [1, 1, 1], WB),
    lambda: white_balance_gains(np.ones((3, 3)), [1, 0, 1], WB),
    lambda: metered_ratios(np.ones((4, 4, 3)), [100, 0, 100]),
    lambda: stage_rng(-1, "exposure"),
    lambda: stage_rng(0, "ambient"),
])
def test_bad_values_are_refused_in_one_line(call):
    with pytest.raises(GelsimError) as e:
        call()
    assert "\n" not in str(e.value)


def test_camera_state_off_draws_nothing_and_changes_nothing():
    frame = np.full((8, 8, 3), 120.0, np.float32)
    state = camera_start(5, {}, M.stages)
    gains, after = camera_step(state, frame, [120.0, 120.0, 120.0], M.stages)
    assert np.array_equal(gains, np.ones(3)) and after == state


def test_camera_gains_are_seeded_and_each_stage_keeps_its_draws():
    bg = np.array([118.0, 124.0, 128.0])
    frames = [np.broadcast_to(bg * f, (6, 6, 3)).astype(np.float32) for f in np.linspace(1.0, 0.8, 20)]

    def run(sev):
        state, out = camera_start(42, sev, M.stages), []
        for f in frames:
            g, state = camera_step(state, f, bg, M.stages)
            out.append(g)
        return np.array(out)

    both = run(M.level("camera"))
    assert np.array_equal(both, run(M.level("camera")))                     # same seed, same gains
    exp_only = run({"exposure": 1.0})
    wb_only = run({"white_balance": 1.0})
    assert np.allclose(both, exp_only * wb_only, rtol=1e-12)               # independent draws, product of gains
    assert not np.array_equal(run(M.level("camera")), camera_run_other_seed(frames, bg))


def camera_run_other_seed(frames, bg):
    state, out = camera_start(43, M.level("camera"), M.stages), []
    for f in frames:
        g, state = camera_step(state, f, bg, M.stages)
        out.append(g)
    return np.array(out)
