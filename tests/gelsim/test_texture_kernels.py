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
    te, tf, sums, slopes = K.restore_band(t, tq, K.widen(mean, nx), K.widen(1.0 / gain, nx), K.widen(share, nx),
                                          fs, 0.02)
    m = _grow(mean, shape)
    band = m + (tq - m) * _grow(1.0 / gain, shape)
    assert np.allclose(te, band * _grow(share, shape), atol=1e-6)
    assert np.allclose(tf, t - band, atol=1e-6)
    assert np.allclose(sums / fs**2, _cells((t - band) ** 2, fs), rtol=1e-4, atol=1e-9)
    # tf's slopes, taken one row behind inside the pass: slope_sums' own pass over tf, bit for bit
    assert np.array_equal(slopes, K.slope_sums(tf, 0.02, fs, *sums.shape))
    assert np.allclose(K.band_share(t, K.widen(share, nx), fs), t * _grow(share, shape), atol=1e-7)


@pytest.mark.parametrize("fs", (1, 2, 3, 6))
def test_cell_sums_add_each_cell_in_order(fs):
    # The kernels sum the cells side by side so that the loop vectorises; each cell must still be
    # the plain float64 sum of its pixels from left to right (the order the statistics were made in).
    rng = np.random.default_rng(fs)
    # magnitudes over 24 decades, so that float64 rounds the sums and their order shows
    row = (rng.standard_normal(12 * fs) * 10.0 ** rng.uniform(-12, 12, 12 * fs)).astype(np.float32)
    sums = np.full((2, 12), 0.25)
    K._add_cells(row, fs, sums, 1, np.empty(12))
    for c in range(12):
        acc = 0.0
        for v in row[c * fs:(c + 1) * fs]:
            acc += float(v)
        assert sums[1, c] == 0.25 + acc
    assert np.all(sums[0] == 0.25)


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
    # The texture onto a depth window smaller than the padded arrays, in place.
    depth = np.zeros((shape[0] + 2, nx + 1), np.float32)
    depth[:] = rng.random(depth.shape, dtype=np.float32) * np.float32(0.02)
    win = depth[1:shape[0] - 2, :nx - 2]
    before = win.copy()
    in_macro = rng.random(win.shape) < 0.7
    mask = np.ones((shape[0] + 5, nx), bool)
    K.add_texture(win, g, K.widen(field, nx), fs, in_macro, touch, mask[2:shape[0] - 1, 1:nx - 1])
    ref = np.maximum(before + np.where(in_macro, (g - _grow(field, shape))[:-3, :-2], 0.0), 0.0)
    assert (ref == 0).any() and (ref > 0).any()
    assert np.allclose(win, ref, atol=1e-6)
    assert np.array_equal(mask[2:shape[0] - 1, 1:nx - 1], in_macro & touch[:-3, :-2])
    assert mask[0].all() and mask[:, 0].all()   # outside the window: untouched
    full = _grow(field, shape)
    for y, x in ((0, 0), (shape[0] - 1, nx - 1), (shape[0] // 2, nx // 3), (fs // 2, 1)):
        assert K.field_at(field, fs, y, x) == pytest.approx(float(full[y, x]), abs=1e-6)


# ---------------------------------------------------------------- the statistics grid's cell kernels

def _sinc_ref(qdx2, d):
    qr = np.minimum(np.sqrt(qdx2.astype(np.float64)) * d, 1.0)
    return np.where(qr > 0, np.arcsin(qr) / np.maximum(qr, 1e-300), 1.0) ** 2


def test_asin_over_x_matches_arcsin_to_float32_rounding():
    from numba import njit

    @njit
    def many(x):
        out = np.empty_like(x)
        for i in range(x.size):
            out[i] = K._asin_over_x(x[i])
        return out

    x = np.linspace(0.0, 1.0, 100_001).astype(np.float32)
    ref = np.where(x > 0, np.arcsin(x.astype(np.float64)) / np.maximum(x, 1e-30), 1.0)
    assert np.abs(many(x) / ref - 1.0).max() < 3e-6


def _moments(rng, rows=11, cols=17):
    mom = np.empty((rows, cols, 5), np.float32)
    mom[..., 0] = rng.normal(-0.02, 0.005, (rows, cols))
    var = rng.uniform(1e-7, 1e-4, (rows, cols))
    mom[..., 1] = mom[..., 0].astype(np.float64) ** 2 + var
    gxx, gyy = rng.uniform(0.0, 0.02, (2, rows, cols))
    mom[..., 2], mom[..., 3] = gxx, gyy
    mom[..., 4] = rng.uniform(-1.0, 1.0, (rows, cols)) * np.sqrt(gxx * gyy)
    mom[0, 0, 1] = mom[0, 0, 0] ** 2 - 1e-6   # a box filter's negative variance: floored
    mom[0, 1, 2:] = 0.0                      # a flat cell
    return mom


def test_band_cells_are_the_corrected_moments():
    rng = np.random.default_rng(5)
    mom = _moments(rng)
    d, q_lo, q_hi = 0.03, 2.0, np.pi / 0.03
    var, q, aniso, mean = K.band_cells(mom, np.float32(d), np.float32(q_lo), np.float32(q_hi))
    m = mom[..., 0].astype(np.float64)
    v = np.maximum(mom[..., 1] - m * m, K.VAR_FLOOR_MM2)
    gxx = np.maximum(mom[..., 2], 0.0)
    gyy = np.maximum(mom[..., 3], 0.0)
    cx, cy = _sinc_ref(gxx / v, d), _sinc_ref(gyy / v, d)
    gxx, gyy, gxy = gxx * cx, gyy * cy, mom[..., 4] * np.sqrt(cx * cy)
    s2 = gxx + gyy
    assert np.allclose(var, v, rtol=1e-3, atol=1e-12)
    assert np.array_equal(mean, mom[..., 0])
    assert np.allclose(q, np.clip(np.sqrt(s2 / v), q_lo, q_hi), rtol=1e-4)
    ref_a = np.minimum(np.sqrt((gxx - gyy) ** 2 + 4 * gxy ** 2) / np.maximum(s2, K.VAR_FLOOR_MM2), 1.0)
    assert np.allclose(aniso, ref_a, atol=1e-4)
    assert q[0, 1] == np.float32(q_lo) and aniso[0, 1] == 0.0


def _share_ref(q, e_star, yarn_comp, cloth_k, ell):
    comp = yarn_comp + (0.0 if cloth_k is None else 1.0 / (cloth_k * (1.0 + (q * ell) ** 2)))
    return 1.0 / (1.0 + e_star / 2.0 * q * comp)


@pytest.mark.parametrize("blur_mm, support", [(0.0, None), (0.02, (0.5, None)), (0.03, (0.5, (0.8, 0.4)))])
def test_map_cells_are_johnsons_tables(blur_mm, support):
    from gelsim.gel.johnson import TableLookup, segment_arrays

    rng = np.random.default_rng(6)
    rows, cols = 13, 19
    var = rng.uniform(1e-7, 1e-4, (rows, cols)).astype(np.float32)
    q = rng.uniform(3.0, 60.0, (rows, cols)).astype(np.float32)
    aniso = rng.uniform(0.0, 1.0, (rows, cols)).astype(np.float32)
    aniso[0, :3] = (0.0, 1.0, 0.5)
    p = rng.uniform(0.0, 0.08, (rows, cols)).astype(np.float32)
    e_star, s_max = 0.26, 1e3
    yarn_comp, cloth = (0.0, None) if support is None else support
    has_cloth = cloth is not None
    cloth_k, ell = cloth if has_cloth else (1.0, 0.0)
    gain = np.exp(-0.5 * (q * np.float32(blur_mm)) ** 2).astype(np.float32)
    inv_gain, share, d_eff, span, phi = K.map_cells(
        var, q, aniso, p, gain, np.float32(e_star), np.float32(yarn_comp), has_cloth,
        np.float32(cloth_k), np.float32(ell), np.float32(s_max), *segment_arrays())
    q64 = q.astype(np.float64)
    sh = _share_ref(q64, e_star, yarn_comp, cloth_k if has_cloth else None, ell)
    depth = np.sqrt(var / gain**2) * (4.0 - (4.0 - 2.0 * np.sqrt(2.0)) * aniso)
    de = np.maximum(depth * sh, K.DEPTH_FLOOR_MM)
    s = np.minimum(p / (e_star / 4.0 * q64 * de), s_max)
    tabs = TableLookup(s.astype(np.float32), aniso)
    assert np.allclose(inv_gain, 1.0 / gain, rtol=1e-5)
    assert np.allclose(share, sh, rtol=1e-5)
    assert np.allclose(d_eff, de, rtol=1e-4)
    assert np.allclose(span, 1.0 - tabs.blend("lam"), atol=2e-4)
    assert np.allclose(phi, tabs.blend("contact_fraction"), atol=2e-4)
    assert (s >= 1).any() and (s < 1).any()    # both sides of complete contact were read
    assert np.all(phi[s >= 1.0001] == 1.0) and np.all(span[s >= 1.0001] == 0.0)


def test_fine_cells_print_the_kept_fundamental_on_the_crowns():
    from gelsim.gel.johnson import kept_relief, segment_arrays

    rng = np.random.default_rng(7)
    rows, cols = 12, 15
    var_f = rng.uniform(1e-9, 1e-6, (rows, cols)).astype(np.float32)
    g2 = rng.uniform(0.0, 5e-3, (rows, cols)).astype(np.float32)
    p = rng.uniform(0.0, 0.05, (rows, cols)).astype(np.float32)
    phi = rng.uniform(0.0, 1.0, (rows, cols)).astype(np.float32)
    dx, q_lo, e_star, yarn_comp, cloth_k, ell = 0.035, 2.0, 0.26, 0.4, 0.9, 0.3
    q_hi = np.pi / dx
    kept = K.fine_cells(var_f, g2, np.float32(dx), np.float32(q_lo), np.float32(q_hi), p, phi, np.float32(e_star),
                        np.float32(yarn_comp), True, np.float32(cloth_k), np.float32(ell), np.float32(1e3),
                        *segment_arrays())
    v = var_f.astype(np.float64)
    g = g2 * _sinc_ref(0.5 * g2 / v, dx)
    qf = np.clip(np.sqrt(g / v), q_lo, q_hi)
    sh = _share_ref(qf, e_star, yarn_comp, cloth_k, ell)
    s = np.minimum(p / np.maximum(phi, K.PHI_FLOOR) / (e_star / 4.0 * qf * np.maximum(4.0 * np.sqrt(v) * sh, 1e-9)), 1e3)
    ref = kept_relief(s.astype(np.float32), None) * sh
    assert (s >= 1).any() and (s < 1).any()
    assert np.allclose(kept, ref, atol=2e-4)


@pytest.mark.parametrize("fs", (1, 2, 5, 15))
def test_macro_floor_is_the_upsampled_penetration_cut_at_the_contact(fs):
    # press_twoscale's floor under the gel: the coarse compression and contact indicator read at the
    # window's pixels as OpenCV's resize reads them, the indicator cut at one half, and the depth
    # raised to the penetration there (one pass in place of six OpenCV calls).
    rng = np.random.default_rng(fs)
    rows, cols = 7, 9
    comp = (rng.random((rows, cols), dtype=np.float32) * np.float32(0.01))
    inside = (rng.random((rows, cols)) < 0.6).astype(np.float32)
    up_shape = (rows * fs, cols * fs)
    oy, ox = fs // 2 + 1, fs // 3 + 2
    ny, nx = up_shape[0] - oy - fs, up_shape[1] - ox - fs
    env = (rng.random((ny, nx), dtype=np.float32) - np.float32(0.5)) * np.float32(0.1)
    depth = rng.random((ny, nx), dtype=np.float32) * np.float32(0.05)
    gamma = np.float32(0.03)
    got_depth = depth.copy()
    got = K.macro_floor(got_depth, env, K.widen(comp, up_shape[1])[:, ox:ox + nx],
                        K.widen(inside, up_shape[1])[:, ox:ox + nx], fs, oy, gamma)
    up_c = _grow(comp, up_shape)[oy:oy + ny, ox:ox + nx]
    up_i = _grow(inside, up_shape)[oy:oy + ny, ox:ox + nx]
    want = up_i >= 0.5
    undecided = np.abs(up_i - 0.5) < 1e-6
    assert got.shape == want.shape and got.dtype == bool
    assert np.array_equal(got[~undecided], want[~undecided])
    assert 0 < want.mean() < 1
    pen = env.astype(np.float64) - up_c + gamma
    ref = np.maximum(depth, np.where(got, pen, 0.0))
    assert np.allclose(got_depth, ref, rtol=0, atol=1e-7)
    assert np.any(got_depth > depth) and np.all(got_depth >= depth)
