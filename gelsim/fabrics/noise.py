"""Lattice noise that is a pure function of absolute coordinates and a key.

Random-looking structure (felt, fleece, leather grain, slubs, fibre fuzz, yarn
spacing jitter) is drawn from values hashed from *integer lattice coordinates*
and a 32-bit key, never from ``np.random`` over the output array. Two patches
that share a point therefore agree on it exactly, so a sensor can slide over a
fabric larger than its view.

All functions here take the sampling positions as 1-D coordinate vectors
(``u`` along image columns, ``v`` along image rows, in mm): the fabric is
rendered on an axis-aligned grid and rotated afterwards (see ``render``), which
makes 2-D lattice interpolation separable: one pass over the rows of the small
lattice, one over the columns of the output.
"""
from __future__ import annotations

import zlib

import numpy as np

_M32 = 0xFFFFFFFF


def make_key(*parts: int | str) -> int:
    """A 32-bit key from integers and strings (seed, fabric name, channel)."""
    h = 0x9E3779B9
    for p in parts:
        if isinstance(p, str):
            p = zlib.crc32(p.encode("utf-8"))
        h = _mix_int((h ^ (int(p) & _M32)) * 0x85EBCA6B & _M32)
    return h


def _mix_int(h: int) -> int:
    # lowbias32 finaliser (Wellons): good avalanche with two multiplies.
    h ^= h >> 16
    h = (h * 0x7FEB352D) & _M32
    h ^= h >> 15
    h = (h * 0x846CA68B) & _M32
    h ^= h >> 16
    return h


def hash_u32(ix: np.ndarray, iy: np.ndarray | int, key: int) -> np.ndarray:
    """uint32 hash of integer lattice coordinates (broadcast ``ix`` against ``iy``)."""
    x = (np.asarray(ix, dtype=np.int64) & _M32).astype(np.uint32)
    y = (np.asarray(iy, dtype=np.int64) & _M32).astype(np.uint32)
    # Distinct odd multipliers per axis so that (a, b) and (b, a) hash differently.
    h = x * np.uint32(0x8DA6B343) ^ y * np.uint32(0xD8163841) ^ np.uint32(key & _M32)
    h ^= h >> np.uint32(16)
    h *= np.uint32(0x7FEB352D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x846CA68B)
    h ^= h >> np.uint32(16)
    return h


def hash_unit(ix: np.ndarray, iy: np.ndarray | int, key: int) -> np.ndarray:
    """Uniform values in [0, 1) (float64) hashed from lattice coordinates."""
    return hash_u32(ix, iy, key).astype(np.float64) * (1.0 / 4294967296.0)


def _axis(coord: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Lattice index (relative to the first one), smoothstep weight, first index, count."""
    g = coord / cell
    i = np.floor(g)
    f = g - i
    w = (f * f * (3.0 - 2.0 * f)).astype(np.float32)   # C1 weights: no creases in the shading
    i = i.astype(np.int64)
    i0 = int(i.min())
    return i - i0, w, i0, int(i.max()) - i0 + 2


def value_noise(u: np.ndarray, v: np.ndarray, cell_u_mm: float, cell_v_mm: float, key: int) -> np.ndarray:
    """Smooth value noise in [-1, 1], float32 (len(v), len(u)).

    Lattice values at integer multiples of the cell size are hashed from their
    lattice coordinates and ``key``; between them the value is interpolated with
    smoothstep weights, separably (rows of the small lattice first).
    """
    ru, wu, iu0, nu = _axis(u, cell_u_mm)
    rv, wv, iv0, nv = _axis(v, cell_v_mm)
    lat = (hash_unit(np.arange(iu0, iu0 + nu)[None, :], np.arange(iv0, iv0 + nv)[:, None], key)
           * 2.0 - 1.0).astype(np.float32)
    wv = wv[:, None]
    rows = lat[rv] * (1.0 - wv) + lat[rv + 1] * wv          # (H, nu), small
    a = np.take(rows, ru, axis=1)
    b = np.take(rows, ru + 1, axis=1)
    b -= a
    b *= wu
    b += a
    return b


def fbm(u: np.ndarray, v: np.ndarray, cell_u_mm: float, cell_v_mm: float, key: int, octaves: int,
        gain: float = 0.5) -> np.ndarray:
    """Sum of ``octaves`` value noises, each half the cell of the previous, normalised to about [-1, 1]."""
    out = value_noise(u, v, cell_u_mm, cell_v_mm, key)
    amp, total = 1.0, 1.0
    for k in range(1, octaves):
        amp *= gain
        total += amp
        n = value_noise(u, v, cell_u_mm / 2 ** k, cell_v_mm / 2 ** k, make_key(key, k))
        n *= amp
        out += n
    out *= 1.0 / total
    return out


def noise_1d(coord: np.ndarray, cell_mm: float, key: int, lane: np.ndarray | int = 0) -> np.ndarray:
    """Smooth 1-D value noise in [-1, 1] along ``coord`` (float64), one independent lane per ``lane``."""
    g = coord / cell_mm
    i = np.floor(g)
    f = g - i
    w = f * f * (3.0 - 2.0 * f)
    i = i.astype(np.int64)
    a = hash_unit(i, lane, key) * 2.0 - 1.0
    b = hash_unit(i + 1, lane, key) * 2.0 - 1.0
    return a + (b - a) * w


def jittered_index(coord: np.ndarray, pitch_mm: float, jitter: float, key: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest yarn of a row of yarns with randomly jittered spacing.

    Yarn ``k`` is centred at ``(k + 0.5 + jitter * (h_k - 0.5)) * pitch`` with
    ``h_k`` hashed from ``k``. Returns (index of the nearest yarn (int64), signed
    offset from its centre in mm, distance to the neighbouring centre on the same
    side in mm), all shaped like ``coord``. ``jitter`` < 0.5 keeps the order.
    """
    k = np.floor(coord / pitch_mm).astype(np.int64)
    cand = np.stack([k - 1, k, k + 1])
    centres = (cand + 0.5 + jitter * (hash_unit(cand, 0, key) - 0.5)) * pitch_mm
    d = coord[None] - centres
    best = np.argmin(np.abs(d), axis=0)
    idx = np.take_along_axis(cand, best[None], 0)[0]
    off = np.take_along_axis(d, best[None], 0)[0]
    side = np.where(off >= 0, 1, -1)
    nb = idx + side
    nb_centre = (nb + 0.5 + jitter * (hash_unit(nb, 0, key) - 0.5)) * pitch_mm
    own_centre = coord - off
    gap = np.abs(nb_centre - own_centre)
    return idx, off, gap
