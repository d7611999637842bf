"""Heightfields of catalog fabrics: a pure function of absolute fabric-plane coordinates.

The family renderers (:mod:`.families`) work on an axis-aligned grid, which makes
most of their work 1-D (yarn positions, profiles) or separable (lattice noise).
A rotated patch is rendered on the axis-aligned grid of fabric-plane points
``(k * mm_per_px, l * mm_per_px)`` (integers k, l) that covers it, only in the
tiles the patch touches, and resampled bilinearly. Grid values depend only on
``(k, l)``, so adjacent patches agree.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import GelsimError
from .catalog import Fabric
from .families import RENDERERS
from .noise import fbm, make_key

F32 = np.float32
# Pixel positions within this many pixels of an integer are treated as on the pixel lattice,
# so that patches placed at multiples of mm_per_px sample exactly the same points.
_SNAP_PX = 1e-6
# Side of the tiles a rotated patch is rendered in: small enough to skip most of the
# bounding box a 45-degree patch wastes, large enough that per-tile overhead is small.
_TILE_PX = 256
# Most sub-samples per pixel side when antialiasing coarse patches (16 per pixel bounds the cost).
_MAX_SUPERSAMPLE = 4
# Largest patch, px per side: 8192 covers 80 mm at 0.01 mm/px.
_MAX_SIDE_PX = 8192


def _snap(x: float) -> float:
    r = round(x)
    return float(r) if abs(x - r) < _SNAP_PX else x


def _surface(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    """Height in units of the relief (0..1), float32 (len(v), len(u)), for the axis-aligned grid."""
    s = RENDERERS[fab.family](fab, u, v, key)
    a, b = fab.hairiness, fab.waviness
    if a == 0 and b == 0:
        return np.ascontiguousarray(s, dtype=F32)
    s = s * F32(1.0 - a - b)
    if a > 0:
        # Fibre fuzz: two octaves at the fibre scale, biased upwards (loose fibres stand proud).
        fz = fbm(u, v, fab.fibre_mm * 2, fab.fibre_mm * 2, make_key(key, "fuzz"), 2)
        fz *= F32(0.5 * a)
        fz += F32(0.5 * a)
        s += fz
    if b > 0:
        wv = fbm(u, v, fab.waviness_mm / 2, fab.waviness_mm / 2, make_key(key, "wave"), 2)
        wv *= F32(0.5 * b)
        wv += F32(0.5 * b)
        s += wv
    return s


@dataclass(frozen=True)
class RotatedHeights:
    """A rotated patch before its last steps (what :func:`heightfield_parts` leaves to whoever finishes it: the
    host here, :func:`gelsim.scene_torch.finish_rotated` on a device): the fabric's structure on the axis-aligned
    grid of fabric-plane points ``((k0 + k) p, (l0 + l) p)`` (``src``, float32 ``(nl, nk)``, in units of the relief;
    ``p`` the patch's mm per px), read bilinearly at output pixel (i, j)'s point ``U = c J + s I - k0``,
    ``V = -s J + c I - l0`` (``J = j0 + j``, ``I = i0 + i``; :meth:`maps`), then scaled by ``relief_mm`` and cut at 0.
    ``cos``, ``sin``: of the rotation; ``width_px``, ``height_px``: the patch's size."""
    src: np.ndarray
    j0: float
    i0: float
    width_px: int
    height_px: int
    cos: float
    sin: float
    k0: int
    l0: int
    relief_mm: float

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The output pixels' positions on ``src``: (U, V), float32 ``(height_px, width_px)`` px each (float64
        arithmetic, rounded once)."""
        c, s = self.cos, self.sin
        jj = self.j0 + np.arange(self.width_px, dtype=np.float64)
        ii = self.i0 + np.arange(self.height_px, dtype=np.float64)
        return (c * jj[None, :] + s * ii[:, None] - self.k0).astype(F32), \
            (-s * jj[None, :] + c * ii[:, None] - self.l0).astype(F32)

    def finish(self) -> np.ndarray:
        """The patch's heights, mm, float32 ``(height_px, width_px)``: OpenCV's bilinear remap (edge replicated),
        scaled and cut (what :func:`heightfield` returns)."""
        map_u, map_v = self.maps()
        out = cv2.remap(self.src, map_u, map_v, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return _relief(out, self.relief_mm)


def _relief(s: np.ndarray, relief_mm: float) -> np.ndarray:
    """Structure (units of the relief) to heights in mm >= 0, in place."""
    s *= F32(relief_mm)
    np.maximum(s, 0.0, out=s)
    return s


def heightfield(fabric: Fabric, *, x0_mm: float, y0_mm: float, width_px: int, height_px: int,
                mm_per_px: float, seed: int = 0, rotation_deg: float = 0.0, _antialias: bool = True) -> np.ndarray:
    """Surface height of ``fabric`` in mm above its base plane, float32 ``(height_px, width_px)``.

    Pixel ``(i, j)`` samples the sensor-plane point ``(x, y) = (x0_mm + j*mm_per_px,
    y0_mm + i*mm_per_px)``; the fabric is rotated by ``rotation_deg`` (plus its own
    ``orientation_deg``) about the fabric's origin, i.e. the point seen is the fabric point
    ``(u, v) = (x cos t + y sin t, -x sin t + y cos t)``. Heights are >= 0 and peak at about
    ``fabric.relief_mm``. A pure function of the absolute coordinates, the fabric and ``seed``:
    adjacent patches join seamlessly (exactly when their origins are multiples of ``mm_per_px``).
    At coarse resolutions (physics, 0.1-0.2 mm/px) each pixel is the mean of up to 4 x 4 sub-samples,
    so that yarn structure finer than the pixels averages out instead of aliasing into false patterns.
    """
    out = heightfield_parts(fabric, x0_mm=x0_mm, y0_mm=y0_mm, width_px=width_px, height_px=height_px,
                            mm_per_px=mm_per_px, seed=seed, rotation_deg=rotation_deg, _antialias=_antialias)
    return out.finish() if isinstance(out, RotatedHeights) else out


def heightfield_parts(fabric: Fabric, *, x0_mm: float, y0_mm: float, width_px: int, height_px: int,
                      mm_per_px: float, seed: int = 0, rotation_deg: float = 0.0,
                      _antialias: bool = True) -> np.ndarray | RotatedHeights:
    """:func:`heightfield`'s heights, or for a rotated patch without sub-samples its :class:`RotatedHeights` (the
    heights before their resampling, for a device to finish; ``finish()`` gives the same bytes as
    :func:`heightfield`)."""
    if not (isinstance(width_px, (int, np.integer)) and isinstance(height_px, (int, np.integer))):
        raise GelsimError(f"width_px and height_px must be integers, got {width_px!r} x {height_px!r}")
    if not (0 < width_px <= _MAX_SIDE_PX and 0 < height_px <= _MAX_SIDE_PX):
        raise GelsimError(f"patch {width_px}x{height_px} px is out of range; use 1-{_MAX_SIDE_PX} px per side")
    if not (math.isfinite(mm_per_px) and mm_per_px > 0):
        raise GelsimError(f"mm_per_px {mm_per_px} must be a positive number; e.g. 0.0197 for the ViTac sensor")
    if not all(math.isfinite(t) for t in (x0_mm, y0_mm, rotation_deg)):
        raise GelsimError("x0_mm, y0_mm and rotation_deg must be finite numbers")
    k = supersampling(fabric, mm_per_px) if _antialias else 1
    if k > 1 and max(width_px, height_px) * k <= _MAX_SIDE_PX:
        # Box-filter k x k sub-samples centred on each pixel, on a grid aligned in absolute coordinates
        # (so the result is still a pure function of the coordinates).
        sub = mm_per_px / k
        off = 0.5 * sub - 0.5 * mm_per_px
        h = heightfield(fabric, x0_mm=x0_mm + off, y0_mm=y0_mm + off, width_px=width_px * k,
                        height_px=height_px * k, mm_per_px=sub, seed=seed, rotation_deg=rotation_deg,
                        _antialias=False)
        return h.reshape(height_px, k, width_px, k).mean(axis=(1, 3), dtype=F32)
    key = make_key(int(seed), fabric.name, fabric.family)
    j0 = _snap(x0_mm / mm_per_px)
    i0 = _snap(y0_mm / mm_per_px)
    theta = (rotation_deg + fabric.orientation_deg) % 360.0
    if theta == 0.0:
        u = (j0 + np.arange(width_px)) * mm_per_px
        v = (i0 + np.arange(height_px)) * mm_per_px
        s = _surface(fabric, u, v, key)
    else:
        return _rotated(fabric, j0, i0, width_px, height_px, mm_per_px, theta, key)
    return _relief(s, fabric.relief_mm)


def supersampling(fabric: Fabric, mm_per_px: float) -> int:
    """Sub-samples per pixel side (1-4): enough for 4 samples per period of the fabric's finest structure
    (yarn/loop pitch or feature size; fibre fuzz is noise and may alias)."""
    scales = [v for v in (fabric.warp_pitch_mm, fabric.weft_pitch_mm, fabric.feature_mm) if v is not None]
    if fabric.family in ("leather", "suede") and fabric.pore_diameter_mm:
        scales.append(fabric.pore_spacing_mm)
    finest = min(scales)
    return int(min(_MAX_SUPERSAMPLE, max(1, math.ceil(4.0 * mm_per_px / finest - 1e-9))))


def _rotated(fab: Fabric, j0: float, i0: float, w: int, h: int, mpp: float, theta: float,
             key: int) -> RotatedHeights:
    t = math.radians(theta)
    c, s = math.cos(t), math.sin(t)
    # Fabric-grid coordinates (in pixels) of the output pixels: U = c*J + s*I, V = -s*J + c*I.
    jj = j0 + np.arange(w, dtype=np.float64)
    ii = i0 + np.arange(h, dtype=np.float64)
    corners_j = np.array([jj[0], jj[-1], jj[0], jj[-1]])
    corners_i = np.array([ii[0], ii[0], ii[-1], ii[-1]])
    cu = c * corners_j + s * corners_i
    cv = -s * corners_j + c * corners_i
    k0 = int(math.floor(cu.min())) - 2
    l0 = int(math.floor(cv.min())) - 2
    nk = int(math.ceil(cu.max())) + 3 - k0
    nl = int(math.ceil(cv.max())) + 3 - l0
    if max(nk, nl) >= 32767:   # cv2.remap's limit on the source size
        raise GelsimError(f"rotated patch needs a {nk}x{nl} px source grid; use a coarser mm_per_px "
                          "or a smaller patch (at most about 23000 px diagonal)")
    src = np.zeros((nl, nk), F32)
    # Render only the tiles of the source grid that the rotated patch touches.
    for tl in range(0, nl, _TILE_PX):
        for tk in range(0, nk, _TILE_PX):
            ke, le = min(tk + _TILE_PX, nk), min(tl + _TILE_PX, nl)
            if not _tile_needed(k0 + tk, k0 + ke, l0 + tl, l0 + le, c, s, jj[0], jj[-1], ii[0], ii[-1]):
                continue
            u = (k0 + np.arange(tk, ke)) * mpp
            v = (l0 + np.arange(tl, le)) * mpp
            src[tl:le, tk:ke] = _surface(fab, u, v, key)
    return RotatedHeights(src, j0, i0, w, h, c, s, k0, l0, fab.relief_mm)


def _tile_needed(ka, kb, la, lb, c, s, ja, jb, ia, ib) -> bool:
    """Whether the fabric-grid tile [ka, kb) x [la, lb) overlaps the rotated output rectangle
    (separating-axis test on two rectangles, with a 2-px margin for the bilinear footprint)."""
    m = 2.0
    tile_k = np.array([ka - m, kb + m, ka - m, kb + m])
    tile_l = np.array([la - m, la - m, lb + m, lb + m])
    # Tile corners in output-pixel coordinates (inverse rotation).
    tj = c * tile_k - s * tile_l
    ti = s * tile_k + c * tile_l
    if tj.max() < ja or tj.min() > jb or ti.max() < ia or ti.min() > ib:
        return False
    oj = np.array([ja, jb, ja, jb])
    oi = np.array([ia, ia, ib, ib])
    ok = c * oj + s * oi
    ol = -s * oj + c * oi
    return not (ok.max() < ka - m or ok.min() > kb + m or ol.max() < la - m or ol.min() > lb + m)
