"""The LEDs' soft shadows of a calibrated table (:mod:`gelsim.optics.lut`, whose docstring gives the model).

Seen from the camera a press is a bump of the membrane into the gel, lit through the gel at grazing
angles, so each LED's shadow falls on the side away from it. Per LED direction ``k``: the *occlusion*
``o_k = max(0, max_{s>0}(h(p + s u_k) - h(p) - s tan(e_k)))`` (mm), its darkness ``o_k / (o_k + sat)``,
mixed to colour by the table's ``shadow_rgb``, blurred by the penumbra (and the camera), all on a grid of
``f x f``-pixel blocks, then interpolated back bilinearly: ``f`` the coarsest the penumbra allows
(:meth:`ShadowSpec.grid_factor`).

numpy kernels: one frame's box (OpenCV); torch kernels: ``(B, h, w)`` grids of whole frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ...errors import GelsimError
from . import torch_module
from .box import grow_extent
from .filters import mix_channels, mix_channels_torch, smooth, smooth_torch
from .resample import area_mean, area_mean_box, area_mean_torch, upsample, upsample_torch

# The renderer's shadow grid (ShadowSpec.grid_factor; docs/performance.md, "The shadow grid"). A shadow's
# edge is a step of darkness blurred by the penumbra (Gaussian, sigma soft_mm), so the grid must resolve
# that blur, not the image pixel; in grid pixels s = soft_mm / (mm_per_px f):
# - s >= SHADOW_GRID_MIN_SIGMA: a Gaussian passes the grid's Nyquist frequency at exp(-pi^2 s^2 / 2),
#   0.7% at s = 1, so sampling the blurred shadow on the grid aliases nothing visible;
# - bilinear interpolation back errs by at most h^2 / 8 max|f''| = A phi(1) / (8 s^2) on a step of A DN
#   (phi(1) = 0.242: the steepest curvature of a unit Gaussian edge). Measured against a full-resolution
#   grid with the R1.5 table (vitac, 320x240 to 960x720): 1.3-1.9x that bound on a steep ball, 2.0-2.9x on
#   a steep weave (the occlusion found on the block means of fine relief adds its own error), so
#   SHADOW_GRID_MODEL_MARGIN times the bound must stay within SHADOW_GRID_TOL_DN.
SHADOW_GRID_MIN_SIGMA = 1.0
SHADOW_GRID_TOL_DN = 1.0        # one 8-bit step, about the cameras' read noise (0.92 DN, R1.5)
SHADOW_GRID_MODEL_MARGIN = 3.0  # the measured error over the interpolation bound, rounded up (see above)
# The calibration fits the shadows on a half-resolution grid (its design: gelsim.calibrate, shadow_factors).
FIT_SCALE = 0.5
# Below a third of a grid pixel a blur changes nothing visible: the penumbra is then skipped.
MIN_BLUR_PX = 0.3


@dataclass(frozen=True)
class ShadowSpec:
    """A table's shadows (its file's ``shadow_*`` keys, :func:`gelsim.optics.lut.load_table`): ``dirs_deg``
    float32 ``(K,)`` in-plane directions towards the LEDs (0 = +x, 90 = +y); ``tan`` ``(K,)`` the grazing
    rays' slopes; ``mix`` float32 ``(3, K)`` DN of full darkness per colour (the table's ``shadow_rgb``
    transposed, at the profile's gain); ``sat_mm``: the occlusion at half darkness; ``soft_mm``: the
    penumbra's Gaussian sigma; ``step_dn``: the largest colour change of full darkness (DN, the table's
    ``shadow_rgb`` as fitted, so that a unit's gains never change the grid)."""
    dirs_deg: np.ndarray
    tan: np.ndarray
    mix: np.ndarray
    sat_mm: float
    soft_mm: float
    step_dn: float

    def grid_factor(self, mm_per_px: float) -> int:
        """Full-resolution pixels per grid pixel of the shadows at ``mm_per_px``: the coarsest power of two
        keeping the penumbra at least :data:`SHADOW_GRID_MIN_SIGMA` grid pixels wide and its interpolation
        error (:data:`SHADOW_GRID_MODEL_MARGIN` times ``step_dn phi(1) / (8 sigma^2)``) within
        :data:`SHADOW_GRID_TOL_DN` (see there); 1 for hard-edged shadows. On the R1.5 table: 4 at 960x720
        (sigma 1.27 grid px), 2 at 640x480, 1 at 320x240."""
        curvature = math.exp(-0.5) / math.sqrt(2.0 * math.pi)          # phi(1)
        sigma_px = self.soft_mm / mm_per_px

        def fits(f: int) -> bool:
            s = sigma_px / f
            err = SHADOW_GRID_MODEL_MARGIN * self.step_dn * curvature / (8.0 * s * s) if s > 0 else math.inf
            return s >= SHADOW_GRID_MIN_SIGMA and err <= SHADOW_GRID_TOL_DN

        f = 1
        while fits(2 * f):
            f *= 2
        return f

    def reach_px(self, depth_max_mm: float, mm_per_px: float, blur_px: float) -> int:
        """How far beyond an imprint ``depth_max_mm`` deep its shadows reach, px: ``depth / tan`` at the
        flattest ray, plus 3 sigma of their blur (penumbra and ``blur_px``)."""
        soft_px = math.hypot(self.soft_mm / mm_per_px, blur_px)
        return int(math.ceil(depth_max_mm / max(float(np.min(self.tan)), 1e-3) / mm_per_px + 3.0 * soft_px))


def scale_factor(scale: float) -> int:
    """Full-resolution pixels per grid pixel of a grid ``scale`` (1/n) times the resolution."""
    f = round(1.0 / scale)
    if f < 1 or abs(f * scale - 1.0) > 1e-6:
        raise GelsimError(f"shadow scale {scale} is not 1/n for an integer n; use 0.5 or 0.25")
    return f


def _bilinear_shift(src: np.ndarray, pad: int, shape: tuple[int, int], vx: float, vy: float,
                    minus: float) -> np.ndarray:
    """``src(p + v) - minus`` for the ``shape`` interior of ``src`` padded by ``pad`` on every side
    (bilinear; ``|v| <= pad - 1``): float32 ``shape``. Four shifted views mixed by cv2, no warp."""
    h, w = shape
    ix, iy = math.floor(vx), math.floor(vy)
    fx, fy = vx - ix, vy - iy
    y0, x0 = pad + iy, pad + ix

    def view(dy, dx):
        return src[y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w]

    a = cv2.addWeighted(view(0, 0), (1 - fx) * (1 - fy), view(0, 1), fx * (1 - fy), -minus)
    if fy > 0:
        b = cv2.addWeighted(view(1, 0), (1 - fx) * fy, view(1, 1), fx * fy, 0.0)
        cv2.add(a, b, a)
    return a


def occlusion_grid(hg: np.ndarray, dir_deg: float, rise: float, slopes: tuple[float, float] | None = None) -> np.ndarray:
    """Occlusion ``max(0, max_{s = 1, 2, ...} h(p + s u) - h(p) - s rise)`` on ``hg``'s own grid, mm.

    ``hg``: float32 ``(h, w)`` heights (mm, 0 outside); ``u``: unit vector at ``dir_deg`` (0 = +x,
    90 = +y), ``s`` in grid pixels; ``rise``: mm the grazing ray climbs per grid pixel. Only
    ``s <= L = (max h - min h) / rise`` can occlude, so the running max is taken over windows
    doubling up to ``L`` (``M_2w(p) = max(M_w(p), M_w(p + w u) - w rise)``, bilinear shifts): about
    ``log2 L + 1`` passes over the grid instead of a rotation there and back. ``slopes``: the
    largest ``|h(x + 1, y) - h(x, y)|`` and ``|h(x, y + 1) - h(x, y)|`` (mm, :func:`grid_slopes`), if
    known: the bilinear surface climbs at most ``|ux| sx + |uy| sy`` per grid pixel along ``u``."""
    h, w = hg.shape
    lo, hi, _, _ = cv2.minMaxLoc(hg)
    reach = (hi - min(lo, 0.0)) / rise if rise > 0 else math.hypot(h, w)
    reach = min(reach, math.hypot(h, w))
    ux, uy = math.cos(math.radians(dir_deg)), math.sin(math.radians(dir_deg))
    if reach < 1.0 or (slopes is not None and abs(ux) * slopes[0] + abs(uy) * slopes[1] < rise):
        # no occluder rises above a one-step ray, or the surface nowhere climbs as steeply as the
        # ray along u (so h(p + s u) - h(p) < s rise for every s): no shadow at all
        return np.zeros((h, w), np.float32)
    pad = int(math.ceil(reach)) + 2
    buf = cv2.copyMakeBorder(hg, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
    inner = buf[pad:pad + h, pad:pad + w]
    m = _bilinear_shift(buf, pad, (h, w), ux, uy, rise)      # window s = 1
    cover = 1
    while cover < reach:
        inner[...] = m                                       # the border stays 0: outside the box
        s = _bilinear_shift(buf, pad, (h, w), cover * ux, cover * uy, cover * rise)
        cv2.max(m, s, m)
        cover *= 2
    cv2.subtract(m, hg, m)
    cv2.max(m, 0.0, m)
    return m


def grid_slopes(hg: np.ndarray) -> tuple[float, float]:
    """Largest absolute height step between neighbours along x and along y inside ``hg`` (mm).

    The step down to the 0 outside the box need not count: outside is never higher than the
    (non-negative) heights inside, and a ray leaving the (convex) box never comes back."""
    out = []
    for a, b in ((hg[:, 1:], hg[:, :-1]), (hg[1:], hg[:-1])):
        out.append(float(cv2.absdiff(a, b).max()) if a.size else 0.0)
    return out[0], out[1]


def occlusion(depth: np.ndarray, mm_per_px: float, dir_deg: float, tan_e: float,
              scale: float = FIT_SCALE) -> np.ndarray:
    """Height of the surface towards the light above the grazing ray, mm: float32 like ``depth``.

    ``o(p) = max(0, max_{s > 0} h(p + s u) - h(p) - s tan_e)`` with ``u`` the unit
    in-plane vector at ``dir_deg`` (0 = +x, 90 = +y). Computed on a grid ``scale`` times the
    resolution (:func:`occlusion_grid`) and interpolated back bilinearly."""
    f = scale_factor(scale)
    occ = occlusion_grid(area_mean(depth, f), dir_deg, tan_e * mm_per_px * f)
    return upsample(occ, f, depth.shape)


def occlusion_factors(depth: np.ndarray, mm_per_px: float, dirs_deg, tans, sat_mm: float,
                      factor: int, extent=None) -> np.ndarray | None:
    """Unblurred shadow darkness ``o_k / (o_k + sat_mm)`` per direction on the grid: float32 ``(h', w', K)``;
    None when no direction casts any shadow. ``extent``: the box of ``depth`` outside which it is 0, if known
    (only its blocks are averaged: :func:`~gelsim.optics.ops.resample.area_mean_box`, the same values)."""
    hg = area_mean_box(depth, factor, extent)
    slopes = grid_slopes(hg)
    sat = float(sat_mm)
    chans, lit = [], False
    for phi, tan_e in zip(dirs_deg, tans):
        rise = float(tan_e) * mm_per_px * factor
        if abs(math.cos(math.radians(phi))) * slopes[0] + abs(math.sin(math.radians(phi))) * slopes[1] < rise:
            chans.append(None)                  # no shadow this way (see occlusion_grid)
            continue
        occ = occlusion_grid(hg, float(phi), rise, slopes)
        den = cv2.add(occ, sat)
        chans.append(cv2.divide(occ, den))
        lit = True
    if not lit:
        return None
    chans = [np.zeros(hg.shape, np.float32) if c is None else c for c in chans]
    return chans[0][..., None] if len(chans) == 1 else cv2.merge(chans)


def shadow_factors(depth: np.ndarray, mm_per_px: float, dirs_deg, tans, sat_mm: float,
                   soft_mm: float = 0.0, scale: float = FIT_SCALE) -> tuple[np.ndarray, np.ndarray]:
    """Soft shadow darkness per light direction on a ``scale`` grid (the calibration's design).

    For each direction ``k`` the hard occlusion ``o_k`` (:func:`occlusion`) becomes
    ``o_k / (o_k + sat_mm)`` (the shadow deepens with the height of the occluder above the
    grazing ray, and fades out towards its tip, where ``o_k`` falls to 0 over
    ``depth / tan_k``); then a Gaussian blur of ``soft_mm`` (sigma, mm) softens its edges:
    the LEDs are extended sources and the membrane scatters, so no real shadow edge is sharp.

    Returns ``(f, to_full)``: float32 ``(h', w', K)`` with ``h' = ceil(scale h)`` and the 2x3
    map from full-resolution pixels to that grid (for ``cv2.warpAffine(..., WARP_INVERSE_MAP)``).
    Pixel centres: full-resolution ``x`` is grid ``x' = scale (x + 1/2) - 1/2``.
    """
    factor = scale_factor(scale)
    f = occlusion_factors(depth, mm_per_px, dirs_deg, tans, sat_mm, factor)
    if f is None:
        h, w = depth.shape
        f = np.zeros((-(-h // factor), -(-w // factor), len(dirs_deg)), np.float32)
    hs, ws = f.shape[:2]
    sigma = soft_mm / mm_per_px * scale
    if sigma > MIN_BLUR_PX:
        f = smooth(f, sigma, "constant").reshape(hs, ws, -1)
    to_full = np.array([[scale, 0, 0.5 * scale - 0.5], [0, scale, 0.5 * scale - 0.5]])
    return f, to_full


def shadow_grid(d: np.ndarray, spec: ShadowSpec, mm_per_px: float, extra_blur_px: float, extent=None):
    """The shadows' colour change of imprint ``d`` (float32 mm; the box they fall in, 0 beyond it) on
    the grid, blurred by the penumbra and by ``extra_blur_px`` (sigma, full-resolution px):
    ``(small, factor)`` with float32 ``(h', w', 3)`` DN to be upsampled by ``factor`` (:func:`upsample`;
    :meth:`ShadowSpec.grid_factor`); None where no LED casts a shadow. ``extent``: as for
    :func:`occlusion_factors`."""
    factor = spec.grid_factor(mm_per_px)
    f = occlusion_factors(d, mm_per_px, spec.dirs_deg, spec.tan, spec.sat_mm, factor, extent)
    if f is None or not f.any():
        return None
    small = mix_channels(f, spec.mix).reshape(f.shape[0], f.shape[1], 3)
    sigma = math.hypot(spec.soft_mm / mm_per_px, extra_blur_px) / factor
    if sigma > MIN_BLUR_PX:
        small = smooth(small, sigma, "constant")
    return small, factor


# ---------------------------------------------------------------- torch

def occlusion_torch(hg, dir_deg: float, rise: float, span_mm: float):
    """:func:`occlusion_grid` for a batch ``(B, h, w)`` of grids. ``span_mm``: the batch's largest height
    range (max - min(min, 0)); frames of a smaller range run passes past their own reach, which cannot
    raise their result (every window they add lies below the surface it is compared with, by at least
    one ``rise``)."""
    torch = torch_module()
    b, h, w = hg.shape
    reach = min(span_mm / rise if rise > 0 else math.hypot(h, w), math.hypot(h, w))
    if reach < 1.0:
        return torch.zeros_like(hg)
    ux, uy = math.cos(math.radians(dir_deg)), math.sin(math.radians(dir_deg))
    pad = int(math.ceil(reach)) + 2
    buf = hg.new_zeros((b, h + 2 * pad, w + 2 * pad))

    def shifted(src, vx, vy, minus):
        """``src(p + v) - minus`` bilinearly (:func:`_bilinear_shift`)."""
        ix, iy = math.floor(vx), math.floor(vy)
        fx, fy = vx - ix, vy - iy
        y0, x0 = pad + iy, pad + ix

        def view(dy, dx):
            return src[:, y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w]

        a = view(0, 0) * ((1 - fx) * (1 - fy)) + view(0, 1) * (fx * (1 - fy)) - minus
        if fy > 0:
            a = a + (view(1, 0) * ((1 - fx) * fy) + view(1, 1) * (fx * fy))
        return a

    buf[:, pad:pad + h, pad:pad + w] = hg
    m = shifted(buf, ux, uy, rise)                                   # window s = 1
    cover = 1
    while cover < reach:
        buf[:, pad:pad + h, pad:pad + w] = m                         # the border stays 0
        m = torch.maximum(m, shifted(buf, cover * ux, cover * uy, cover * rise))
        cover *= 2
    return torch.clamp(m - hg, min=0.0)


def shadow_grid_torch(d, spec: ShadowSpec, mm_per_px: float, extra_blur_px: float):
    """:func:`shadow_grid` of whole frames ``(B, H, W)``: ``(B, 3, h', w')`` DN (zero where no shadow falls),
    to be upsampled by ``spec.grid_factor(mm_per_px)``. A direction casts per frame as the numpy kernel
    decides (the largest neighbour step along it at least the ray's rise)."""
    torch = torch_module()
    factor = spec.grid_factor(mm_per_px)
    hg = area_mean_torch(d, factor)                                   # (B, hs, ws)
    span = float(hg.amax()) - min(float(hg.amin()), 0.0)
    sx = (hg[:, :, 1:] - hg[:, :, :-1]).abs().amax(dim=(1, 2))        # per frame (grid_slopes)
    sy = (hg[:, 1:] - hg[:, :-1]).abs().amax(dim=(1, 2))
    chans = []
    for phi, tan_e in zip(spec.dirs_deg, spec.tan):
        rise = float(tan_e) * mm_per_px * factor
        ux, uy = abs(math.cos(math.radians(phi))), abs(math.sin(math.radians(phi)))
        casts = (sx * ux + sy * uy) >= rise
        if not bool(casts.any()):
            chans.append(torch.zeros_like(hg))
            continue
        occ = occlusion_torch(hg, float(phi), rise, span)
        chans.append(torch.where(casts[:, None, None], occ / (occ + float(spec.sat_mm)), 0.0))
    small = mix_channels_torch(chans, spec.mix)                       # (B, 3, hs, ws)
    sigma = math.hypot(spec.soft_mm / mm_per_px, extra_blur_px) / factor
    return smooth_torch(small, sigma, "constant") if sigma > MIN_BLUR_PX else small


class ShadowTerm:
    """The shadows as a term of the table's shading (:class:`gelsim.optics.lut.TableModel`): ``spec`` at a
    resolution of ``mm_per_px``. :meth:`part` (numpy) and :meth:`part_torch` (torch) give its change."""

    def __init__(self, spec: ShadowSpec, mm_per_px: float):
        self.spec = spec
        self.mm = float(mm_per_px)
        self.factor = spec.grid_factor(self.mm)

    def part(self, depth: np.ndarray, extent, margin_px: int, blur_sigma_px: float):
        """``(box, grid, factor)``: the box the shadows of imprint ``depth`` (float32 ``(H, W)`` mm) may fall in
        (its ``extent``, :func:`~gelsim.optics.ops.box.imprint_extent`, grown by ``margin_px`` and by their
        reach) and their change there on the grid (:func:`shadow_grid`, blurred by the camera's
        ``blur_sigma_px`` too; None where no LED casts one), to be upsampled by ``factor``."""
        roi = grow_extent(extent, margin_px, depth.shape)
        _, dmax, _, _ = cv2.minMaxLoc(depth[roi])
        big = grow_extent(extent, margin_px + self.spec.reach_px(dmax, self.mm, blur_sigma_px), depth.shape)
        r0, c0 = big[0].start, big[1].start   # where depth > 0, in the box's own coordinates
        g = shadow_grid(depth[big], self.spec, self.mm, blur_sigma_px,
                        (extent[0] - r0, extent[1] - r0, extent[2] - c0, extent[3] - c0))
        return big, None if g is None else g[0], self.factor

    def part_torch(self, d, blur_sigma_px: float):
        """The change over whole frames: ``(B, 3, H, W)`` DN from imprints ``(B, H, W)`` mm (the grid aligned
        with the frame, where :meth:`part`'s is aligned with the box)."""
        return upsample_torch(shadow_grid_torch(d, self.spec, self.mm, blur_sigma_px), self.factor,
                              tuple(d.shape[1:]))
