"""The object's heights seen through a frame's pose, on a torch device: the twin of
:meth:`gelsim.scene.HeightPatch.sample` for a batch of frames (each of its own patch and pose). Parity:
``tests/gelsim/test_scene_torch.py`` (within :data:`SAMPLE_TOL_MM` of the numpy kernel).
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
        torch = ops.torch_module()
        hp = max(p.heights_mm.shape[0] for p in patches)
        wp = max(p.heights_mm.shape[1] for p in patches)
        out = np.empty((len(patches), hp, wp), np.float32)
        for s, p in enumerate(patches):
            a = p.heights_mm
            out[s] = np.pad(a, ((0, hp - a.shape[0]), (0, wp - a.shape[1])), mode="edge")
        mm = {float(p.mm_per_px) for p in patches}
        if len(mm) != 1:
            raise ValueError("patches of one bank share their cell size")
        return cls(torch.as_tensor(out, device=device), [p.heights_mm.shape for p in patches],
                   [tuple(p.origin_mm) for p in patches], mm.pop())


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
