"""The compositing's fused kernels against the OpenCV passes they replace (gelsim/optics/kernels.py)."""
import math

import cv2
import numpy as np
import pytest

from gelsim.optics import kernels as K
from gelsim.optics.composite import NoiseBank

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
        got = _kernel(K.add_noise_u8, frame, bank, oy, ox, sigma)
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
            got = _kernel(K.add_shot_noise_u8, frame, bank, oy, ox, gain, read_var)
            np.testing.assert_array_equal(got, ref)


def test_fma32_rounds_once():
    """fma(a, b, c) keeps the product's low bits that a float32 multiply then add loses."""
    from numba import njit

    @njit
    def f(a, b, c):
        return K.fma32(a, b, c)

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
    np.testing.assert_array_equal(_kernel(K.add_noise_u8, frame, bank, 0, 0, 1.0), ref)
    if not FUSES:
        pytest.skip("OpenCV's addWeighted rounds the variance twice without FMA instructions")
    frame = np.full((h, w, 3), _A, np.float32)
    bank[...] = 50.0 * 2.0 ** 12                 # sqrt(2^-24) * z = 50 DN
    ref = _opencv_shot(frame, bank[:h, :w], _A, _C)
    assert (ref == 51).all()
    np.testing.assert_array_equal(_kernel(K.add_shot_noise_u8, frame, bank, 0, 0, _A, _C), ref)
