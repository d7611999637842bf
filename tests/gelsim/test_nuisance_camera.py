"""gelsim.nuisance.camera: the webcam's start-up (auto-exposure and white balance settling), and the gain kernels."""
import math

import numpy as np
import pytest
import torch

from gelsim.errors import GelsimError
from gelsim.nuisance import draw_startup, load_nuisance, settling, stage_rng, startup_gains
from gelsim.optics.composite import BatchInput, CameraGains, FrameInput, check_gains

M = load_nuisance()
SU = M.stages.startup


def test_exposure_holds_for_the_delay_then_ramps_and_settles_by_the_settle_frame():
    g = settling(0.05, 2, 8, 0.02, np.arange(20))
    assert np.all(g[:2] == 0.05)                                    # the first correction lands 2 frames late
    assert np.all(np.diff(g[1:9]) > 0)                              # a ramp: every frame brighter, no jump to 1
    assert g[3] < 0.5 < g[6]                                        # several frames of it, not a step
    assert abs(math.log(g[8])) == pytest.approx(math.log1p(0.02), rel=1e-9)   # within the stable region at frame 8
    assert np.all(g[8:] == g[8])                                    # and the controller stops there
    assert settling(0.05, 2, 8, 0.02, np.arange(7))[6] < 1 / 1.02   # not before


def test_a_start_inside_the_stable_region_never_moves_and_channels_ramp_on_their_own():
    assert np.all(settling(1.01, 1, 4, 0.02, np.arange(10)) == 1.01)
    g = settling(np.array([1.15, 1.0, 0.9]), 1, 4, 0.02, np.arange(8))
    assert g.shape == (8, 3) and np.all(g[:, 1] == 1.0)
    assert np.all(np.diff(g[:5, 0]) < 0) and np.all(np.diff(g[:5, 2]) > 0)
    assert np.all(np.abs(np.log(g[4:])) <= math.log1p(0.02) + 1e-12)


def test_the_share_of_recordings_that_catch_the_start_up_grows_with_severity_as_supersets():
    seeds = range(2000)
    caught = {s: {k for k in seeds if draw_startup(stage_rng(k, "startup"), SU, s).age_frames is not None}
              for s in (0.0, 0.5, 1.0, 2.0, 4.0)}
    assert not caught[0.0]
    for lo, hi in ((0.5, 1.0), (1.0, 2.0), (2.0, 4.0)):
        assert caught[lo] <= caught[hi] and len(caught[lo]) < len(caught[hi])
    # about severity x restart_share of them (binomial, 2000 draws: within 4 standard errors)
    for s in (1.0, 4.0):
        p = min(1.0, s * SU.restart_share)
        assert abs(len(caught[s]) / 2000 - p) < 4 * math.sqrt(p * (1 - p) / 2000)
    # a caught recording's start-up does not depend on the severity: no frame gets darker at a higher one
    k = min(caught[1.0])
    g1 = startup_gains(draw_startup(stage_rng(k, "startup"), SU, 1.0), 30, SU)
    g4 = startup_gains(draw_startup(stage_rng(k, "startup"), SU, 4.0), 30, SU)
    assert np.array_equal(g1, g4)


def test_startup_gains_follow_the_stream_age_and_stay_in_the_sources_ranges():
    restart = M.stages_for("webcam-restart").startup
    assert restart.restart_share == 1.0
    lows = []
    for k in range(200):
        s = draw_startup(stage_rng(k, "startup"), restart, 1.0)
        assert s.age_frames is not None and restart.preroll_frames[0] <= s.age_frames <= restart.preroll_frames[1]
        g = startup_gains(s, 30, restart)
        assert g.shape == (30, 3) and np.all(g > 0)
        if s.age_frames == 0:
            lows.append(g[0, 1])
            assert restart.exposure_start[0] <= g[0, 1] <= restart.exposure_start[1]
        # settled (within the stable region of both controllers, so within about 4%) by the last settle frame
        last = max(s.exposure_settle_frames, s.white_balance_settle_frames) - s.age_frames
        if last < 30:
            assert np.all(np.abs(g[max(last, 0):] - 1.0) <= 1.02 ** 2 - 1 + 1e-9)
    assert lows and min(lows) >= restart.exposure_start[0]
    not_caught = draw_startup(stage_rng(1, "startup"), SU, 0.0)
    assert not_caught.age_frames is None and startup_gains(not_caught, 30, SU) is None


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
    lambda: settling(0.0, 2, 8, 0.02, np.arange(3)),
    lambda: settling(float("nan"), 2, 8, 0.02, np.arange(3)),
    lambda: settling(0.5, 8, 8, 0.02, np.arange(3)),
    lambda: settling(0.5, 2, 8, 0.02, np.array([-1, 0])),
    lambda: settling(0.5, 2, 8, 0.02, np.array([0.5])),
    lambda: draw_startup(stage_rng(0, "startup"), SU, 5.0),
    lambda: stage_rng(-1, "startup"),
    lambda: stage_rng(0, "ambient"),
])
def test_bad_values_are_refused_in_one_line(call):
    with pytest.raises(GelsimError) as e:
        call()
    assert "\n" not in str(e.value)
