"""gelsim.bench.metrics: the image metrics and the pooling of errors over frames and scenes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gelsim.bench import ErrorAcc, psnr_from_mse, ssim
from gelsim.errors import GelsimError


def test_ssim_identical_and_degraded():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    assert ssim(a, a) == pytest.approx(1.0)
    noisy = np.clip(a + rng.normal(0, 20, a.shape), 0, 255).astype(np.uint8)
    worse = np.clip(a + rng.normal(0, 60, a.shape), 0, 255).astype(np.uint8)
    assert 1.0 > ssim(a, noisy) > ssim(a, worse) > 0.0
    with pytest.raises(GelsimError):
        ssim(a, a[:-1])

def test_psnr_and_error_pooling():
    assert psnr_from_mse(0.0) is None
    assert psnr_from_mse(1.0) == pytest.approx(20 * math.log10(255))
    acc = ErrorAcc()
    ref = np.full((4, 4, 3), 100, np.uint8)
    acc.add_frame(ref + 2, ref)
    acc.add_frame(ref, ref)
    acc.add_markers(np.array([[[3.0, 4.0]]]), np.zeros((1, 1, 2)), 0.5)
    acc.add_forces(np.array([1.0, 2.0]), np.array([1.5, 2.0]))
    s = acc.summary()
    assert s["image_l1"] == pytest.approx(1.0)                       # half the pixels off by 2 DN
    assert s["psnr"] == pytest.approx(10 * math.log10(255 ** 2 / 2.0), abs=1e-3)
    assert s["marker_err_mm"] == pytest.approx(2.5)                  # 5 px at 0.5 mm/px
    assert s["force_err_n"] == pytest.approx(0.25)

def test_texture_pooling_per_scene_then_over_scenes():
    acc = ErrorAcc()
    # scene a: gel relief 0.5 of the reference's in both frames, image texture 2x; scene b: 0.8 / 1
    # (through the fast shader: 0.25 in scene a, not measured in b)
    for _ in range(2):
        acc.add_texture("a", 0.01, 0.02, 4.0, 2.0, 1.0, 4.0)
    acc.add_texture("b", 0.008, 0.01, 3.0, 3.0)
    acc.add_texture("b", float("nan"), 0.01, 3.0, 3.0)        # no region: left out
    ratios = acc.texture_ratios()
    assert ratios["a"] == pytest.approx((0.5, 2.0, 0.25)) and ratios["b"][:2] == pytest.approx((0.8, 1.0))
    assert ratios["b"][2] is None
    s = acc.summary()
    assert s["kept_relief"] == pytest.approx(math.sqrt(0.5 * 0.8), abs=1e-4)   # geometric mean
    assert (s["kept_relief_min"], s["kept_relief_max"]) == (0.5, 0.8)
    assert s["image_texture"] == pytest.approx(math.sqrt(2.0), abs=1e-4)
    assert s["texture_err"] == pytest.approx((0.5 + 0.2) / 2) and s["image_texture_err"] == pytest.approx(0.5)
    assert s["image_texture_fast"] == 0.25 and s["image_texture_fast_err"] == 0.75
    acc.add_area(12.0, 10.0)
    acc.add_area(8.0, 10.0)
    acc.add_area(5.0, 0.0)                                        # no reference contact: left out
    assert acc.summary()["contact_area_err"] == pytest.approx(0.2)
    empty = ErrorAcc().summary()
    assert empty["kept_relief"] is None and empty["texture_err"] is None and empty["contact_area_err"] is None
