"""gelsim.fidelity: the levels load from gelsim/assets/fidelity.toml, fastest first."""
import pytest

from gelsim.errors import GelsimError
from gelsim.fidelity import Fidelity, fidelity_levels, get_fidelity


def test_levels_load_in_file_order_and_the_default_is_balanced():
    levels = fidelity_levels()
    assert list(levels) == ["fast", "balanced", "reference"]
    assert all(isinstance(f, Fidelity) and f.name == n for n, f in levels.items())
    assert get_fidelity() == levels["balanced"] and get_fidelity(levels["fast"]) is levels["fast"]
    # the reference is the yardstick: the exact imprint on the full grid, the OpenGL renderer
    ref = levels["reference"]
    assert (ref.imprint_model, ref.imprint_scale, ref.render_backend) == ("elastic", 1.0, "pyrender")


def test_unknown_level_names_the_choices():
    with pytest.raises(GelsimError, match="fast, balanced, reference|balanced"):
        get_fidelity("ultra")


def test_estimate_is_linear_in_pixels_through_both_measured_sizes():
    import dataclasses

    f = dataclasses.replace(get_fidelity(), est_ms_per_frame_vga=20.0, est_ms_per_frame_960=40.0,
                            est_worker_efficiency=0.8)
    assert f.estimate_seconds(1000, 640, 480) == pytest.approx(20.0)
    assert f.estimate_seconds(1000, 960, 720) == pytest.approx(40.0)
    # halfway in pixels, halfway in time; below the small size the line goes on, never below zero
    mid = (640 * 480 + 960 * 720) / 2
    assert f.estimate_seconds(1000, int(mid), 1) == pytest.approx(30.0, rel=1e-6)
    assert 0.0 <= f.estimate_seconds(1000, 1, 1) < f.estimate_seconds(1000, 320, 240) < 20.0
    # several workers each run at the stated efficiency; one worker runs at full speed
    assert f.estimate_seconds(1000, 960, 720, workers=2) == pytest.approx(40.0 / (2 * 0.8))
    assert f.estimate_seconds(1000, 960, 720, workers=1) == pytest.approx(40.0)


def test_every_level_measures_both_sizes():
    """Each level in gelsim/assets/fidelity.toml states both measured figures (no silent default), the larger
    frame costing more."""
    for f in fidelity_levels().values():
        assert f.est_ms_per_frame_960 > f.est_ms_per_frame_vga > 0 and 0.1 <= f.est_worker_efficiency <= 1.0
