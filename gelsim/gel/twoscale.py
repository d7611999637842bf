"""The two-scale imprint: exact elasticity at the contact's scale, Johnson's contact at the texture's.

A pressed cloth has two length scales: the contact patch (millimetres, where the gel's finite
thickness and the cloth's compression matter) and the texture (yarns, loops, 0.1-2 mm, where the
gel behaves as a half-space). This model treats each with the physics of its scale:

1. **Envelope.** The object's *crown envelope* ``E`` is its grey-scale closing over the texture's
   scale (``texture_mm``, e.g. a weave's largest pitch): the surface through the crowns, with the
   valleys filled. Objects without texture (``texture_mm`` None: a sphere, a mesh) are their own
   envelope. ``t = P - E <= 0`` is the texture: depth below the crowns.
2. **Macro contact.** The envelope is pressed on the gel layer (bonded base, finite thickness,
   :mod:`gelsim.gel.layer`) with the cloth's compression in series, solved exactly (Polonsky-Keer)
   on a coarse grid of at most ``macro_cells`` cells across the touched region. This gives the
   approach for a force (or the force for an approach), the contact patch, the gel's smooth
   displacement around it and the local mean pressure ``p(x)``. A sequence warm-starts each frame
   from the previous one's pressure, so a solve takes a few iterations.
3. **Texture.** Inside the patch, the texture is pressed at the local mean pressure as Johnson's
   sinusoidal contact prescribes (:mod:`gelsim.gel.johnson`): from local statistics of ``t``
   (crown-to-valley depth D, wavenumber q = RMS slope / RMS height, anisotropy of the slopes) comes
   ``p* = E* q D / 4`` and ``s = p / p*``; the gel follows the texture where it is within
   ``zeta(s) D`` of the crowns and spans the deeper valleys with slope ``lam(s)``. Exact, on a
   regular wave, for the contact fraction and the kept fundamental of 1-D and 2-D waves; yarn
   flattening (:mod:`gelsim.gel.support`) takes its share of the relief first.

The gel's depth map is the macro displacement plus the texture's, then the membrane's blur.
Cost at 960x720 over a whole-pad fabric press: see docs/imprint.md.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
from numba import njit

from . import texture_kernels as kernels
from .johnson import segment_arrays
from .layer import Operator, effective_modulus_mpa, pk_solve
from .support import FabricSupport
from .util import bbox

# Macro solve's stopping rule (relative L1 change of the pressure per iteration): the macro
# pressure feeds s = p / p*, which needs it to about 1% (the texture statistics' own spread is
# several %); 1e-3 per iteration keeps the force-approach relation within 0.5% of a 1e-6 solve
# (tests/gelsim/test_gel.py), in single precision.
MACRO_TOL = 1e-3
MACRO_MAXIT = 500
# The layer's displacement falls below 2% of its peak within 3 thicknesses of the contact
# (bonded base): the output window reaches that far beyond the patch.
OUT_MARGIN_THICKNESS = 3.0
# The envelope's closing spans this many times the texture's scale: a jittered weave's
# crowns stand up to ~20% of a pitch off their nominal place.
ENVELOPE_SPAN = 1.2
# A patch narrower than this many coarse cells is solved again on a grid fitted to it (a Hertz
# contact's radius to about 3% from 24 cells across).
MIN_CONTACT_CELLS = 24
# That grid spans the region the object reaches within this many approaches of its top: a sphere's
# contact radius is where it reaches one approach deep, so the grid spans twice the radius.
REFINE_REACH = 4.0
# Samples of a window's bearing curve (the depth at a given contact fraction to about 1%).
BEARING_SAMPLES = 10000
# The texture statistics see features down to 1/16 of the texture's scale (see texture_depth).
STATS_BLUR_PER_TEXTURE = 16.0
# A texture needs this many pixels per period for its slopes to be read (central differences
# alias beyond q dx = pi / 2).
MIN_TEXTURE_PX = 4.0
# Fewest pixels across the contact window (see widen_window).
MIN_WINDOW_PX = 8
# p / p* beyond complete contact changes nothing (the tables end at 1); a cap keeps it finite.
S_MAX = 1e3
# Relief coarser than this many gel thicknesses is the macro solve's, not the texture's.
TEXTURE_CAP_THICKNESS = 1.0
# Outer passes for the cloth's secant stiffness at the contact's mean pressure: a pass is repeated
# while the stiffness it used is off by more than SUPPORT_TOL (relative) from the one its pressure
# implies, at most SUPPORT_PASSES times. Measured on 6 slip and twist sequences (142 contact frames)
# against the converged fixed point (10 passes, 5e-4): indentation and contact area within 2.1%
# (mean 0.25%); one pass per warm-started frame, as before, was off by up to 42% (mean 1.6%) on
# frames whose contact grows or shrinks, and always one pass by up to 73%.
SUPPORT_PASSES = 4
SUPPORT_TOL = 0.02
# The contact's growth with the force (see solve_macro) is measured between frames whose forces differ
# by at least this (log ratio, ~10%): over smaller steps the motion changes the contact more.
EXPONENT_MIN_STEP = 0.1
# The exponent taken before one is measured (a sequence's second frame): the captured sequences' second
# frames measured 0.23-0.51 (a Hertz contact on a half-space: 2/3; the cloth and the pad's edge flatten it).
CONTACT_EXPONENT = 0.3
# The crown envelope's closing (a weave's largest pitch, up to 61 px at 960x720) switches from OpenCV's
# morphology to window doubling (see _running_extreme) at this kernel size: on a 960x720 window they
# cost the same near k = 40; at k = 61, 3.2 ms against 4.8-5.8 ms (measured on the loaded 2-core machine).
CLOSING_DOUBLING_MIN = 41


@dataclass(frozen=True)
class MacroState:
    """A frame's macro solution: warm-starts the next frame's, and gives the mean pressure field.

    pressure_mpa: the coarse grid's pressure, MPa; its block (i, j) covers work pixels
    ``origin + (i, j) * block`` to ``+ block``; ``work_shape`` the work grid's (ny, nx);
    ``bottomed``: the pad was at its travel (the next frame tries that first); ``force_n`` the force it
    carried, N, and ``contact_exponent`` d ln(contact cells) / d ln(force) measured from its own warm
    start (None: not known), which predict the next frame's contact (see solve_macro)."""
    key: tuple
    pressure_mpa: np.ndarray
    origin: tuple[int, int] = (0, 0)
    block: int = 1
    work_shape: tuple[int, int] = (0, 0)
    bottomed: bool = False
    force_n: float = 0.0
    contact_exponent: float | None = None

    def pressure_field(self) -> np.ndarray:
        """The local mean pressure on the work grid (MPa, float32; bilinear between block centres)."""
        ny, nx = self.work_shape
        return cv2.max(_window_pressure(self.pressure_mpa.astype(np.float32), self.block, self.origin,
                                        (0, ny, 0, nx), self.work_shape), 0.0)


def _closing(img: np.ndarray, k: int) -> np.ndarray:
    """Grey closing with a k x k square, replicated borders. (OpenCV splits a square kernel into
    row and column passes itself: one call is 25-45% faster than four 1-D passes, same result.)
    From CLOSING_DOUBLING_MIN on, the passes double their window instead (same result)."""
    if k < 2:
        return img
    if k >= CLOSING_DOUBLING_MIN:
        d = _running_extreme(img, k, cv2.max, 0)
        d = _running_extreme(d, k, cv2.max, 1)
        d = _running_extreme(d, k, cv2.min, 0)
        return _running_extreme(d, k, cv2.min, 1)
    return cv2.morphologyEx(img, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)


def texture_scale_mm(texture_mm: float | None, gel) -> float | None:
    """The texture's scale the model works with, mm: ``texture_mm`` capped below the gel's thickness
    (coarser relief is the macro solve's: the layer's finite thickness matters there, and the coarse
    grid resolves it); None for an object without texture."""
    return None if texture_mm is None else min(float(texture_mm), TEXTURE_CAP_THICKNESS * gel.thickness_mm)


def envelope_kernel_px(tex_mm: float, dx: float) -> int:
    """Side of the closing's square (odd, px at ``dx`` mm per pixel) that spans ENVELOPE_SPAN times the
    texture's scale ``tex_mm`` (:func:`texture_scale_mm`)."""
    return int(math.ceil(ENVELOPE_SPAN * tex_mm / dx)) | 1


def coarse_envelope_kernel_cells(tex_mm: float, dx: float, f: int) -> int:
    """Side of the closing's square (odd, in cells of ``f`` pixels of ``dx`` mm) that completes the crown
    envelope on the macro grid after :func:`_crown_pool`. The fine grid's envelope fills valleys narrower
    than its closing, :func:`envelope_kernel_px` pixels; each coarse cell already holds the highest
    point within about a cell, so pooling and a closing of k cells fill those narrower than about k + 1
    cells. k is the smallest odd count whose k + 1 cells span the fine closing (at least 1: no
    closing), so that the macro solve neither sees valleys the fine envelope fills nor fills wider ones.
    At ``f`` = 1 (no pooling) it is the fine grid's own closing.

    (The fine grid's rule applied to the cells, with no allowance for the pooling, closed up to 2.5x
    the span: 3 cells on the 0.3 mm cells of a whole-pad press at 64 cells, for a 0.36 mm span. The
    pinwale corduroy's 0.3 mm gaps between wales were filled, its pressure spread over them, and it
    kept 0.067 of its tufts' relief at 1 N where a 192-cell grid keeps 0.142. Matching the nominal
    span instead of the fine closing left the fast level's grid, whose fine closing rounds up further,
    seeing felt valleys its fine envelope fills: its agreement with the reference on felt fell from
    0.948 to 0.850.)"""
    return max(1, math.ceil(envelope_kernel_px(tex_mm, dx) / f - 1.0)) | 1


def crown_envelope(surface_mm: np.ndarray, tex_mm: float, dx: float) -> np.ndarray:
    """The crown envelope of an object's own surface (mm, float32 (ny, nx) at ``dx`` mm per pixel): its
    grey closing over ENVELOPE_SPAN times the texture's scale ``tex_mm``. Taken on the object's heights,
    not on what the gel sees of them through its dome or a tilt: on a slope a flat closing follows the
    surface into its valleys (on a monotone profile it changes nothing), and the vitac gel's dome
    (slopes up to 0.12 at the pad's rim) hid up to half of a fine weave's depth below its crowns there."""
    return _closing(surface_mm, envelope_kernel_px(tex_mm, dx))


def _running_extreme(img: np.ndarray, k: int, op, axis: int) -> np.ndarray:
    """``op`` (cv2.max or cv2.min) over k pixels along ``axis`` of 2-D ``img``, as OpenCV's dilation or
    erosion by a 1 x k line does it (anchor at k // 2, replicated borders): the window is grown by
    doubling, max(m[i], m[i + w]) of the width-w one, then two overlapping windows make k: log2(k) + 1
    passes, whatever k (OpenCV's morphology takes about k / 8 SIMD operations per pixel)."""
    a = k // 2
    n = img.shape[axis]
    pad = (a, k - 1 - a, 0, 0) if axis == 0 else (0, 0, a, k - 1 - a)
    m = cv2.copyMakeBorder(img, *pad, cv2.BORDER_REPLICATE)

    def part(arr, start, length):
        return arr[start:start + length] if axis == 0 else arr[:, start:start + length]

    w, size = 1, n + k - 1  # m[i] holds the extreme over padded pixels [i, i + w)
    while 2 * w <= k:
        size -= w
        m = op(part(m, 0, size), part(m, w, size))
        w *= 2
    return op(part(m, 0, n), part(m, k - w, n))


def _pool(img: np.ndarray, f: int) -> np.ndarray:
    """Area average over f x f blocks (edge blocks padded by replication)."""
    if f == 1:
        return img
    ny, nx = img.shape
    py, px = -ny % f, -nx % f
    if py or px:
        img = np.pad(img, ((0, py), (0, px)), mode="edge")
    return img.reshape(img.shape[0] // f, f, img.shape[1] // f, f).mean(axis=(1, 3), dtype=np.float64)


def _upsample(coarse: np.ndarray, f: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear from block centres back to the fine grid (``shape``), float32. OpenCV's resize
    maps fine pixel x to coarse (x + 0.5) / f - 0.5, so block i's centre, fine pixel
    f i + (f - 1) / 2, lands on coarse cell i: no shift is needed."""
    if f == 1:
        return coarse[: shape[0], : shape[1]].astype(np.float32)
    cy, cx = coarse.shape
    up = cv2.resize(coarse.astype(np.float32), (cx * f, cy * f), interpolation=cv2.INTER_LINEAR)
    return up[: shape[0], : shape[1]]


@dataclass(frozen=True)
class TextureDepth:
    """The texture's part of the gel surface over a window of (ny, nx) pixels, padded to whole
    statistics cells (the arrays may be larger than the window; read their first ny rows and nx
    columns). ``g``: the gel surface's texture, mm, float32, <= 0 below the crowns; ``mean``: its
    local mean on the statistics grid of ``fs``-pixel cells (mm, float32 (rows, cols); read at a
    pixel as :mod:`gelsim.gel.texture_kernels` reads coarse fields); ``touch``: the texture-scale
    contact, bool."""
    g: np.ndarray
    mean: np.ndarray
    fs: int
    touch: np.ndarray

    def mean_at(self, y: int, x: int) -> float:
        """mean g at pixel (y, x), mm (<= 0: minus how far the crowns stand below the mean)."""
        return kernels.field_at(self.mean, self.fs, y, x)

    def add_to(self, depth: np.ndarray, in_macro: np.ndarray, mask: np.ndarray) -> None:
        """``depth`` (mm, float32 (ny, nx)) += g - mean g where ``in_macro``, floored at 0; ``mask``
        (bool (ny, nx)) = in_macro and the texture's contact. In place."""
        kernels.add_texture(depth, self.g, kernels.widen(self.mean, self.g.shape[1]), self.fs, in_macro,
                            self.touch, mask)


def texture_depth(surface: np.ndarray, env: np.ndarray, pressure_at, dx: float, gel,
                   support: FabricSupport | None, texture_mm: float, cloth_mpa_per_mm: float):
    """The texture's part of the gel surface for the texture ``t = surface - env`` (the object's
    surface less its crown envelope, mm, float32 (ny, nx); t <= 0 is the depth below the crowns)
    under the local mean pressure: ``pressure_at((cols, rows), (NY, NX))`` gives it (MPa, float32
    (rows, cols)) averaged over cells of ``NY / rows`` x ``NX / cols`` pixels tiling the first NY
    rows and NX columns from the window's corner (NY >= ny, NX >= nx: the cells may overhang it).
    ``cloth_mpa_per_mm``: the cloth's secant stiffness at the patch's mean pressure (inf: rigid).

    Returns a :class:`TextureDepth`. The macro solve gives the gel's local *mean* displacement (its
    q = 0 part carries the load), so the texture enters as a zero-mean oscillation about it
    (g - mean g); the crowns are pushed in -mean g further.

    Two bands. The texture's own (``t`` blurred over texture / 16) sets p*, the contact and the
    spans through Johnson's map. Finer relief (pores, fibre fuzz, sharp yarn edges) sits on the
    crowns in contact, which carry p / (contact fraction): it prints by Johnson's kept fundamental
    at its own p*, and not at all where the gel spans a valley. Statistics are taken on a grid of
    about texture / 4 cells (the fields they feed vary over a texture period); the map itself runs
    at full resolution, in the fused passes of :mod:`gelsim.gel.texture_kernels`.
    """
    e_star = effective_modulus_mpa(gel)
    ny, nx = surface.shape
    fs = max(1, int(texture_mm / (4.0 * dx)))
    # The texture's band varies over at least 8 pixels per period when fs >= 2: its statistics come
    # from a copy at half the resolution (a quarter of the work; the band is smooth at that scale).
    half = fs >= 2 and min(ny, nx) >= 8
    if half:
        fs -= fs % 2
    # Cells of exactly fs pixels (2 fs at half resolution; fs even), so that every average over a
    # cell is over whole pixels (OpenCV's area resize takes its fast path only for whole-number
    # factors, 0.2 against 1.2 ms at 960x720, and the kernels sum whole cells). So t is padded, its
    # edge replicated, to whole cells, and the outputs are cropped back: the overhanging cells'
    # statistics see the edge continued, as the blur does.
    unit = 2 * fs if half else fs
    NY, NX = ny + -ny % unit, nx + -nx % unit
    t = np.empty((NY, NX), np.float32)
    cv2.subtract(surface, env, t[:ny, :nx])
    t[:ny, nx:] = t[:ny, nx - 1:nx]
    t[ny:] = t[ny - 1]
    cs = (NX // fs, NY // fs)
    # The texture's band: a blur of texture / 16 removes the finer relief and leaves q of a wave at
    # the texture's scale as it was (slope and height scale alike; the height is restored below).
    sigma = texture_mm / (STATS_BLUR_PER_TEXTURE * dx)
    blurred = sigma >= 0.5
    tq = cv2.GaussianBlur(t, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE) if blurred else t
    k = max(1, int(round(texture_mm / (dx * fs))))

    def smooth(small):
        # Two boxes one texture period wide (a triangle): the first zeroes the texture's
        # fundamental, the pair keeps the rest of it below 5% (sinc^2).
        return cv2.blur(cv2.blur(small, (k, k), borderType=cv2.BORDER_REPLICATE), (k, k),
                        borderType=cv2.BORDER_REPLICATE)

    q_lo = np.float32(2.0 * math.pi / (k * fs * dx))   # one period of the smoothing window
    tables = segment_arrays()
    # The support's compliance per unit pressure (kernels._share): none, the yarns', and the cloth's.
    yarn_comp, has_cloth, cloth_k, ell = 0.0, False, 1.0, 0.0
    if support is not None:
        yarn_comp = 1.0 / support.yarn_stiffness_mpa_per_mm
        if math.isfinite(cloth_mpa_per_mm):
            has_cloth, cloth_k, ell = True, cloth_mpa_per_mm, support.shear_length_mm
    share_args = (np.float32(e_star), np.float32(yarn_comp), has_cloth, np.float32(cloth_k), np.float32(ell))

    # The band's statistics (kernels.band_cells), from the cells' moments smoothed over a period.
    d_band = 2.0 * dx if half else dx
    tq_s = cv2.resize(tq, (NX // 2, NY // 2), interpolation=cv2.INTER_AREA) if half else tq
    f = tq_s.shape[1] // cs[0]
    mom = kernels.moment_sums(tq_s, d_band, f, cs[1], cs[0])
    mom = smooth(mom if f == 1 else mom / np.float32(f * f))   # (a pixel's cell: its sums are its means)
    # Between one period of the window and the grid's Nyquist wavenumber.
    var, q, aniso, m_tq = kernels.band_cells(mom, np.float32(d_band), q_lo, np.float32(math.pi / d_band))
    # The blur lowered the texture's own band by gain = exp(-(q s)^2 / 2) (s its width, mm): its
    # height is restored, and what the restored band leaves of t is the finer relief. (Only the
    # oscillation about the local mean is scaled back: the mean is not blurred.) Johnson's map
    # per cell: kernels.map_cells.
    p_small = pressure_at(cs, (NY, NX))
    gain = np.exp(np.float32(-0.5) * np.square(q * np.float32(sigma * dx if blurred else 0.0)))
    inv_gain, share, d_eff, span, phi = kernels.map_cells(var, q, aniso, p_small, gain, *share_args,
                                                          np.float32(S_MAX), *tables)
    cell_px = np.float32(fs * fs)
    if blurred:
        te, tf, tf2_sum, tg2_sum = kernels.restore_band(t, tq, kernels.widen(m_tq, NX), kernels.widen(inv_gain, NX),
                                                        kernels.widen(share, NX), fs, dx)
    else:
        te, tf = kernels.band_share(t, kernels.widen(share, NX), fs), None
    # The cut: the depth whose bearing area is the theory's contact fraction. The contact area
    # depends on p / (E* RMS slope), not on the heights' distribution (Johnson; Persson for random
    # surfaces), while the depth at which a given area is reached does: a peaked knit loop has
    # little area near its top, a flat-topped float much. The texture is stationary over a patch,
    # so one bearing curve of depth over the local crown-to-valley depth serves every cell (on a
    # wave it is exactly the tables' zeta). te = share * (the texture's band).
    cut = _bearing_cut(te, ny, nx, d_eff, fs, phi)
    kept_f = cut   # (not read without a finer band)
    if tf is not None:
        # The finer relief on the crowns in contact, at the crowns' pressure p / (contact fraction):
        # its height and mean slope are enough (its p* is taken as the 2-D wave's; tf has no mean).
        var_f = smooth((tf2_sum / cell_px).astype(np.float32))
        g2 = smooth((tg2_sum / cell_px).astype(np.float32))
        kept_f = kernels.fine_cells(var_f, g2, np.float32(dx), q_lo, np.float32(math.pi / dx), p_small, phi,
                                    *share_args, np.float32(S_MAX), *tables)
    # g = te where te >= -cut (in contact: plus the finer relief it prints), else
    # -cut + lam (te + cut) = te - (1 - lam) min(te + cut, 0).
    g, touch, g_sum = kernels.press_texture(te, te if tf is None else tf, kernels.widen(cut, NX),
                                            kernels.widen(span, NX),
                                            kernels.widen(kept_f, NX), fs, tf is not None)
    return TextureDepth(g, smooth((g_sum / cell_px).astype(np.float32)), fs, touch)


def _bearing_cut(te: np.ndarray, ny: int, nx: int, d_eff: np.ndarray, fs: int, phi: np.ndarray) -> np.ndarray:
    """The cut, mm (float32, the shape of ``phi``): ``d_eff`` times the depth (over the crown-to-valley
    depth) above which ``phi`` of the area lies, read from the window's bearing curve of -te / d_eff
    (about ``BEARING_SAMPLES`` samples of the first ``ny`` rows and ``nx`` columns of ``te``; ``d_eff``
    on the stats grid of ``fs``-pixel cells, read at each sample's cell). The gather and the reading
    are compiled loops (numpy's strided gathers and a dozen passes over the cells took 0.3 ms per
    frame); the sort is numpy's (its SIMD sort is 3x numba's)."""
    stride = max(1, int(math.sqrt(ny * nx / BEARING_SAMPLES)))
    z = kernels.bearing_samples(te, ny, nx, d_eff, fs, stride)
    z.sort()
    return kernels.bearing_read(z, np.asarray(phi, np.float32), d_eff)


def press_twoscale(work: np.ndarray, dx: float, gel, *, force_n: float | None, depth_mm: float | None,
                   support: FabricSupport | None, texture_mm: float | None, window: str, macro_cells: int,
                   warm: MacroState | None = None, sag: np.ndarray | None = None,
                   envelope: Callable[[tuple[int, int, int, int]], np.ndarray] | None = None,
                   own: np.ndarray | None = None, valley_mm: float | None = None, cells_per_valley: float = 0.0):
    """Press ``work`` (protrusion, mm, (ny, nx) at ``dx`` mm/px) into ``gel``.

    ``macro_cells``, ``valley_mm``, ``cells_per_valley``: the macro grid's size (:func:`macro_cell_px`).

    ``sag``: the gel's dome, mm >= 0 (ny, nx), already subtracted from ``work`` (None: a flat gel);
    the crown envelope is taken on the object's own heights, ``work + sag`` (see
    :func:`crown_envelope`). ``envelope``: that envelope when already known for this frame, as a function
    of a box (r0, r1, c0, c1) of the grid giving its rows r0:r1 and columns c0:c1 (mm, on the object's
    own heights like ``work + sag``: a sequence takes it once on the object and sees it through each
    frame's pose; only the touched window is read), or None to take it here over that window.
    ``own``: the object's own heights ``work + sag`` when the caller has them (``work`` before the
    sag was subtracted), so that they need not be rebuilt; None: rebuilt where needed.

    Returns (depth mm (ny, nx) float32 before the membrane's blur, contact mask, approach mm,
    force N, bottomed, MacroState).
    """
    ny, nx = work.shape
    pmax = float(work.max())
    vmax = gel.max_indentation_mm
    full = window == "full"
    tex = texture_scale_mm(texture_mm, gel)
    # Below MIN_TEXTURE_PX pixels per period the texture is not resolved on this grid (its slopes
    # cannot be read): the macro solve takes the area-averaged surface and there is no texture stage.
    has_texture = tex is not None and tex >= MIN_TEXTURE_PX * dx
    # 1-2. Macro contact on a coarse grid over the region the gel can reach, warm-started from the
    # previous frame when its grid matches; again over a region fitted to the contact when the
    # first grid resolves the patch with fewer than MIN_CONTACT_CELLS cells across.
    # (``window="full"`` solves on the same grid and only widens the output to the whole frame.)
    reach = vmax
    sol = None
    for _ in range(2):
        box = bbox(work > np.float32(pmax - reach))
        f = macro_cell_px(box, macro_cells, dx, valley_mm, cells_per_valley)
        sol = solve_macro(work, box, dx, gel, tex if has_texture else None, support, force_n, depth_mm,
                           f, warm, sag, own)
        cb = bbox(sol.p > 0)
        if cb is None or max(cb[1] - cb[0], cb[3] - cb[2]) >= MIN_CONTACT_CELLS or sol.f == 1:
            break
        # The object reaches at most REFINE_REACH approaches deep inside the new region's edge.
        new_reach = min(vmax, REFINE_REACH * max(sol.delta, 1e-6))
        if new_reach >= 0.99 * reach:
            break
        reach = new_reach
    r0, c0, f, cm, env_c, emax, p, delta, bottomed, key, cshape, area = (
        sol.r0, sol.c0, sol.f, sol.cm, sol.env_c, sol.emax, sol.p, sol.delta, sol.bottomed, sol.key, sol.cshape,
        sol.area)
    r1, c1 = sol.r1, sol.c1
    force = float(p.sum() * area)
    state = MacroState(key, p, (r0, c0), f, (ny, nx), bottomed, force, sol.contact_exponent)
    mask = np.zeros((ny, nx), bool)
    # (cb: the loop's last box, that of this p > 0)
    if cb is None:
        return np.zeros((ny, nx), np.float32), mask, delta, force, bottomed, state
    # 3. The gel's displacement around the patch: one more convolution over a padded window.
    # (Clipped to the frame: the gel beyond it is not imaged.)
    mc = max(ny, nx) if full else int(math.ceil(OUT_MARGIN_THICKNESS * gel.thickness_mm / cm))
    q0, q1, s0, s1 = cb
    lo_q, hi_q = max(q0 - mc, -(r0 // f)), min(q1 + mc, -(-(ny - r0) // f))
    lo_s, hi_s = max(s0 - mc, -(c0 // f)), min(s1 + mc, -(-(nx - c0) // f))
    big = np.zeros((hi_q - lo_q, hi_s - lo_s))
    big[q0 - lo_q:q1 - lo_q, s0 - lo_s:s1 - lo_s] = p[q0:q1, s0:s1]
    u_f = _upsample(np.maximum(Operator(big.shape, cm, gel).gel(big), 0.0), f, (big.shape[0] * f, big.shape[1] * f))
    fr0, fc0 = r0 + lo_q * f, c0 + lo_s * f
    if (fr0, fc0) == (0, 0) and u_f.shape == (ny, nx):
        depth = u_f  # the window is the frame (a whole-pad cloth): no copy
    else:
        depth = np.zeros((ny, nx), np.float32)
        a0, a1 = max(0, fr0), min(ny, fr0 + u_f.shape[0])
        b0, b1 = max(0, fc0), min(nx, fc0 + u_f.shape[1])
        depth[a0:a1, b0:b1] = u_f[a0 - fr0:a1 - fr0, b0 - fc0:b1 - fc0]
    # 4. The contact window (coarse contact, one block of margin), at full resolution.
    w0, w1 = r0 + max(0, cb[0] - 1) * f, min(r1, r0 + (cb[1] + 1) * f)
    v0, v1 = c0 + max(0, cb[2] - 1) * f, min(c1, c0 + (cb[3] + 1) * f)
    # A patch touching the frame's edge on a fine grid can leave a window one pixel wide; OpenCV
    # reads an array of up to 4 elements in one column as a scalar, so widen it (pressure beyond
    # the macro grid reads zero inside the frame, see _window_pressure).
    w0, w1 = widen_window(w0, w1, ny)
    v0, v1 = widen_window(v0, v1, nx)
    if has_texture and envelope is not None:
        env = envelope((w0, w1, v0, v1))
        env = env if sag is None else cv2.subtract(env, sag[w0:w1, v0:v1])
    elif has_texture:
        # (The interpolated coarse envelope would save this closing's 2-4 ms at 960x720, but loses
        # the holes and pores finer than a coarse cell: mesh contact 0.51 -> 0.38 of the reference's.)
        ke = envelope_kernel_px(tex, dx)
        W0, W1, V0, V1 = max(0, w0 - ke), min(ny, w1 + ke), max(0, v0 - ke), min(nx, v1 + ke)
        if sag is None:
            env = crown_envelope(work[W0:W1, V0:V1], tex, dx)[w0 - W0:w1 - W0, v0 - V0:v1 - V0]
        else:
            heights = own[W0:W1, V0:V1] if own is not None else cv2.add(work[W0:W1, V0:V1], sag[W0:W1, V0:V1])
            env = crown_envelope(heights, tex, dx)
            env = cv2.subtract(env[w0 - W0:w1 - W0, v0 - V0:v1 - V0], sag[w0:w1, v0:v1])
    else:
        env = work[w0:w1, v0:v1]
    dwin = depth[w0:w1, v0:v1]
    # In contact the gel rests on the envelope: the depth is the penetration (the fine detail the
    # coarse grid averaged away). The patch's edge lies between the last coarse cell in contact and
    # the first out of it: the contact indicator, interpolated and cut at one half, puts it at the
    # midpoint, unbiased (the interpolated pressure's footprint overstates it by half a cell, the
    # interpolated gap understates it by as much).
    win = (w0, w1, v0, v1)
    if support is not None:
        # On a compliant cloth the gel takes the penetration less the cloth's own compression
        # (the macro solve's closure minus the gel's displacement, in its contact cells).
        op = cloth_operator(cshape, cm, gel, None)
        comp = np.maximum(np.where(p > 0, (hc_of(sol) + delta) - op.gel(p), 0.0), 0.0).astype(np.float32)
        # Carried one cell past the contact cells: the fine patch reaches half a cell beyond them.
        comp = cv2.dilate(comp, np.ones((3, 3), np.uint8))
    else:
        comp = np.zeros(p.shape, np.float32)
    comp_sub, oy, ox = _window_grid(comp, f, (r0, c0), win, (ny, nx))
    in_sub, _, _ = _window_grid((p > 0).astype(np.float32), f, (r0, c0), win, (ny, nx))
    nx_up = comp_sub.shape[1] * f
    # The gel cannot pass through the object: inside the patch it lies at least as deep as the
    # penetration the gel takes, env - (emax - delta) - comp (outside, the elastic displacement
    # alone). One pass over the window (OpenCV took six: two upsamplings, the sum, the cut, the
    # product and the maximum).
    in_macro = kernels.macro_floor(dwin, env, kernels.widen(comp_sub, nx_up)[:, ox:ox + dwin.shape[1]],
                                   kernels.widen(in_sub, nx_up)[:, ox:ox + dwin.shape[1]], f, oy,
                                   np.float32(-(emax - delta)))
    if has_texture:
        # The cloth's secant stiffness at the patch's mean pressure, MPa/mm (inf: rigid).
        cloth = 1e-3 * cloth_stiffness(support, p, force, area)

        def pressure_at(cs, shape):
            return _cell_pressure(p, f, (r0, c0), (w0, w0 + shape[0], v0, v0 + shape[1]), cs, (ny, nx))

        texture = texture_depth(work[w0:w1, v0:v1], env, pressure_at, dx, gel, support, tex, cloth)
        texture.add_to(dwin, in_macro, mask[w0:w1, v0:v1])
        # The approach is the crowns': the macro one plus their sink below the mean surface there.
        if in_macro.any():
            _, _, _, (tx, ty) = cv2.minMaxLoc(env, mask=in_macro.view(np.uint8))
            delta = float(delta) - texture.mean_at(ty, tx)
    else:
        mask[w0:w1, v0:v1] = in_macro
    # The pad's travel bounds the depth (the macro solve's 1e-3 tolerance may overshoot it by a hair).
    cv2.min(depth, float(vmax), dst=depth)  # (OpenCV's: a third of numpy's time here)
    return depth, mask, float(delta), force, bottomed, state


@dataclass(frozen=True)
class MacroSolution:
    r0: int
    r1: int
    c0: int
    c1: int
    f: int
    cm: float
    env_c: np.ndarray
    emax: float
    p: np.ndarray
    delta: float
    bottomed: bool
    key: tuple
    cshape: tuple
    area: float
    contact_exponent: float | None = None


def macro_cell_px(box: tuple[int, int, int, int], macro_cells: int, dx: float, valley_mm: float | None = None,
                  cells_per_valley: float = 0.0) -> int:
    """The macro grid's cell, in pixels of the ``dx`` mm grid, over ``box`` = (r0, r1, c0, c1): ``macro_cells``
    cells across its longer side, or finer where the object has a narrow envelope valley (``valley_mm``, a
    corduroy's gap between wales): at least ``cells_per_valley`` cells across it (0: no such rule). A
    valley that the grid spans with one cell is filled by the crown pooling and the closing, so the gel
    spans it and the tufts on either side carry less (pinwale corduroy, docs/fidelity.md)."""
    r0, r1, c0, c1 = box
    f = max(1, int(math.ceil(max(r1 - r0, c1 - c0) / macro_cells)))
    if valley_mm and cells_per_valley > 0:
        f = min(f, max(1, int(valley_mm / (cells_per_valley * dx))))
    return f


def solve_macro(work, box, dx, gel, tex, support, force_n, depth_mm, f, warm, sag=None,
                 own=None) -> MacroSolution:
    """The coarse contact problem over ``box`` = (r0, r1, c0, c1) of ``work`` on cells of ``f`` x ``f`` px
    (:func:`macro_cell_px`; ``sag``, ``own``: see press_twoscale)."""
    r0, r1, c0, c1 = box
    vmax = gel.max_indentation_mm
    region = work[r0:r1, c0:c1]
    cm = dx * f
    cshape = (-(-(r1 - r0) // f), -(-(c1 - c0) // f))
    if tex is not None:
        # Crown envelope on the coarse grid: each cell's highest point (see _crown_pool), then a
        # closing over the texture's scale fills the valleys between crowns.
        # (On the object's own heights, see crown_envelope: the dome's sag added back, and taken off again
        # after the closing at each cell's crown window's centre, pixel f i of the region.)
        if sag is None:
            own = region
        else:
            own = own[r0:r1, c0:c1] if own is not None else cv2.add(region, sag[r0:r1, c0:c1])
        pooled = _crown_pool(own, f, cshape) if f > 1 else own
        env_c = _closing(pooled, coarse_envelope_kernel_cells(tex, dx, f)).astype(np.float64)
        if sag is not None:
            env_c -= sag[r0:r1:f, c0:c1:f]
    else:
        env_c = _pool(region, f)
    emax = float(env_c.max())
    hc = env_c - emax
    area = cm * cm
    key = (cshape, f)
    warmed = warm is not None and warm.key == key and warm.origin == (r0, c0)
    same_grid = warmed  # (the warm state's own grid: its contact cells count like this frame's)
    if warmed:
        p = warm.pressure_mpa
    elif warm is not None and warm.work_shape == work.shape:
        # The previous frame's pressure on this frame's grid (its cell centres, bilinear): the
        # region moves by a pixel or two between frames and the patch barely changes.
        p = resample_pressure(warm, (r0, c0), f, cshape)
        warmed = bool(np.any(p > 0))
    if not warmed:
        p = np.sqrt(np.maximum(hc + max(0.05 * vmax, 1e-4), 0.0))
    # A force the pad cannot reach within its travel bottoms it out. After a bottomed frame that is
    # tried first: one solve at the travel instead of a force-controlled solve past it and then that one.
    at_travel = force_n is not None and warm is not None and warm.bottomed
    # The first pass takes the cloth's stiffness at the contact predicted for this frame's force: over a
    # sequence the contact grows with the force as a power law, cells ~ F^a (a = 0.1-0.6 on the
    # captured cloths), and a is read off the warm frame and its own warm start. (The warm frame's
    # contact as it stands was off by more than the tolerance on most frames whose force changed: a
    # second and often a third pass.)
    n_warm = int(np.count_nonzero(p > 0))
    predictable = force_n is not None and same_grid and not warm.bottomed and warm.force_n > 0 and n_warm > 0
    a = CONTACT_EXPONENT if not predictable or warm.contact_exponent is None else warm.contact_exponent
    cells = n_warm * (force_n / warm.force_n) ** a if predictable else None
    p, delta, bottomed = solve_on_cloth(hc, cm, gel, support, force_n, depth_mm, p, vmax=vmax, tol=MACRO_TOL,
                                        maxit=MACRO_MAXIT, at_travel=at_travel, cells=cells)
    exponent = None
    if predictable and not bottomed:
        step = math.log(force_n / warm.force_n)
        n = int(np.count_nonzero(p > 0))
        if abs(step) >= EXPONENT_MIN_STEP and n > 0:
            exponent = min(max(math.log(n / n_warm) / step, 0.0), 1.0)
        else:  # (a small step's change is the motion's more than the force's)
            exponent = warm.contact_exponent
    return MacroSolution(r0, r1, c0, c1, f, cm, env_c, emax, p, float(delta), bool(bottomed), key, cshape, area, exponent)


def solve_at(op: Operator, hc: np.ndarray, area: float, delta: float, p: np.ndarray, tol: float = MACRO_TOL,
              maxit: int = MACRO_MAXIT) -> np.ndarray:
    """The macro contact at the approach ``delta`` (mm), warm-started from ``p`` (MPa, e.g. a solution
    at a larger approach, or the previous frame's): its pressure, MPa.

    The start keeps ``p`` on the cells the object overlaps at ``delta`` (the contact at a smaller
    approach lies within them): 9-14 iterations on the captured bottomed frames, where adding 1 MPa
    on every overlapping cell (a start far above a cloth's kPa) took 25-28."""
    overlap = hc + delta > 0
    p0 = np.where(overlap, np.maximum(p, 0), 0.0)
    if not np.any(p0 > 0):  # (no pressure there yet: start uniform on the overlap)
        p0 = overlap.astype(np.float64)
    return pk_solve(op, hc, area, delta=delta, p0=p0, tol=tol, maxit=maxit)[0]


def _crown_pool(region: np.ndarray, f: int, cshape: tuple[int, int]) -> np.ndarray:
    """The highest point (mm, float32 ``cshape``) of ``region`` (mm, float32) near each of the coarse
    grid's ``f``-pixel blocks: its dilation by an f x f square read by OpenCV's nearest-neighbour
    resize to ``cshape``, which reads pixel c = floor(i n / m) for cell i (n pixels, m cells along
    an axis): the maximum over pixels [c - f // 2, c - f // 2 + f).

    Computed as those windows' maxima, rows then columns (one pass over the region, where the
    full-resolution dilation and its read took 0.9 ms per 960x720 frame; the same values, a maximum
    is exact). When the grid divides the region evenly (the usual whole-frame box: 720 x 960 px in
    48 x 64 blocks of 15) c = f i, the windows tile the axis, and the maxima are numpy's strided
    reductions (0.2 ms; SIMD maxima, which numba's loop of :func:`_window_max` does not reach: 0.4 ms).

    (Cell i's window then starts f // 2 pixels before its block, half a block off the block the rest
    of the model gives it, and the last f // 2 rows and columns fall in no window. Kept as it was:
    centring it moves the envelope by half a cell, a change to the model's results.)
    """
    rows = _axis_window_max(region, f, cshape[0])
    # (The second pass runs on the transposed, contiguous rows: a reduction over strided columns is
    # 3 times slower.)
    return np.ascontiguousarray(_axis_window_max(np.ascontiguousarray(rows.T), f, cshape[1]).T)


def _axis_window_max(a: np.ndarray, f: int, m: int) -> np.ndarray:
    """For each of m cells along the first axis of ``a`` (2-D, n rows): the maximum over rows
    [c - f // 2, c - f // 2 + f) (clipped to the axis) about the row c that OpenCV's INTER_NEAREST
    resize from n to m samples reads, floor(i * (1 / (m / n))) (its double arithmetic); (m, k)."""
    n = a.shape[0]
    c = np.minimum(np.floor(np.arange(m) * (1.0 / (m / n))), n - 1).astype(np.int64)
    if not np.array_equal(c, f * np.arange(m)):
        return _window_max(a, c - f // 2, f)
    lo = f - f // 2  # cell 0's window is [-(f // 2), lo); cell i's starts at lo + (i - 1) f
    out = np.empty((m,) + a.shape[1:], a.dtype)
    out[0] = a[:min(lo, n)].max(axis=0)
    full = min(m - 1, (n - lo) // f)  # cells 1..full end within the axis
    if full > 0:
        out[1:full + 1] = a[lo:lo + full * f].reshape((full, f) + a.shape[1:]).max(axis=1)
    for i in range(full + 1, m):  # (at most the last cell, clipped at the axis' end)
        out[i] = a[lo + (i - 1) * f:].max(axis=0)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _window_max(a, starts, f: int):
    """Row i of the result: the maximum of rows [starts[i], starts[i] + f) of ``a`` (2-D), clipped to
    its rows (each window holds at least one row)."""
    n, k = a.shape
    out = np.empty((starts.size, k), a.dtype)
    for i in range(starts.size):
        lo, hi = max(starts[i], 0), min(starts[i] + f, n)
        o = out[i]
        o[:] = a[lo]
        for r in range(lo + 1, hi):
            ar = a[r]
            for j in range(k):
                o[j] = max(o[j], ar[j])
    return out


def resample_pressure(warm: MacroState, origin: tuple[int, int], f: int, cshape: tuple[int, int]) -> np.ndarray:
    """``warm``'s pressure (MPa) at the centres of a grid of ``cshape`` blocks of ``f`` work pixels
    starting at ``origin``, float64."""
    ys = origin[0] + (np.arange(cshape[0]) + 0.5) * f - 0.5
    xs = origin[1] + (np.arange(cshape[1]) + 0.5) * f - 0.5
    # Fine pixel -> old coarse cell coordinate: (x + 0.5) / block - 0.5 - old origin / block.
    b, (oy, ox) = warm.block, warm.origin
    gy = (ys + 0.5) / b - 0.5 - oy / b
    gx = (xs + 0.5) / b - 0.5 - ox / b
    mx, my = np.meshgrid(gx.astype(np.float32), gy.astype(np.float32))
    return cv2.remap(warm.pressure_mpa.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0).astype(np.float64)


def hc_of(sol: "MacroSolution") -> np.ndarray:
    """The macro grid's object surface relative to its top (mm, <= 0)."""
    return sol.env_c - sol.emax


def widen_window(a: int, b: int, n: int, least: int = MIN_WINDOW_PX) -> tuple[int, int]:
    """[a, b) grown about its middle to at least ``least`` pixels, within [0, n)."""
    if b - a >= least or n <= b - a:
        return a, b
    a = max(0, min(a - (least - (b - a)) // 2, n - least))
    return a, min(n, a + least)


def _frame_edges(origin: int, f: int, n: int, size: int) -> tuple[bool, bool]:
    """Whether a coarse grid's low and high edges along one axis (``n`` blocks of ``f`` fine pixels from
    fine pixel ``origin``) are the frame's (``size`` fine pixels)."""
    return origin <= 0, origin + n * f >= size


def _beyond(idx: np.ndarray, n: int, edges: tuple[bool, bool]) -> np.ndarray:
    """Coarse indices ``idx`` mapped into a grid of ``n`` samples with one spare sample on each side
    (index + 1; 0 and n + 1 read zero): beyond a frame edge (``edges``: low, high) the edge sample."""
    lo = 1 if edges[0] else 0
    hi = n if edges[1] else n + 1
    return np.clip(idx + 1, lo, hi)


def _window_grid(p: np.ndarray, f: int, origin, win, frame: tuple[int, int]) -> tuple[np.ndarray, int, int]:
    """How a coarse field (e.g. the pressure, MPa; the grid's origin is the fine pixel of its first
    block, ``f`` fine pixels a block) is read bilinearly at the fine pixels of ``win`` = (w0, w1, v0,
    v1) in a frame of ``frame`` = (ny, nx) fine pixels: ``(sub, oy, ox)``, the coarse cells around the
    window (float32, one more on each side) whose ``f``-fold bilinear upsampling (OpenCV's resize)
    has the window's pixel (0, 0) at (oy, ox) (:func:`gelsim.gel.texture_kernels.macro_floor` reads it so).

    Beyond the grid the field is zero where the grid's edge lies inside the frame (the macro grid
    covers what the object can reach: its edge cells are out of contact, and the contact's edge falls
    at the midpoint, see press_twoscale) and holds its edge cells' values where the grid's edge is the
    frame's (a contact the frame cuts goes on to the edge: a zero there halved the pressure and the
    cloth's compression over the last half cell, and pressed a knit 0.1 mm too deep along the frame)."""
    r0, c0 = origin
    w0, w1, v0, v1 = win
    # Coarse cells covering the window, one extra on each side for the interpolation.
    i0, i1 = (w0 - r0) // f - 1, -(-(w1 - r0) // f) + 1
    j0, j1 = (v0 - c0) // f - 1, -(-(v1 - c0) // f) + 1
    padded = np.zeros((p.shape[0] + 2, p.shape[1] + 2), np.float32)
    padded[1:-1, 1:-1] = p
    rows = _beyond(np.arange(i0, i1), p.shape[0], _frame_edges(r0, f, p.shape[0], frame[0]))
    cols = _beyond(np.arange(j0, j1), p.shape[1], _frame_edges(c0, f, p.shape[1], frame[1]))
    sub = np.ascontiguousarray(padded[rows[:, None], cols[None, :]])
    return sub, w0 - (r0 + i0 * f), v0 - (c0 + j0 * f)


def _window_pressure(p: np.ndarray, f: int, origin, win, frame: tuple[int, int]) -> np.ndarray:
    """A coarse field read bilinearly at the fine pixels of ``win`` = (w0, w1, v0, v1) as
    :func:`_window_grid` says (the reading that :func:`gelsim.gel.texture_kernels.macro_floor` makes
    inside its pass and :func:`_cell_pressure` averages): float32 (w1 - w0, v1 - v0), a view."""
    sub, oy, ox = _window_grid(p, f, origin, win, frame)
    up = _upsample(sub, f, (sub.shape[0] * f, sub.shape[1] * f))
    return up[oy:oy + win[1] - win[0], ox:ox + win[3] - win[2]]


def _cell_pressure(p: np.ndarray, f: int, origin, win, cs: tuple[int, int], frame: tuple[int, int]) -> np.ndarray:
    """The coarse pressure ``p`` (MPa; grid of ``f``-pixel blocks from fine pixel ``origin``) read as
    :func:`_window_pressure` reads it at the fine pixels of ``win`` = (w0, w1, v0, v1), then averaged
    over ``cs`` = (cols, rows) cells tiling the window as OpenCV's INTER_AREA does: float32
    (rows, cols). Both steps are linear and separable, so they are done on the coarse grid by two
    small matrices (the fine field and its average took two full-window passes)."""
    w0, w1, v0, v1 = win
    cols, rows = cs
    ry = axis_cell_matrix(w0, w1, origin[0], f, p.shape[0], rows, frame[0])
    rx = axis_cell_matrix(v0, v1, origin[1], f, p.shape[1], cols, frame[1])
    # OpenCV's product runs on the worker's one thread (numpy's BLAS may start threads at these sizes).
    out = cv2.gemm(cv2.gemm(ry, p.astype(np.float32), 1.0, None, 0.0), rx, 1.0, None, 0.0, flags=cv2.GEMM_2_T)
    return np.maximum(out, np.float32(0.0))


@functools.lru_cache(maxsize=16)
def axis_cell_matrix(a: int, b: int, origin: int, f: int, n: int, cells: int, size: int) -> np.ndarray:
    """float32 (cells, n), read-only: the n coarse samples (``f``-pixel blocks from fine pixel ``origin``)
    read bilinearly at fine pixels a..b-1, then averaged over ``cells`` cells tiling them (one axis of
    :func:`_cell_pressure`). Cached: a sequence's frames mostly share their window (a whole-pad cloth:
    72% of the captured frames' axes), and building it took about half of _cell_pressure's time."""
    m = _cell_means(_bilinear_matrix((np.arange(a, b) + 0.5 - origin) / f - 0.5, n,
                                     _frame_edges(origin, f, n, size)), cells)
    m.flags.writeable = False
    return m


def _bilinear_matrix(coords: np.ndarray, n: int, edges: tuple[bool, bool]) -> np.ndarray:
    """float32 (len(coords), n): linear interpolation weights of samples 0..n-1 at ``coords`` (sample units);
    beyond 0..n-1 a zero, or at a frame edge (``edges``: low, high) the edge sample (as _window_pressure)."""
    i0 = np.floor(coords).astype(np.intp)
    w = (coords - i0).astype(np.float32)
    m = np.zeros((len(coords), n + 2), np.float32)   # one spare column on each side, dropped below
    r = np.arange(len(coords))
    m[r, _beyond(i0, n, edges)] += 1.0 - w
    m[r, _beyond(i0 + 1, n, edges)] += w
    return np.ascontiguousarray(m[:, 1:n + 1])


def _cell_means(rows_px: np.ndarray, cells: int) -> np.ndarray:
    """The rows of ``rows_px`` (one per pixel) averaged over ``cells`` equal cells tiling them, as
    OpenCV's INTER_AREA averages pixels (the same call: a narrow image of a few columns)."""
    return cv2.resize(rows_px, (rows_px.shape[1], cells), interpolation=cv2.INTER_AREA)


def cloth_stiffness(support: FabricSupport | None, p: np.ndarray, force_n: float | None, area: float,
                    close_px: int = 0, cells: float | None = None) -> float:
    """The cloth's secant stiffness (kPa/mm) at the contact's mean pressure under ``p`` (MPa, the
    current estimate): the load ``force_n`` (N; None: the load ``p`` carries) over the cells ``p``
    touches (or, with ``force_n``, over ``cells`` when given: a predicted contact), closed over
    ``close_px`` cells when >= 2 (the apparent contact of a texture, see elastic.press_elastic); inf for
    a rigid object."""
    if support is None:
        return math.inf
    if cells is not None and force_n is not None:
        n = cells
    else:
        touch = p > 0
        if close_px >= 2 and touch.any():
            touch = cv2.morphologyEx(touch.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((close_px, close_px), np.uint8))
        n = int(np.count_nonzero(touch))
    if force_n is not None:
        pm_kpa = 1e3 * force_n / (area * max(n, 1))
    else:
        # (the contact cells' mean pressure, spread over the closed contact)
        pm_kpa = 1e3 * float(p[p > 0].mean()) * (np.count_nonzero(p > 0) / n) if n else 1.0
    return support.secant_stiffness_kpa_per_mm(pm_kpa)


def solve_on_cloth(h: np.ndarray, d: float, gel, support: FabricSupport | None, force_n: float | None,
                   depth_mm: float | None, p: np.ndarray, *, vmax: float, tol: float, maxit: int,
                   close_px: int = 0, dtype=np.float32, at_travel: bool = False,
                   cells: float | None = None) -> tuple[np.ndarray, float, bool]:
    """Frictionless contact of the surface ``h`` (mm, <= 0 below its top, on a grid of ``d`` mm cells)
    with the layer of ``gel`` on the cloth ``support`` (None: rigid), at the force ``force_n`` (N) or the
    approach ``depth_mm`` (mm), the travel ``vmax`` (mm) bounding the approach. ``p``: a first estimate of
    the pressure (MPa); ``tol``, ``maxit``: Polonsky-Keer's; ``close_px``: see :func:`cloth_stiffness`;
    ``dtype``: the operator's arithmetic; ``at_travel``: try the travel first (the previous frame
    bottomed out); ``cells``: the contact predicted for the force, for the first pass's stiffness (see
    :func:`cloth_stiffness`). Returns (pressure MPa, approach mm, bottomed). The reference
    (:mod:`gelsim.gel.elastic`) and the macro solve here both go through this.

    The cloth's secant stiffness depends on the contact's mean pressure, so the solve is repeated
    (at most SUPPORT_PASSES times) until the stiffness it used is within SUPPORT_TOL of the one its
    pressure implies. A pass whose force-controlled approach lies beyond the travel is solved again at
    the travel with the same operator. The invariant of a press that bottoms out: the force it reports
    (the gel's, at the travel) is at most the request. For one linear operator the contact force grows
    with the approach, and the request needs an approach beyond the travel, so the force at the travel
    is below it (up to the solver's tolerance); a re-solve with another stiffness can break that (a
    stiffer cloth carries more at the same approach: the reference did, 2.03 N for 2 N).
    A bottomed pass's successor takes the stiffness at the request's mean pressure over the contact at
    the travel, as a force-controlled pass does: the cloth carries only the gel's share then, but that
    fixed point feeds itself (a softer cloth carries less at the travel) and is far from converged in
    SUPPORT_PASSES passes (measured: a 20 mm sphere at 10 N on a soft cloth, 2.1 N after 4 passes, 0.3 N
    after 30)."""
    area = d * d
    bottomed = False
    delta = 0.0 if depth_mm is None else float(depth_mm)
    at_travel = at_travel and force_n is not None
    used = None
    for _ in range(SUPPORT_PASSES):
        ks = cloth_stiffness(support, p, force_n, area, close_px, cells if used is None else None)
        if used is not None and abs(ks - used) <= SUPPORT_TOL * used:
            break
        op = cloth_operator(h.shape, d, gel, support, ks, dtype)
        used = ks
        if at_travel:
            # The force grows with the approach, so the pass is bottomed exactly when the force at the
            # travel falls short of the request.
            p = solve_at(op, h, area, vmax, p, tol, maxit)
            bottomed = float(p.sum()) * area < force_n
            delta = vmax
        if force_n is not None and not bottomed:
            p, delta, _ = pk_solve(op, h, area, force=force_n, p0=p, tol=tol, maxit=maxit)
            bottomed = delta > vmax
            if bottomed:
                p = solve_at(op, h, area, vmax, p, tol, maxit)
                delta = vmax
        if force_n is None:
            bottomed = depth_mm > vmax
            delta = vmax if bottomed else float(depth_mm)
            p = solve_at(op, h, area, delta, p, tol, maxit)
        at_travel = bottomed
        if support is None or not math.isfinite(ks):
            break
    return p, float(delta), bool(bottomed)


def cloth_operator(shape, d: float, gel, support: FabricSupport | None, ks: float = math.inf,
                   dtype=np.float32) -> Operator:
    """The layer's operator on a grid of ``d`` mm cells with the cloth ``support`` in series: its secant
    compliance at the stiffness ``ks`` (kPa/mm, inf: none) and the yarn crowns' Winkler compliance;
    the bare layer for a rigid object (None)."""
    if support is None:
        return Operator(shape, d, gel, dtype=dtype)
    return Operator(shape, d, gel, 1e3 / ks if math.isfinite(ks) else 0.0, support.shear_length_mm,
                    winkler_compliance=1.0 / support.yarn_stiffness_mpa_per_mm, dtype=dtype)
