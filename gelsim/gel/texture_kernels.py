"""Fused per-pixel passes of the two-scale imprint: its texture stage (:func:`gelsim.gel.twoscale.texture_depth`),
and the macro contact's floor under the gel (:func:`macro_floor`), which reads its coarse fields by the same contract.

The texture stage maps the texture ``t`` (full resolution) through fields that live on a coarse
*statistics grid* of ``fs`` x ``fs``-pixel cells (the texture's local mean, the blur's gain, the
gel's share of relief, Johnson's cut and span slope, the finer relief's kept fraction). Written
as OpenCV calls, each field is first interpolated to a full-resolution array and then combined
with the others, one pass over memory each: about 25 passes over a 960x720 window, which made the
stage memory-bound (and slower still with two workers sharing the memory bus). Here each pass
reads the coarse fields where it needs them and does all of its arithmetic per pixel, and the
cell sums the next step needs are gathered on the way.

Contract shared by every kernel:
- full-resolution arrays are float32 ``(NY, NX)`` with ``NY = rows * fs`` and ``NX = cols * fs``
  (the caller pads to whole cells); coarse fields are float32 ``(rows, cols)``;
- a coarse field is read at a pixel as OpenCV's ``resize(field, (NX, NY), INTER_LINEAR)`` reads it:
  cell ``c``'s value sits at pixel ``fs c + (fs - 1) / 2``, linear in between, held beyond the
  first and last centres;
- cell sums are float64 ``(rows, cols)``; dividing by ``fs * fs`` gives OpenCV's ``INTER_AREA``
  average over whole cells.

Numba compiles the kernels on first use (about a second, cached on disk afterwards). They use numpy's
error model (a division by zero gives inf, not an exception; every denominator here is floored):
Python's check before each division kept the loops from vectorising (10x slower on the cell kernels).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .johnson import KEYS as TABLE_KEYS

# Columns of johnson.segment_arrays read here.
CONTACT, KEPT, LAM = (TABLE_KEYS.index(k) for k in ("contact_fraction", "kept", "lam"))


@njit(cache=True, nogil=True, error_model="numpy")
def _rows(n_px: int, fs: int, n_cells: int):
    """Per pixel row: the two coarse rows to blend and the second's weight (see the contract)."""
    i0 = np.empty(n_px, np.int64)
    i1 = np.empty(n_px, np.int64)
    w = np.empty(n_px, np.float32)
    for x in range(n_px):
        u = (x + 0.5) / fs - 0.5
        k = max(0, min(int(np.floor(u)), n_cells - 1))
        i0[x] = k
        i1[x] = min(k + 1, n_cells - 1)
        w[x] = min(max(u - k, 0.0), 1.0) if i1[x] > k else 0.0
    return i0, i1, w


@njit(cache=True, nogil=True, error_model="numpy")
def _add_cells(row, fs: int, sums, ci: int, acc) -> None:
    """Add ``row`` (NX,) to the cell sums of coarse row ``ci``, fs pixels per cell; ``acc``: a
    float64 work row of at least ``sums.shape[1]``. Each cell's pixels are summed in float64 in
    order, the cells side by side (pixel k of every cell, then k + 1): the loop over cells
    vectorises, where one cell at a time (an inner loop of fs) did not (0.4 against 1.1 ms per
    960x720 pass at fs = 6; the same sums, bit for bit)."""
    cols = sums.shape[1]
    for c in range(cols):
        acc[c] = 0.0
    for k in range(fs):
        for c in range(cols):
            acc[c] += row[c * fs + k]
    s = sums[ci]
    for c in range(cols):
        s[c] += acc[c]


def widen(field: np.ndarray, nx: int) -> np.ndarray:
    """A coarse field read at full resolution along its rows only: float32 ``(rows, nx)`` (OpenCV's
    linear resize along x; the kernels blend between these rows per pixel row, which together is
    OpenCV's separable ``INTER_LINEAR`` resize to full resolution)."""
    import cv2

    return cv2.resize(field, (nx, field.shape[0]), interpolation=cv2.INTER_LINEAR)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def restore_band(t, tq, mean, inv_gain, share, fs: int, dx: float):
    """The texture's band restored to its height, split from the finer relief.

    ``t``: the texture (mm, <= 0); ``tq``: ``t`` blurred (its own band, lowered by the blur's
    gain); ``mean``: the band's local mean; ``inv_gain``: 1 / gain; ``share``: the gel's share of
    relief (coarse fields already :func:`widen`-ed); ``dx``: mm per pixel. Returns (te = share *
    restored band, mm; tf = t - restored band, mm; the cells' sums of tf^2; the cells' sums of
    tf's squared slope, :func:`slope_sums` of tf). The restored band is mean + (tq - mean) / gain:
    only the oscillation about the local mean was lowered by the blur. (The reciprocal is
    interpolated, not the gain: a division per pixel took 0.9 ms at 960x720. tf's slopes are taken
    one row behind, while its rows are in the cache: the same sums as slope_sums' own pass.)"""
    ny, nx = t.shape
    rows, cols = mean.shape[0], nx // fs
    ys0, ys1, wys = _rows(ny, fs, rows)
    te = np.empty_like(t)
    tf = np.empty_like(t)
    s_tf2 = np.zeros((rows, cols), np.float64)
    s_g2 = np.zeros((rows, cols), np.float64)
    acc = np.empty(cols, np.float64)
    sq = np.empty(nx, np.float32)
    h = np.float32(0.5 / dx)
    gx = np.empty(nx, np.float32)
    gy = np.empty(nx, np.float32)
    for i in range(ny):
        y0, y1, wy = ys0[i], ys1[i], wys[i]
        m0, m1, g0, g1, s0, s1 = mean[y0], mean[y1], inv_gain[y0], inv_gain[y1], share[y0], share[y1]
        ti, tqi, tei, tfi = t[i], tq[i], te[i], tf[i]
        for j in range(nx):
            m = m0[j] + wy * (m1[j] - m0[j])
            band = m + (tqi[j] - m) * (g0[j] + wy * (g1[j] - g0[j]))
            f = ti[j] - band
            tei[j] = band * (s0[j] + wy * (s1[j] - s0[j]))
            tfi[j] = f
            sq[j] = f * f
        _add_cells(sq, fs, s_tf2, i // fs, acc)
        if i >= 1:
            _slope_row(tf, i - 1, h, gx, gy, fs, s_g2, acc)
    if ny >= 1:
        _slope_row(tf, ny - 1, h, gx, gy, fs, s_g2, acc)
    return te, tf, s_tf2, s_g2


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def band_share(t, share, fs: int):
    """``te = share * t`` (mm) for a texture without a separate finer band (no blur); ``share``
    :func:`widen`-ed."""
    ny, nx = t.shape
    ys0, ys1, wys = _rows(ny, fs, share.shape[0])
    te = np.empty_like(t)
    for i in range(ny):
        s0, s1, wy = share[ys0[i]], share[ys1[i]], wys[i]
        ti, tei = t[i], te[i]
        for j in range(nx):
            tei[j] = ti[j] * (s0[j] + wy * (s1[j] - s0[j]))
    return te


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _slopes(b, i: int, h: float, gx, gy) -> None:
    """Row i of ``b``'s central-difference slopes into ``gx``, ``gy`` (nx,), ``h`` = 1 / (2 pixel size).
    At the array's edges the missing neighbour is mirrored about the edge pixel (OpenCV's default
    border for its derivative filters), which reads a zero slope across it."""
    ny, nx = b.shape
    up = b[i - 1] if i > 0 else b[min(1, ny - 1)]
    dn = b[i + 1] if i < ny - 1 else b[max(ny - 2, 0)]
    bi = b[i]
    for j in range(1, nx - 1):
        gx[j] = (bi[j + 1] - bi[j - 1]) * h
    gx[0] = 0.0
    gx[nx - 1] = 0.0
    for j in range(nx):
        gy[j] = (dn[j] - up[j]) * h


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def moment_sums(b, d: float, fs: int, rows: int, cols: int):
    """The cells' sums of b, b^2, bx^2, by^2 and bx by (b's slopes by :func:`_slopes`, mm/mm, at
    ``d`` mm per pixel): float32 ``(rows, cols, 5)``, ``fs`` x ``fs`` pixels per cell. (The five sums
    are gathered in one pass: five row passes and their cell sums took twice as long, four times at
    fs = 1, the half-resolution copy's usual cell at fine pitches. Within a row the cells are summed
    side by side, as in :func:`_add_cells`: 1.5 against 2.3 ms at fs = 1 on 480 x 360, the same sums.)"""
    ny, nx = b.shape
    h = np.float32(0.5 / d)
    gx = np.empty(nx, np.float32)
    gy = np.empty(nx, np.float32)
    if fs == 1:
        # A cell is a pixel: its sums are the pixel's own terms, written once (float32 products, as
        # the general path's float64 sums of one term round back to). 0.5 ms less per call at 480 x 360.
        one = np.empty((rows, cols, 5), np.float32)
        for i in range(ny):
            _slopes(b, i, h, gx, gy)
            bi, o = b[i], one[i]
            for c in range(cols):
                v, x, y = bi[c], gx[c], gy[c]
                o[c, 0] = v
                o[c, 1] = v * v
                o[c, 2] = x * x
                o[c, 3] = y * y
                o[c, 4] = x * y
        return one
    out = np.zeros((rows, cols, 5), np.float64)
    acc = np.empty((5, cols), np.float64)
    a0, a1, a2, a3, a4 = acc[0], acc[1], acc[2], acc[3], acc[4]
    for i in range(ny):
        _slopes(b, i, h, gx, gy)
        bi = b[i]
        o = out[i // fs]
        acc[:] = 0.0
        for k in range(fs):
            for c in range(cols):
                j = c * fs + k
                v, x, y = bi[j], gx[j], gy[j]
                a0[c] += v
                a1[c] += v * v
                a2[c] += x * x
                a3[c] += y * y
                a4[c] += x * y
        for c in range(cols):
            o[c, 0] += a0[c]
            o[c, 1] += a1[c]
            o[c, 2] += a2[c]
            o[c, 3] += a3[c]
            o[c, 4] += a4[c]
    return out.astype(np.float32)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _slope_row(tf, i: int, h, gx, gy, fs: int, out, acc) -> None:
    """Add row ``i``'s squared slopes |grad tf|^2 (:func:`_slopes`; ``gx``, ``gy`` work rows) to
    the cell sums ``out`` (float64 (rows, cols); ``acc`` as for :func:`_add_cells`)."""
    _slopes(tf, i, h, gx, gy)
    for j in range(gx.size):
        gx[j] = gx[j] * gx[j] + gy[j] * gy[j]
    _add_cells(gx, fs, out, i // fs, acc)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def slope_sums(tf, dx: float, fs: int, rows: int, cols: int):
    """The cells' sums of the squared slope |grad tf|^2 (:func:`_slopes`, mm/mm), float64 ``(rows, cols)``:
    a pass of its own over ``tf``, the reference for the sums :func:`restore_band` takes inside its pass."""
    ny, nx = tf.shape
    out = np.zeros((rows, cols), np.float64)
    h = np.float32(0.5 / dx)
    gx = np.empty(nx, np.float32)
    gy = np.empty(nx, np.float32)
    acc = np.empty(cols, np.float64)
    for i in range(ny):
        _slope_row(tf, i, h, gx, gy, fs, out, acc)
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def press_texture(te, tf, cut, span, kept_f, fs: int, with_fine: bool):
    """Johnson's map at every pixel, and the finer relief on the crowns in contact.

    ``te``: the gel's share of the texture's band (mm, <= 0 below the crowns); ``cut``: the depth
    below the crowns down to which the gel follows it (mm, >= 0); ``span``: 1 - the slope the gel
    keeps across a valley deeper than that; ``kept_f``: the fraction of the finer relief ``tf`` that
    prints on the crowns in contact (read only if ``with_fine``); the coarse fields :func:`widen`-ed.
    Returns (g: the gel surface's texture part, mm; in contact, bool; the cells' sums of g).
    g = te - span min(te + cut, 0) (+ kept_f tf where in contact)."""
    ny, nx = te.shape
    rows, cols = cut.shape[0], nx // fs
    ys0, ys1, wys = _rows(ny, fs, rows)
    g = np.empty_like(te)
    touch = np.empty((ny, nx), np.bool_)
    s_g = np.zeros((rows, cols), np.float64)
    acc = np.empty(cols, np.float64)
    zero = np.float32(0.0)
    for i in range(ny):
        y0, y1, wy = ys0[i], ys1[i], wys[i]
        c0, c1, p0, p1 = cut[y0], cut[y1], span[y0], span[y1]
        k0, k1 = kept_f[y0], kept_f[y1]
        gi, tei, tfi, touchi = g[i], te[i], tf[i], touch[i]
        for j in range(nx):
            e = tei[j]
            below = min(e + (c0[j] + wy * (c1[j] - c0[j])), zero)
            inside = below >= zero
            fine = tfi[j] * (k0[j] + wy * (k1[j] - k0[j])) if with_fine else zero
            gi[j] = e - (p0[j] + wy * (p1[j] - p0[j])) * below + (fine if inside else zero)
            touchi[j] = inside
        _add_cells(gi, fs, s_g, i // fs, acc)
    return g, touch, s_g


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def add_texture(depth, g, field, fs: int, in_macro, touch, mask) -> None:
    """The texture onto the gel's depth, in place: ``depth`` (mm, float32 (ny, nx), a view of the
    window) gains ``g - field`` (the texture's oscillation about its local mean; ``g`` and ``touch``
    cover at least (ny, nx), ``field`` coarse, :func:`widen`-ed) where ``in_macro`` (bool (ny, nx):
    the macro contact), and is floored at 0 everywhere; ``mask`` (bool (ny, nx), written) is
    in_macro and touch. (One pass where OpenCV took four: subtract, masked accumulate, max, and.)"""
    ny, nx = depth.shape
    ys0, ys1, wys = _rows(g.shape[0], fs, field.shape[0])
    zero = np.float32(0.0)
    for i in range(ny):
        f0, f1, wy = field[ys0[i]], field[ys1[i]], wys[i]
        gi, di, mi, ti, oi = g[i], depth[i], in_macro[i], touch[i], mask[i]
        for j in range(nx):
            d = di[j] + (gi[j] - (f0[j] + wy * (f1[j] - f0[j])) if mi[j] else zero)
            di[j] = max(d, zero)
            oi[j] = mi[j] and ti[j]


@njit(cache=True, nogil=True, error_model="numpy")
def macro_floor(depth, env, comp, inside, fs: int, oy: int, gamma):
    """The macro contact's floor under the gel, in place, and the contact itself.

    ``depth`` (mm, float32 (ny, nx), a view of the window) becomes max(depth, env - comp + gamma)
    where the contact indicator ``inside`` reads at least 1/2, and stays as it is elsewhere;
    ``env``: the object's crown envelope over the window (mm, float32 (ny, nx)); ``comp`` (the
    cloth's compression, mm) and ``inside`` are coarse grids of ``fs``-pixel blocks already
    :func:`widen`-ed and cut to the window's columns, read along rows from row ``oy`` of their
    ``fs``-fold upsampling (the module's contract); ``gamma``: a constant (mm). Returns the
    contact, bool (ny, nx). (Each coarse field is blended as (1 - w) a + w b, OpenCV's resize's form.)"""
    ny, nx = depth.shape
    ys0, ys1, wys = _rows(oy + ny, fs, comp.shape[0])
    out = np.empty((ny, nx), np.bool_)
    zero, half = np.float32(0.0), np.float32(0.5)
    for i in range(ny):
        y0, y1, wy = ys0[oy + i], ys1[oy + i], wys[oy + i]
        wa = np.float32(1.0) - wy
        c0, c1, k0, k1 = comp[y0], comp[y1], inside[y0], inside[y1]
        di, ei, oi = depth[i], env[i], out[i]
        for j in range(nx):
            m = k0[j] * wa + k1[j] * wy >= half
            pen = (ei[j] - (c0[j] * wa + c1[j] * wy)) + gamma
            di[j] = max(di[j], pen if m else zero)
            oi[j] = m
    return out


def field_at(field: np.ndarray, fs: int, y: int, x: int) -> float:
    """A coarse field's value at pixel (y, x), read as in the module's contract."""
    ys0, ys1, wys = _rows(y + 1, fs, field.shape[0])
    xs0, xs1, wxs = _rows(x + 1, fs, field.shape[1])
    y0, y1, wy, x0, x1, wx = ys0[y], ys1[y], float(wys[y]), xs0[x], xs1[x], float(wxs[x])
    top = (1.0 - wx) * field[y0, x0] + wx * field[y0, x1]
    bot = (1.0 - wx) * field[y1, x0] + wx * field[y1, x1]
    return float((1.0 - wy) * top + wy * bot)


# --------------------------------------------------------------------------------------
# The statistics grid's cell arithmetic (float32 (rows, cols) fields; one fused pass each where
# numpy took 10-30 passes over temporaries, about 3 ms per 960x720 frame in all)
# --------------------------------------------------------------------------------------
# Floors that keep the ratios finite: a variance (mm^2), a depth (mm), a contact fraction.
VAR_FLOOR_MM2 = 1e-14
DEPTH_FLOOR_MM = 1e-9
PHI_FLOOR = 0.01


# arcsin(x) / x on [0, 1] without a call into libm (the scalar call, 6 ns, kept these loops from
# vectorising): its Taylor series below ASIN_SERIES_BELOW, Abramowitz & Stegun 4.4.46 above
# (pi/2 - sqrt(1 - x) P7(x), absolute error <= 2e-8). Both are within float32 rounding of arcsin.
ASIN_SERIES_BELOW = 0.25
ASIN_SERIES = (1.0, 1.0 / 6.0, 3.0 / 40.0, 5.0 / 112.0, 35.0 / 1152.0)   # of x^0, x^2, x^4, ...
ASIN_AS_4_4_46 = (1.5707963050, -0.2145988016, 0.0889789874, -0.0501743046,
                  0.0308918810, -0.0170881256, 0.0066700901, -0.0012624911)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True, inline="always")
def _asin_over_x(x):
    """arcsin(x) / x for float32 x in [0, 1] (1 at 0)."""
    a = ASIN_AS_4_4_46
    big = (np.float32(np.pi / 2) - np.sqrt(np.float32(1.0) - x) * (
        np.float32(a[0]) + x * (np.float32(a[1]) + x * (np.float32(a[2]) + x * (np.float32(a[3]) + x * (
            np.float32(a[4]) + x * (np.float32(a[5]) + x * (np.float32(a[6]) + x * np.float32(a[7]))))))))) \
        / max(x, np.float32(ASIN_SERIES_BELOW))
    c = ASIN_SERIES
    x2 = x * x
    small = np.float32(c[0]) + x2 * (np.float32(c[1]) + x2 * (np.float32(c[2]) + x2 * (
        np.float32(c[3]) + x2 * np.float32(c[4]))))
    return small if x < np.float32(ASIN_SERIES_BELOW) else big


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True, inline="always")
def _sinc_factor(qdx2, d):
    """Factor on a central difference's mean square slope that undoes its sin(q d) / (q d)
    response, from the read (q d)^2 (``d`` mm per pixel): (arcsin(q d) / (q d))^2, q d capped at 1."""
    r = _asin_over_x(min(np.sqrt(qdx2) * d, np.float32(1.0)))
    return r * r


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True, inline="always")
def _share(q, e_half, yarn_comp, has_cloth: bool, cloth_k, ell):
    """The gel's share of relief at wavenumber q (1/mm): 1 / (1 + E*/2 q C), C the support's
    compliance per unit pressure (mm/MPa; yarns' Winkler plus, with ``has_cloth``, the cloth's
    Pasternak 1 / (k (1 + (q ell)^2))). ``yarn_comp`` 0 without a support gives 1."""
    comp = yarn_comp
    if has_cloth:
        comp = comp + np.float32(1.0) / (cloth_k * (np.float32(1.0) + (q * ell) * (q * ell)))
    return np.float32(1.0) / (np.float32(1.0) + e_half * q * comp)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _read_table(s, a, key: int, lo, hi, per_step, v0, slope, out) -> None:
    """``out[j]`` = table column ``key`` (an index into johnson.KEYS) at p / p* = ``s[j]``, blended
    from the 2-D wave (``a[j]`` = 0) to the 1-D wave (1); 1 at s >= 1 (complete contact). The tables
    lie on a uniform grid of s from ``lo`` to ``hi`` (``per_step`` = 1 / its step; see
    ``johnson.segment_arrays``); values past its ends sit at the end, so its end values hold, as
    np.interp's do. (A loop of its own: its gathers keep a loop from vectorising, and the
    arithmetic that feeds it vectorises apart from it, 3x faster in all.)"""
    last = v0.shape[2] - 1
    c1, d1, c2, d2 = v0[0, key], slope[0, key], v0[1, key], slope[1, key]
    for j in range(s.size):
        u = (min(max(s[j], lo), hi) - lo) * per_step
        i = min(np.int64(u), last)
        f = u - np.float32(i)
        v = c2[i] + d2[i] * f
        v = v + a[j] * (c1[i] + d1[i] * f - v)
        out[j] = np.float32(1.0) if s[j] >= np.float32(1.0) else v


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def band_cells(mom, d, q_lo, q_hi):
    """The texture band's statistics per cell from its smoothed cell means ``mom`` (float32
    ``(rows, cols, 5)``: b, b^2, bx^2, by^2, bx by; slopes by central differences at ``d`` mm per
    pixel). Returns float32 (rows, cols) fields: (variance mm^2; wavenumber 1/mm, clipped to
    [q_lo, q_hi]; anisotropy 0 (isotropic) to 1 (a 1-D wave); mean mm).

    Each axis's mean square slope is corrected for the central difference's response, read on that
    axis alone: a wave of q per axis reads sin(q d) / d there (exact for a wave at any angle, which
    a Sobel's cross smoothing is not); q = RMS slope / RMS height; the anisotropy is the slope tensor's
    eigenvalue spread over its trace."""
    rows, cols = mom.shape[0], mom.shape[1]
    n = rows * cols
    # Planar copies first: the interleaved channels kept the loop below from vectorising (5x slower).
    planes = np.empty((5, n), np.float32)
    flat = mom.reshape(n, 5)
    for i in range(n):
        for k in range(5):
            planes[k, i] = flat[i, k]
    b, b2, bxx, byy, bxy = planes[0], planes[1], planes[2], planes[3], planes[4]
    var = np.empty(n, np.float32)
    q = np.empty(n, np.float32)
    aniso = np.empty(n, np.float32)
    for i in range(n):
        m = b[i]
        v = max(b2[i] - m * m, np.float32(VAR_FLOOR_MM2))
        # (OpenCV's box filter keeps running sums: a mean of squares near zero can come out -1e-6.)
        gxx = max(bxx[i], np.float32(0.0))
        gyy = max(byy[i], np.float32(0.0))
        cx = _sinc_factor(gxx / v, d)
        cy = _sinc_factor(gyy / v, d)
        gxx *= cx
        gyy *= cy
        gxy = bxy[i] * np.sqrt(cx * cy)
        s2 = gxx + gyy
        q[i] = min(max(np.sqrt(s2 / v), q_lo), q_hi)
        spread = np.sqrt((gxx - gyy) * (gxx - gyy) + np.float32(4.0) * gxy * gxy)
        aniso[i] = min(spread / max(s2, np.float32(VAR_FLOOR_MM2)), np.float32(1.0))
        var[i] = v
    shape = (rows, cols)
    return var.reshape(shape), q.reshape(shape), aniso.reshape(shape), b.copy().reshape(shape)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def map_cells(var, q, aniso, p, gain, e_star, yarn_comp, has_cloth: bool, cloth_k, ell, s_max,
              lo, hi, per_step, v0, slope):
    """Johnson's map per cell for the texture's band: ``var`` (mm^2, as blurred), ``q`` (1/mm),
    ``aniso`` (0-1) from :func:`band_cells`; ``p``: the local mean pressure (MPa); ``gain``: the
    blur's gain on the band, exp(-(q s)^2 / 2) for a blur of width s mm (1: none; numpy's exp
    vectorises, a compiled loop's does not); the gel's E* (MPa) and the support
    as in :func:`_share`; ``s_max``: the cap on p / p*; the tables from ``johnson.segment_arrays``.

    Returns float32 (rows, cols) fields: (1 / gain; the gel's share
    of relief; the effective crown-to-valley depth d_eff, mm; 1 - the span slope lam; the contact
    fraction phi). The depth is 2 sqrt(2) sigma for a 1-D wave and 4 sigma for the 2-D one, blended
    by the anisotropy (exact for both; the deepest valley would count the narrow crevices between
    yarns, which the gel cannot enter and a finer grid resolves deeper); s = p / p* =
    p / (E*/4 q d_eff)."""
    shape = var.shape
    n = var.size
    var, q, aniso, p, gain = var.ravel(), q.ravel(), aniso.ravel(), p.ravel(), gain.ravel()
    inv_gain = np.empty(n, np.float32)
    share = np.empty(n, np.float32)
    d_eff = np.empty(n, np.float32)
    span = np.empty(n, np.float32)
    phi = np.empty(n, np.float32)
    e_half = np.float32(e_star / 2.0)
    e_quarter = np.float32(e_star / 4.0)
    one_d_drop = np.float32(4.0 - 2.0 * np.sqrt(2.0))
    ps = np.empty(n, np.float32)
    for j in range(n):
        qi, a = q[j], aniso[j]
        inv = np.float32(1.0) / gain[j]
        sh = _share(qi, e_half, yarn_comp, has_cloth, cloth_k, ell)
        depth = np.sqrt(var[j]) * inv * (np.float32(4.0) - one_d_drop * a)
        de = max(depth * sh, np.float32(DEPTH_FLOOR_MM))
        ps[j] = min(p[j] / (e_quarter * qi * de), s_max)
        inv_gain[j] = inv
        share[j] = sh
        d_eff[j] = de
    _read_table(ps, aniso, LAM, lo, hi, per_step, v0, slope, span)
    _read_table(ps, aniso, CONTACT, lo, hi, per_step, v0, slope, phi)
    for j in range(n):
        span[j] = np.float32(1.0) - span[j]
    return inv_gain.reshape(shape), share.reshape(shape), d_eff.reshape(shape), span.reshape(shape), \
        phi.reshape(shape)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def fine_cells(var_f, g2, dx, q_lo, q_hi, p, phi, e_star, yarn_comp, has_cloth: bool, cloth_k, ell, s_max,
               lo, hi, per_step, v0, slope):
    """The share of the finer relief that prints on the crowns in contact, per cell: ``var_f``
    (mm^2) and ``g2`` (mean square slope, central differences at ``dx`` mm per pixel) its smoothed
    cell means; ``p`` the local mean pressure (MPa), carried by the crowns' contact fraction
    ``phi``; its p* taken as the 2-D wave's at its RMS height and wavenumber (clipped to
    [q_lo, q_hi]). Other arguments as :func:`map_cells`. Returns float32 (rows, cols): Johnson's
    kept fundamental times the gel's share of relief."""
    shape = var_f.shape
    n = var_f.size
    var_f, g2, p, phi = var_f.ravel(), g2.ravel(), p.ravel(), phi.ravel()
    kept = np.empty(n, np.float32)
    e_half = np.float32(e_star / 2.0)
    e_quarter = np.float32(e_star / 4.0)
    ps = np.empty(n, np.float32)
    shares = np.empty(n, np.float32)
    for j in range(n):
        v = max(var_f[j], np.float32(VAR_FLOOR_MM2))
        g = max(g2[j], np.float32(0.0))
        g *= _sinc_factor(np.float32(0.5) * g / v, dx)
        qf = min(max(np.sqrt(g / v), q_lo), q_hi)
        sh = _share(qf, e_half, yarn_comp, has_cloth, cloth_k, ell)
        crown_p = p[j] / max(phi[j], np.float32(PHI_FLOOR))
        ps[j] = min(crown_p / (e_quarter * qf * max(np.float32(4.0) * np.sqrt(v) * sh, np.float32(DEPTH_FLOOR_MM))),
                    s_max)
        shares[j] = sh
    _read_table(ps, np.zeros(n, np.float32), KEPT, lo, hi, per_step, v0, slope, kept)
    for j in range(n):
        kept[j] *= shares[j]
    return kept.reshape(shape)


@njit(cache=True, nogil=True, error_model="numpy")
def bearing_samples(te, ny: int, nx: int, d_eff, fs: int, stride: int):
    """The bearing curve's samples, unsorted: z = -te / d_eff at every ``stride``-th pixel of the first
    ``ny`` rows and ``nx`` columns of ``te`` (mm), each over ``d_eff`` (mm, float32 (rows, cols) on
    cells of ``fs`` px) at its own cell; float32 (ceil(ny / stride) * ceil(nx / stride),)."""
    rows = (ny + stride - 1) // stride
    cols = (nx + stride - 1) // stride
    last_r, last_c = d_eff.shape[0] - 1, d_eff.shape[1] - 1
    z = np.empty(rows * cols, np.float32)
    k = 0
    for a in range(rows):
        i = a * stride
        d_row = d_eff[min(i // fs, last_r)]
        t_row = te[i]
        for b in range(cols):
            j = b * stride
            z[k] = -t_row[j] / d_row[min(j // fs, last_c)]
            k += 1
    return z


@njit(cache=True, nogil=True, error_model="numpy")
def bearing_read(z, phi, d_eff):
    """d_eff times the bearing curve ``z`` (sorted, float32 (n,), n >= 1) read at probability ``phi``:
    float32, the shape of ``phi`` and ``d_eff`` (mm). The n samples sit at probabilities (k + 0.5) / n,
    evenly spaced, so the curve is read by arithmetic (a binary search took 7x longer): linear
    between samples, held at the ends (as np.interp)."""
    n = z.size
    out = np.empty(phi.shape, np.float32)
    for r in range(phi.shape[0]):
        for c in range(phi.shape[1]):
            if n == 1:
                v = np.float64(z[0])
            else:
                x = min(max(np.float32(phi[r, c] * np.float32(n) - np.float32(0.5)), np.float32(0.0)),
                        np.float32(n - 1))
                i = min(int(x), n - 2)
                v = z[i] + (np.float64(x) - i) * (z[i + 1] - z[i])
            out[r, c] = v * d_eff[r, c]
    return out
