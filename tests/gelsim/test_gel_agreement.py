"""gelsim.gel.agreement: the patch, the force and the agreement measures against their definitions
(the fabrics themselves are pressed in test_gel_fabrics.py)."""
import numpy as np
import pytest

from gelsim.gel import Imprint
from gelsim.gel.agreement import (EDGE_MM, FABRICS, FORCE_N, PATCH, PRESSURE_MPA, agreement, fabric, inner,
                                  slope_rms, texture)
from gelsim.sensor import load_profile


def _imprint(depth, mask, approach_mm=0.05):
    return Imprint(depth.astype(np.float32), mask, approach_mm, FORCE_N, 0.0, False)


def _grid():
    h, w = PATCH.shape
    mm = PATCH.image.mm_per_px
    return np.meshgrid((np.arange(w) - (w - 1) / 2) * mm, (np.arange(h) - (h - 1) / 2) * mm)


def test_patch_is_the_vitac_pixel_on_a_flat_gel_at_a_firm_hand_press():
    assert PATCH.shape == (192, 256)
    assert PATCH.image.mm_per_px == load_profile("vitac").image.mm_per_px
    assert PATCH.gel.dome_radius_mm == 0.0
    assert 1e3 * PRESSURE_MPA == pytest.approx(7.46, abs=0.01)   # kPa: 2 N on the whole pad
    assert FORCE_N == pytest.approx(PRESSURE_MPA * 256 * 192 * 0.0197 ** 2, rel=1e-3)


def test_inner_drops_the_rim():
    m = round(EDGE_MM / PATCH.image.mm_per_px)
    a = np.arange(192 * 256).reshape(192, 256)
    assert inner(a).shape == (192 - 2 * m, 256 - 2 * m)
    assert inner(a)[0, 0] == a[m, m]


def test_texture_keeps_the_weave_and_drops_the_smooth_shape():
    x, y = _grid()
    weave = 0.01 * np.sin(2 * np.pi * x / 0.2)
    smooth = 0.05 + 0.02 * np.exp(-(x * x + y * y) / (2 * 3.0 ** 2))   # a 3 mm dome under the weave
    t = texture(weave + smooth)
    assert np.abs(texture(smooth)).max() < 0.1 * 0.01
    assert np.corrcoef(t.ravel(), inner(weave).ravel())[0, 1] > 0.999
    assert t.std() == pytest.approx(inner(weave).std(), rel=0.02)


def test_slope_rms_of_a_plane():
    x, y = _grid()
    assert slope_rms(0.03 * x + 0.04 * y) == pytest.approx(0.05, rel=1e-6)


def test_agreement_is_one_with_itself_and_sees_each_difference():
    x, y = _grid()
    depth = 0.05 + 0.01 * np.sin(2 * np.pi * x / 0.2) * np.cos(2 * np.pi * y / 0.3)
    mask = depth > 0.05
    ref = _imprint(depth, mask)
    same = agreement(ref, ref)
    assert same == pytest.approx({"corr": 1.0, "slope": 1.0, "contact": 1.0, "approach": 1.0})
    other = agreement(_imprint(2 * depth, mask | (depth > 0.045), approach_mm=0.04), ref)
    assert other["corr"] == pytest.approx(1.0)
    assert other["slope"] == pytest.approx(2.0)
    assert other["contact"] > 1.2
    assert other["approach"] == pytest.approx(0.8)
    quarter = 0.05 + 0.01 * np.cos(2 * np.pi * x / 0.2) * np.cos(2 * np.pi * y / 0.3)  # a quarter period out
    assert abs(agreement(_imprint(quarter, mask), ref)["corr"]) < 0.05


def test_fabric_is_the_named_catalog_fabric_over_the_patch():
    fab, prot = fabric("mesh")
    assert fab.id == FABRICS["mesh"]
    assert prot.shape == PATCH.shape and prot.dtype == np.float32
    assert fabric("mesh")[1] is prot   # cached
