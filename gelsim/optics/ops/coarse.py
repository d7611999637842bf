"""The calibrated table's depth and halo terms (:mod:`gelsim.optics.lut`, whose docstring gives the model),
on a coarse grid of about :data:`COARSE_GRID_MM`, interpolated back bilinearly.

Features on the grid (``h``: the imprint's block means, mm): the depth term's ``[h, h xn, h yn]``
(``xn, yn``: the grid pixel's position in -1..1 of the field), the halo's ``[g db/dx, g db/dy, s]``
(``b, b0``: ``h`` blurred by the halo's two widths, ``s = max(b - b0, 0)`` the spill, ``g = min(s /
gate, 1)`` its gate); the colour change is the features times the table's colours (:class:`CoarseSpec`).

numpy kernels: one frame (OpenCV, a matmul for the colours); torch kernels: ``(B, H, W)`` frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import torch_module
from .filters import mix_channels_torch, slopes, slopes_torch, smooth, smooth_torch
from .resample import area_mean_box, area_mean_torch, upsample, upsample_torch

# The depth and halo terms are smooth (the depth term follows the press's shape: a fabric's texture
# changes it by about 0.1 DN), so they are computed on a coarse grid of about 0.125 mm, which the
# halo's narrower blur (0.25 mm) spans at 2 grid pixels (a Gaussian of sigma >= 2 px is well
# sampled), and interpolated back bilinearly.
COARSE_GRID_MM = 0.125
# Where the two terms change no pixel by one 8-bit step (1 DN, about the R1.5's 0.92 DN read noise),
# they are skipped: a whole-pad fabric press 0.04-0.05 mm deep changes pixels by at most 0.4-0.8 DN
# (vitac, catalog fabrics 1, 12, 30, 45, 80 at 3-4 N; a broad change, not the texture), and bringing
# the terms back to full resolution would cost about 2 ms of a 960x720 frame's 10.
COARSE_SKIP_DN = 1.0


@dataclass(frozen=True)
class CoarseSpec:
    """A table's depth and halo terms: ``depth_term`` whether it has the depth term; ``halo`` its widths
    (a dict of ``halo_sigma_mm``, ``halo_base_mm``, ``halo_gate_mm``) or None; ``rgb`` float32 ``(k, 3)``
    DN per unit of each feature, in :func:`coarse_grid`'s order, at the profile's gain; ``box`` the
    table's ``position_box`` (:func:`clamp_positions`) or None."""
    depth_term: bool
    halo: dict | None
    rgb: np.ndarray
    box: np.ndarray | None = None


def coarse_factor(mm_per_px: float) -> int:
    """Full-resolution pixels per coarse-grid pixel (an integer >= 1)."""
    return max(1, int(COARSE_GRID_MM / mm_per_px))


def clamp_positions(xn: np.ndarray, yn: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """Field positions ``xn, yn`` (float32 arrays) clamped into a table's ``position_box`` (None: as given)."""
    if box is None:
        return xn, yn
    return (np.clip(xn, box[0], box[1]).astype(np.float32), np.clip(yn, box[2], box[3]).astype(np.float32))


def grid_positions(shape: tuple[int, int], mm_per_px: float, field_mm: tuple[float, float], f: int,
                   box=None) -> tuple[np.ndarray, np.ndarray]:
    """The coarse grid's pixel positions in -1..1 of the field, clamped into ``box``: float32 ``xn (w',)``,
    ``yn (h',)`` for a frame of ``shape`` (H, W). Grid pixel ``x'`` is centred on full-resolution
    ``f (x' + 1/2) - 1/2``."""
    h, w = shape
    hs, ws = -(-h // f), -(-w // f)
    xn = ((f * (np.arange(ws) + 0.5) - 0.5 - (w - 1) / 2.0) * mm_per_px / (field_mm[0] / 2.0)).astype(np.float32)
    yn = ((f * (np.arange(hs) + 0.5) - 0.5 - (h - 1) / 2.0) * mm_per_px / (field_mm[1] / 2.0)).astype(np.float32)
    return clamp_positions(xn, yn, box)


def coarse_grid(depth: np.ndarray, mm_per_px: float, field_mm: tuple[float, float], depth_term: bool,
                halo: dict | None, box=None, positions=None, extent=None) -> tuple[np.ndarray, int]:
    """The depth and halo terms' features on the coarse grid: float32 ``(h', w', k)``, ``k`` = 3 for the
    depth term's ``[d, d xn, d yn]`` if ``depth_term`` and 3 for the halo's ``[g db/dx, g db/dy, s]``
    if ``halo`` (a dict of ``halo_sigma_mm``, ``halo_base_mm``, ``halo_gate_mm``); and the grid's
    factor (:func:`coarse_factor`). ``depth``: the whole frame's imprint, mm; the gel continues past
    the image (replicated borders), as for the camera blur; ``box``: the table's ``position_box``
    (:func:`clamp_positions`); ``positions``: :func:`grid_positions`' ``(xn, yn)`` if known; ``extent``: the
    box outside which ``depth`` is 0 (:func:`~gelsim.optics.ops.box.imprint_extent`), if known: only its
    blocks are averaged (:func:`area_mean_box`, the same values)."""
    f = coarse_factor(mm_per_px)
    hg = area_mean_box(depth, f, extent)
    gmm = mm_per_px * f
    feats = []
    if depth_term:
        xn, yn = grid_positions(depth.shape, mm_per_px, field_mm, f, box) if positions is None else positions
        feats += [hg, hg * xn[None, :], hg * yn[:, None]]
    if halo is not None:
        b = smooth(hg, halo["halo_sigma_mm"] / gmm, "replicate")
        b0 = smooth(hg, halo["halo_base_mm"] / gmm, "replicate")
        sp = cv2.subtract(b, b0)
        cv2.max(sp, 0.0, sp)
        gate = cv2.min(cv2.multiply(sp, 1.0 / halo["halo_gate_mm"]), 1.0)
        gx, gy = slopes(b, gmm)
        feats += [cv2.multiply(gx, gate), cv2.multiply(gy, gate), sp]
    return np.ascontiguousarray(np.stack(feats, axis=-1), dtype=np.float32), f


def coarse_features(depth: np.ndarray, mm_per_px: float, field_mm: tuple[float, float], depth_term: bool,
                    halo: dict | None) -> np.ndarray:
    """:func:`coarse_grid`'s features at full resolution, interpolated as the renderer does:
    float32 ``(H, W, k)`` (for the calibration's design matrix)."""
    g, f = coarse_grid(depth, mm_per_px, field_mm, depth_term, halo)
    k = g.shape[-1]
    chans = [upsample(np.ascontiguousarray(g[..., i]), f, depth.shape) for i in range(k)]
    return np.stack(chans, axis=-1)


def coarse_small(depth: np.ndarray, spec: CoarseSpec, mm_per_px: float, field_mm: tuple[float, float],
                 positions=None, extent=None) -> tuple[np.ndarray, int]:
    """The terms' colour change on the coarse grid: ``(small, f)``, float32 ``(h', w', 3)`` DN and the
    grid's factor (not yet skipped below :data:`COARSE_SKIP_DN`); ``positions`` and ``extent`` as for
    :func:`coarse_grid`."""
    g, f = coarse_grid(depth, mm_per_px, field_mm, spec.depth_term, spec.halo, spec.box, positions, extent)
    hs, ws, k = g.shape
    return (g.reshape(-1, k) @ spec.rgb).reshape(hs, ws, 3), f


def coarse_crop(depth: np.ndarray, spec: CoarseSpec, mm_per_px: float, field_mm: tuple[float, float],
                positions=None, extent=None):
    """:func:`coarse_small` over the grid's box where the change is not zero, grown by one zero grid pixel,
    so that the crop's bilinear values equal those of the whole grid: ``(roi, crop, f)``, the crop
    (float32 ``(h', w', 3)`` DN) whose upsampling by ``f`` (:func:`upsample`) gives the change over
    ``roi`` (cut to its size) of the frame; None where no pixel changes by :data:`COARSE_SKIP_DN`.
    ``positions`` and ``extent`` as for :func:`coarse_grid`."""
    small, f = coarse_small(depth, spec, mm_per_px, field_mm, positions, extent)
    hs, ws = small.shape[:2]
    # |change| with a grid row's colours side by side: numpy's max along an axis of 3 took 0.75 ms
    # here (a loop per pixel), along rows of 3 ws values and down columns 0.04 ms
    mag = np.abs(small).reshape(hs, ws * 3)
    row_max = mag.max(axis=1)
    if row_max.max() < COARSE_SKIP_DN:
        return None
    rows = np.flatnonzero(row_max > 0)
    cols = np.flatnonzero(mag.max(axis=0).reshape(ws, 3).max(axis=1) > 0)
    r0, r1 = max(0, rows[0] - 1), min(hs, rows[-1] + 2)
    c0, c1 = max(0, cols[0] - 1), min(ws, cols[-1] + 2)
    crop = np.ascontiguousarray(small[r0:r1, c0:c1])
    h, w = depth.shape
    y0, x0 = r0 * f, c0 * f
    y1, x1 = min(h, r1 * f), min(w, c1 * f)
    return (slice(y0, y1), slice(x0, x1)), crop, f


# ---------------------------------------------------------------- torch

def coarse_small_torch(d, spec: CoarseSpec, mm_per_px: float, field_mm: tuple[float, float], positions=None):
    """:func:`coarse_small` of whole frames ``(B, H, W)``: ``(B, 3, h', w')`` DN, zero in a frame where no
    pixel changes by :data:`COARSE_SKIP_DN` (as :func:`coarse_crop` skips it); ``positions``: the grid's
    ``(xn, yn)`` as tensors on ``d``'s device, if known."""
    torch = torch_module()
    f = coarse_factor(mm_per_px)
    hg = area_mean_torch(d, f)
    gmm = mm_per_px * f
    feats = []
    if spec.depth_term:
        xn, yn = positions if positions is not None else (
            torch.tensor(v, device=d.device) for v in grid_positions(tuple(d.shape[1:]), mm_per_px, field_mm, f, spec.box))
        feats += [hg, hg * xn[None, :], hg * yn[:, None]]
    if spec.halo is not None:
        halo = spec.halo
        b = smooth_torch(hg, halo["halo_sigma_mm"] / gmm, "replicate")
        b0 = smooth_torch(hg, halo["halo_base_mm"] / gmm, "replicate")
        sp = torch.clamp(b - b0, min=0.0)
        gate = torch.clamp(sp * (1.0 / halo["halo_gate_mm"]), max=1.0)
        gx, gy = slopes_torch(b, gmm)
        feats += [gx * gate, gy * gate, sp]
    small = mix_channels_torch(feats, spec.rgb.T)                     # (B, 3, hs, ws)
    seen = small.abs().amax(dim=(1, 2, 3)) >= COARSE_SKIP_DN         # per frame
    return small * seen[:, None, None, None]


class CoarseTerm:
    """The depth and halo terms as a term of the table's shading (:class:`gelsim.optics.lut.TableModel`):
    ``spec`` for a profile of ``mm_per_px``, ``field_mm`` and ``shape`` (H, W), whose grid positions are
    computed once. Added unblurred by the camera: they are smooth at its scale."""

    def __init__(self, spec: CoarseSpec, mm_per_px: float, field_mm: tuple[float, float], shape: tuple[int, int]):
        self.spec = spec
        self.mm = float(mm_per_px)
        self.field_mm = field_mm
        self.shape = tuple(shape)
        self.positions = grid_positions(self.shape, self.mm, field_mm, coarse_factor(self.mm), spec.box)
        self._on_device: dict = {}

    def _positions(self, shape, device=None):
        """The grid positions for a frame of ``shape`` (computed here unless it is the profile's), as
        tensors on ``device`` (None: arrays)."""
        if tuple(shape) != self.shape:
            return None
        if device is None:
            return self.positions
        if device not in self._on_device:
            torch = torch_module()
            self._on_device[device] = tuple(torch.tensor(v, device=device) for v in self.positions)
        return self._on_device[device]

    def part(self, depth: np.ndarray, extent, margin_px: int, blur_sigma_px: float):
        """``(box, grid, factor)`` of :func:`coarse_crop` for imprint ``depth`` (float32 ``(H, W)`` mm), or None
        (``extent``: where ``depth > 0``, :func:`~gelsim.optics.ops.box.imprint_extent`, whose blocks alone are
        averaged; ``margin_px`` and ``blur_sigma_px``: as for every term, unused here)."""
        return coarse_crop(depth, self.spec, self.mm, self.field_mm, self._positions(depth.shape), extent)

    def part_torch(self, d, blur_sigma_px: float):
        """The change over whole frames: ``(B, 3, H, W)`` DN from imprints ``(B, H, W)`` mm."""
        f = coarse_factor(self.mm)
        small = coarse_small_torch(d, self.spec, self.mm, self.field_mm, self._positions(d.shape[1:], d.device))
        return upsample_torch(small, f, tuple(d.shape[1:]))
