"""The texture stage's fused kernels against the OpenCV passes they replace (gelsim/gel/texture_kernels.py)."""
import cv2
import numpy as np
import pytest

from gelsim.gel import texture_kernels as K

FS = (1, 2, 3, 6, 7)


def _grow(field, shape):
    """OpenCV's reading of a coarse field at full resolution (the kernels' contract)."""
    return cv2.resize(field, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def _cells(a, fs):
    """OpenCV's area average over whole fs x fs cells."""
    return cv2.resize(a, (a.shape[1] // fs, a.shape[0] // fs), interpolation=cv2.INTER_AREA)


def _case(fs, seed=0, rows=9, cols=13):
    rng = np.random.default_rng([seed, fs])
    shape = (rows * fs, cols * fs)
    t = (rng.random(shape, dtype=np.float32) - 1.0) * np.float32(0.05)
    coarse = [rng.random((rows, cols), dtype=np.float32) + np.float32(0.5) for _ in range(4)]
    return rng, shape, t, coarse


@pytest.mark.parametrize("fs", FS)
def test_restore_band_equals_the_opencv_passes(fs):
    _, shape, t, (mean, gain, share, _) = _case(fs)
    tq = cv2.GaussianBlur(t, (0, 0), 1.0, borderType=cv2.BORDER_REPLICATE)
    nx = shape[1]
    te, tf, sums = K.restore_band(t, tq, K.widen(mean, nx), K.widen(1.0 / gain, nx), K.widen(share, nx), fs)
    m = _grow(mean, shape)
    band = m + (tq - m) * _grow(1.0 / gain, shape)
    assert np.allclose(te, band * _grow(share, shape), atol=1e-6)
    assert np.allclose(tf, t - band, atol=1e-6)
    assert np.allclose(sums / fs**2, _cells((t - band) ** 2, fs), rtol=1e-4, atol=1e-9)
    assert np.allclose(K.band_share(t, K.widen(share, nx), fs), t * _grow(share, shape), atol=1e-7)


@pytest.mark.parametrize("fs", FS)
def test_slope_and_moment_sums_equal_sobel_and_area_average(fs):
    _, shape, t, _ = _case(fs, seed=1)
    rows, cols = shape[0] // fs, shape[1] // fs
    d = 0.02
    gx = cv2.Sobel(t, cv2.CV_32F, 1, 0, ksize=1, scale=0.5 / d)
    gy = cv2.Sobel(t, cv2.CV_32F, 0, 1, ksize=1, scale=0.5 / d)
    slope = K.slope_sums(t, d, fs, rows, cols) / fs**2
    ref = _cells(gx * gx + gy * gy, fs)
    assert np.allclose(slope, ref, rtol=1e-4)
    mom = K.moment_sums(t, d, fs, rows, cols) / np.float32(fs**2)
    for k, a in enumerate((t, t * t, gx * gx, gy * gy, gx * gy)):
        ref = _cells(a, fs)
        assert np.allclose(mom[..., k], ref, rtol=1e-4, atol=1e-6 * np.abs(ref).max()), k


@pytest.mark.parametrize("fs", FS)
def test_press_texture_is_johnsons_map(fs):
    rng, shape, t, (cut, span, kept, field) = _case(fs, seed=2)
    cut *= np.float32(0.02)
    span = span - np.float32(0.5)
    nx = shape[1]
    tf = (rng.random(shape, dtype=np.float32) - 0.5) * np.float32(0.01)
    g, touch, sums = K.press_texture(t, tf, K.widen(cut, nx), K.widen(span, nx), K.widen(kept, nx), fs, True)
    below = np.minimum(t + _grow(cut, shape), 0.0)
    ref = t - _grow(span, shape) * below
    inside = below >= 0
    ref[inside] += (tf * _grow(kept, shape))[inside]
    # Both the contact and its complement occur in this case, so each branch is checked.
    assert 0 < inside.mean() < 1
    assert np.array_equal(touch, inside)
    assert np.allclose(g, ref, atol=1e-7)
    assert np.allclose(sums / fs**2, _cells(ref, fs), atol=1e-7)
    g0, _, _ = K.press_texture(t, tf, K.widen(cut, nx), K.widen(span, nx), K.widen(kept, nx), fs, False)
    assert np.allclose(g0, t - _grow(span, shape) * below, atol=1e-7)
    out = K.minus_field(g, K.widen(field, nx), fs, shape[0] - 3, nx - 2)
    assert out.shape == (shape[0] - 3, nx - 2)
    assert np.allclose(out, (g - _grow(field, shape))[:-3, :-2], atol=1e-6)
    full = _grow(field, shape)
    for y, x in ((0, 0), (shape[0] - 1, nx - 1), (shape[0] // 2, nx // 3), (fs // 2, 1)):
        assert K.field_at(field, fs, y, x) == pytest.approx(float(full[y, x]), abs=1e-6)
