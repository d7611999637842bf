"""The numpy backend's fused numba kernels of the markers and of the readout against the OpenCV passes they
replace (gelsim/optics/ops/markers.py, gelsim/optics/ops/readout.py)."""
import math

import cv2
import numpy as np
import pytest

from gelsim.optics.ops import markers as M
from gelsim.optics.ops import readout as R
from gelsim.optics.ops.readout import NoiseBank

PAD = 8
# a * a = 1 + 2^-11 + 2^-24 exactly: the 2^-24 survives a fused multiply-add only (a float32 multiply drops it)
_A = 1.0 + 2.0 ** -12
_C = -(1.0 + 2.0 ** -11)


def _opencv_fuses():
    """Whether OpenCV's addWeighted rounds ``a * alpha + gamma`` once (FMA instructions) on this CPU."""
    a = np.full((4, 64), _A, np.float32)
    return bool((cv2.addWeighted(a, _A, a, 0.0, _C) == 2.0 ** -24).all())


FUSES = _opencv_fuses()


def _frame(rng, h, w):
    """float32 (h, w, 3) DN beyond both ends of 8 bits, a third of it on exact ties (x.5)."""
    f = (rng.random((h, w, 3), dtype=np.float32) * 320.0 - 30.0).astype(np.float32)
    f[::3] = np.floor(f[::3]) + np.float32(0.5)
    return f


def _opencv_shot(frame, z, gain, read_var):
    """NoiseBank's former shot-noise passes (OpenCV)."""
    var = cv2.addWeighted(frame, gain, frame, 0.0, read_var)
    cv2.max(var, 0.0, var)
    cv2.sqrt(var, var)
    cv2.multiply(var, z, var)
    return cv2.add(frame, var, dtype=cv2.CV_8U)


def _kernel(fn, frame, bank, oy, ox, *scalars):
    h, w, c = frame.shape
    out = np.empty_like(frame, dtype=np.uint8)
    fn(frame.reshape(h, w * c), bank.reshape(bank.shape[0], -1), oy, c * ox,
       *(np.float32(s) for s in scalars), out.reshape(h, w * c))
    return out


@pytest.mark.parametrize("shape", [(5, 7), (33, 61), (120, 160)])
def test_add_noise_equals_addweighted_into_8_bits(shape):
    rng = np.random.default_rng(shape)
    h, w = shape
    bank = rng.standard_normal((h + PAD, w + PAD, 3), dtype=np.float32)
    for sigma in (0.0, 0.92, 3.7, 40.0):
        frame = _frame(rng, h, w)
        oy, ox = (int(v) for v in rng.integers(PAD + 1, size=2))
        z = bank[oy:oy + h, ox:ox + w]
        ref = cv2.addWeighted(frame, 1.0, z, float(np.float32(sigma)), 0.0, dtype=cv2.CV_8U)
        got = _kernel(R.add_noise_u8, frame, bank, oy, ox, sigma)
        np.testing.assert_array_equal(got, ref)
    assert (ref == 0).any() and (ref == 255).any()      # both saturations were exercised


@pytest.mark.skipif(not FUSES,
                    reason="OpenCV's addWeighted rounds the variance twice without FMA instructions")
@pytest.mark.parametrize("shape", [(5, 7), (33, 61), (120, 160)])
def test_add_shot_noise_equals_the_opencv_passes(shape):
    rng = np.random.default_rng([1, *shape])
    h, w = shape
    bank = rng.standard_normal((h + PAD, w + PAD, 3), dtype=np.float32)
    for gain, read_var in ((0.0026, 0.95), (0.03, 0.0), (5.0, 2500.0), (0.37, 1.3)):
        g, rv = float(np.float32(gain)), float(np.float32(read_var))
        for _ in range(3):
            frame = _frame(rng, h, w)
            oy, ox = (int(v) for v in rng.integers(PAD + 1, size=2))
            ref = _opencv_shot(frame, bank[oy:oy + h, ox:ox + w], g, rv)
            got = _kernel(R.add_shot_noise_u8, frame, bank, oy, ox, gain, read_var)
            np.testing.assert_array_equal(got, ref)


def test_fma32_rounds_once():
    """fma(a, b, c) keeps the product's low bits that a float32 multiply then add loses."""
    from numba import njit

    @njit
    def f(a, b, c):
        return R.fma32(a, b, c)

    a, c = np.float32(_A), np.float32(_C)
    assert f(a, a, c) == np.float32(2.0 ** -24)
    assert np.float32(a * a) + c == 0.0


@pytest.mark.parametrize("shot_gain", [0.0, 0.0026])
def test_noise_bank_apply_equals_the_opencv_passes(shot_gain):
    """NoiseBank.apply (the renderer's noise) gives the frames its former OpenCV passes gave."""
    h, w = 48, 64
    bank = NoiseBank((h, w), 0.92, shot_gain, seed=3)
    rng = np.random.default_rng(7)
    for seed in range(6):
        frame = _frame(rng, h, w)
        z = bank.pick(seed)
        if shot_gain == 0:
            ref = cv2.addWeighted(frame, 1.0, z, math.sqrt(bank.read_var), 0.0, dtype=cv2.CV_8U)
        else:
            ref = _opencv_shot(frame, z, bank.shot_gain, bank.read_var)
        got = bank.apply(frame, seed)
        if shot_gain and not FUSES:
            assert np.abs(got.astype(int) - ref).max() <= 1
        else:
            np.testing.assert_array_equal(got, ref)
    # the generator form draws the same field as the seed it was made from
    np.testing.assert_array_equal(bank.apply(frame, np.random.default_rng(5)), bank.apply(frame, 5))


def test_noise_kernels_round_as_opencv_on_crafted_pixels():
    """Pixels where another order of rounding gives another DN: a tie broken by a noise below half a
    float32 step (the float32 sum stays on the tie, which goes to even), and a variance that only a
    fused multiply-add keeps (1 DN of it, scaled by a large z, is 50 DN)."""
    h, w = 2, 64
    bank = np.zeros((h + PAD, w + PAD, 3), np.float32)
    frame = np.full((h, w, 3), 100.5, np.float32)
    bank[...] = 2.0 ** -20                       # 100.5 + 2^-20 rounds back to 100.5 in float32
    ref = cv2.addWeighted(frame, 1.0, bank[:h, :w], 1.0, 0.0, dtype=cv2.CV_8U)
    assert (ref == 100).all()
    np.testing.assert_array_equal(_kernel(R.add_noise_u8, frame, bank, 0, 0, 1.0), ref)
    if not FUSES:
        pytest.skip("OpenCV's addWeighted rounds the variance twice without FMA instructions")
    frame = np.full((h, w, 3), _A, np.float32)
    bank[...] = 50.0 * 2.0 ** 12                 # sqrt(2^-24) * z = 50 DN
    ref = _opencv_shot(frame, bank[:h, :w], _A, _C)
    assert (ref == 51).all()
    np.testing.assert_array_equal(_kernel(R.add_shot_noise_u8, frame, bank, 0, 0, _A, _C), ref)


# ---------------------------------------------------------------- markers


def _numpy_coverage(corners, pad_px):
    """The former numpy marker_coverage: (origin, coverage (N, P, P))."""
    n = corners.shape[0]
    lo = np.floor(corners.min(axis=1)).astype(np.int64) - pad_px
    size = int(np.ceil(corners.max(axis=1) - corners.min(axis=1)).max()) + 2 * pad_px + 2
    grid = np.arange(size, dtype=np.float32)
    xs = (lo[:, 0:1] + grid[None, :]).astype(np.float32)[:, None, :]
    ys = (lo[:, 1:2] + grid[None, :]).astype(np.float32)[:, :, None]
    v0 = corners
    v1 = np.roll(corners, -1, axis=1)
    e = v1 - v0
    area2 = (v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]).sum(axis=1)
    sign = np.where(area2 >= 0, 1.0, -1.0).astype(np.float32)[:, None]
    length = np.maximum(np.linalg.norm(e, axis=-1), 1e-6)
    nx, ny = -e[..., 1] * sign / length, e[..., 0] * sign / length
    c = -(nx * v0[..., 0] + ny * v0[..., 1])
    cov = np.ones((n, size, size), np.float32)
    for k in range(4):
        d = nx[:, k, None, None] * xs + ny[:, k, None, None] * ys
        d += (c[:, k] + 0.5)[:, None, None]
        np.clip(d, 0.0, 1.0, out=d)
        cov *= d
    return lo, cov


def _opencv_apply(frame, lo, strip):
    """The former apply_marker_factors: a 3-channel factor, one cv2.multiply per patch, in marker order."""
    factor = cv2.merge([strip] * frame.shape[2])
    h, w = frame.shape[:2]
    p = factor.shape[0]
    for i, (x0, y0) in enumerate(lo.tolist()):
        ax, ay = max(x0, 0), max(y0, 0)
        bx, by = min(x0 + p, w), min(y0 + p, h)
        if bx <= ax or by <= ay:
            continue
        region = frame[ay:by, ax:bx]
        cv2.multiply(region, factor[ay - y0:by - y0, i * p + ax - x0:i * p + bx - x0], region)


def _quads(rng, n, h, w, size=9.0):
    """Sheared, turned, stretched squares (either winding), some across the frame's edges, some overlapping."""
    centres = np.column_stack([rng.uniform(-6, w + 6, n), rng.uniform(-6, h + 6, n)])
    base = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * size / 2
    quads = []
    for c in centres:
        a = np.eye(2) + rng.normal(0, 0.15, (2, 2))
        q = base @ a.T
        quads.append((q[::-1] if rng.random() < 0.3 else q) + c)
    return np.asarray(quads, np.float32)


@pytest.mark.parametrize("pad", [1, 3])
def test_marker_coverage_equals_the_numpy_expression(pad):
    from gelsim.optics.ops.markers import coverage_strip

    rng = np.random.default_rng(pad)
    for _ in range(5):
        corners = _quads(rng, 40, 60, 80) + rng.random((40, 1, 2)).astype(np.float32)
        lo_ref, ref = _numpy_coverage(corners, pad)
        lo, strip = coverage_strip(corners, pad)
        n, p, _ = ref.shape
        cov = strip.reshape(p, n, p).transpose(1, 0, 2)
        np.testing.assert_array_equal(lo, lo_ref)
        np.testing.assert_array_equal(cov, ref)
        np.testing.assert_array_equal(strip, ref.transpose(1, 0, 2).reshape(p, n * p))
    assert 0.0 < ref.mean() < 1.0 and (ref == 1.0).any()


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_multiply_patches_equals_a_multiply_per_patch(channels):
    """Patches overlap and cross every edge of the frame: the products, in marker order, are OpenCV's."""
    rng = np.random.default_rng(channels)
    h, w = 50, 70
    corners = _quads(rng, 60, h, w)
    lo, cov = _numpy_coverage(corners, 2)
    n, p, _ = cov.shape
    strip = (1.0 - 0.8 * cov.transpose(1, 0, 2).reshape(p, n * p)).astype(np.float32)
    strip += rng.normal(0, 1e-3, strip.shape).astype(np.float32)     # no factor exactly 1: order shows
    frame = (rng.random((h, w, channels), dtype=np.float32) * 255).astype(np.float32)
    ref = frame.copy()
    _opencv_apply(ref, lo, strip)
    got = frame.copy()
    M.multiply_patches_rows(got, lo, strip, 0)
    np.testing.assert_array_equal(got, ref)
    assert (lo < 0).any() and (lo[:, 0] + p > w).any() and (lo[:, 1] + p > h).any()


def test_marker_factors_darken_as_before():
    """The renderer's markers: factors and darkened frame bit for bit those of the former OpenCV passes."""
    from gelsim.optics.ops.markers import apply_marker_factors, marker_factors

    rng = np.random.default_rng(11)
    h, w = 72, 96
    for sigma in (0.0, 0.6, 1.3):
        corners = _quads(rng, 50, h, w, size=7.0)
        corners[0] += 1000.0                                 # wholly outside: left out
        frame = (rng.random((h, w, 3), dtype=np.float32) * 255).astype(np.float32)
        lo, factor = marker_factors(corners, 0.7, sigma, frame.shape)
        r = int(math.ceil(3.0 * sigma)) if sigma > 0 else 0
        inside = ((corners.max(axis=1) >= -r - 1) & (corners.min(axis=1) <= np.array([w, h]) + r)).all(axis=1)
        assert not inside[0] and inside[1:].sum() > 40
        lo_ref, cov = _numpy_coverage(corners[inside], r + 1)
        n, p, _ = cov.shape
        strip = np.ascontiguousarray(cov.transpose(1, 0, 2).reshape(p, n * p))
        if r:
            strip = cv2.GaussianBlur(strip, (2 * r + 1, 2 * r + 1), sigma, borderType=cv2.BORDER_REPLICATE)
        strip = cv2.addWeighted(strip, -0.7, strip, 0.0, 1.0)
        np.testing.assert_array_equal(lo, lo_ref)
        np.testing.assert_array_equal(factor, strip)
        ref = frame.copy()
        _opencv_apply(ref, lo_ref, strip)
        apply_marker_factors(frame, (lo, factor))
        np.testing.assert_array_equal(frame, ref)


def test_multiply_patches_band_by_band_equals_the_whole_frame():
    """The renderer darkens markers band by band (multiply_patches_rows on each band's own rows): the
    same products as one pass over the frame, whatever the bands' height, patches crossing their edges."""
    rng = np.random.default_rng(5)
    h, w = 50, 70
    corners = _quads(rng, 60, h, w)
    lo, cov = _numpy_coverage(corners, 2)
    n, p, _ = cov.shape
    strip = (1.0 - 0.8 * cov.transpose(1, 0, 2).reshape(p, n * p)).astype(np.float32)
    strip += rng.normal(0, 1e-3, strip.shape).astype(np.float32)
    frame = (rng.random((h, w, 3), dtype=np.float32) * 255).astype(np.float32)
    ref = frame.copy()
    M.multiply_patches_rows(ref, lo, strip, 0)
    assert (ref != frame).mean() > 0.3
    for band in (1, 3, 7, 16, h):
        got = frame.copy()
        for y0 in range(0, h, band):
            rows = np.ascontiguousarray(got[y0:y0 + band])    # a separate buffer, as the renderer's band
            M.multiply_patches_rows(rows, lo, strip, y0)
            got[y0:y0 + band] = rows
        np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("shot_gain", [0.0, 0.03])
def test_noise_band_by_band_equals_the_whole_frame(shot_gain):
    """NoiseBank.apply_rows on bands (separate buffers, as the renderer's) writes what apply writes."""
    rng = np.random.default_rng(6)
    h, w = 37, 53
    nb = NoiseBank((h, w), 2.0, shot_gain, seed=3, frames=2, pad_px=PAD)
    frame = _frame(rng, h, w)
    for seed in range(4):
        ref = nb.apply(frame, seed)
        for band in (1, 5, 16):
            out = np.zeros((h, w, 3), np.uint8)
            off = nb.offsets(seed)
            for y0 in range(0, h, band):
                nb.apply_rows(np.ascontiguousarray(frame[y0:y0 + band]), off, out, y0)
            np.testing.assert_array_equal(out, ref)
