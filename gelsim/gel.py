"""The gel imprint: how far an object pressed into the elastomer pushes its surface in.

Input is the object's *protrusion* map in the sensor frame (``float32 (H, W)``, mm,
largest where the object touches first, see :mod:`gelsim.indenters`) and either the
normal force (N) or the rigid-body approach (mm). Output is an :class:`Imprint`:
the depth the gel surface is pushed in (``>= 0``, 0 where untouched), the contact
mask, indentation, force and contact area.

Two models, chosen by ``fidelity.imprint_model`` and computed on a grid of
``fidelity.imprint_scale`` times the image resolution (then resampled):

``"elastic"`` (reference)
    Frictionless contact of a rigid (optionally Winkler-supported) object with an
    elastic layer of thickness ``h`` bonded to a rigid base. Surface displacement is
    ``u = K * p`` with ``K`` the layer's surface Green's function: the Boussinesq
    half-space part integrated exactly over each pixel (Love 1929) plus a smooth
    finite-thickness correction from the layer's Fourier compliance
    ``U(q) = 2 (1 - nu^2) / (E q) * S(q h)``, with
    ``S(x) = ((3-4nu) sinh 2x - 2x) / ((3-4nu) cosh 2x + 2x^2 + (1 + (3-4nu)^2) / 2)``
    (frictionless top, bonded base; ``S -> 1`` gives the half-space, ``S ~ x (1-2nu) /
    (2 (1-nu)^2)`` the uniaxial-strain limit of a thin layer). Convolutions are linear
    (zero-padded FFT). The contact problem (``p >= 0``, gap ``>= 0``, ``p * gap = 0``, total
    force or approach prescribed) is solved with the constrained conjugate-gradient
    method of Polonsky and Keer (Wear 1999). A fabric's through-thickness compliance
    is a Winkler layer under the object's surface: it adds ``p / k_s`` to the gap.

``"pyramid"`` (fast, after Taxim, Si and Yuan 2022)
    The object's penetration ``I = max(P - (P_max - delta), 0)`` spread by a Gaussian
    pyramid (coarse to fine, each level clamped to stay at or above ``I``: the gel
    never passes through the object), then the membrane blur. Force and approach are
    tied by ``F = c E* V / sqrt(A) / S(kappa h / a)^beta``, with ``V`` the penetration
    volume, ``A`` its area, ``a = sqrt(A / pi)``; ``c``, ``kappa``, ``beta`` are fitted to the
    elastic model and stored in ``assets/imprint_law.toml`` (see :func:`fit_pyramid_law`).
    For a sphere on a half-space the law is Hertz's with ``c = (4/3) sqrt(2/pi) =
    1.064``; for a flat punch ``c = 2 / sqrt(pi) = 1.128``.

Both models clip the approach at ``gel.max_indentation_mm`` (the pad bottoms out; the
force beyond is carried by the sensor's frame and ``bottomed_out`` is set) and work
only over the touched region (bounding box of the possible contact plus a margin).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy import fft as sfft
from scipy.special import j0

from .errors import GelsimError
from .params import ASSETS_DIR, build, load_toml, param

LAW_FILE = ASSETS_DIR / "imprint_law.toml"

# Polonsky-Keer stopping rule: relative change of the pressure field (L1) per
# iteration. 1e-6 puts the solver's error well below the pixel discretisation error
# (about 1% on a contact radius of 10 px).
_CG_TOL = 1e-6
_CG_MAXIT = 2000
# Beyond x = q h = 20 the layer factor S differs from 1 by < 1e-15 (terms in exp(-2x)).
_S_X_MAX = 20.0


# --------------------------------------------------------------------------------------
# Results and parameters
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Imprint:
    """The gel's response to one pressed object, at image resolution.

    depth_mm: float32 (H, W), how far the gel surface is pushed in, mm, >= 0, 0 where untouched.
    contact_mask: bool (H, W), object and gel in contact.
    indentation_mm: rigid-body approach of the object into the gel, mm (deepest penetration).
    normal_force_n: normal force carried by the gel, N (below the request if bottomed out).
    contact_area_mm2: area in contact, mm^2.
    bottomed_out: the approach reached ``gel.max_indentation_mm`` and was clipped there.
    """
    depth_mm: np.ndarray
    contact_mask: np.ndarray
    indentation_mm: float
    normal_force_n: float
    contact_area_mm2: float
    bottomed_out: bool


@dataclass(frozen=True)
class ImprintLaw:
    """Constants of the pyramid model's force law, fitted to the elastic model."""
    force_coef: float = param(lo=0.1, hi=10.0, doc="c in F = c E* V / sqrt(A) / S(kappa h / a)^beta")
    layer_kappa: float = param(lo=0.01, hi=100.0, doc="kappa: the contact size's wavenumber, q = kappa / a")
    pyramid_sigma_per_thickness: float = param(lo=0.01, hi=10.0,
                                               doc="blur of the coarsest pyramid level, in gel thicknesses")
    layer_exponent: float = param(1.0, lo=0.0, hi=3.0, doc="beta: the layer factor enters as S^-beta")
    contact_fraction: float = param(0.5, lo=0.0, hi=1.0,
                                    doc="pixels whose penetration is at least this fraction of the approach are in contact")
    fitted_poisson_ratio: float = param(0.48, lo=0.0, hi=0.5, doc="Poisson's ratio of the fit")
    fitted_thickness_mm: float = param(2.0, lo=0.1, hi=20.0, doc="gel thickness of the fit")
    note: str = ""


@functools.cache
def imprint_law() -> ImprintLaw:
    """The pyramid model's force-law constants from ``assets/imprint_law.toml``."""
    return build(ImprintLaw, load_toml(LAW_FILE).get("law", {}), where="imprint_law.law")


def effective_modulus_mpa(gel) -> float:
    """E* = E / (1 - nu^2) of the gel against a rigid object, MPa."""
    return gel.young_modulus_mpa / (1.0 - gel.poisson_ratio ** 2)


def hertz(diameter_mm: float, force_n: float, gel) -> tuple[float, float]:
    """Hertz contact of a rigid sphere on the gel as a half-space.

    Returns ``(contact_radius_mm, indentation_mm)``: ``a = (3 F R / (4 E*))^(1/3)``,
    ``d = a^2 / R`` with ``1/E* = (1 - nu^2) / E`` (E in MPa = N/mm^2).
    """
    if not (diameter_mm > 0 and math.isfinite(diameter_mm)):
        raise GelsimError(f"sphere diameter {diameter_mm} mm is not positive; give a diameter > 0")
    if not (force_n >= 0 and math.isfinite(force_n)):
        raise GelsimError(f"force {force_n} N is negative or not finite; give a force >= 0")
    r = diameter_mm / 2.0
    a = (3.0 * force_n * r / (4.0 * effective_modulus_mpa(gel))) ** (1.0 / 3.0)
    return a, a * a / r


def measure_contact_radius_mm(imprint: Imprint, mm_per_px: float) -> float:
    """Radius of the circle with the imprint's contact area, mm (``mm_per_px`` is kept
    for callers that measure from the mask; the area already carries the scale)."""
    if imprint.contact_area_mm2 > 0:
        return math.sqrt(imprint.contact_area_mm2 / math.pi)
    n = int(np.count_nonzero(imprint.contact_mask))
    return math.sqrt(n / math.pi) * mm_per_px


# --------------------------------------------------------------------------------------
# Elastic layer: Green's function
# --------------------------------------------------------------------------------------
def layer_factor(x: np.ndarray, nu: float) -> np.ndarray:
    """S(q h): the bonded layer's normal compliance relative to the half-space's (float64)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.ones_like(x)
    m = x < _S_X_MAX
    xm = x[m]
    k = 3.0 - 4.0 * nu
    num = k * np.sinh(2.0 * xm) - 2.0 * xm
    den = k * np.cosh(2.0 * xm) + 2.0 * xm * xm + 0.5 * (1.0 + k * k)
    out[m] = num / den
    return out


@functools.lru_cache(maxsize=8)
def _layer_correction_table(nu: float, rho_max: float) -> tuple[np.ndarray, np.ndarray]:
    """G(rho) = int_0^inf (S(x) - 1) J0(x rho) dx on rho in [0, rho_max].

    The layer's kernel is ``(1 - nu^2) / (pi E) * (1 / r + G(r / h) / h)``. The integrand
    decays as exp(-2x); the step resolves J0's period 2 pi / rho_max ten times over.
    """
    n_rho = 1024  # G varies over rho ~ 1; 1024 samples keep linear interpolation < 1e-5 off
    rho = np.linspace(0.0, rho_max, n_rho)
    dx = min(0.01, 2 * math.pi / rho_max / 40.0)
    x = np.arange(0.0, _S_X_MAX + dx, dx)
    w = np.full(x.shape, dx)
    w[0] = w[-1] = dx / 2
    f = (layer_factor(x, nu) - 1.0) * w
    g = np.empty(n_rho)
    for i in range(0, n_rho, 128):  # blocks keep the J0 matrix to a few MB
        g[i:i + 128] = j0(np.outer(rho[i:i + 128], x)) @ f
    return rho, g


def _love(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Antiderivative F with d2F/dxdy = 1/r (Love 1929), finite on the axes."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ax, ay = np.abs(x), np.abs(y)
        t1 = np.where(ax > 0, x * np.arcsinh(y / np.where(ax > 0, ax, 1.0)), 0.0)
        t2 = np.where(ay > 0, y * np.arcsinh(x / np.where(ay > 0, ay, 1.0)), 0.0)
    return t1 + t2


@functools.lru_cache(maxsize=16)
def _kernel_fft(ny: int, nx: int, dx: float, e_mpa: float, nu: float, h_mm: float) -> np.ndarray:
    """rfft2 of the layer's influence coefficients on the zero-padded (2 ny, 2 nx) grid.

    Coefficient (i, j): displacement (mm) at a pixel centre per unit pressure (MPa) on a
    pixel (i, j) away. Wrapped indices make the circular convolution linear.
    """
    iy = np.arange(2 * ny)
    iy = np.where(iy < ny, iy, iy - 2 * ny) * dx
    ix = np.arange(2 * nx)
    ix = np.where(ix < nx, ix, ix - 2 * nx) * dx
    y, x = np.meshgrid(iy, ix, indexing="ij")
    a = dx / 2
    love = _love(x + a, y + a) - _love(x + a, y - a) - _love(x - a, y + a) + _love(x - a, y - a)
    r = np.hypot(x, y)
    rho_needed = float(r.max() / h_mm) * 1.01 + 1e-6
    rho_max = 2.0 ** math.ceil(math.log2(max(rho_needed, 1.0)))  # fewer distinct tables to cache
    rho, g = _layer_correction_table(nu, rho_max)
    corr = np.interp(r / h_mm, rho, g) / h_mm * dx * dx
    k = (1.0 - nu * nu) / (math.pi * e_mpa) * (love + corr)
    return sfft.rfft2(k, workers=1)


class _Operator:
    """u = K * p on an (ny, nx) window, plus the Winkler support's p / k_s."""

    def __init__(self, shape: tuple[int, int], dx: float, gel, support_compliance: float):
        self.ny, self.nx = shape
        self.s = (2 * self.ny, 2 * self.nx)
        self.kf = _kernel_fft(self.ny, self.nx, float(dx), float(gel.young_modulus_mpa),
                              float(gel.poisson_ratio), float(gel.thickness_mm))
        self.cs = support_compliance

    def gel(self, p: np.ndarray) -> np.ndarray:
        u = sfft.irfft2(sfft.rfft2(p, s=self.s, workers=1) * self.kf, s=self.s, workers=1)
        return u[: self.ny, : self.nx]

    def __call__(self, p: np.ndarray) -> np.ndarray:
        u = self.gel(p)
        return u + self.cs * p if self.cs else u


def _pk_solve(op: _Operator, h: np.ndarray, area: float, *, force: float | None = None,
              delta: float | None = None, p0: np.ndarray) -> tuple[np.ndarray, float]:
    """Polonsky-Keer constrained CG. ``h``: object surface relative to its first touch
    (P - P_max, mm, <= 0). Force control (``force``, N) or approach control (``delta``, mm).
    Returns (pressure MPa, approach mm)."""
    force_ctl = force is not None
    target = h if force_ctl else h + delta
    p = p0.astype(np.float64).copy()
    if force_ctl:
        p *= force / (area * p.sum())
    t = np.zeros_like(p)
    g_old, d = 1.0, 0.0
    gbar = 0.0
    for _ in range(_CG_MAXIT):
        ic = p > 0
        if not ic.any():
            break
        g = op(p) - target
        if force_ctl:
            gbar = float(g[ic].mean())
            g -= gbar
        gg = float(np.dot(g[ic], g[ic]))
        t[ic] = g[ic] + (d * gg / g_old) * t[ic]
        t[~ic] = 0.0
        g_old = max(gg, 1e-300)
        r = op(t)
        if force_ctl:
            r -= float(r[ic].mean())
        den = float(np.dot(r[ic], t[ic]))
        if den == 0.0:
            break
        tau = float(np.dot(g[ic], t[ic])) / den
        p_old = p.copy()
        p[ic] -= tau * t[ic]
        np.maximum(p, 0.0, out=p)
        iol = (p == 0) & (g < 0)
        if iol.any():
            d = 0.0
            p[iol] -= tau * g[iol]
        else:
            d = 1.0
        if force_ctl:
            s = p.sum()
            if s <= 0:
                break
            p *= force / (area * s)
        s = p.sum()
        if s <= 0 or np.abs(p - p_old).sum() / s < _CG_TOL:
            break
    if force_ctl:
        ic = p > 0
        u = op(p) - h
        delta = float(u[ic].mean()) if ic.any() else 0.0
    return p, float(delta)


# --------------------------------------------------------------------------------------
# Pyramid law and smoothing
# --------------------------------------------------------------------------------------
def _law_force(vol: np.ndarray, area: np.ndarray, gel, ks: float | None) -> np.ndarray:
    """Pyramid-model force (N) for penetration volume (mm^3) and area (mm^2)."""
    law = imprint_law()
    estar = effective_modulus_mpa(gel)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.sqrt(area / math.pi)
        s = layer_factor(np.where(a > 0, law.layer_kappa * gel.thickness_mm / np.where(a > 0, a, 1.0),
                                  _S_X_MAX), gel.poisson_ratio)
        kg = np.where(area > 0, law.force_coef * estar / (np.sqrt(np.maximum(area, 1e-300))
                                                          * s ** law.layer_exponent), 0.0)
        if ks:
            kg = np.where(kg > 0, kg * ks / (kg + ks), 0.0)
    return kg * vol


def _penetration_stats(v: np.ndarray, cell_area: float, vmax: float, n_bins: int = 2048):
    """Area (mm^2) and volume (mm^3) penetrated at approach ``edges``: histogram form.

    ``v`` = P_max - P (mm) of the sampled pixels. Bins are vmax / 2048 wide: at most
    half a micrometre for the pads we simulate, far below any relief that shades.
    """
    v = v[v < vmax]
    edges = np.linspace(0.0, vmax, n_bins + 1)
    idx = np.minimum((v * (n_bins / vmax)).astype(np.int64), n_bins - 1)
    cnt = np.bincount(idx, minlength=n_bins).astype(np.float64)
    vsum = np.bincount(idx, weights=v.astype(np.float64), minlength=n_bins)
    c_cnt = np.concatenate([[0.0], np.cumsum(cnt)])
    c_v = np.concatenate([[0.0], np.cumsum(vsum)])
    area = c_cnt * cell_area
    vol = (edges * c_cnt - c_v) * cell_area
    return edges, area, vol


def _resize(img: np.ndarray, shape: tuple[int, int], interp=cv2.INTER_LINEAR) -> np.ndarray:
    if img.shape == shape:
        return img
    return cv2.resize(img, (shape[1], shape[0]), interpolation=interp)


def _pyramid_spread(pen: np.ndarray, sigma_px: float, skip_finest: bool = False) -> np.ndarray:
    """Gel surface from the penetration map: coarse-to-fine Gaussian pyramid.

    Level l has pixels 2^l times larger and blurs by ``_LEVEL_SIGMA`` of its own pixels,
    so the blurs halve from the coarsest (``sigma_px``) down to the image grid, like
    Taxim's kernels 201, 101, ... 5 px; after each level the surface is lifted back to
    the penetration (the gel cannot pass through the object). ``skip_finest`` leaves the
    finest level's blur to the membrane blur that follows.
    """
    levels = max(0, int(math.floor(math.log2(max(sigma_px / _LEVEL_SIGMA, 1.0)))))
    pens = [pen]
    for _ in range(levels):
        prev = pens[-1]
        if min(prev.shape) < 4:
            break
        pens.append(cv2.resize(prev, ((prev.shape[1] + 1) // 2, (prev.shape[0] + 1) // 2),
                               interpolation=cv2.INTER_AREA))
    d = pens[-1]
    for lvl in range(len(pens) - 1, -1, -1):
        if d.shape != pens[lvl].shape:
            d = cv2.resize(d, (pens[lvl].shape[1], pens[lvl].shape[0]), interpolation=cv2.INTER_LINEAR)
        if lvl > 0 or not skip_finest or len(pens) == 1:
            d = cv2.GaussianBlur(d, (0, 0), _LEVEL_SIGMA, borderType=cv2.BORDER_CONSTANT)
        cv2.max(d, pens[lvl], dst=d)
    return d


# Blur per pyramid level in that level's pixels: one sigma of 1 px per octave keeps
# neighbouring levels' kernels overlapping (a 2x coarser grid with sigma 1 px is a
# sigma of 2 px here), the analogue of Taxim's halving kernel sizes.
_LEVEL_SIGMA = 1.0


def _membrane_blur(depth: np.ndarray, sigma_px: float) -> np.ndarray:
    # Below a third of a pixel a Gaussian changes nothing visible in the image.
    if sigma_px < 0.33:
        return depth
    k = 2 * int(math.ceil(3.0 * sigma_px)) + 1  # +-3 sigma holds 99.7% of the weight
    return cv2.GaussianBlur(depth, (k, k), sigma_px, borderType=cv2.BORDER_CONSTANT)


# --------------------------------------------------------------------------------------
# press
# --------------------------------------------------------------------------------------
def _check_inputs(protrusion_mm, profile, fidelity, force_n, depth_mm, support):
    if (force_n is None) == (depth_mm is None):
        raise GelsimError("give exactly one of force_n and depth_mm to press()")
    for name, val in (("force_n", force_n), ("depth_mm", depth_mm),
                      ("support_stiffness_kpa_per_mm", support)):
        if val is not None and not (math.isfinite(val) and val >= 0):
            raise GelsimError(f"{name} = {val} is negative or not finite; give a finite value >= 0")
    if support is not None and support == 0:
        raise GelsimError("support_stiffness_kpa_per_mm = 0 carries no load; give a stiffness > 0 or None (rigid)")
    p = np.asarray(protrusion_mm)
    if p.ndim != 2:
        raise GelsimError(f"protrusion map has shape {p.shape}; give a 2-D (H, W) array in mm")
    if p.size == 0 or not (math.isfinite(float(p.max())) and math.isfinite(float(p.min()))):
        raise GelsimError("protrusion map has NaN or Inf values; give finite heights in mm")
    return p


def _work_shape(profile, scale: float) -> tuple[int, int]:
    h, w = profile.shape
    return max(8, round(h * scale)), max(8, round(w * scale))


def _bbox(mask: np.ndarray, margin: int, shape) -> tuple[slice, slice] | None:
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    r0, r1 = max(0, rows[0] - margin), min(shape[0], rows[-1] + 1 + margin)
    c0, c1 = max(0, cols[0] - margin), min(shape[1], cols[-1] + 1 + margin)
    return slice(r0, r1), slice(c0, c1)


def _fast_len(n: int) -> int:
    return sfft.next_fast_len(n, real=True)


def _no_contact(profile) -> Imprint:
    return Imprint(np.zeros(profile.shape, np.float32), np.zeros(profile.shape, bool), 0.0, 0.0, 0.0, False)


def press(protrusion_mm: np.ndarray, profile, fidelity, *, force_n: float | None = None,
          depth_mm: float | None = None, support_stiffness_kpa_per_mm: float | None = None,
          window: str = "touched") -> Imprint:
    """Press an object into the gel.

    protrusion_mm: (H, W) protrusion map in mm at the profile's image resolution, or
        already at ``fidelity.imprint_scale`` times it (same field of view).
    force_n: normal force, N (0 = no contact); or depth_mm: approach past first touch, mm.
    support_stiffness_kpa_per_mm: Winkler stiffness under the object's surface (a fabric:
        compressive modulus / thickness), kPa/mm; None = rigid object.
    window: "touched" computes over the touched region only (default); "full" over the whole
        frame (for checking the former).
    Returns an :class:`Imprint` at the profile's image resolution (float32 depth).
    """
    from .fidelity import get_fidelity

    fidelity = get_fidelity(fidelity)
    prot = _check_inputs(protrusion_mm, profile, fidelity, force_n, depth_mm, support_stiffness_kpa_per_mm)
    if (force_n is not None and force_n == 0) or (depth_mm is not None and depth_mm == 0):
        return _no_contact(profile)
    gel = profile.gel
    ws = _work_shape(profile, fidelity.imprint_scale)
    if prot.shape == profile.shape:
        work = _resize(np.ascontiguousarray(prot, dtype=np.float32), ws, cv2.INTER_AREA)
    elif prot.shape == ws:
        work = np.ascontiguousarray(prot, dtype=np.float32)
    else:
        raise GelsimError(f"protrusion map is {prot.shape}; give {profile.shape} (the profile's image) "
                          f"or {ws} (its imprint grid)")
    dx = profile.image.mm_per_px * profile.shape[1] / ws[1]
    ks = None if support_stiffness_kpa_per_mm is None else support_stiffness_kpa_per_mm * 1e-3  # MPa/mm
    if fidelity.imprint_model == "elastic":
        out = _press_elastic(work, dx, gel, force_n, depth_mm, ks, window)
    else:
        out = _press_pyramid(work, dx, gel, force_n, depth_mm, ks, window)
    depth_w, mask_w, delta, force, bottomed = out
    depth = _resize(depth_w, profile.shape)
    mask = mask_w if mask_w.shape == profile.shape else _resize(mask_w.astype(np.float32), profile.shape) >= 0.5
    depth = depth.astype(np.float32, copy=False)  # finite and >= 0 by construction
    area = float(np.count_nonzero(mask_w)) * dx * dx
    return Imprint(depth, mask, float(delta), float(force), area, bool(bottomed))


def _pen_window(work: np.ndarray, v: np.ndarray, delta: float, margin_px: int, window: str):
    if window == "full":
        return slice(0, work.shape[0]), slice(0, work.shape[1])
    return _bbox(v < delta, margin_px, work.shape)


def _law_delta(work: np.ndarray, v: np.ndarray, dx: float, gel, force: float, ks) -> tuple[float, bool]:
    """Approach (mm) the pyramid law gives for ``force`` (N), and whether it bottomed out."""
    vmax = gel.max_indentation_mm
    probe = 4  # count candidates on every 4th pixel first: 1/16 of the work
    n = int(np.count_nonzero(v[::probe, ::probe] < vmax)) * probe * probe
    stride = max(1, int(math.sqrt(n / 40000.0)))  # ~40k samples fix A and V within ~0.5%
    vs = v[::stride, ::stride]
    edges, area, vol = _penetration_stats(vs.ravel(), dx * dx * stride * stride, vmax)
    f = _law_force(vol, area, gel, ks)
    f = np.maximum.accumulate(f)
    if force >= f[-1]:
        return vmax, True
    return float(np.interp(force, f, edges)), False


def _press_pyramid(work, dx, gel, force_n, depth_mm, ks, window):
    law = imprint_law()
    pmax = float(work.max())
    v = pmax - work
    bottomed = False
    if force_n is not None:
        delta, bottomed = _law_delta(work, v, dx, gel, force_n, ks)
    else:
        delta = float(depth_mm)
        if delta >= gel.max_indentation_mm:
            delta, bottomed = gel.max_indentation_mm, True
    sigma_px = law.pyramid_sigma_per_thickness * gel.thickness_mm / dx
    margin = int(math.ceil(3 * sigma_px))  # a Gaussian is < 1.2% of its peak beyond 3 sigma
    sl = _pen_window(work, v, delta, margin, window)
    if sl is None or delta <= 0:
        return np.zeros(work.shape, np.float32), np.zeros(work.shape, bool), 0.0, 0.0, False
    # Align the window to the coarsest pyramid level so that its cells are the full
    # frame's cells: the touched-region result then equals the full-frame one.
    step = 2 ** max(0, int(math.floor(math.log2(max(sigma_px / _LEVEL_SIGMA, 1.0)))))
    r0, c0 = sl[0].start // step * step, sl[1].start // step * step
    r1 = min(work.shape[0], -(-sl[0].stop // step) * step)
    c1 = min(work.shape[1], -(-sl[1].stop // step) * step)
    sl = (slice(r0, r1), slice(c0, c1))
    pen = np.float32(delta) - v[sl]
    cv2.max(pen, 0.0, dst=pen)
    vol = float(cv2.sumElems(pen)[0]) * dx * dx
    pen_area = float(cv2.countNonZero(pen)) * dx * dx
    force = float(_law_force(np.array(vol), np.array(pen_area), gel, ks))
    if force_n is not None and not bottomed:
        force = float(force_n)
    scale = 1.0
    if ks:
        kg = float(_law_force(np.array(1.0), np.array(pen_area), gel, None))
        scale = ks / (kg + ks)  # gel's share of the penetration, springs in series
    sigma_m = gel.membrane_smoothing_mm / dx
    d = _pyramid_spread(pen * np.float32(scale) if scale != 1.0 else pen, sigma_px,
                        skip_finest=sigma_m >= _LEVEL_SIGMA)
    d = _membrane_blur(d, sigma_m)
    m = pen >= np.float32(law.contact_fraction * delta)
    if d.shape == work.shape:
        return d, m, delta, force, bottomed
    depth = np.zeros(work.shape, np.float32)
    mask = np.zeros(work.shape, bool)
    depth[sl] = d
    mask[sl] = m
    return depth, mask, delta, force, bottomed


def _press_elastic(work, dx, gel, force_n, depth_mm, ks, window):
    pmax = float(work.max())
    v = (pmax - work).astype(np.float64)
    cs = 0.0 if not ks else 1.0 / ks
    area = dx * dx
    h_mm = gel.thickness_mm
    # The layer's displacement falls below 2% of its peak within 3 thicknesses of the
    # contact (bonded base); the half-space's 1/r tail is cut at the frame's edge.
    out_margin = int(math.ceil(3.0 * h_mm / dx))
    bottomed = False
    full = window == "full"
    if force_n is not None:
        guess, _ = _law_delta(work, v, dx, gel, force_n, None if not ks else ks)
        bound = min(max(2.0 * guess, 1e-4), gel.max_indentation_mm)  # 0.1 um floor: a first guess only
        while True:
            sl = _pen_window(work, v, bound, 2, "full" if full else "touched")
            op = _Operator((sl[0].stop - sl[0].start, sl[1].stop - sl[1].start), dx, gel, cs)
            hh = -v[sl]
            p0 = np.maximum(bound * 0.5 + hh, 0.0) + (hh >= -1e-12)
            p, delta = _pk_solve(op, hh, area, force=force_n, p0=p0)
            if delta <= bound or bound >= gel.max_indentation_mm:
                break
            bound = min(2.0 * bound, gel.max_indentation_mm)
        if delta > gel.max_indentation_mm:
            depth_mm, bottomed = gel.max_indentation_mm, True
    if depth_mm is not None:
        delta = float(depth_mm)
        if delta > gel.max_indentation_mm:
            delta, bottomed = gel.max_indentation_mm, True
        sl = _pen_window(work, v, delta, 2, "full" if full else "touched")
        if sl is None:
            return np.zeros(work.shape, np.float32), np.zeros(work.shape, bool), 0.0, 0.0, False
        op = _Operator((sl[0].stop - sl[0].start, sl[1].stop - sl[1].start), dx, gel, cs)
        hh = -v[sl]
        p0 = np.maximum(delta + hh, 0.0) * (effective_modulus_mpa(gel) / h_mm)
        p, _ = _pk_solve(op, hh, area, delta=delta, p0=p0)
    force = float(p.sum() * area)
    # Displacement over the output window (contact window + margin): one more convolution.
    ny, nx = work.shape
    r0, r1 = sl[0].start, sl[0].stop
    c0, c1 = sl[1].start, sl[1].stop
    if full:
        R0, R1, C0, C1 = 0, ny, 0, nx
    else:
        R0, R1 = max(0, r0 - out_margin), min(ny, r1 + out_margin)
        C0, C1 = max(0, c0 - out_margin), min(nx, c1 + out_margin)
    big = np.zeros((R1 - R0, C1 - C0))
    big[r0 - R0:r1 - R0, c0 - C0:c1 - C0] = p
    u = _Operator(big.shape, dx, gel, 0.0).gel(big)
    depth = np.zeros(work.shape, np.float32)
    mask = np.zeros(work.shape, bool)
    depth[R0:R1, C0:C1] = _membrane_blur(np.maximum(u, 0.0).astype(np.float32), gel.membrane_smoothing_mm / dx)
    mask[sl] = p > 0
    return depth, mask, delta, force, bottomed


# --------------------------------------------------------------------------------------
# Fitting the pyramid law to the elastic model
# --------------------------------------------------------------------------------------
def _fit_cases(profile, diameters=(2.0, 4.0, 10.0, 20.0), forces=(0.003, 0.01, 0.03, 0.1, 0.3)):
    """Spheres of the fit over two decades of force: (name, protrusion, force N)."""
    from . import indenters

    return [(f"sphere {d:g} mm", indenters.sphere(d, profile), f) for d in diameters for f in forces]


def fit_pyramid_law(profile=None, resolution_px: int = 480) -> dict[str, Any]:
    """Fit the pyramid model's constants to the elastic model; returns them with residuals.

    c from spheres on a thick gel (20 mm: a half-space for these contacts); kappa and beta
    by least squares on log force from spheres on the profile's gel; the coarsest blur from
    the depth outside a sphere's contact. A cylinder on its side is reported as a check
    that took no part in the fit. About a minute; ``benchmarks/bench_gel.py --fit`` writes
    the result to LAW_FILE.
    """
    from scipy.optimize import least_squares

    from . import indenters
    from .fidelity import get_fidelity
    from .sensor import load_profile

    base = (profile or load_profile("vitac")).with_resolution(resolution_px)
    elastic = dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0)
    law0 = imprint_law()
    dx = base.image.mm_per_px

    def stats(prot, delta):
        pen = np.maximum(delta - (prot.max() - prot), 0.0)
        return float(pen.sum()) * dx * dx, float(np.count_nonzero(pen)) * dx * dx

    def law_force(vol, area, gel, c, kappa, beta):
        a = np.sqrt(np.asarray(area) / math.pi)
        s = layer_factor(kappa * gel.thickness_mm / a, gel.poisson_ratio)
        return c * effective_modulus_mpa(gel) * np.asarray(vol) / np.sqrt(area) / s ** beta

    thick = dataclasses.replace(base, gel=dataclasses.replace(base.gel, thickness_mm=20.0))
    cs = []
    for _, prot, f in _fit_cases(thick, diameters=(4.0, 10.0), forces=(0.003, 0.03, 0.3)):
        im = press(prot, thick, elastic, force_n=f)
        cs.append(f / float(law_force(*stats(prot, im.indentation_mm), thick.gel, 1.0, 1.0, 0.0)))
    c = float(np.exp(np.mean(np.log(cs))))
    rows, runs = [], []
    for name, prot, f in _fit_cases(base):
        im = press(prot, base, elastic, force_n=f)
        runs.append((name, prot, f, im))
        if not im.bottomed_out:
            rows.append((f, *stats(prot, im.indentation_mm)))
    rows = np.array(rows)

    def resid(x):
        return np.log(law_force(rows[:, 1], rows[:, 2], base.gel, c, math.exp(x[0]), x[1]) / rows[:, 0])

    sol = least_squares(resid, [0.0, 1.0])
    kappa, beta = float(math.exp(sol.x[0])), float(sol.x[1])
    law = dataclasses.replace(law0, force_coef=c, layer_kappa=kappa, layer_exponent=beta)
    # Coarsest blur: depth outside the contact of a mid-size sphere case, same approach.
    name, prot, f, im = runs[7]
    best = None
    for ratio in np.geomspace(0.05, 2.0, 25):
        trial = dataclasses.replace(law, pyramid_sigma_per_thickness=float(ratio))
        depth_w, *_ = _press_pyramid_with(trial, prot, base, im.indentation_mm)
        err = float(np.sqrt(np.mean((depth_w - im.depth_mm)[~im.contact_mask] ** 2)))
        if best is None or err < best[1]:
            best = (float(ratio), err)
    law = dataclasses.replace(law, pyramid_sigma_per_thickness=best[0])
    check = [(f"cylinder 4 mm x 6 mm (check)", indenters.cylinder(4.0, base, length_mm=6.0), f)
             for f in (0.01, 0.1)]
    res = []
    for name, prot, f, im in runs + [(n, p, f, press(p, base, elastic, force_n=f)) for n, p, f in check]:
        v = prot.max() - prot
        edges, area, vol = _penetration_stats(v.ravel(), dx * dx, base.gel.max_indentation_mm)
        with _law_override(law):
            ff = np.maximum.accumulate(_law_force(vol, area, base.gel, None))
        d = float(np.interp(f, ff, edges))
        res.append({"case": name, "force_n": f, "elastic_mm": round(im.indentation_mm, 5),
                    "pyramid_mm": round(d, 5), "rel": round(d / im.indentation_mm - 1, 4)})
    # Contact: penetration at least a fraction of the approach; the fraction that best
    # matches the elastic model's contact radii at the pyramid law's approach.
    fracs = np.linspace(0.2, 0.7, 51)
    errs = np.zeros_like(fracs)
    for r, (name, prot, f, im) in zip(res, runs):
        pen = np.maximum(r["pyramid_mm"] - (prot.max() - prot), 0.0)
        for i, fr in enumerate(fracs):
            area = float(np.count_nonzero(pen >= fr * r["pyramid_mm"])) * dx * dx
            errs[i] += math.log(max(area, dx * dx) / im.contact_area_mm2) ** 2 / 4  # (log radius ratio)^2
    frac = float(fracs[int(np.argmin(errs))])
    return {"force_coef": round(c, 4), "layer_kappa": round(kappa, 4), "layer_exponent": round(beta, 4),
            "contact_fraction": round(frac, 3),
            "contact_radius_rms_log": round(math.sqrt(float(errs.min()) / len(runs)), 4),
            "pyramid_sigma_per_thickness": round(best[0], 4),
            "fitted_poisson_ratio": base.gel.poisson_ratio, "fitted_thickness_mm": base.gel.thickness_mm,
            "fit_resolution_px": resolution_px,
            "c_per_case": [round(float(x), 4) for x in cs], "force_resid_max": round(float(np.abs(sol.fun).max()), 4),
            "outside_rms_mm": best[1], "residuals": res}


class _law_override:
    """Temporarily replace the cached law (fitting only)."""

    def __init__(self, law: ImprintLaw):
        self.law = law

    def __enter__(self):
        global imprint_law
        self.saved = imprint_law
        law = self.law
        imprint_law = lambda: law  # noqa: E731
        return self

    def __exit__(self, *exc):
        global imprint_law
        imprint_law = self.saved


def _press_pyramid_with(law: ImprintLaw, prot, profile, delta):
    with _law_override(law):
        dx = profile.image.mm_per_px
        return _press_pyramid(prot.astype(np.float32), dx, profile.gel, None, delta, None, "touched")


def write_law(values: dict[str, Any], path=LAW_FILE) -> None:
    """Write fitted constants to the law file (temporary name, then rename)."""
    import os

    from .params import dump_toml

    keep = ("force_coef", "layer_kappa", "layer_exponent", "pyramid_sigma_per_thickness", "contact_fraction",
            "fitted_poisson_ratio", "fitted_thickness_mm")
    law = {k: values[k] for k in keep}
    law["note"] = ("fitted by gelsim.gel.fit_pyramid_law: c on a 20 mm gel (half-space), kappa and beta on "
                   "the profile's gel, blur on the depth outside a sphere's contact; "
                   f"max |log F error| {values.get('force_resid_max')}, "
                   f"rms log contact-radius error {values.get('contact_radius_rms_log')}")
    header = ("Force law and smoothing of the pyramid imprint model (gelsim/gel.py), fitted to the\n"
              "elastic model. Regenerate: .venv/bin/python benchmarks/bench_gel.py --fit\n"
              "contact_fraction: 0.5 would be exact for Hertz (penetration d/2 at r = a); the fit matches the\n"
              "elastic layer's contact radii, which exceed Hertz's as the contact grows against the thickness.")
    text = dump_toml({"law": law}, header=header)
    tmp = f"{path}.tmp"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)
    imprint_law.cache_clear()
