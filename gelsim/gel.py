"""The gel imprint: how far an object pressed into the elastomer pushes its surface in.

Input is the object's *protrusion* map in the sensor frame (``float32 (H, W)``, mm,
largest where the object touches first, see :mod:`gelsim.indenters`) and either the
normal force (N) or the rigid-body approach (mm). Output is an :class:`Imprint`:
the depth the gel surface is pushed in (``>= 0``, 0 where untouched), the contact
mask, indentation, force and contact area.

Two models, chosen by ``fidelity.imprint_model`` and computed on a grid of
``fidelity.imprint_scale`` times the image resolution (then resampled):

``"elastic"`` (reference)
    Frictionless contact of a rigid (optionally fabric-supported, see below) object with an
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
    method of Polonsky and Keer (Wear 1999).

Fabric support (both models). A fabric's through-thickness compliance (Kawabata: 10-50%
of its thickness lost under a few kPa) comes from the voids between fibres and yarns
closing; the yarns themselves are stiff bundles that bridge those voids, so a load on one
crown is spread over the neighbouring yarns instead of sinking that crown alone. We model
the fabric as a Pasternak layer ``k_s w - k_s l^2 lap w = p`` under the object's surface:
``k_s`` (compressive modulus / thickness) sets the mean compression ``p / k_s``, and the
shear length ``l`` (about the fabric's thickness: the span over which the yarns share a
load) makes it stiffer by ``1 + (q l)^2`` at wavenumber q. Texture finer than ``l`` (yarn
crowns, 0.1-1 mm) therefore keeps most of its relief while the fabric as a whole
compresses; a Winkler layer (``l = 0``, each point on its own spring) flattens every scale
alike, which no GelSight image of cloth shows. In the elastic model the support adds
``w = K_s * p`` (kernel ``K0(r / l) / (2 pi l^2 k_s)``) to the gap.

``"pyramid"`` (fast, after Taxim, Si and Yuan 2022)
    The object's penetration ``I = max(P - (P_max - delta), 0)`` spread by a Gaussian
    pyramid (coarse to fine, each level clamped to stay at or above ``I``: the gel
    never passes through the object), then the membrane blur. Given the right approach
    this reproduces the elastic model's depth map of a texture closely (the clamps put the
    gel on the crowns, the blurs span the valleys); the contact is where the last clamp
    holds and the penetration exceeds ``contact_fraction`` of its peak. Force and approach
    are tied by ``F = c E* V / sqrt(A) / R(kappa a / h)^beta``, with ``V`` the volume under
    the pyramid's gel surface (measured on a half-resolution pass and refined: for a texture
    the gel spans the valleys, so V exceeds the penetration volume by more than for a smooth
    object), ``A`` the *apparent* contact area (that of the protrusion closed over h/4, so
    that a fabric touching only on its crowns loads the gel over the whole patch),
    ``a = sqrt(A / pi)`` and ``R`` the layer's mean compliance under a uniformly loaded disk
    relative to the half-space's (1 for a << h; it falls to 0.04 for the whole ViTac pad on
    a 2 mm gel). ``c``, ``kappa``, ``beta`` are fitted to the elastic model on spheres and on
    whole-pad contacts and stored in ``assets/imprint_law.toml`` (see :func:`fit_pyramid_law`).
    On a support, the gel takes ``k_s / (k_g + k_s)`` of the large-scale penetration (springs
    in series, ``k_s`` stiffened for a contact narrower than l) and its share of the texture
    at the texture's own wavenumber (Pasternak stiffening). Measured agreement with the
    elastic model on seven fabrics: docs/imprint.md.

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
from scipy.special import ive, j0, j1, k0, k1, kve

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
    force_coef: float = param(lo=0.01, hi=10.0, doc="c in F = c E* V / sqrt(A) / R(kappa a / h)^beta, "
                                                          "V under the pyramid's gel surface")
    layer_kappa: float = param(lo=0.01, hi=100.0, doc="kappa: the contact radius enters as kappa a / h")
    pyramid_sigma_per_thickness: float = param(lo=0.01, hi=10.0,
                                               doc="blur of the coarsest pyramid level, in gel thicknesses")
    layer_exponent: float = param(1.0, lo=0.0, hi=3.0, doc="beta: the layer factor enters as R^-beta")
    apparent_cell_per_thickness: float = param(0.25, lo=0.0, hi=10.0,
                                               doc="valleys narrower than this (in gel thicknesses) count as "
                                                   "apparent contact")
    support_length_mm: float = param(0.5, lo=0.0, hi=20.0,
                                     doc="default shear length of a fabric support (Pasternak), mm")
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


@functools.lru_cache(maxsize=16)
def _support_kernel_fft(ny: int, nx: int, dx: float, ell: float) -> np.ndarray:
    """rfft2 of a Pasternak support's influence coefficients (unit stiffness) on the
    zero-padded (2 ny, 2 nx) grid.

    A Pasternak layer ``k w - k l^2 lap w = p`` spreads a point load as
    ``K0(r / l) / (2 pi l^2 k)``: coefficient (i, j) is that at the pixel offset times the
    pixel area, the centre the exact integral over a disk of one pixel's area
    (``1 - X K1(X)``, X = dx / (sqrt(pi) l)). The weights sum to 1 (uniform load: w = p / k).
    """
    iy = np.arange(2 * ny)
    iy = np.where(iy < ny, iy, iy - 2 * ny) * dx
    ix = np.arange(2 * nx)
    ix = np.where(ix < nx, ix, ix - 2 * nx) * dx
    r = np.hypot(iy[:, None], ix[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(r > 0, k0(np.maximum(r, 1e-300) / ell), 0.0) * (dx * dx / (2 * math.pi * ell * ell))
    x0 = dx / (math.sqrt(math.pi) * ell)
    c[0, 0] = 1.0 - x0 * float(k1(x0))
    return sfft.rfft2(c, workers=1)


class _Operator:
    """u = K * p on an (ny, nx) window, plus the fabric support's compression.

    ``support_compliance`` = 1 / k_s (mm/MPa); ``support_len`` (mm) = the support's
    Pasternak shear length (0 or None: a Winkler support, ``p / k_s`` point by point).
    """

    def __init__(self, shape: tuple[int, int], dx: float, gel, support_compliance: float,
                 support_len: float | None = None):
        self.ny, self.nx = shape
        self.s = (2 * self.ny, 2 * self.nx)
        self.kf = _kernel_fft(self.ny, self.nx, float(dx), float(gel.young_modulus_mpa),
                              float(gel.poisson_ratio), float(gel.thickness_mm))
        self.cs = support_compliance
        self.pasternak = bool(support_compliance) and support_len is not None and support_len > 0.5 * dx
        if self.pasternak:
            self.kf = self.kf + support_compliance * _support_kernel_fft(self.ny, self.nx, float(dx),
                                                                        float(support_len))

    def gel(self, p: np.ndarray) -> np.ndarray:
        u = sfft.irfft2(sfft.rfft2(p, s=self.s, workers=1) * self.kf, s=self.s, workers=1)
        return u[: self.ny, : self.nx]

    def __call__(self, p: np.ndarray) -> np.ndarray:
        u = self.gel(p)
        return u + self.cs * p if (self.cs and not self.pasternak) else u


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
@functools.lru_cache(maxsize=32)
def _disk_layer_table(nu: float) -> tuple[np.ndarray, np.ndarray]:
    """R(rho) on a log grid of rho = a / h (float64).

    R is the mean displacement of a uniformly loaded disk of radius a on the bonded
    layer relative to the half-space's (``16 p a / (3 pi E*)``):
    ``R = int S(x h / a) w(x) dx / int w(x) dx`` with ``w = (2 J1(x) / x)^2``, x = q a
    (the disk's load spectrum weighted by the layer's compliance). R -> 1 for a << h and
    falls as the contact outgrows the thickness (the nearly incompressible layer is
    squeezed only near the contact's edge).
    """
    log_rho = np.linspace(math.log(1e-3), math.log(1e3), 121)  # contacts from h/1000 to 1000 h
    # Midpoint rule, step 0.01 (J1's period is 2 pi); w falls as 8 / (pi x^3), so the part
    # beyond x = 80 is 1e-4 of the integral.
    x = (np.arange(8000) + 0.5) * 0.01
    w = (2.0 * j1(x) / x) ** 2
    r = np.array([float(layer_factor(x / math.exp(lr), nu) @ w) for lr in log_rho]) / float(w.sum())
    return log_rho, r


def disk_layer_factor(rho: np.ndarray, nu: float) -> np.ndarray:
    """R(a / h): the bonded layer's mean compliance under a uniformly loaded disk relative to
    the half-space's (1 for a << h), float64, same shape as ``rho``."""
    log_rho, r = _disk_layer_table(float(nu))
    return np.interp(np.log(np.maximum(np.asarray(rho, dtype=np.float64), 1e-300)), log_rho, r)


@functools.lru_cache(maxsize=1)
def _pasternak_disk_table() -> tuple[np.ndarray, np.ndarray]:
    """log(a / l) and 1 - 2 I1(a/l) K1(a/l) on a grid from a = l / 400 to 400 l."""
    la = np.linspace(-6.0, 6.0, 193)  # steps of 1/16 in log: linear interpolation < 1e-3 off
    alpha = np.exp(la)
    return la, 1.0 - 2.0 * ive(1, alpha) * kve(1, alpha)  # exp(a) exp(-a) cancel: no overflow


def _support_disk_stiffness(ks: float, area_app: np.ndarray, ell: float | None) -> np.ndarray:
    """Mean stiffness (MPa/mm) of a Pasternak support of shear length ``ell`` under a uniform
    load on a disk of area ``area_app``: ``ks / (1 - 2 I1(a/l) K1(a/l))`` (``ks`` for a
    Winkler support or a disk much wider than l; stiffer for a small one, whose load the
    yarns spread beyond it)."""
    area_app = np.asarray(area_app, dtype=np.float64)
    if not ell:
        return np.full(area_app.shape, ks)
    la, share = _pasternak_disk_table()
    x = np.log(np.maximum(np.sqrt(area_app / math.pi) / ell, 1e-300))
    s = np.interp(x, la, share)
    s = np.where(x > la[-1], 1.0 - np.exp(-x), s)  # wide disks: 2 I1 K1 -> l / a
    return ks / np.maximum(s, 1e-12)


def _law_stiffness(area_app: np.ndarray, gel, ks: float | None, ell: float | None = None,
                   ratio: float = 1.0) -> np.ndarray:
    """Pyramid-model force per penetration volume, N/mm^3, for apparent contact area (mm^2).

    The law holds for the volume under the pyramid's gel surface, ``ratio`` times the
    penetration volume. A support (``ks`` MPa/mm, shear length ``ell`` mm) acts in series.
    """
    law = imprint_law()
    estar = effective_modulus_mpa(gel)
    area_app = np.asarray(area_app, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.sqrt(area_app / math.pi)
        r = disk_layer_factor(law.layer_kappa * a / gel.thickness_mm, gel.poisson_ratio)
        kg = np.where(area_app > 0, ratio * law.force_coef * estar / (np.sqrt(np.maximum(area_app, 1e-300))
                                                                      * r ** law.layer_exponent), 0.0)
        if ks:
            kse = _support_disk_stiffness(ks, area_app, ell)
            kg = np.where(kg > 0, kg * kse / (kg + kse), 0.0)
    return kg


class _LawSamples:
    """Penetration statistics of a protrusion for the pyramid law.

    ``v`` = P_max - P (mm) on the work grid. The law needs, for each approach delta, the
    penetration volume V (mm^3) and the *apparent* contact area A (mm^2): the area the
    loaded region spans, not the sum of the touching spots. A textured object (a fabric)
    touches only on its crowns, yet the gel feels the load spread over the whole patch:
    the layer's stiffening (R) and the 1/sqrt(A) depend on that extent. A is taken from the
    protrusion's grey-scale closing over a square of ``apparent_cell_per_thickness`` gel
    thicknesses: valleys narrower than that (the gel spans them) are filled to the crowns'
    level, while a smooth convex object is left as it is.
    """

    def __init__(self, v: np.ndarray, dx: float, gel, vmax: float):
        law = imprint_law()
        probe = 4  # count candidates on every 4th pixel first: 1/16 of the work
        n = int(np.count_nonzero(v[::probe, ::probe] < vmax)) * probe * probe
        stride = max(1, int(math.sqrt(n / 40000.0)))  # ~40k samples fix A and V within ~0.5%
        vs = np.ascontiguousarray(v[::stride, ::stride], dtype=np.float32)
        cell = int(round(law.apparent_cell_per_thickness * gel.thickness_mm / (dx * stride)))
        cell = min(cell, 2 * max(vs.shape) + 1)  # wider than the frame changes nothing
        self.cell_area = dx * dx * stride * stride
        # Closing of P = opening of v (v = P_max - P): erode v (the crowns' reach) then dilate.
        va = vs if cell < 2 else cv2.morphologyEx(vs, cv2.MORPH_OPEN, np.ones((cell, cell), np.uint8),
                                                  borderType=cv2.BORDER_REPLICATE)
        keep = vs < vmax
        self.v = vs[keep].astype(np.float64)
        self.va = va[va < vmax].astype(np.float64)
        self.vmax = vmax

    def curve(self, gel, ks, ell=None, ratio: float = 1.0, n_bins: int = 2048) -> tuple[np.ndarray, np.ndarray]:
        """(approach edges mm, law force N at each), force non-decreasing.

        Bins are vmax / 2048 wide: at most half a micrometre for the pads we simulate,
        far below any relief that shades."""
        vmax = self.vmax
        key = n_bins
        if getattr(self, "_hist", (None,))[0] != key:  # the histograms do not depend on the law
            edges = np.linspace(0.0, vmax, n_bins + 1)
            idx = np.minimum((self.v * (n_bins / vmax)).astype(np.int64), n_bins - 1)
            cnt = np.bincount(idx, minlength=n_bins).astype(np.float64)
            vsum = np.bincount(idx, weights=self.v, minlength=n_bins)
            ia = np.minimum((self.va * (n_bins / vmax)).astype(np.int64), n_bins - 1)
            app = np.bincount(ia, minlength=n_bins).astype(np.float64)
            c_cnt = np.concatenate([[0.0], np.cumsum(cnt)])
            c_v = np.concatenate([[0.0], np.cumsum(vsum)])
            c_app = np.concatenate([[0.0], np.cumsum(app)])
            vol = (edges * c_cnt - c_v) * self.cell_area
            self._hist = (key, edges, vol, c_app * self.cell_area, _law_stiffness(c_app * self.cell_area, gel, None))
        _, edges, vol, area_app, k1 = self._hist
        if not ks:  # the gel alone: force proportional to the volume ratio
            return edges, np.maximum.accumulate(k1 * (ratio * vol))
        f = _law_stiffness(area_app, gel, ks, ell, ratio) * vol
        return edges, np.maximum.accumulate(f)

    def at(self, delta: float) -> tuple[float, float]:
        """(penetration volume mm^3, apparent area mm^2) at approach ``delta`` (mm)."""
        m = self.v < delta
        return (float((delta - self.v[m]).sum()) * self.cell_area,
                float(np.count_nonzero(self.va < delta)) * self.cell_area)

    def force(self, delta: float, gel, ks, ell=None, ratio: float = 1.0) -> float:
        vol, app = self.at(delta)
        return float(_law_stiffness(np.array(app), gel, ks, ell, ratio) * vol)


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
          window: str = "touched", support_length_mm: float | None = None) -> Imprint:
    """Press an object into the gel.

    protrusion_mm: (H, W) protrusion map in mm at the profile's image resolution, or
        already at ``fidelity.imprint_scale`` times it (same field of view).
    force_n: normal force, N (0 = no contact); or depth_mm: approach past first touch, mm.
    support_stiffness_kpa_per_mm: Winkler stiffness under the object's surface (a fabric:
        compressive modulus / thickness), kPa/mm; None = rigid object.
    window: "touched" computes over the touched region only (default); "full" over the whole
        frame (for checking the former).
    support_length_mm: the support's shear length, mm (a fabric: about its thickness);
        None = ``support_length_mm`` of assets/imprint_law.toml; 0 = a Winkler support
        (each point on its own spring, which flattens texture of every scale alike).
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
    if support_length_mm is not None and not (math.isfinite(support_length_mm) and support_length_mm >= 0):
        raise GelsimError(f"support_length_mm = {support_length_mm} is negative or not finite; give a length "
                          ">= 0 mm (about the fabric's thickness) or None")
    ell = imprint_law().support_length_mm if support_length_mm is None else float(support_length_mm)
    if fidelity.imprint_model == "elastic":
        out = _press_elastic(work, dx, gel, force_n, depth_mm, ks, window, ell)
    else:
        out = _press_pyramid(work, dx, gel, force_n, depth_mm, ks, window, ell)
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
    edges, f = _LawSamples(v, dx, gel, gel.max_indentation_mm).curve(gel, ks, None, _RATIO_GUESS)
    if force >= f[-1]:
        return gel.max_indentation_mm, True
    return float(np.interp(force, f, edges)), False


# Volume under the pyramid's surface over the penetration volume: about 2 for smooth
# objects at the fitted blur (a starting guess only; each press measures its own).
_RATIO_GUESS = 2.0
# Force control: stop refining the volume ratio once it moves by less than this (the
# approach then moves by about as much, well inside the law's own error).
_RATIO_TOL = 0.01


def _pyramid_window(work, v, delta, sigma_px, window):
    margin = int(math.ceil(3 * sigma_px))  # a Gaussian is < 1.2% of its peak beyond 3 sigma
    sl = _pen_window(work, v, delta, margin, window)
    if sl is None:
        return None
    # Align the window to the coarsest pyramid level so that its cells are the full
    # frame's cells: the touched-region result then equals the full-frame one.
    step = 2 ** max(0, int(math.floor(math.log2(max(sigma_px / _LEVEL_SIGMA, 1.0)))))
    r0, c0 = sl[0].start // step * step, sl[1].start // step * step
    r1 = min(work.shape[0], -(-sl[0].stop // step) * step)
    c1 = min(work.shape[1], -(-sl[1].stop // step) * step)
    return slice(r0, r1), slice(c0, c1)


def _pyramid_surface(vw, delta, dx, gel, samples, support, ratio, sigma_px):
    """(penetration taken by the gel, gel surface before the membrane blur, volume ratio)
    on the window ``vw`` (= P_max - P, mm) at approach ``delta``; ``support`` = None or
    (ks MPa/mm, shear length mm, texture wavenumber 1/mm)."""
    pen = np.float32(delta) - vw
    np.maximum(pen, 0.0, out=pen)
    if support is not None:
        ks, ell, q = support
        app = np.array(samples.at(delta)[1])
        kg = float(_law_stiffness(app, gel, None, None, ratio))
        kse = float(_support_disk_stiffness(ks, app, ell))
        pen = _support_share(pen, kg, kse, ks, ell, q, dx, gel)
    skip = gel.membrane_smoothing_mm / dx >= _LEVEL_SIGMA
    d = _pyramid_spread(pen, sigma_px, skip_finest=skip)
    vp = float(cv2.sumElems(pen)[0])
    return pen, d, (float(cv2.sumElems(d)[0]) / vp if vp > 0 else ratio)


def _texture_wavenumber(v: np.ndarray, ell: float, dx: float) -> float:
    """Wavenumber (1/mm) of the protrusion's texture finer than ``ell``: RMS slope over RMS
    height of the protrusion minus its blur over ``ell`` (exact for a sinusoid), from about
    128 x 128 samples; at least 1 / ell."""
    step = max(1, min(v.shape) // 128)
    vs = np.ascontiguousarray(v[::step, ::step], dtype=np.float32)
    high = vs - _coarse_blur(vs, ell / (dx * step))
    gy, gx = np.gradient(high.astype(np.float64))
    h_rms = float(np.sqrt(np.mean(high.astype(np.float64) ** 2)))
    s_rms = float(np.sqrt(np.mean(gx * gx + gy * gy))) / (dx * step)
    return max(s_rms / h_rms if h_rms > 0 else 0.0, 1.0 / ell)


def _press_pyramid(work, dx, gel, force_n, depth_mm, ks, window, support_len=None):
    law = imprint_law()
    pmax = float(work.max())
    v = pmax - work
    bottomed = False
    vmax = gel.max_indentation_mm
    samples = _LawSamples(v, dx, gel, vmax)
    sigma_px = law.pyramid_sigma_per_thickness * gel.thickness_mm / dx
    ratio = _RATIO_GUESS
    support = None
    if ks:
        ell = imprint_law().support_length_mm if support_len is None else support_len
        support = (ks, ell, _texture_wavenumber(v, ell, dx) if ell > 0.5 * dx else 0.0)

    def delta_for(r):
        edges, f = samples.curve(gel, ks, support_len, r)
        if force_n >= f[-1]:
            return vmax, True
        return float(np.interp(force_n, f, edges)), False

    if force_n is not None:
        delta, bottomed = delta_for(ratio)
    else:
        delta = float(depth_mm)
        if delta >= vmax:
            delta, bottomed = vmax, True
    # The law holds for the volume under the gel surface, which the pyramid gives (and a
    # support's share of the penetration depends on it): settle its ratio to the
    # penetration volume on every other pixel (a quarter of the work), then make the one
    # full-resolution pass that is the result.
    coarse = False
    if force_n is not None or support is not None:
        for _ in range(2):  # the ratio moves by a few % after the first
            sl = _pyramid_window(work, v, delta, sigma_px, window)
            if sl is None or delta <= 0 or min(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start) < 64:
                break
            _, _, new_ratio = _pyramid_surface(v[sl][::2, ::2], delta, 2 * dx, gel, samples, support,
                                               ratio, sigma_px / 2)
            coarse, settled, ratio = True, abs(new_ratio / ratio - 1.0) < _RATIO_TOL, new_ratio
            if force_n is not None:
                delta, bottomed = delta_for(ratio)
            if settled:
                break
    for it in range(1 if coarse else 4):  # small windows: settle at full resolution
        sl = _pyramid_window(work, v, delta, sigma_px, window)
        if sl is None or delta <= 0:
            return np.zeros(work.shape, np.float32), np.zeros(work.shape, bool), 0.0, 0.0, False
        pen, d, new_ratio = _pyramid_surface(v[sl], delta, dx, gel, samples, support, ratio, sigma_px)
        settled = abs(new_ratio / ratio - 1.0) < _RATIO_TOL
        if coarse or settled or it == 3 or (force_n is None and support is None):
            ratio = ratio if coarse and force_n is not None else new_ratio
            break
        ratio = new_ratio
        if force_n is not None:
            delta, bottomed = delta_for(ratio)
    if force_n is not None and not bottomed:
        force = float(force_n)
    else:
        force = samples.force(delta, gel, ks, support_len, ratio)
    # In contact: the gel surface rests on the object (the pyramid's last clamp holds) and
    # the object reaches past contact_fraction of the approach (the fitted contact radius
    # of smooth objects; a texture's valleys, where the gel spans from crown to crown, are out).
    m = (pen >= d) & (pen >= np.float32(law.contact_fraction * float(pen.max())))
    d = _membrane_blur(d, gel.membrane_smoothing_mm / dx)
    if d.shape == work.shape:
        return d, m, delta, force, bottomed
    depth = np.zeros(work.shape, np.float32)
    mask = np.zeros(work.shape, bool)
    depth[sl] = d
    mask[sl] = m
    return depth, mask, delta, force, bottomed


def _support_share(pen, kg, kse, ks, ell, q, dx, gel) -> np.ndarray:
    """The gel's share of the penetration when the object rests on a fabric support.

    Springs in series at the contact's scale: the gel takes ``kse / (kg + kse)`` of the
    large-scale penetration (``kse``: the support's stiffness over the apparent contact).
    A Pasternak support of shear length ``l`` is stiffer by ``1 + (q l)^2`` at wavenumber
    q, so the texture (the penetration minus its blur over ``l``) is shared at the
    texture's wavenumber ``q`` instead: gel stiffness ``E* q / 2`` against
    ``ks (1 + (q l)^2)``. A Winkler support (l below half a pixel) shares every scale alike.
    """
    scale_l = kse / (kg + kse)
    if ell <= 0.5 * dx:
        return pen * np.float32(scale_l)
    kg_t = effective_modulus_mpa(gel) * q / 2.0
    ks_t = ks * (1.0 + (q * ell) ** 2)
    scale_t = ks_t / (kg_t + ks_t)
    low = _coarse_blur(pen, ell / dx)
    out = pen * np.float32(scale_t)  # = low * scale_l + (pen - low) * scale_t
    low *= np.float32(scale_l - scale_t)
    out += low
    np.maximum(out, 0.0, out=out)
    return out


def _coarse_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of ``sigma_px`` computed on a grid about sigma/2 coarser (then
    bilinear back): a wide blur at the cost of a small one."""
    f = max(1, int(sigma_px // 2))
    if f == 1:
        return cv2.GaussianBlur(img, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    small = cv2.resize(img, ((img.shape[1] + f - 1) // f, (img.shape[0] + f - 1) // f), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma_px / f, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)


def _press_elastic(work, dx, gel, force_n, depth_mm, ks, window, support_len=None):
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
            op = _Operator((sl[0].stop - sl[0].start, sl[1].stop - sl[1].start), dx, gel, cs, support_len)
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
        op = _Operator((sl[0].stop - sl[0].start, sl[1].stop - sl[1].start), dx, gel, cs, support_len)
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


def _broad_cases(profile, forces=(0.5, 2.0)):
    """Contacts much wider than the gel is thick: the whole pad on a plane and on gentle
    domes (radius 60 and 300 mm), as when a fabric lies over the pad: (name, protrusion, force N)."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    y = (np.arange(h) - (h - 1) / 2)[:, None] * mm
    x = (np.arange(w) - (w - 1) / 2)[None, :] * mm
    out = [(f"plane (whole pad)", np.zeros((h, w), np.float32), f) for f in forces]
    for r in (60.0, 300.0):
        dome = (-(x * x + y * y) / (2 * r)).astype(np.float32)
        out += [(f"dome R {r:g} mm", dome - dome.min(), f) for f in forces]
    return out


def fit_pyramid_law(profile=None, resolution_px: int = 480) -> dict[str, Any]:
    """Fit the pyramid model's constants to the elastic model; returns them with residuals.

    c from spheres on a thick gel (20 mm: a half-space for these contacts); kappa and beta
    by least squares on log force from spheres on the profile's gel and from broad contacts
    (the whole pad on a plane and on gentle domes, at a quarter of the resolution: smooth
    shapes); the coarsest blur from the depth outside a sphere's contact. A cylinder on its
    side is reported as a check that took no part in the fit. A few minutes;
    ``benchmarks/bench_gel.py --fit`` writes the result to LAW_FILE.
    """
    from scipy.optimize import least_squares

    from . import indenters
    from .fidelity import get_fidelity
    from .sensor import load_profile

    base = (profile or load_profile("vitac")).with_resolution(resolution_px)
    broad = base.with_resolution(max(64, resolution_px // 2))
    elastic = dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0)
    law0 = imprint_law()
    dx = base.image.mm_per_px

    def surface_volume(prot, delta, prof, trial):
        # Volume under the pyramid's gel surface at approach delta (mm^3), and the apparent area.
        mm = prof.image.mm_per_px
        with _law_override(trial):
            depth, *_ = _press_pyramid(prot.astype(np.float32), mm, prof.gel, None, delta, None, "touched")
            app = _LawSamples(prot.max() - prot, mm, prof.gel, prof.gel.max_indentation_mm).at(delta)[1]
        return float(depth.sum(dtype=np.float64)) * mm * mm, app

    def law_force(vol, area, gel, c, kappa, beta):
        area = np.asarray(area, dtype=np.float64)
        r = disk_layer_factor(kappa * np.sqrt(area / math.pi) / gel.thickness_mm, gel.poisson_ratio)
        return c * effective_modulus_mpa(gel) * np.asarray(vol) / np.sqrt(area) / r ** beta

    thick = dataclasses.replace(base, gel=dataclasses.replace(base.gel, thickness_mm=20.0))
    runs, broad_runs, thick_runs = [], [], []
    for name, prot, f in _fit_cases(base):
        runs.append((name, prot, f, press(prot, base, elastic, force_n=f)))
    for name, prot, f in _broad_cases(broad):
        broad_runs.append((name, prot, f, press(prot, broad, elastic, force_n=f)))
    for name, prot, f in _fit_cases(thick, diameters=(4.0, 10.0), forces=(0.003, 0.03, 0.3)):
        thick_runs.append((name, prot, f, press(prot, thick, elastic, force_n=f)))
    # Coarsest blur first (the law's volume depends on it): depth outside the contact of a
    # mid-size sphere case, same approach.
    name, prot, f, im = runs[7]
    best = None
    for ratio in np.geomspace(0.05, 2.0, 25):
        trial = dataclasses.replace(law0, pyramid_sigma_per_thickness=float(ratio))
        depth_w, *_ = _press_pyramid_with(trial, prot, base, im.indentation_mm)
        err = float(np.sqrt(np.mean((depth_w - im.depth_mm)[~im.contact_mask] ** 2)))
        if best is None or err < best[1]:
            best = (float(ratio), err)
    law = dataclasses.replace(law0, pyramid_sigma_per_thickness=best[0])
    cs = []
    for _, prot, f, im in thick_runs:
        cs.append(f / float(law_force(*surface_volume(prot, im.indentation_mm, thick, law), thick.gel, 1.0, 1.0, 0.0)))
    c = float(np.exp(np.mean(np.log(cs))))
    rows = [(f, *surface_volume(prot, im.indentation_mm, base, law)) for _, prot, f, im in runs if not im.bottomed_out]
    rows += [(f, *surface_volume(prot, im.indentation_mm, broad, law)) for _, prot, f, im in broad_runs
             if not im.bottomed_out]
    rows = np.array(rows)

    def resid(x):
        return np.log(law_force(rows[:, 1], rows[:, 2], base.gel, c, math.exp(x[0]), x[1]) / rows[:, 0])

    sol = least_squares(resid, [0.0, 1.0])
    kappa, beta = float(math.exp(sol.x[0])), float(sol.x[1])
    law = dataclasses.replace(law, force_coef=c, layer_kappa=kappa, layer_exponent=beta)
    check = [(f"cylinder 4 mm x 6 mm (check)", indenters.cylinder(4.0, base, length_mm=6.0), f)
             for f in (0.01, 0.1)]
    res = []
    cases = ([(n, p, f, im, base) for n, p, f, im in runs]
             + [(n, p, f, im, broad) for n, p, f, im in broad_runs]
             + [(n, p, f, press(p, base, elastic, force_n=f), base) for n, p, f in check])
    for name, prot, f, im, prof in cases:
        with _law_override(law):
            d = _press_pyramid(prot.astype(np.float32), prof.image.mm_per_px, prof.gel, f, None, None,
                               "touched")[2]
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
    current = imprint_law()
    for k in ("apparent_cell_per_thickness", "support_length_mm"):  # chosen, not fitted
        law[k] = getattr(current, k)
    law["note"] = ("fitted by gelsim.gel.fit_pyramid_law: c on a 20 mm gel (half-space), kappa and beta on "
                   "spheres and broad contacts on the profile's gel, blur on the depth outside a sphere's contact; "
                   f"max |log F error| {values.get('force_resid_max')}, "
                   f"rms log contact-radius error {values.get('contact_radius_rms_log')}")
    header = ("Force law and smoothing of the pyramid imprint model (gelsim/gel.py), fitted to the\n"
              "elastic model. Regenerate: .venv/bin/python benchmarks/bench_gel.py --fit\n"
              "contact_fraction: 0.5 would be exact for Hertz (penetration d/2 at r = a); the fit matches the\n"
              "elastic layer's contact radii, which exceed Hertz's as the contact grows against the thickness.\n"
              "Chosen, not fitted: apparent_cell_per_thickness (valleys narrower than h/4 count as apparent\n"
              "contact: the gel spans them); support_length_mm (a fabric support's Pasternak shear length when\n"
              "the caller gives none: 0.5 mm, a typical cloth thickness; pass the fabric's own thickness).")
    text = dump_toml({"law": law}, header=header)
    tmp = f"{path}.tmp"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)
    imprint_law.cache_clear()
