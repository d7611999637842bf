"""Fused per-pixel passes of the two-scale imprint's texture stage (:func:`gelsim.gel.twoscale._texture_depth`).

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

Numba compiles the kernels on first use (about a second, cached on disk afterwards).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _add_cells(row, fs: int, sums, ci: int) -> None:
    """Add ``row`` (NX,) to the cell sums of coarse row ``ci``, fs pixels per cell."""
    for c in range(sums.shape[1]):
        acc = 0.0
        for j in range(c * fs, (c + 1) * fs):
            acc += row[j]
        sums[ci, c] += acc


def widen(field: np.ndarray, nx: int) -> np.ndarray:
    """A coarse field read at full resolution along its rows only: float32 ``(rows, nx)`` (OpenCV's
    linear resize along x; the kernels blend between these rows per pixel row, which together is
    OpenCV's separable ``INTER_LINEAR`` resize to full resolution)."""
    import cv2

    return cv2.resize(field, (nx, field.shape[0]), interpolation=cv2.INTER_LINEAR)


@njit(cache=True, nogil=True, fastmath=True)
def restore_band(t, tq, mean, inv_gain, share, fs: int):
    """The texture's band restored to its height, split from the finer relief.

    ``t``: the texture (mm, <= 0); ``tq``: ``t`` blurred (its own band, lowered by the blur's
    gain); ``mean``: the band's local mean; ``inv_gain``: 1 / gain; ``share``: the gel's share of
    relief (coarse fields already :func:`widen`-ed). Returns (te = share * restored band, mm;
    tf = t - restored band, mm; the cells' sums of tf^2). The restored band is
    mean + (tq - mean) / gain: only the oscillation about the local mean was lowered by the blur.
    (The reciprocal is interpolated, not the gain: a division per pixel took 0.9 ms at 960x720.)"""
    ny, nx = t.shape
    rows, cols = mean.shape[0], nx // fs
    ys0, ys1, wys = _rows(ny, fs, rows)
    te = np.empty_like(t)
    tf = np.empty_like(t)
    s_tf2 = np.zeros((rows, cols), np.float64)
    sq = np.empty(nx, np.float32)
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
        _add_cells(sq, fs, s_tf2, i // fs)
    return te, tf, s_tf2


@njit(cache=True, nogil=True, fastmath=True)
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


@njit(cache=True, nogil=True, fastmath=True)
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


@njit(cache=True, nogil=True, fastmath=True)
def moment_sums(b, d: float, fs: int, rows: int, cols: int):
    """The cells' sums of b, b^2, bx^2, by^2 and bx by (b's slopes by :func:`_slopes`, mm/mm, at
    ``d`` mm per pixel): float32 ``(rows, cols, 5)``, ``fs`` x ``fs`` pixels per cell."""
    ny, nx = b.shape
    out = np.zeros((5, rows, cols), np.float64)
    h = np.float32(0.5 / d)
    gx = np.empty(nx, np.float32)
    gy = np.empty(nx, np.float32)
    acc = np.empty((5, nx), np.float32)
    for i in range(ny):
        _slopes(b, i, h, gx, gy)
        bi = b[i]
        for j in range(nx):
            v = bi[j]
            acc[0, j] = v
            acc[1, j] = v * v
            acc[2, j] = gx[j] * gx[j]
            acc[3, j] = gy[j] * gy[j]
            acc[4, j] = gx[j] * gy[j]
        for m in range(5):
            _add_cells(acc[m], fs, out[m], i // fs)
    return out.transpose(1, 2, 0).astype(np.float32)


@njit(cache=True, nogil=True, fastmath=True)
def slope_sums(tf, dx: float, fs: int, rows: int, cols: int):
    """The cells' sums of the squared slope |grad tf|^2 (:func:`_slopes`, mm/mm), float64 ``(rows, cols)``."""
    ny, nx = tf.shape
    out = np.zeros((rows, cols), np.float64)
    h = np.float32(0.5 / dx)
    gx = np.empty(nx, np.float32)
    gy = np.empty(nx, np.float32)
    for i in range(ny):
        _slopes(tf, i, h, gx, gy)
        for j in range(nx):
            gx[j] = gx[j] * gx[j] + gy[j] * gy[j]
        _add_cells(gx, fs, out, i // fs)
    return out


@njit(cache=True, nogil=True, fastmath=True)
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
        _add_cells(gi, fs, s_g, i // fs)
    return g, touch, s_g


@njit(cache=True, nogil=True, fastmath=True)
def minus_field(g, field, fs: int, ny: int, nx: int):
    """``g - field`` over the first ny rows and nx columns (``field`` coarse, :func:`widen`-ed)."""
    ys0, ys1, wys = _rows(g.shape[0], fs, field.shape[0])
    out = np.empty((ny, nx), np.float32)
    for i in range(ny):
        f0, f1, wy = field[ys0[i]], field[ys1[i]], wys[i]
        gi, oi = g[i], out[i]
        for j in range(nx):
            oi[j] = gi[j] - (f0[j] + wy * (f1[j] - f0[j]))
    return out


def field_at(field: np.ndarray, fs: int, y: int, x: int) -> float:
    """A coarse field's value at pixel (y, x), read as in the module's contract."""
    ys0, ys1, wys = _rows(y + 1, fs, field.shape[0])
    xs0, xs1, wxs = _rows(x + 1, fs, field.shape[1])
    y0, y1, wy, x0, x1, wx = ys0[y], ys1[y], float(wys[y]), xs0[x], xs1[x], float(wxs[x])
    top = (1.0 - wx) * field[y0, x0] + wx * field[y0, x1]
    bot = (1.0 - wx) * field[y1, x0] + wx * field[y1, x1]
    return float((1.0 - wy) * top + wy * bot)
