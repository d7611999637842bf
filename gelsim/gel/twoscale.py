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

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .johnson import map_parameters
from .layer import Operator, effective_modulus_mpa, pk_solve
from .support import FabricSupport

# Macro solve's stopping rule (relative L1 change of the pressure per iteration): the macro
# pressure feeds s = p / p*, for which 1e-4 is far below the texture statistics' own spread.
MACRO_TOL = 1e-4
MACRO_MAXIT = 500
# The layer's displacement falls below 2% of its peak within 3 thicknesses of the contact
# (bonded base): the output window reaches that far beyond the patch.
OUT_MARGIN_THICKNESS = 3.0
# The envelope's closing spans this many times the texture's scale: a jittered weave's
# crowns stand up to ~20% of a pitch off their nominal place.
ENVELOPE_SPAN = 1.2
# The crown-to-valley depth is the deepest valley within this many times the texture's scale
# (a full period of the coarsest direction, with room for a jittered yarn).
STATS_SPAN = 1.5
# Outer passes for the cloth's secant stiffness at the contact's mean pressure (the second
# changes the approach by < 1%: measured on the catalog at 1-4 N).
SUPPORT_PASSES = 2


@dataclass(frozen=True)
class MacroState:
    """A frame's macro solution, to warm-start the next frame's (opaque to callers)."""
    key: tuple
    pressure_mpa: np.ndarray


def _closing(img: np.ndarray, k: int) -> np.ndarray:
    """Grey closing with a k x k square, as separable row/column passes (same result, faster)."""
    if k < 2:
        return img
    r, c = np.ones((1, k), np.uint8), np.ones((k, 1), np.uint8)
    d = cv2.dilate(cv2.dilate(img, r, borderType=cv2.BORDER_REPLICATE), c, borderType=cv2.BORDER_REPLICATE)
    return cv2.erode(cv2.erode(d, r, borderType=cv2.BORDER_REPLICATE), c, borderType=cv2.BORDER_REPLICATE)


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


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


def _texture_depth(t: np.ndarray, p_fine: np.ndarray, dx: float, gel, support: FabricSupport | None,
                   texture_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texture's part of the gel surface for the texture ``t`` (mm, <= 0: depth below the
    crowns) under the local mean pressure ``p_fine`` (MPa), both float32 (ny, nx).

    Returns (g - mean g: the gel surface's oscillation about its local mean, mm; -mean g: how far
    the crowns stand below that mean, mm, >= 0; the texture-scale contact, bool). The macro solve
    gives the gel's local *mean* displacement (its q = 0 part carries the load), so the texture
    enters as a zero-mean oscillation about it; the crowns are pushed in -mean g further.
    Statistics are taken on a grid of about texture/4 cells (the fields they feed vary over a
    texture period); the map itself runs at full resolution.
    """
    e_star = effective_modulus_mpa(gel)
    fs = max(1, int(texture_mm / (4.0 * dx)))
    ny, nx = t.shape
    cs = (-(-nx // fs), -(-ny // fs))
    # Central differences, each axis alone: a wave of q per axis reads sin(q dx) / dx there, which
    # is inverted below (exact for a wave at any angle; the Sobel's cross smoothing is not).
    gx = cv2.Sobel(t, cv2.CV_32F, 1, 0, ksize=1, scale=0.5 / dx)
    gy = cv2.Sobel(t, cv2.CV_32F, 0, 1, ksize=1, scale=0.5 / dx)
    k = max(1, int(round(texture_mm / (dx * fs))))

    def shrink(a):
        return cv2.resize(a, cs, interpolation=cv2.INTER_AREA) if fs > 1 else a

    def smooth(small):
        # Two boxes one texture period wide (a triangle): the first zeroes the texture's
        # fundamental, the pair keeps the rest of it below 5% (sinc^2).
        return cv2.blur(cv2.blur(small, (k, k), borderType=cv2.BORDER_REPLICATE), (k, k),
                        borderType=cv2.BORDER_REPLICATE)

    def grow(small):
        return cv2.resize(small, (nx, ny), interpolation=cv2.INTER_LINEAR) if fs > 1 else small

    m1 = smooth(shrink(t))
    m2 = smooth(shrink(cv2.multiply(t, t)))
    gxx = smooth(shrink(cv2.multiply(gx, gx)))
    gyy = smooth(shrink(cv2.multiply(gy, gy)))
    gxy = smooth(shrink(cv2.multiply(gx, gy)))
    # Crown-to-valley depth: the deepest valley within STATS_SPAN texture scales (each coarse cell
    # takes its block's minimum: sampling alone misses the valley floors).
    tmin = cv2.resize(cv2.erode(t, np.ones((fs, fs), np.uint8), borderType=cv2.BORDER_REPLICATE), cs,
                      interpolation=cv2.INTER_NEAREST) if fs > 1 else t
    ke = max(1, int(round(STATS_SPAN * texture_mm / (dx * fs))))
    depth = -cv2.blur(cv2.erode(tmin, np.ones((ke, ke), np.uint8), borderType=cv2.BORDER_REPLICATE), (ke, ke),
                      borderType=cv2.BORDER_REPLICATE)
    var = np.maximum(m2 - m1 * m1, np.float32(1e-12))
    # Undo the central difference's sinc per axis: q_axis = asin(dx q_read) / dx.
    cx = _sinc_correction(gxx / var, dx)
    cy = _sinc_correction(gyy / var, dx)
    gxx *= cx
    gyy *= cy
    gxy *= np.sqrt(cx * cy)
    slope2 = gxx + gyy
    q = np.sqrt(slope2 / var)                                    # 1/mm
    aniso = np.sqrt((gxx - gyy) ** 2 + 4.0 * gxy * gxy) / np.maximum(slope2, np.float32(1e-12))
    share = (support.texture_share(q, e_star) if support is not None else np.ones_like(q)).astype(np.float32)
    d_eff = np.maximum(depth * share, np.float32(1e-9))
    s = shrink(p_fine) / (np.float32(e_star / 4.0) * q * d_eff)
    zeta, lam = map_parameters(s, aniso)
    cut = (zeta * d_eff).astype(np.float32)
    # g = te where te >= -cut, else -cut + lam (te + cut) = te - (1 - lam) min(te + cut, 0), te = share t
    te = cv2.multiply(t, grow(share))
    below = cv2.min(cv2.add(te, grow(cut)), 0.0)
    g = cv2.subtract(te, cv2.multiply(grow((1.0 - lam).astype(np.float32)), below))
    gm = grow(smooth(shrink(g)))
    return cv2.subtract(g, gm), cv2.multiply(gm, -1.0), below >= 0.0


def _sinc_correction(qdx2: np.ndarray, dx: float) -> np.ndarray:
    """Factor on a central difference's mean square slope that undoes its sin(q dx) / (q dx)
    response, from the read (q dx)^2 (float32, same shape)."""
    qr = np.minimum(np.sqrt(qdx2) * np.float32(dx), np.float32(1.0))
    return np.where(qr > 1e-3, np.arcsin(qr) / np.maximum(qr, np.float32(1e-3)), np.float32(1.0)) ** 2


def press_twoscale(work: np.ndarray, dx: float, gel, *, force_n: float | None, depth_mm: float | None,
                   support: FabricSupport | None, texture_mm: float | None, window: str, macro_cells: int,
                   warm: MacroState | None = None):
    """Press ``work`` (protrusion, mm, (ny, nx) at ``dx`` mm/px) into ``gel``.

    Returns (depth mm (ny, nx) float32 before the membrane's blur, contact mask, approach mm,
    force N, bottomed, MacroState).
    """
    ny, nx = work.shape
    pmax = float(work.max())
    vmax = gel.max_indentation_mm
    full = window == "full"
    # The texture's scale, capped at the gel's thickness: coarser relief is the macro solve's
    # (the layer's finite thickness matters there, and a coarse grid resolves it).
    tex = None if texture_mm is None else min(float(texture_mm), gel.thickness_mm)
    has_texture = tex is not None and tex > 2.0 * dx
    # 1. The region the gel can reach, and its coarse grid.
    r0, r1, c0, c1 = (0, ny, 0, nx) if full else _bbox(work > np.float32(pmax - vmax))
    region = work[r0:r1, c0:c1]
    f = max(1, int(math.ceil(max(r1 - r0, c1 - c0) / macro_cells)))
    cm = dx * f
    cshape = (-(-(r1 - r0) // f), -(-(c1 - c0) // f))
    if has_texture:
        # Crown envelope on the coarse grid: each cell's highest point (block centres of a
        # dilation), then a closing over the texture's scale fills the valleys between crowns.
        pooled = cv2.resize(cv2.dilate(region, np.ones((f, f), np.uint8)), (cshape[1], cshape[0]),
                            interpolation=cv2.INTER_NEAREST) if f > 1 else region
        env_c = _closing(pooled, int(math.ceil(ENVELOPE_SPAN * tex / cm)) | 1).astype(np.float64)
    else:
        env_c = _pool(region, f)
    emax = float(env_c.max())
    hc = env_c - emax
    area = cm * cm
    # 2. Macro contact, warm-started from the previous frame when its grid matches.
    key = (cshape, f)
    warm_ok = warm is not None and warm.key == key
    p = warm.pressure_mpa if warm_ok else np.sqrt(np.maximum(hc + max(0.05 * vmax, 1e-4), 0.0))
    bottomed = False
    delta = 0.0
    passes = 1 if (support is None or warm_ok) else SUPPORT_PASSES
    for _ in range(passes):
        op = _macro_operator(cshape, cm, gel, support, p, force_n, area)
        if force_n is not None:
            p, delta, _ = pk_solve(op, hc, area, force=force_n, p0=p, tol=MACRO_TOL, maxit=MACRO_MAXIT)
            bottomed = delta > vmax
        if force_n is None or bottomed:
            bottomed = bottomed or depth_mm > vmax
            delta = vmax if bottomed else float(depth_mm)
            p, _, _ = pk_solve(op, hc, area, delta=delta, p0=np.maximum(p, 0) + (hc + delta > 0),
                               tol=MACRO_TOL, maxit=MACRO_MAXIT)
    force = float(p.sum() * area)
    state = MacroState(key, p)
    depth = np.zeros((ny, nx), np.float32)
    mask = np.zeros((ny, nx), bool)
    cb = _bbox(p > 0)
    if cb is None:
        return depth, mask, delta, force, bottomed, state
    # 3. The gel's displacement around the patch: one more convolution over a padded window.
    mc = 0 if full else int(math.ceil(OUT_MARGIN_THICKNESS * gel.thickness_mm / cm))
    q0, q1, s0, s1 = (0, cshape[0], 0, cshape[1]) if full else cb
    big = np.zeros((q1 - q0 + 2 * mc, s1 - s0 + 2 * mc))
    big[mc:mc + q1 - q0, mc:mc + s1 - s0] = p[q0:q1, s0:s1]
    u_f = _upsample(np.maximum(Operator(big.shape, cm, gel).gel(big), 0.0), f, (big.shape[0] * f, big.shape[1] * f))
    fr0, fc0 = r0 + (q0 - mc) * f, c0 + (s0 - mc) * f
    a0, a1 = max(0, fr0), min(ny, fr0 + u_f.shape[0])
    b0, b1 = max(0, fc0), min(nx, fc0 + u_f.shape[1])
    depth[a0:a1, b0:b1] = u_f[a0 - fr0:a1 - fr0, b0 - fc0:b1 - fc0]
    # 4. The contact window (coarse contact, one block of margin), at full resolution.
    w0, w1 = r0 + max(0, cb[0] - 1) * f, min(r1, r0 + (cb[1] + 1) * f)
    v0, v1 = c0 + max(0, cb[2] - 1) * f, min(c1, c0 + (cb[3] + 1) * f)
    if has_texture:
        ke = int(math.ceil(ENVELOPE_SPAN * tex / dx)) | 1
        W0, W1, V0, V1 = max(0, w0 - ke), min(ny, w1 + ke), max(0, v0 - ke), min(nx, v1 + ke)
        env = _closing(np.ascontiguousarray(work[W0:W1, V0:V1]), ke)[w0 - W0:w1 - W0, v0 - V0:v1 - V0]
    else:
        env = work[w0:w1, v0:v1]
    dwin = depth[w0:w1, v0:v1]
    # In the patch the gel rests on the envelope (the fine detail the coarse grid averaged away).
    pen_env = cv2.subtract(env, float(emax - delta))
    in_macro = pen_env >= dwin - np.float32(1e-9)
    np.maximum(dwin, pen_env, out=dwin)
    p_win = cv2.max(_window_pressure(p.astype(np.float32), f, (r0, c0), (w0, w1, v0, v1)), 0.0)
    in_macro |= p_win > 0
    if has_texture:
        t = cv2.subtract(np.ascontiguousarray(work[w0:w1, v0:v1]), env)
        g, sink, touch = _texture_depth(t, p_win, dx, gel, support, tex)
        g[~in_macro] = 0.0
        dwin += g
        np.maximum(dwin, 0.0, out=dwin)
        mask[w0:w1, v0:v1] = in_macro & touch & (p_win > 0)
        # The approach is the crowns': the macro one plus their sink below the mean surface there.
        top = np.unravel_index(int(np.argmax(np.where(in_macro, env, -np.inf))), t.shape)
        delta = float(delta) + float(sink[top])
    else:
        mask[w0:w1, v0:v1] = in_macro & (p_win > 0)
    return depth, mask, float(delta), force, bottomed, state


def _window_pressure(p: np.ndarray, f: int, origin, win) -> np.ndarray:
    """The coarse pressure (MPa) bilinearly at the fine pixels of ``win`` = (w0, w1, v0, v1), given
    the coarse grid's origin (fine pixel of its first block) and block size ``f``."""
    r0, c0 = origin
    w0, w1, v0, v1 = win
    # Coarse cells covering the window, one extra on each side for the interpolation.
    i0, i1 = max(0, (w0 - r0) // f - 1), min(p.shape[0], -(-(w1 - r0) // f) + 1)
    j0, j1 = max(0, (v0 - c0) // f - 1), min(p.shape[1], -(-(v1 - c0) // f) + 1)
    up = _upsample(p[i0:i1, j0:j1], f, ((i1 - i0) * f, (j1 - j0) * f))
    oy, ox = w0 - (r0 + i0 * f), v0 - (c0 + j0 * f)
    return np.ascontiguousarray(up[oy:oy + w1 - w0, ox:ox + v1 - v0])


def _macro_operator(shape, cm: float, gel, support: FabricSupport | None, p: np.ndarray,
                    force_n: float | None, area: float) -> Operator:
    """The coarse grid's layer operator, with the cloth's secant compliance at the contact's mean
    pressure (from ``p``, the current estimate) and the yarn crowns' Winkler compliance."""
    if support is None:
        return Operator(shape, cm, gel)
    n = int(np.count_nonzero(p > 0))
    if force_n is not None:
        pm_kpa = 1e3 * force_n / (area * max(n, 1))
    else:
        pm_kpa = 1e3 * float(p[p > 0].mean()) if n else 1.0
    ks = support.secant_stiffness_kpa_per_mm(pm_kpa)
    return Operator(shape, cm, gel, 1e3 / ks if math.isfinite(ks) else 0.0, support.shear_length_mm,
                    winkler_compliance=1.0 / support.yarn_stiffness_mpa_per_mm)
