"""Printed markers on the gel membrane and how the gel's in-plane motion moves them.

Rest positions are a square or hexagonal grid of ``profile.markers.pitch_mm`` centred on
the image, each square marker ``size_mm`` across, jittered by ``jitter_mm`` (drawn from
``seed``). The gel moves them three ways, superposed (as FOTS does, 2024):

* dilation under pressure: the nearly incompressible gel, bonded to the rigid base, is
  squeezed out from under the object, so surface points move *outward*. In a thin layer
  with a bonded base and a free top the depth-averaged lateral displacement is 2/3 of the
  surface's, and volume conservation gives the surface displacement ``U = (3 / 2h) grad Phi``
  with ``lap Phi = depth``. The flow does not reach far beyond the layer's thickness
  (the surface bulges there), so ``Phi`` is screened over ``l = h``:
  ``(lap - 1/l^2) Phi = depth`` ("elastic" marker model, solved by FFT). The "gaussian"
  model (FOTS-style) replaces the screened kernel by a Gaussian of the same reach:
  ``U = -(3 l^2 / 2h) grad (G_l * depth)``, identical for broad imprints.
* shear: the contact surface moves with the object by ``shear_mm`` (stick); the
  displacement decays outside the contact over ``l`` (weight 1 in contact).
* twist: rotation by ``twist_deg`` about the contact's centroid, with the same weight.
  Positive angles turn +x towards +y (right-handed about the sensor frame's +z).

Fields are computed on a coarse grid (cells of ``h / 6``: they vary over the layer
thickness) and interpolated at the marker centres and the four corners of each square,
so squares shear, rotate and stretch.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from .errors import GelsimError
from .optics.ops.resample import area_mean_box

# Coarse-grid cells per gel thickness: the displacement fields vary over about one
# thickness; six samples per thickness resolve them (the fields change by < 1% against
# twelve) and keep the markers near 1 ms per frame.
CELLS_PER_THICKNESS = 6.0
# Corner order for drawing: top-left, top-right, bottom-right, bottom-left (image axes).
_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], np.float64)


@dataclass(frozen=True)
class Markers:
    """Marker positions in pixels, ``(x, y)`` = (column, row), pixel centres at integers.

    rest_px: float32 (N, 2) rest centres; xy_px: float32 (N, 2) displaced centres;
    corners_px: float32 (N, 4, 2) displaced corners in drawing order (TL, TR, BR, BL).
    """
    rest_px: np.ndarray
    xy_px: np.ndarray
    corners_px: np.ndarray

    def __len__(self) -> int:
        return int(self.rest_px.shape[0])


def marker_grid(profile, *, seed: int = 0) -> np.ndarray:
    """Rest centres of the printed markers, float32 (N, 2) px; empty if markers are disabled.

    Square layout: rows and columns ``pitch_mm`` apart; hex: rows ``pitch * sqrt(3) / 2``
    apart, every other row shifted by half a pitch. The grid is centred on the image and
    keeps markers that lie wholly inside it (before jitter), in row-major order; jitter is
    Gaussian with sigma ``jitter_mm``. With ``missing_fraction`` > 0 that fraction of them
    (rounded) is left out, chosen by ``seed``; the rest keep their order.
    """
    return _marker_grid(profile.markers, profile.image, int(seed)).copy()


@functools.lru_cache(maxsize=64)
def _marker_grid(spec, image, seed: int) -> np.ndarray:
    if not spec.enabled:
        return np.zeros((0, 2), np.float32)
    mmpp = image.mm_per_px
    h, w = image.height_px, image.width_px
    pitch = spec.pitch_mm / mmpp
    half = spec.size_mm / mmpp / 2.0
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    dy = pitch * (math.sqrt(3.0) / 2.0 if spec.layout == "hex" else 1.0)
    nrow = int(math.ceil(h / dy)) + 1
    ncol = int(math.ceil(w / pitch)) + 1
    rows = np.arange(-nrow, nrow + 1)
    cols = np.arange(-ncol, ncol + 1)
    jj, ii = np.meshgrid(cols, rows)
    x = cx + jj * pitch
    if spec.layout == "hex":
        x = x + np.where(ii % 2 == 1, pitch / 2.0, 0.0)
    y = cy + ii * dy
    pts = np.column_stack([x.ravel(), y.ravel()])
    # Which markers exist and their order depend on the printed grid, not on the jitter,
    # so every seed gives the same N in the same row-major order.
    inside = ((pts[:, 0] - half >= -0.5) & (pts[:, 0] + half <= w - 0.5)
              & (pts[:, 1] - half >= -0.5) & (pts[:, 1] + half <= h - 0.5))
    pts = pts[inside]
    pts = pts[np.lexsort((pts[:, 0], pts[:, 1]))]
    if spec.jitter_mm > 0:
        rng = np.random.default_rng(seed)
        pts = pts + rng.normal(0.0, spec.jitter_mm / mmpp, pts.shape)
    n_missing = int(round(spec.missing_fraction * len(pts)))
    if n_missing:
        # a stream of its own, so that the jitter of the markers kept does not depend on it
        gone = np.random.default_rng([seed, 0x6D15]).choice(len(pts), n_missing, replace=False)
        pts = np.delete(pts, gone, axis=0)
    return pts.astype(np.float32)


def square_corners(centres: np.ndarray, profile) -> np.ndarray:
    half = profile.markers.size_mm / profile.image.mm_per_px / 2.0
    return centres[:, None, :].astype(np.float64) + _CORNERS[None] * half


def rest_markers(profile, *, seed: int = 0) -> Markers:
    """Undeformed markers (frames before contact)."""
    rest = marker_grid(profile, seed=seed)
    c = square_corners(rest, profile).astype(np.float32)
    return Markers(rest, rest.copy(), c)


def _check_rest(rest, profile, seed):
    if rest is None:
        return marker_grid(profile, seed=seed)
    r = np.asarray(rest, dtype=np.float32)
    if r.ndim != 2 or r.shape[1] != 2 or not np.isfinite(r).all():
        raise GelsimError(f"rest marker positions have shape {r.shape}; give a finite (N, 2) array in px")
    return r


def _screened(fields: np.ndarray, ell_cells: float, pad: int) -> np.ndarray:
    """The screened-Poisson potentials ``(lap - 1/l^2) Phi = field`` of ``fields`` (float32 ``(k, h, w)``) with
    ``pad`` cells of zeros around them, solved as a circular convolution on that (h + 2 pad, w + 2 pad) grid
    (the window in its corner: the same convolution, shifted): float32 ``(k, h, w)``. One FFT pair for the k
    fields, in single precision (pocketfft's own float32 transforms: the potentials' gradients within about
    4e-6 of their peak of the float64 solve's, the markers within 1e-4 px)."""
    k, h, w = fields.shape
    grid = (h + 2 * pad, w + 2 * pad)
    spec = scipy.fft.rfft2(fields, s=grid)
    spec *= _screen_multiplier32(*grid, float(ell_cells))
    return scipy.fft.irfft2(spec, s=grid)[:, :h, :w]


@functools.lru_cache(maxsize=64)
def screen_multiplier(hp: int, wp: int, ell_cells: float) -> np.ndarray:
    """-1/(q^2 + 1/l^2) on the rfft2 grid of an (hp, wp) field (read-only, cached: a window's size
    repeats from frame to frame)."""
    qy = 2 * np.pi * np.fft.fftfreq(hp)[:, None]
    qx = 2 * np.pi * np.fft.rfftfreq(wp)[None, :]
    mult = -1.0 / (qx * qx + qy * qy + 1.0 / (ell_cells * ell_cells))
    mult.flags.writeable = False
    return mult


@functools.lru_cache(maxsize=64)
def _screen_multiplier32(hp: int, wp: int, ell_cells: float) -> np.ndarray:
    """:func:`screen_multiplier` in float32 (read-only, cached)."""
    m = screen_multiplier(hp, wp, ell_cells).astype(np.float32)
    m.flags.writeable = False
    return m


def _bilinear(field: np.ndarray, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """Sample ``field`` (Hc, Wc[, k]) at fractional cell coordinates, clamped at the edges."""
    hc, wc = field.shape[:2]
    cx = np.clip(cx, 0.0, wc - 1.0)
    cy = np.clip(cy, 0.0, hc - 1.0)
    x0 = np.minimum(np.floor(cx).astype(np.int64), wc - 2) if wc > 1 else np.zeros(cx.shape, np.int64)
    y0 = np.minimum(np.floor(cy).astype(np.int64), hc - 2) if hc > 1 else np.zeros(cy.shape, np.int64)
    fx = (cx - x0)[..., None] if field.ndim == 3 else cx - x0
    fy = (cy - y0)[..., None] if field.ndim == 3 else cy - y0
    x1 = np.minimum(x0 + 1, wc - 1)
    y1 = np.minimum(y0 + 1, hc - 1)
    return ((field[y0, x0] * (1 - fx) + field[y0, x1] * fx) * (1 - fy)
            + (field[y1, x0] * (1 - fx) + field[y1, x1] * fx) * fy)


def field_window(profile, box: tuple[int, int, int, int]) -> tuple[int, int, int, int, int]:
    """The coarse grid of the in-plane fields over an imprint whose touched pixels (depth > 0 or contact) have
    the bounding box ``box`` = (x, y, width, height) px: ``(f, r0, c0, hc, wc)``, cells of f x f px, the grid's
    corner at pixel (r0, c0), hc x wc cells."""
    gel = profile.gel
    mmpp = profile.image.mm_per_px
    h, w = profile.shape
    bx, by, bw, bh = box
    # Integer cells: INTER_AREA then averages whole blocks (its fast path).
    f = max(1, int(round(gel.thickness_mm / CELLS_PER_THICKNESS / mmpp)))
    ell = gel.thickness_mm / (f * mmpp)  # reach of the in-plane fields, cells
    # The fields fall below 1% of their peak 4 reaches beyond the imprint (exp(-4) for the
    # screened kernel, far less for the Gaussian): compute over the imprint plus that margin.
    margin = int(math.ceil(4 * ell)) * f
    r0 = max(0, (by - margin) // f * f)
    c0 = max(0, (bx - margin) // f * f)
    hc = max(2, (min(h, by + bh + margin) - r0) // f)
    wc = max(2, (min(w, bx + bw + margin) - c0) // f)
    while r0 + hc * f > h:
        hc -= 1
    while c0 + wc * f > w:
        wc -= 1
    if hc < 2 or wc < 2:
        f = 1
        r0, c0, hc, wc = by, bx, max(2, bh), max(2, bw)
        r0, c0 = min(r0, h - hc), min(c0, w - wc)
    return f, r0, c0, hc, wc


def _cell_means(depth: np.ndarray, mask: np.ndarray, box, window) -> np.ndarray:
    """The means of ``depth`` (mm) and ``mask`` over the cells of ``window`` = (f, r0, c0, hc, wc)
    (:func:`field_window`): float32 (2, hc, wc). Both are zero outside the touched ``box`` (x, y, width,
    height px), so only the cells that meet it are averaged (the window's margin of 4 reaches is not read);
    the others are 0. Depth: OpenCV's INTER_AREA block means (:func:`~gelsim.optics.ops.resample.area_mean_box`,
    the same values as over the whole window); mask: the blocks' counts (an integral image of its bytes, no
    float copy) times 1/f^2 in float32, which is what INTER_AREA computes for 0/1 values."""
    f, r0, c0, hc, wc = window
    bx, by, bw, bh = box
    win = (slice(r0, r0 + hc * f), slice(c0, c0 + wc * f))
    out = np.zeros((2, hc, wc), np.float32)
    out[0] = area_mean_box(depth[win].astype(np.float32, copy=False), f, (by - r0, by + bh - r0, bx - c0, bx + bw - c0))
    i0, i1 = max(0, (by - r0) // f), min(hc, -(-(by + bh - r0) // f))
    j0, j1 = max(0, (bx - c0) // f), min(wc, -(-(bx + bw - c0) // f))
    if i1 > i0 and j1 > j0:
        sub = (slice(r0 + i0 * f, r0 + i1 * f), slice(c0 + j0 * f, c0 + j1 * f))
        s = cv2.integral(mask[sub].view(np.uint8))[::f, ::f]      # int32 counts at the cells' corners
        counts = s[1:, 1:] - s[1:, :-1] - s[:-1, 1:] + s[:-1, :-1]
        np.multiply(counts, np.float32(1.0 / (f * f)), out=out[1, i0:i1, j0:j1], casting="unsafe")
    return out


def displacement_fields(profile, fidelity, imprint, *, shear_mm=(0.0, 0.0), twist_deg: float = 0.0):
    """In-plane displacement on a coarse grid over the imprint, px.

    Returns (field (Hc, Wc, 2), cell size (sx, sy) px, grid origin px (the full-image
    coordinate of cell (0, 0)'s corner), contact centroid px).

    Returns None when nothing touches.
    """
    from .fidelity import get_fidelity

    fidelity = get_fidelity(fidelity)
    gel = profile.gel
    mmpp = profile.image.mm_per_px
    h, w = profile.shape
    depth, mask = imprint.depth_mm, imprint.contact_mask
    if depth.shape != (h, w) or mask.shape != (h, w):
        raise GelsimError(f"imprint is {depth.shape}, the profile's image is {(h, w)}; "
                          "press with the same profile")
    touched = imprint.touched_extent
    if touched is None:
        return None
    by, bx = touched[0], touched[2]
    bh, bw = touched[1] - by, touched[3] - bx
    f, r0, c0, hc, wc = field_window(profile, (bx, by, bw, bh))
    cell_mm = f * mmpp
    ell = gel.thickness_mm / cell_mm  # reach of the in-plane fields, cells
    cells = _cell_means(depth, mask, (bx, by, bw, bh), (f, r0, c0, hc, wc))
    depth_c, mask_c = cells
    sx = sy = float(f)  # px per cell
    amp = 3.0 / (2.0 * gel.thickness_mm)  # surface displacement per unit depth-averaged flux, 1/mm
    if fidelity.marker_model == "elastic":
        pad = int(math.ceil(3 * ell))  # the screened kernel is < 5% of its peak beyond 3 l
        phi, spread = _screened(cells, ell, pad)
        gy, gx = np.gradient(phi * cell_mm * cell_mm, cell_mm)
        ux, uy = amp * gx, amp * gy
        spread = -spread
    else:
        both = cv2.GaussianBlur(cv2.merge([depth_c, mask_c]), (0, 0), ell, borderType=cv2.BORDER_CONSTANT)
        gy, gx = np.gradient(both[..., 0].astype(np.float64), cell_mm)
        a = amp * gel.thickness_mm ** 2  # 3 l^2 / (2 h) with l = h, mm
        ux, uy = -a * gx, -a * gy
        spread = both[..., 1].astype(np.float64)
    # The window with a ring of cells around it (filled below), px.
    field = np.empty((hc + 2, wc + 2, 2))
    core = field[1:-1, 1:-1]
    core[..., 0] = ux
    core[..., 1] = uy
    core /= mmpp
    cx = cy = 0.0
    s_px = np.asarray(shear_mm, dtype=np.float64) / mmpp
    theta = math.radians(twist_deg)
    if s_px.any() or theta:
        inside = mask_c >= 0.5
        ref = float(spread[inside].mean()) if inside.any() else float(spread.max())
        weight = np.minimum(spread / ref, 1.0) if ref > 0 else np.zeros_like(spread)
        weight[inside] = 1.0
        wsum = float(mask_c.sum())
        xs = c0 + (np.arange(wc) + 0.5) * sx - 0.5  # the cells' centres, px
        ys = (r0 + (np.arange(hc) + 0.5) * sy - 0.5)[:, None]
        cx = float((mask_c * xs).sum() / wsum) if wsum > 0 else (w - 1) / 2.0
        cy = float((mask_c * ys).sum() / wsum) if wsum > 0 else (h - 1) / 2.0
        c, s = math.cos(theta), math.sin(theta)
        rx, ry = xs - cx, ys - cy
        core[..., 0] += weight * (s_px[0] + (c - 1.0) * rx - s * ry)
        core[..., 1] += weight * (s_px[1] + s * rx + (c - 1.0) * ry)
    # The ring: zero inside the image (the fields have decayed), the edge cells' values at the
    # image's edges (the window reaches them).
    field[1:-1, 0] = 0.0 if c0 > 0 else core[:, 0]
    field[1:-1, -1] = 0.0 if c0 + wc * f < w else core[:, -1]
    field[0] = 0.0 if r0 > 0 else field[1]
    field[-1] = 0.0 if r0 + hc * f < h else field[-2]
    return field, (sx, sy), (c0 - sx, r0 - sy), (cx, cy)


def displace(profile, fidelity, imprint, *, shear_mm=(0.0, 0.0), twist_deg: float = 0.0,
             seed: int = 0, rest: np.ndarray | None = None) -> Markers:
    """Markers moved by the gel: dilation from ``imprint``, shear ``shear_mm`` (x, y) mm and
    twist ``twist_deg`` (degrees, +x towards +y) of the contact, decaying outside it.

    ``imprint`` None (or no contact) leaves the markers at rest. ``rest`` overrides the
    rest centres (float (N, 2) px; default :func:`marker_grid` with ``seed``).
    Returns float32 :class:`Markers`.
    """
    for name, val in (("shear_mm", shear_mm), ("twist_deg", twist_deg)):
        if not np.isfinite(np.asarray(val, dtype=np.float64)).all():
            raise GelsimError(f"{name} = {val} is not finite; give finite values")
    if np.asarray(shear_mm).shape != (2,):
        raise GelsimError(f"shear_mm = {shear_mm} must be two numbers (x, y) in mm")
    rest = _check_rest(rest, profile, seed)
    corners = square_corners(rest, profile)
    res = None if imprint is None or rest.shape[0] == 0 else displacement_fields(
        profile, fidelity, imprint, shear_mm=shear_mm, twist_deg=twist_deg)
    if res is None:
        return Markers(rest, rest.copy(), corners.astype(np.float32))
    field, (sx, sy), (ox, oy), _ = res
    pts = np.concatenate([rest.astype(np.float64), corners.reshape(-1, 2)], axis=0)
    disp = _bilinear(field, (pts[:, 0] + 0.5 - ox) / sx - 0.5, (pts[:, 1] + 0.5 - oy) / sy - 0.5)
    moved = pts + disp
    n = rest.shape[0]
    return Markers(rest, moved[:n].astype(np.float32), moved[n:].reshape(n, 4, 2).astype(np.float32))
