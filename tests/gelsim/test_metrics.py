"""gelsim.metrics: the one SSIM and PSNR, including SSIM's edge behaviour."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gelsim import metrics
from gelsim.errors import GelsimError
from gelsim.metrics import mse, psnr, ssim, ssim_map


def _smooth_image(seed=0, shape=(120, 160, 3)):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(40, 220, shape), (0, 0), 2.0)


def _ssim_by_hand(a: np.ndarray, b: np.ndarray) -> float:
    """Wang et al.'s definition written out: for every window centre whose 11 x 11 window lies inside
    the image, Gaussian-weighted means, variances and covariance of the raw pixels (nothing padded)."""
    g = cv2.getGaussianKernel(11, 1.5)
    w = g @ g.T
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    vals = []
    for i in range(5, a.shape[0] - 5):
        for j in range(5, a.shape[1] - 5):
            x, y = a[i - 5:i + 6, j - 5:j + 6], b[i - 5:i + 6, j - 5:j + 6]
            mx, my = (w * x).sum(), (w * y).sum()
            sxx, syy = (w * x * x).sum() - mx * mx, (w * y * y).sum() - my * my
            sxy = (w * x * y).sum() - mx * my
            vals.append((2 * mx * my + c1) * (2 * sxy + c2) / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    return float(np.mean(vals))


def test_ssim_identity_offset_and_noise():
    a = _smooth_image()
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-9)
    # a constant offset only changes the luminance term: 2 mu (mu + d) + C1 over mu^2 + (mu + d)^2 + C1
    mu, d, c1 = 130.0, 20.0, (0.01 * 255) ** 2
    flat = np.full((40, 40), mu)
    assert ssim(flat, flat + d) == pytest.approx((2 * mu * (mu + d) + c1) / (mu ** 2 + (mu + d) ** 2 + c1), rel=1e-6)
    noisy = a + np.random.default_rng(1).normal(0, 20, a.shape)
    worse = a + np.random.default_rng(1).normal(0, 60, a.shape)
    assert 1.0 > ssim(a, noisy) > ssim(a, worse) > 0.0
    with pytest.raises(GelsimError, match="shapes"):
        ssim(a, a[:-1])


def test_ssim_edges_are_the_valid_region():
    """The mean runs over window centres >= 5 px from every edge, on the raw pixels (no padding)."""
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 255, (17, 14))
    b = np.clip(a + rng.normal(0, 25, a.shape), 0, 255)
    assert ssim(a, b) == pytest.approx(_ssim_by_hand(a, b), rel=1e-9)
    # channels are scored apart and averaged
    ab = np.stack([a, b, a], -1)
    ba = np.stack([b, a, a], -1)
    assert ssim(ab, ba) == pytest.approx((2 * _ssim_by_hand(a, b) + 1.0) / 3, rel=1e-9)
    # the smallest image has one valid centre; smaller ones are an error
    assert ssim(a[:11, :11], b[:11, :11]) == pytest.approx(_ssim_by_hand(a[:11, :11], b[:11, :11]), rel=1e-9)
    with pytest.raises(GelsimError, match="11 px"):
        ssim(a[:10], b[:10])


def test_uint8_and_float_inputs_agree():
    a = _smooth_image(shape=(30, 40, 3)).round().astype(np.uint8)
    b = np.clip(a.astype(int) + 7, 0, 255).astype(np.uint8)
    assert ssim(a, b) == pytest.approx(ssim(a.astype(float), b.astype(float)), rel=1e-12)
    assert mse(a, b) == pytest.approx(np.mean((a.astype(float) - b) ** 2))   # no uint8 wrap-around


def test_psnr():
    assert psnr(25.0) == pytest.approx(10 * math.log10(255 ** 2 / 25.0))
    assert psnr(1.0) == pytest.approx(20 * math.log10(metrics.PEAK_DN))
    assert psnr(0.0) == math.inf
    a = np.full((4, 4), 100.0)
    assert psnr(mse(a, a + 5)) == pytest.approx(psnr(25.0))
    with pytest.raises(GelsimError, match="shapes"):
        mse(a, a[:2])


def test_ssim_is_the_valid_region_of_the_map():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    b = np.clip(a + rng.normal(0, 25, a.shape), 0, 255).astype(np.uint8)
    m = ssim_map(a, b)
    assert m.shape == a.shape and m.dtype == np.float64
    assert ssim(a, b) == pytest.approx(m[5:-5, 5:-5].mean(), rel=1e-12)
    assert m[5:-5, 5:-5].mean() != pytest.approx(m.mean(), rel=1e-6)    # the border differs
    np.testing.assert_allclose(ssim_map(a[:4, :4], a[:4, :4]), 1.0)     # no size limit on the map
