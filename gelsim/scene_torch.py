"""The object's heights seen through a frame's pose, on a torch device: the twin of
:meth:`gelsim.scene.HeightPatch.sample` for a batch of frames (each of its own patch and pose), and the sequences'
patches finished here (a rotated fabric's resampling, :func:`finish_rotated`) with their crown envelopes
(:meth:`PatchBank.closed`), so that ``--stages all`` leaves only the fabric's axis-aligned grid to the host. Parity:
``tests/gelsim/test_scene_torch.py`` (within :data:`SAMPLE_TOL_MM` and :data:`FINISH_TOL` of the numpy kernels;
the envelopes exactly).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import batch_ops as ops
from .scene import NEAR_TRANSLATION_PX

#: Heights sampled here within this of :meth:`gelsim.scene.HeightPatch.sample`'s, mm: OpenCV's warp rounds its
#: coordinates its own way (measured: within 1e-5 of the heights' range).
SAMPLE_TOL_MM = 1e-4
#: A rotated fabric's patch finished here (:func:`finish_rotated`) within this of the host's
#: (:meth:`gelsim.fabrics.render.RotatedHeights.finish`), as a fraction of the fabric's relief: the same points read,
#: the bilinear sums rounded in another order (measured: at most 2.3e-7 of the relief on ten fabrics of nine families).
FINISH_TOL = 2e-6


@dataclass
class PatchBank:
    """Height patches on the device: ``heights`` float32 ``(S, Hp, Wp)`` mm, patch s in the corner of the batch's
    largest, continued beyond its own ``sizes[s]`` (rows, cols) by replicating its edge (what the warp's
    replicated border reads there); ``origins`` (x0, y0) mm and ``mm_per_px`` as :class:`gelsim.scene.HeightPatch`."""
    heights: object
    sizes: list
    origins: list
    mm_per_px: float

    @classmethod
    def from_patches(cls, patches: list, device) -> "PatchBank":
        """The bank of ``patches``: :class:`gelsim.scene.HeightPatch` (uploaded) or :class:`gelsim.scene.PatchParts`
        (a rotated fabric's finished here, :func:`finish_rotated`)."""
        mm = {float(p.mm_per_px) for p in patches}
        if len(mm) != 1:
            raise ValueError("patches of one bank share their cell size")
        return cls._stack([_on_device(p, device) for p in patches], [tuple(p.origin_mm) for p in patches],
                          mm.pop())

    @classmethod
    def _stack(cls, arrays: list, origins: list, mm_per_px: float) -> "PatchBank":
        hp = max(a.shape[0] for a in arrays)
        wp = max(a.shape[1] for a in arrays)
        torch = ops.torch_module()
        out = torch.stack([ops.pad_hw(a, (0, wp - a.shape[1], 0, hp - a.shape[0]), "replicate") for a in arrays])
        return cls(out, [tuple(a.shape) for a in arrays], origins, mm_per_px)

    def closed(self, kernels: dict) -> "PatchBank":
        """The crown envelopes of the patches ``kernels`` names (patch index -> the closing's side, px, odd), in
        that order: each patch's grey closing over its own size (:func:`gelsim.batch_ops.closing`, the host's
        :func:`gelsim.gel.twoscale.crown_envelope` exactly)."""
        arrays = [ops.closing(self.heights[s:s + 1, :self.sizes[s][0], :self.sizes[s][1]], k)[0]
                  for s, k in kernels.items()]
        return self._stack(arrays, [self.origins[s] for s in kernels], self.mm_per_px)


def _on_device(patch, device):
    """``patch``'s heights as a float32 ``(h, w)`` tensor on ``device``."""
    torch = ops.torch_module()
    h = getattr(patch, "heights_mm", None)
    if h is None:
        h = patch.heights
        if not isinstance(h, np.ndarray):
            return finish_rotated(h, device)
    return torch.as_tensor(np.ascontiguousarray(h, np.float32), device=device)


def finish_rotated(parts, device):
    """:meth:`gelsim.fabrics.render.RotatedHeights.finish` on ``device``: the fabric's axis-aligned grid uploaded
    (about the patch's size) and read bilinearly at :meth:`~gelsim.fabrics.render.RotatedHeights.maps`' points (the
    same float64 arithmetic, rounded to float32 once; the edge replicated), scaled by the relief and cut at 0: float32
    ``(height_px, width_px)`` mm, within :data:`FINISH_TOL` of the host's (OpenCV's remap rounds its sums its own
    way)."""
    torch = ops.torch_module()
    src = torch.as_tensor(parts.src, device=device)
    nl, nk = src.shape
    c, s = parts.cos, parts.sin
    jj = parts.j0 + torch.arange(parts.width_px, dtype=torch.float64, device=device)
    ii = parts.i0 + torch.arange(parts.height_px, dtype=torch.float64, device=device)
    u = (c * jj[None, :] + s * ii[:, None] - parts.k0).float()
    v = (-s * jj[None, :] + c * ii[:, None] - parts.l0).float()
    u0, v0 = torch.floor(u), torch.floor(v)
    au, av = u - u0, v - v0
    u0, v0 = u0.long(), v0.long()
    cu0, cu1 = u0.clamp(0, nk - 1), (u0 + 1).clamp(0, nk - 1)
    cv0, cv1 = v0.clamp(0, nl - 1), (v0 + 1).clamp(0, nl - 1)
    flat = src.reshape(-1)

    def at(r, q):
        return flat[r * nk + q]

    out = (((at(cv0, cu0) * ((1 - av) * (1 - au)) + at(cv0, cu1) * ((1 - av) * au))
            + at(cv1, cu0) * (av * (1 - au))) + at(cv1, cu1) * (av * au))
    return (out * float(np.float32(parts.relief_mm))).clamp_min(0.0)


def sample_patches(bank: PatchBank, which, poses, shape: tuple[int, int], sensor_mm_per_px: float):
    """:meth:`gelsim.scene.HeightPatch.sample` of patch ``which[b]`` at pose ``poses[b]`` = (x_mm, y_mm, yaw_deg,
    (tilt_x, tilt_y) deg) for every frame: float32 ``(B, H, W)`` mm. Near a translation the same 2 x 2 filter
    (:meth:`gelsim.scene.HeightPatch.sample`'s); else bilinear at the affine map's float coordinates, the patch's edge
    replicated (OpenCV's warpAffine; within about 1e-5 of the heights' range of it, its own float rounding)."""
    torch = ops.torch_module()
    dev = bank.heights.device
    H, W = shape
    bsz = len(which)
    s, p = sensor_mm_per_px, bank.mm_per_px
    cu, cv = (W - 1) / 2.0, (H - 1) / 2.0
    coef = np.zeros((bsz, 6))
    shifted = np.zeros(bsz, bool)
    fx = np.zeros(bsz, np.float32)
    fy = np.zeros(bsz, np.float32)
    ix = np.zeros(bsz, np.int64)
    iy = np.zeros(bsz, np.int64)
    tilt = np.zeros((bsz, 2), np.float32)
    for b, (k, pose) in enumerate(zip(which, poses)):
        x_mm, y_mm, yaw, tl = pose
        c, sn = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        x0, y0 = bank.origins[k]
        a11, a12, a21, a22 = c * s / p, -sn * s / p, sn * s / p, c * s / p
        b1 = (x_mm - x0) / p - a11 * cu - a12 * cv
        b2 = (y_mm - y0) / p - a21 * cu - a22 * cv
        coef[b] = (a11, a12, b1, a21, a22, b2)
        off = (abs(a11 - 1.0) + abs(a21)) * W + (abs(a12) + abs(a22 - 1.0)) * H
        if off <= NEAR_TRANSLATION_PX:
            tx = a11 * cu + a12 * cv + b1 - cu
            ty = a21 * cu + a22 * cv + b2 - cv
            xi, yi = math.floor(tx), math.floor(ty)
            rows, cols = bank.sizes[k]
            if not (xi < 0 or yi < 0 or xi + W + 1 > cols or yi + H + 1 > rows):
                shifted[b] = True
                ix[b], iy[b] = xi, yi
                fx[b], fy[b] = np.float32(tx - xi), np.float32(ty - yi)
        if tl[0] or tl[1]:
            tilt[b] = (np.float32(math.tan(math.radians(tl[1]))), np.float32(math.tan(math.radians(tl[0]))))
    src = bank.heights.index_select(0, ops.as_index(which, dev))
    rows_t = ops.as_index([bank.sizes[k][0] for k in which], dev)[:, None, None]
    cols_t = ops.as_index([bank.sizes[k][1] for k in which], dev)[:, None, None]
    wp = src.shape[2]
    flat = src.reshape(bsz, -1)

    hp = src.shape[1]

    def at(yy, xx):
        i = yy.clamp(0, hp - 1) * wp + xx.clamp(0, wp - 1)
        return torch.gather(flat, 1, i.reshape(bsz, -1)).reshape(i.shape)

    # the general map: float64 coordinates, replicated edge
    cf = torch.as_tensor(coef, device=dev)
    xs = torch.arange(W, device=dev, dtype=torch.float64)[None, None, :]
    ys = torch.arange(H, device=dev, dtype=torch.float64)[None, :, None]
    X = cf[:, 0, None, None] * xs + cf[:, 1, None, None] * ys + cf[:, 2, None, None]
    Y = cf[:, 3, None, None] * xs + cf[:, 4, None, None] * ys + cf[:, 5, None, None]
    x0 = torch.floor(X)
    y0 = torch.floor(Y)
    ax = (X - x0).float()
    ay = (Y - y0).float()
    x0 = x0.long()
    y0 = y0.long()
    cx0, cx1 = x0.clamp(0) .minimum(cols_t - 1), (x0 + 1).clamp(0).minimum(cols_t - 1)
    cy0, cy1 = y0.clamp(0).minimum(rows_t - 1), (y0 + 1).clamp(0).minimum(rows_t - 1)
    out = (at(cy0, cx0) * ((1 - ay) * (1 - ax)) + at(cy0, cx1) * ((1 - ay) * ax)
           + at(cy1, cx0) * (ay * (1 - ax)) + at(cy1, cx1) * (ay * ax))
    if shifted.any():
        ixt = ops.as_index(ix, dev)[:, None, None]
        iyt = ops.as_index(iy, dev)[:, None, None]
        xx = torch.arange(W, device=dev)[None, None, :] + ixt
        yy = torch.arange(H, device=dev)[None, :, None] + iyt
        fxt = torch.as_tensor(fx, device=dev)[:, None, None]
        fyt = torch.as_tensor(fy, device=dev)[:, None, None]
        one = 1.0
        k00, k01 = (one - fxt) * (one - fyt), fxt * (one - fyt)
        k10, k11 = (one - fxt) * fyt, fxt * fyt
        xx1 = xx + 1
        yy1 = yy + 1
        sh = at(yy, xx) * k00 + at(yy, xx1) * k01 + at(yy1, xx) * k10 + at(yy1, xx1) * k11
        out = torch.where(torch.as_tensor(shifted, device=dev)[:, None, None], sh, out)
    if tilt.any():
        xs32 = ((torch.arange(W, device=dev, dtype=torch.float32) - cu) * s).float()
        ys32 = ((torch.arange(H, device=dev, dtype=torch.float32) - cv) * s).float()
        tt = torch.as_tensor(tilt, device=dev)
        out = out + tt[:, 0, None, None] * xs32[None, None, :]
        out = out + tt[:, 1, None, None] * ys32[None, :, None]
    return out
