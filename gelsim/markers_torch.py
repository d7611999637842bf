"""The markers' displacement (:func:`gelsim.markers.displace`) for a batch of imprints on any torch device.

Each frame's fields live on its own coarse window (the imprint's box plus the fields' reach, in cells of a sixth of
the gel's thickness, :func:`gelsim.markers.displacement_fields`); the batch's windows share one array of the largest
size, each in its corner. The ``elastic`` model's screened Poisson solve is the numpy path's circular convolution
on the frame's own zero-padded grid: its kernel (the inverse FFT of the screened multiplier on that grid) is laid
on one common grid, so every frame's convolution is the numpy path's, up to rounding. The ``gaussian`` model's
blur reads zeros past each frame's window, as OpenCV's constant border does.

Stated agreement with the numpy path: marker centres and corners within :data:`TOL_PX` px (tested in
``tests/gelsim/test_markers_torch.py`` on the imprints of the agreement cases, :mod:`gelsim.gel.parity_cases`).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from . import batch_ops as ops
from .errors import GelsimError
from .markers import CELLS_PER_THICKNESS, field_window, screen_multiplier, square_corners
from .optics.ops.resample import area_mean_torch

#: Marker positions (centres and corners) of the device path within this of the numpy path's, px, given the same
#: imprint (the issue's figure). Measured at most 3.1e-5 px at 320x240 on 2026-11-29 (float rounding; the numpy
#: path's FFTs are float32 since then, and its float64 ones gave 1.5-3.1e-5 px too).
TOL_PX = 0.01


@functools.lru_cache(maxsize=128)
def _periodic_kernel(hp: int, wp: int, ell_cells: float) -> np.ndarray:
    """The screened-Poisson solve's kernel on its own (hp, wp) periodic grid: the inverse FFT of
    :func:`gelsim.markers.screen_multiplier` (float64, read-only)."""
    k = np.fft.irfft2(screen_multiplier(hp, wp, ell_cells), s=(hp, wp))
    k.flags.writeable = False
    return k


def _linear_kernels(frames: list[tuple[int, int, int]], ell_cells: float, shape: tuple[int, int], m: tuple[int, int]):
    """Each frame's circular kernel (its window (hc, wc) padded by ``pad`` cells) on the linear-convolution grid
    ``m`` of windows up to ``shape``: entry (i, j) holds the kernel at offset (i, j) wrapped (negative offsets
    at the end), read periodically on the frame's own grid. float64 (B, m0, m1)."""
    out = np.zeros((len(frames), m[0], m[1]))
    oy = np.arange(m[0])
    oy = np.where(oy < shape[0], oy, oy - m[0])
    ox = np.arange(m[1])
    ox = np.where(ox < shape[1], ox, ox - m[1])
    for b, (hc, wc, pad) in enumerate(frames):
        hp, wp = hc + 2 * pad, wc + 2 * pad
        k = _periodic_kernel(hp, wp, float(ell_cells))
        out[b] = k[np.mod(oy, hp)[:, None], np.mod(ox, wp)[None, :]]
    return out


def _gradient(x, spacing: float, rows, cols):
    """numpy.gradient of each frame's (rows[b], cols[b]) corner of ``x`` (B, H, W): (d/drow, d/dcol), central
    inside, one-sided at the frame's edges."""
    torch = ops.torch_module()
    b, h, w = x.shape
    out = []
    for dim, n in ((1, rows), (2, cols)):
        size = x.shape[dim]
        nxt = torch.cat([x.narrow(dim, 1, size - 1), x.narrow(dim, size - 1, 1)], dim=dim)
        prv = torch.cat([x.narrow(dim, 0, 1), x.narrow(dim, 0, size - 1)], dim=dim)
        central = (nxt - prv) / (2.0 * spacing)
        idx = torch.arange(size, device=x.device)
        idx = idx[None, :, None] if dim == 1 else idx[None, None, :]
        last = (n - 1)[:, None, None]
        # the frame's last sample: x[n-1] - x[n-2]
        before = torch.gather(x, dim, (idx - 1).clamp(min=0).expand(b, h, w))
        first = (nxt - x) / spacing
        lastd = (x - before) / spacing
        g = torch.where(idx == 0, first, torch.where(idx == last, lastd, central))
        out.append(g)
    return out


def displace_batch(profile, fidelity, depth_mm, contact_mask, *, shear_mm=None, twist_deg=None, rest=None,
                   seed: int = 0):
    """Markers moved by the gel for ``B`` imprints on the device (:func:`gelsim.markers.displace`).

    depth_mm: float32 ``(B, H, W)`` mm and contact_mask bool ``(B, H, W)`` (an
    :class:`~gelsim.gel.twoscale_torch.ImprintBatch`'s); shear_mm: float ``(B, 2)`` (x, y) mm; twist_deg: float ``(B,)`` degrees; rest: float ``(N, 2)`` or ``(B, N, 2)``
    px rest centres (default :func:`gelsim.markers.marker_grid` with ``seed``).
    Returns (centres float32 ``(B, N, 2)``, corners float32 ``(B, N, 4, 2)``) px, tensors on the imprints' device.
    """
    torch = ops.torch_module()
    from .fidelity import get_fidelity
    from .markers import marker_grid

    fid = get_fidelity(fidelity)
    dev = depth_mm.device
    bsz = depth_mm.shape[0]
    h, w = profile.shape
    if tuple(depth_mm.shape[1:]) != (h, w) or tuple(contact_mask.shape[1:]) != (h, w):
        raise GelsimError(f"imprints are {tuple(depth_mm.shape[1:])}, the profile's image is {(h, w)}; "
                          "press with the same profile")
    shear = np.zeros((bsz, 2)) if shear_mm is None else np.asarray(shear_mm, np.float64).reshape(bsz, 2)
    twist = np.zeros(bsz) if twist_deg is None else np.asarray(twist_deg, np.float64).reshape(bsz)
    if not (np.isfinite(shear).all() and np.isfinite(twist).all()):
        raise GelsimError("shear_mm and twist_deg must be finite; give finite values")
    rest_np = marker_grid(profile, seed=seed) if rest is None else np.asarray(rest, np.float32)
    if rest_np.ndim == 2:
        rest_np = np.broadcast_to(rest_np, (bsz,) + rest_np.shape)
    nmk = rest_np.shape[1]
    corners_np = np.stack([square_corners(r, profile) for r in rest_np]) if nmk else np.zeros((bsz, 0, 4, 2))
    pts = np.concatenate([rest_np.astype(np.float64), corners_np.reshape(bsz, -1, 2)], axis=1)     # (B, 5N, 2)
    pts_t = torch.as_tensor(pts, device=dev)
    if nmk == 0:
        z = torch.zeros((bsz, 0, 2), device=dev)
        return z, torch.zeros((bsz, 0, 4, 2), device=dev)
    nz = (depth_mm > 0) | contact_mask
    box = ops.bbox(nz).cpu().numpy()          # (r0, r1, c0, c1)
    live = [b for b in range(bsz) if box[b][1] > box[b][0]]
    moved = pts_t.clone()
    if live:
        moved_live = _displace_live(profile, fid, depth_mm, contact_mask, box, live, shear, twist, pts_t)
        moved[torch.as_tensor(live, device=dev)] = moved_live
    xy = moved[:, :nmk].float()
    corners = moved[:, nmk:].reshape(bsz, nmk, 4, 2).float()
    return xy, corners


def _displace_live(profile, fid, depth_mm, contact_mask, box, live, shear, twist, pts):
    torch = ops.torch_module()
    dev = depth_mm.device
    gel = profile.gel
    mmpp = profile.image.mm_per_px
    h, w = profile.shape
    n = len(live)
    f = max(1, int(round(gel.thickness_mm / CELLS_PER_THICKNESS / mmpp)))
    wins = []
    for b in live:
        fb, r0, c0, hc, wc = field_window(profile, (int(box[b][2]), int(box[b][0]), int(box[b][3] - box[b][2]),
                                                    int(box[b][1] - box[b][0])))
        if fb != f:   # (the numpy path's fallback to pixel cells, for an image a few cells across)
            raise GelsimError(f"the image ({w}x{h} px) is too small for the device markers' fields; use the numpy "
                              "path (gelsim.markers.displace)")
        wins.append((r0, c0, hc, wc))
    cell_mm = f * mmpp
    ell = gel.thickness_mm / cell_mm
    HC = max(x[2] for x in wins)
    WC = max(x[3] for x in wins)
    lix = torch.as_tensor(live, device=dev)
    r0_t = ops.as_index([x[0] for x in wins], dev)
    c0_t = ops.as_index([x[1] for x in wins], dev)
    hc_t = ops.as_index([x[2] for x in wins], dev)
    wc_t = ops.as_index([x[3] for x in wins], dev)
    both = torch.stack([depth_mm.index_select(0, lix).float(), contact_mask.index_select(0, lix).float()], dim=1)
    big = torch.stack([ops.crop(both[:, i], r0_t, c0_t, (HC * f, WC * f), hc_t * f, wc_t * f) for i in range(2)], 1)
    cells = area_mean_torch(big, f)                                                 # INTER_AREA by a whole factor
    yy = torch.arange(HC, device=dev)[None, :, None]
    xx = torch.arange(WC, device=dev)[None, None, :]
    own = (yy < hc_t[:, None, None]) & (xx < wc_t[:, None, None])
    cells = torch.where(own[:, None], cells, 0.0)
    mask_c = cells[:, 1]
    amp = 3.0 / (2.0 * gel.thickness_mm)
    if fid.marker_model == "elastic":
        pad = int(math.ceil(3 * ell))
        from .gel.layer_torch import grid_for

        m = grid_for((HC, WC))
        kern = _linear_kernels([(x[2], x[3], pad) for x in wins], ell, (HC, WC), m)
        kf = torch.fft.rfft2(torch.as_tensor(kern, device=dev))
        spec = torch.fft.rfft2(cells.double(), s=m)
        pot = torch.fft.irfft2(spec * kf[:, None], s=m)[:, :, :HC, :WC]
        phi, spread = pot[:, 0], -pot[:, 1]
        gy, gx = _gradient(phi * (cell_mm * cell_mm), cell_mm, hc_t, wc_t)
        ux, uy = amp * gx, amp * gy
    else:
        from .optics.ops.filters import smooth_torch

        bl = smooth_torch(cells, ell, border="constant")
        gy, gx = _gradient(bl[:, 0].double(), cell_mm, hc_t, wc_t)
        a = amp * gel.thickness_mm ** 2
        ux, uy = -a * gx, -a * gy
        spread = bl[:, 1].double()
    fx, fy = ux / mmpp, uy / mmpp
    s_px = shear[live] / mmpp
    theta = np.radians(twist[live])
    moving = (np.abs(s_px).sum(axis=1) > 0) | (theta != 0)
    if moving.any():
        inside = (mask_c >= 0.5) & own
        has_in = inside.any(dim=(1, 2))
        mean_in = (spread * inside).sum(dim=(1, 2)) / inside.sum(dim=(1, 2)).clamp(min=1)
        mx = torch.where(own, spread, -math.inf).amax(dim=(1, 2))
        ref = torch.where(has_in, mean_in, mx)
        weight = torch.where(ref[:, None, None] > 0, torch.clamp(spread / ref[:, None, None], max=1.0), 0.0)
        weight = torch.where(inside, 1.0, weight)
        md = mask_c.double() * own
        wsum = md.sum(dim=(1, 2))
        jj = (c0_t[:, None, None] + (xx + 0.5) * f - 0.5).double()
        ii = (r0_t[:, None, None] + (yy + 0.5) * f - 0.5).double()
        cxs = torch.where(wsum > 0, (md * jj).sum(dim=(1, 2)) / wsum.clamp(min=1e-300), (w - 1) / 2.0)
        cys = torch.where(wsum > 0, (md * ii).sum(dim=(1, 2)) / wsum.clamp(min=1e-300), (h - 1) / 2.0)
        c = torch.as_tensor(np.cos(theta), device=dev)[:, None, None]
        s = torch.as_tensor(np.sin(theta), device=dev)[:, None, None]
        sx = torch.as_tensor(s_px[:, 0], device=dev)[:, None, None]
        sy = torch.as_tensor(s_px[:, 1], device=dev)[:, None, None]
        rx, ry = jj - cxs[:, None, None], ii - cys[:, None, None]
        mv = torch.as_tensor(moving, device=dev)[:, None, None]
        fx = torch.where(mv, fx + weight * (sx + (c - 1.0) * rx - s * ry), fx)
        fy = torch.where(mv, fy + weight * (sy + s * rx + (c - 1.0) * ry), fy)
    # the ring of cells around the window: zero inside the image, the edge value at the image's edges
    field = torch.stack([fx, fy], dim=1)                                      # (n, 2, HC, WC)
    hcp, wcp = hc_t + 2, wc_t + 2                                               # each frame's ringed size
    Y = torch.arange(HC + 2, device=dev)
    X = torch.arange(WC + 2, device=dev)
    ys = torch.minimum((Y[None, :] - 1).clamp(min=0), (hc_t - 1)[:, None])     # np.pad's edge mode
    xs = torch.minimum((X[None, :] - 1).clamp(min=0), (wc_t - 1)[:, None])
    ring = torch.gather(field, 2, ys[:, None, :, None].expand(n, 2, HC + 2, WC))
    ring = torch.gather(ring, 3, xs[:, None, None, :].expand(n, 2, HC + 2, WC + 2))
    Y, X = Y[None, :, None], X[None, None, :]
    top = (r0_t > 0)[:, None, None] & (Y == 0)
    left = (c0_t > 0)[:, None, None] & (X == 0)
    bottom = (r0_t + hc_t * f < h)[:, None, None] & (Y == hcp[:, None, None] - 1)
    right = (c0_t + wc_t * f < w)[:, None, None] & (X == wcp[:, None, None] - 1)
    ring = torch.where((top | left | bottom | right)[:, None], 0.0, ring)
    # bilinear at the markers (gelsim.markers._bilinear: clamped to the ringed grid)
    p = pts.index_select(0, lix)
    ox = (c0_t - f).double()[:, None]
    oy = (r0_t - f).double()[:, None]
    cx = ((p[..., 0] + 0.5 - ox) / f - 0.5).clamp(min=0.0)
    cy = ((p[..., 1] + 0.5 - oy) / f - 0.5).clamp(min=0.0)
    cx = torch.minimum(cx, (wcp - 1).double()[:, None])
    cy = torch.minimum(cy, (hcp - 1).double()[:, None])
    x0 = torch.minimum(torch.floor(cx).long(), (wcp - 2)[:, None])
    y0 = torch.minimum(torch.floor(cy).long(), (hcp - 2)[:, None])
    fxw = (cx - x0)[:, None]
    fyw = (cy - y0)[:, None]
    x1 = torch.minimum(x0 + 1, (wcp - 1)[:, None])
    y1 = torch.minimum(y0 + 1, (hcp - 1)[:, None])
    flat = ring.reshape(n, 2, -1)
    W2 = WC + 2

    def at(yi, xi):
        return torch.gather(flat, 2, (yi * W2 + xi)[:, None, :].expand(n, 2, yi.shape[1]))

    disp = (at(y0, x0) * (1 - fxw) + at(y0, x1) * fxw) * (1 - fyw) + (at(y1, x0) * (1 - fxw) + at(y1, x1) * fxw) * fyw
    return p + disp.transpose(1, 2)
