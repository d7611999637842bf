"""Resampling by a whole factor ``f``: the area average down (supersampling's last step, the shadows' and
the depth and halo terms' coarse grids) and bilinear interpolation up (a supersampled imprint, those
grids back to full resolution).

Pixel centres: grid pixel ``x'`` of an ``f``-times coarser grid is centred on fine pixel
``f (x' + 1/2) - 1/2``. numpy kernels: OpenCV's ``resize`` (INTER_AREA, INTER_LINEAR) on float32
``(h, w)`` or ``(h, w, C)`` arrays; torch kernels: ``(..., h, w)`` tensors.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from . import pad_hw


def area_mean(x: np.ndarray, f: int) -> np.ndarray:
    """``x`` averaged over ``f`` x ``f`` blocks, zero-padded at the bottom and right to a multiple of ``f``:
    float32 ``(ceil(h / f), ceil(w / f)[, C])``."""
    if f == 1:
        return np.ascontiguousarray(x, dtype=np.float32)
    h, w = x.shape[:2]
    hs, ws = -(-h // f), -(-w // f)
    if (hs * f, ws * f) != (h, w):
        x = cv2.copyMakeBorder(x, 0, hs * f - h, 0, ws * f - w, cv2.BORDER_CONSTANT, value=0.0)
    return cv2.resize(x, (ws, hs), interpolation=cv2.INTER_AREA)


def area_mean_box(x: np.ndarray, f: int, extent) -> np.ndarray:
    """:func:`area_mean` of ``x`` (float32 ``(h, w)``) that is zero outside ``extent`` = (row0, row1, col0,
    col1), end exclusive (e.g. :func:`~gelsim.optics.ops.box.imprint_extent`; None: the whole of ``x``): only
    the blocks that meet it are averaged, the others are 0. The same values as :func:`area_mean`: OpenCV's
    INTER_AREA by a whole factor sums each block on its own, in the same order wherever it lies, and a block
    cut by the bottom or right edge is zero-padded in both; but by 2 it is vector code with a scalar tail at
    the row's end (a block's rounding depends on where it falls in the row: tested), so there whole rows are
    averaged."""
    if extent is None or f == 1:
        return area_mean(x, f)
    h, w = x.shape[:2]
    hs, ws = -(-h // f), -(-w // f)
    r0, r1, c0, c1 = extent
    i0, i1 = max(0, r0 // f), min(hs, -(-r1 // f))
    j0, j1 = (0, ws) if f == 2 else (max(0, c0 // f), min(ws, -(-c1 // f)))
    out = np.zeros((hs, ws), np.float32)
    if i1 > i0 and j1 > j0:
        out[i0:i1, j0:j1] = area_mean(x[i0 * f:min(h, i1 * f), j0 * f:min(w, j1 * f)], f)
    return out


def upsample(grid: np.ndarray, f: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear from a grid of ``f``-pixel blocks to ``shape`` (H, W), edges replicated (``grid`` itself for
    ``f == 1``): the grid upsampled ``f`` times, then cut to ``shape``."""
    if f == 1:
        return grid
    hs, ws = grid.shape[:2]
    up = cv2.resize(grid, (ws * f, hs * f), interpolation=cv2.INTER_LINEAR)
    h, w = shape
    return up if (hs * f, ws * f) == (h, w) else up[:h, :w]


def upsample_rows(grid: np.ndarray, f: int, a: int, b: int, width: int) -> np.ndarray:
    """Rows ``a:b`` and columns ``:width`` of :func:`upsample` (``grid`` float32 ``(h', w', C)``), computed
    from the grid rows they read only: output row ``y`` reads grid rows ``floor((y + 1/2) / f - 1/2)`` and
    the next, and OpenCV gives a pixel of an integer upsampling the same value from a crop of the grid
    as from the whole (its weights depend on the pixel's position modulo the factor: tested), so a band
    of a frame needs no upsampled copy of the whole grid (an 8 MB array written and read back at 960x720)."""
    if f == 1:
        return grid[a:b, :width]
    ga, gb = max(0, a // f - 1), min(grid.shape[0], (b - 1) // f + 2)
    up = cv2.resize(grid[ga:gb], (grid.shape[1] * f, (gb - ga) * f), interpolation=cv2.INTER_LINEAR)
    return up[a - ga * f:b - ga * f, :width]


# ---------------------------------------------------------------- torch

def area_mean_torch(x, f: int):
    """:func:`area_mean` of an ``(..., h, w)`` tensor (OpenCV's INTER_AREA by a whole factor: the block's
    sum in row-major order times ``1 / f^2``)."""
    if f == 1:
        return x
    h, w = x.shape[-2:]
    hs, ws = -(-h // f), -(-w // f)
    if (hs * f, ws * f) != (h, w):
        x = pad_hw(x, (0, ws * f - w, 0, hs * f - h), "constant")
    acc = None
    for i in range(f):
        for j in range(f):
            s = x[..., i::f, j::f]
            acc = s if acc is None else acc + s
    return acc * (1.0 / (f * f))


def upsample_torch(x, f: int, shape: tuple[int, int]):
    """:func:`upsample` of an ``(..., h, w)`` tensor to ``(..., H, W)``, along the rows first (OpenCV's order)."""
    if f == 1:
        return x[..., :shape[0], :shape[1]]
    for dim, n in ((-1, shape[1]), (-2, shape[0])):
        x = _linear_axis(x, f, n, dim)
    return x


def _linear_axis(x, f: int, n: int, dim: int):
    """One axis of :func:`upsample_torch`: fine pixel ``i`` reads coarse ``(i + 1/2) / f - 1/2``, clamped to
    the first and last coarse pixel (which are then read alone, with weight 1). Computed per phase
    ``i mod f``, whose two neighbours and weights are the same all along the axis."""
    m = x.shape[dim]
    xp = pad_hw(x, (1, 1, 0, 0) if dim in (-1, x.dim() - 1) else (0, 0, 1, 1), "replicate")  # xp[j + 1] = x[j]
    shape = list(x.shape)
    shape[dim] = m * f
    out = x.new_empty(shape)
    for r in range(f):
        t = (r + 0.5) / f - 0.5                              # the phase's offset from its coarse pixel
        lo, w1 = (1, t) if t >= 0 else (0, 1.0 + t)          # read pixels j and j + 1, or j - 1 and j
        w0 = float(np.float32(1.0 - w1))
        w1 = float(np.float32(w1))
        dst = out.narrow(dim, r, m * f - r)[(slice(None),) * (dim % x.dim()) + (slice(None, None, f),)]
        dst.copy_(xp.narrow(dim, lo, m) * w0 + xp.narrow(dim, lo + 1, m) * w1)
    first = int(math.ceil((f - 1) / 2.0))                    # fine pixels left of coarse pixel 0's centre
    if first:
        out.narrow(dim, 0, first).copy_(x.narrow(dim, 0, 1).expand_as(out.narrow(dim, 0, first)))
    last = int(math.ceil((m - 0.5) * f - 0.5))               # from here on, right of the last one's centre
    if last < m * f:
        tail = out.narrow(dim, last, m * f - last)
        tail.copy_(x.narrow(dim, m - 1, 1).expand_as(tail))
    return out.narrow(dim, 0, n)
