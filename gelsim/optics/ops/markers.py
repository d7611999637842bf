"""The markers: the frame times ``1 - darkness * blur(coverage)`` of the printed dots' quadrilaterals.

Coverage of a convex quadrilateral is the product over its 4 edges of ``clip(0.5 + signed distance
inside, 0, 1)`` at each pixel centre: the exact pixel-box coverage of an axis-aligned rectangle at
least 1 px wide, and within a few percent of it at the corners of a sheared one (cv2.fillPoly with
LINE_AA was tried first: its squares came out 1.2 px too wide and moved in whole pixels). Each
marker's coverage is computed on its own patch, ``radius + 1`` px wider than the marker on every
side, blurred there by the camera, and multiplied into the frame; a patch beyond the frame draws
nothing, and a pixel outside every blurred patch is multiplied by exactly 1.

numpy kernels: numba loops (compiled on first use, cached on disk) over the patches of one frame,
single-threaded, releasing the GIL, rounding as numpy's and OpenCV's float32 passes that they replace
(checked in ``tests/gelsim/test_optics_kernels.py``); torch kernel: the patches of ``B`` frames at once.
"""
from __future__ import annotations

import cv2
import numpy as np
from numba import njit

from ...errors import GelsimError
from . import torch_module
from .filters import blur_radius_px, gaussian_blur, gaussian_blur_torch

_LO = np.float32(0.0)


def marker_corners(markers) -> np.ndarray | None:
    """Marker corners as float32 ``(N, 4, 2)`` px from a Markers-like object, an array, or None."""
    if markers is None:
        return None
    corners = getattr(markers, "corners_px", markers)
    corners = np.asarray(corners, dtype=np.float32)
    if corners.size == 0:
        return None
    if corners.ndim != 3 or corners.shape[1:] != (4, 2):
        raise GelsimError(f"marker corners have shape {corners.shape}; give (N, 4, 2) pixel coordinates (x, y)")
    if not np.all(np.isfinite(corners)):
        raise GelsimError("marker corners contain NaN or infinity; check the marker displacement")
    return corners


def fine_px(corners, s: int):
    """Pixel coordinates (an array or a tensor) at ``s`` times the resolution: pixel centres at integers at
    both resolutions, ``x_fine = s (x + 1/2) - 1/2``."""
    return s * (corners + 0.5) - 0.5


@njit(cache=True, nogil=True)
def quad_coverage_strip(lo, nx, ny, cc, out):
    """Coverage of convex quadrilaterals, one ``P x P`` patch each, side by side in ``out``.

    ``lo``: int64 ``(N, 2)`` (x, y) px of each patch's top-left pixel; ``nx, ny``: float32 ``(N, 4)`` the
    edges' inward unit normals; ``cc``: float32 ``(N, 4)`` each edge's offset plus half a pixel (so that
    ``nx x + ny y + cc`` is 0.5 plus the signed distance of pixel centre ``(x, y)`` inside the edge);
    ``out``: float32 ``(P, N P)``, written: patch ``i`` in columns ``i P:(i + 1) P``, its row ``r``,
    column ``j`` the pixel ``(lo[i, 0] + j, lo[i, 1] + r)``. Coverage is the product over the edges,
    in their order, of ``clip(nx x + ny y + cc, 0, 1)``, each product and sum rounded to float32 as
    numpy's broadcast expression wrote it before."""
    p = out.shape[0]
    n = lo.shape[0]
    one = np.float32(1.0)
    for i in range(n):
        for r in range(p):
            y = np.float32(lo[i, 1] + r)
            o = out[r][i * p:(i + 1) * p]
            for j in range(p):
                x = np.float32(lo[i, 0] + j)
                v = one
                for k in range(4):
                    d = (nx[i, k] * x + ny[i, k] * y) + cc[i, k]
                    v *= min(max(d, _LO), one)
                o[j] = v


@njit(cache=True, nogil=True)
def multiply_patches_rows(rows, lo, factor, y_lo):
    """Multiply a frame's rows ``y_lo:y_lo + n`` (px), ``rows`` float32 ``(n, W, C)`` in place (the whole
    frame: ``y_lo`` 0), by patches of a factor, in patch order.

    ``lo``: int64 ``(N, 2)`` (x, y) px of each patch's top-left pixel; ``factor``: float32 ``(P, N P)``,
    patch ``i`` in columns ``i P:(i + 1) P`` (as :func:`quad_coverage_strip` lays them out), the same
    for every channel. Parts of a patch beyond the rows are skipped. The products are pixel by pixel
    those of a whole frame's pass, so a frame finished band by band (while its rows are in the
    cache) gets the same values."""
    n, w, c = rows.shape
    p = factor.shape[0]
    for i in range(lo.shape[0]):
        x0, y0 = lo[i, 0], lo[i, 1]
        ax, ay = max(x0, 0), max(y0, y_lo)
        bx, by = min(x0 + p, w), min(y0 + p, y_lo + n)
        for y in range(ay, by):
            f = factor[y - y0][i * p + ax - x0:i * p + bx - x0]
            row = rows[y - y_lo]
            for x in range(bx - ax):
                fx = f[x]
                for k in range(c):
                    row[ax + x, k] *= fx


def coverage_strip(corners: np.ndarray, pad_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Anti-aliased coverage of convex quadrilateral markers, one patch per marker, side by side.

    ``corners``: float32 ``(N, 4, 2)`` (x, y) px, pixel centres at integers. Returns ``(origin, strip)``:
    int64 ``(N, 2)`` (x, y) of each patch's top-left pixel and float32 ``(P, N P)`` coverage in 0-1, patch
    ``i`` in columns ``i P:(i + 1) P`` (the layout :func:`marker_factors` blurs in one call), each patch
    ``pad_px`` wider than its marker on every side."""
    n = corners.shape[0]
    lo = np.floor(corners.min(axis=1)).astype(np.int64) - pad_px
    size = int(np.ceil(corners.max(axis=1) - corners.min(axis=1)).max()) + 2 * pad_px + 2
    v0 = corners
    v1 = np.roll(corners, -1, axis=1)
    e = v1 - v0                                                           # (N, 4, 2)
    # orientation of each quad (shoelace sign) so that the normals point inwards
    area2 = (v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]).sum(axis=1)
    sign = np.where(area2 >= 0, 1.0, -1.0).astype(np.float32)[:, None]
    length = np.maximum(np.linalg.norm(e, axis=-1), 1e-6)
    nx, ny = -e[..., 1] * sign / length, e[..., 0] * sign / length       # (N, 4)
    c = -(nx * v0[..., 0] + ny * v0[..., 1])
    strip = np.empty((size, n * size), np.float32)
    # per pixel: the product over the edges of clip(nx x + ny y + c + 0.5, 0, 1), in one pass
    quad_coverage_strip(lo, np.ascontiguousarray(nx, np.float32), np.ascontiguousarray(ny, np.float32),
                        np.ascontiguousarray(c + np.float32(0.5), np.float32), strip)
    return lo, strip


def marker_factors(corners: np.ndarray, darkness: float, blur_sigma_px: float,
                   shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """The factors a frame of ``shape`` (H, W, C) is multiplied by: ``(origin, factor)`` with int64 ``(N, 2)``
    (x, y) of each marker's patch's top-left pixel and float32 ``(P, N P)`` ``1 - darkness * blur(coverage)``,
    the ``P x P`` patches side by side, the same for every channel; None if no marker's blurred patch
    reaches the frame. Depends on nothing else, so a frame whose markers did not move can reuse it."""
    h, w = shape[:2]
    radius = blur_radius_px(blur_sigma_px)
    inside = ((corners.max(axis=1) >= -radius - 1) & (corners.min(axis=1) <= np.array([w, h]) + radius)).all(axis=1)
    corners = corners[inside]
    if corners.shape[0] == 0:
        return None
    # side by side in one strip: each patch has >= radius zero columns at both ends,
    # so the blur does not mix neighbouring patches
    lo, strip = coverage_strip(corners, radius + 1)
    if radius:
        strip = gaussian_blur(strip, blur_sigma_px)
    strip = cv2.addWeighted(strip, -darkness, strip, 0.0, 1.0)        # 1 - darkness * coverage
    return lo, strip


def apply_marker_factors(frame: np.ndarray, factors: tuple[np.ndarray, np.ndarray] | None, y0: int = 0) -> None:
    """Multiply ``frame`` (float32 C-contiguous ``(H, W, C)``, in place) by :func:`marker_factors`' patches,
    in marker order (one pass of :func:`multiply_patches_rows`: a Python loop of OpenCV multiplies over
    about 100 patches took 0.4 ms per frame). ``y0``: the frame row (px) that ``frame``'s first row is,
    for a band of a frame (the same values there as the whole frame's pass)."""
    if factors is None:
        return
    lo, factor = factors
    multiply_patches_rows(frame, lo, factor, y0)


# ---------------------------------------------------------------- torch

def marker_factor_torch(corners, shape: tuple[int, int], darkness: float, blur_sigma_px: float):
    """:func:`marker_factors` as a ``(B, H, W)`` factor, from corners float32 ``(B, N, 4, 2)`` (x, y) px (a
    frame without markers may carry them far off the image, where they draw nothing)."""
    torch = torch_module()
    b, n = corners.shape[:2]
    h, w = shape
    radius = blur_radius_px(blur_sigma_px)
    pad = radius + 1
    cmin = corners.amin(dim=2)                                        # (B, N, 2)
    cmax = corners.amax(dim=2)
    lo = torch.floor(cmin).long() - pad                               # (B, N, 2) patch origin
    # the same patch size for every marker of the batch: a larger patch only adds zero coverage
    size = int(torch.ceil(cmax - cmin).amax()) + 2 * pad + 2
    grid = torch.arange(size, device=corners.device)
    xs = (lo[..., 0:1] + grid).float()[:, :, None, :]                 # (B, N, 1, P)
    ys = (lo[..., 1:2] + grid).float()[:, :, :, None]                 # (B, N, P, 1)
    v0 = corners
    v1 = torch.roll(corners, -1, dims=2)
    ex, ey = v1[..., 0] - v0[..., 0], v1[..., 1] - v0[..., 1]         # (B, N, 4)
    prod = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    area2 = ((prod[..., 0] + prod[..., 1]) + prod[..., 2]) + prod[..., 3]
    sign = torch.where(area2 >= 0, 1.0, -1.0)[..., None]
    length = torch.clamp(torch.sqrt(ex * ex + ey * ey), min=1e-6)
    nx, ny = -ey * sign / length, ex * sign / length
    c = -(nx * v0[..., 0] + ny * v0[..., 1])
    cov = None
    for k in range(4):
        d = nx[..., k, None, None] * xs + ny[..., k, None, None] * ys
        d = torch.clamp(d + (c[..., k] + 0.5)[..., None, None], 0.0, 1.0)
        cov = d if cov is None else cov * d
    cov = cov.reshape(b * n, size, size)
    if radius:
        cov = gaussian_blur_torch(cov, blur_sigma_px)
    fac = (cov * (-darkness) + 1.0).reshape(b, n, size, size)
    # scatter the patches into the frame's factor by product: a pixel outside a marker's blurred
    # square multiplies by exactly 1, so overlapping zero borders leave it as it is
    py = lo[..., 1, None, None] + grid[:, None]                       # (B, N, P, 1)
    px = lo[..., 0, None, None] + grid[None, :]                       # (B, N, 1, P)
    inside = (py >= 0) & (py < h) & (px >= 0) & (px < w)
    frame_of = torch.arange(b, device=corners.device)[:, None, None, None]
    idx = torch.where(inside, (frame_of * h + py) * w + px, b * h * w)  # b*h*w: a slot that is thrown away
    out = torch.ones(b * h * w + 1, device=corners.device)
    out.scatter_reduce_(0, idx.reshape(-1), fac.reshape(-1), reduce="prod")
    return out[:-1].reshape(b, h, w)
