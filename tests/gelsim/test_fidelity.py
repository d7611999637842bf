"""gelsim.fidelity: the levels load from assets/fidelity.toml, fastest first."""
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
