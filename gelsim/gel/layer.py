"""The gel as an elastic layer: its surface Green's function and the contact solver.

The gel is an elastic layer of thickness ``h`` (Young's modulus E, Poisson's ratio nu)
bonded to a rigid base. Its surface displacement under a normal pressure is
``u = K * p`` with ``K`` the layer's surface Green's function: the Boussinesq half-space
part integrated exactly over each pixel (Love 1929) plus a smooth finite-thickness
correction from the layer's Fourier compliance ``U(q) = 2 (1 - nu^2) / (E q) * S(q h)``,
``S(x) = ((3-4nu) sinh 2x - 2x) / ((3-4nu) cosh 2x + 2x^2 + (1 + (3-4nu)^2) / 2)``
(frictionless top, bonded base; ``S -> 1`` gives the half-space, ``S ~ x (1-2nu) /
(2 (1-nu)^2)`` the uniaxial-strain limit of a thin layer). Convolutions are linear
(zero-padded FFT).

The contact problem (``p >= 0``, gap ``>= 0``, ``p * gap = 0``, total force or approach
prescribed) is solved by the constrained conjugate-gradient method of Polonsky and Keer
(Wear 1999), :func:`pk_solve`. It is used at full resolution by the reference imprint
(:mod:`gelsim.gel.elastic`) and on a coarse grid of the object's envelope by the two-scale
imprint (:mod:`gelsim.gel.twoscale`).

Units: lengths in mm, pressures in MPa (= N/mm^2), forces in N.
"""
from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from scipy.special import j0, j1, k0, k1

# Polonsky-Keer stopping rule: relative change of the pressure field (L1) per iteration.
# 1e-6 puts the solver's error well below the pixel discretisation error (about 1% on a
# contact radius of 10 px).
CG_TOL = 1e-6
CG_MAXIT = 2000
# Beyond x = q h = 20 the layer factor S differs from 1 by < 1e-15 (terms in exp(-2x)).
_S_X_MAX = 20.0


def effective_modulus_mpa(gel) -> float:
    """E* = E / (1 - nu^2) of the gel against a rigid object, MPa."""
    return gel.young_modulus_mpa / (1.0 - gel.poisson_ratio ** 2)


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
def layer_correction_table(nu: float, rho_max: float) -> tuple[np.ndarray, np.ndarray]:
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


def love_influence(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Antiderivative F with d2F/dxdy = 1/r (Love 1929), finite on the axes."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ax, ay = np.abs(x), np.abs(y)
        t1 = np.where(ax > 0, x * np.arcsinh(y / np.where(ax > 0, ax, 1.0)), 0.0)
        t2 = np.where(ay > 0, y * np.arcsinh(x / np.where(ay > 0, ay, 1.0)), 0.0)
    return t1 + t2


def wrapped_offsets(n: int, m: int, dx: float) -> np.ndarray:
    """Signed offsets (mm) of a zero-padded length-m grid (m >= 2n - 1), wrapped so that the circular
    convolution of a length-n signal is linear: entries 0..n-1 are offsets 0..n-1, the last n - 1
    entries offsets -(n-1)..-1 (the ones between are never reached)."""
    i = np.arange(m)
    return np.where(i < n, i, i - m) * dx


def padded_size(n: int) -> int:
    """Length of the zero-padded grid for a linear convolution of length-n signals: 2n as before
    when that is a fast DFT size (n = 48, 64: 96, 128), else OpenCV's next fast size >= 2n - 1
    (its DFT of a length with a large prime factor costs O(n p))."""
    m = 2 * n
    return m if cv2.getOptimalDFTSize(m) == m else cv2.getOptimalDFTSize(2 * n - 1)


@functools.lru_cache(maxsize=32)
def kernel_spectrum(ny: int, nx: int, dx: float, e_mpa: float, nu: float, h_mm: float) -> np.ndarray:
    """OpenCV's packed real DFT (CCS, float64, read-only) of the layer's influence coefficients on the
    zero-padded (padded_size(ny), padded_size(nx)) grid.

    Coefficient (i, j): displacement (mm) at a pixel centre per unit pressure (MPa) on a
    pixel (i, j) away.
    """
    y, x = np.meshgrid(wrapped_offsets(ny, padded_size(ny), dx), wrapped_offsets(nx, padded_size(nx), dx), indexing="ij")
    a = dx / 2
    love = love_influence(x + a, y + a) - love_influence(x + a, y - a) - love_influence(x - a, y + a) + love_influence(x - a, y - a)
    r = np.hypot(x, y)
    # The farthest offset the (2 ny, 2 nx) grid held (n dx each way), whatever the padded size: the
    # same correction table, so the same coefficients.
    rho_needed = float(np.hypot(ny * dx, nx * dx) / h_mm) * 1.01 + 1e-6
    rho_max = 2.0 ** math.ceil(math.log2(max(rho_needed, 1.0)))  # fewer distinct tables to cache
    rho, g = layer_correction_table(nu, rho_max)
    corr = np.interp(r / h_mm, rho, g) / h_mm * dx * dx
    k = (1.0 - nu * nu) / (math.pi * e_mpa) * (love + corr)
    return _readonly(cv2.dft(k))


@functools.lru_cache(maxsize=32)
def support_kernel_spectrum(ny: int, nx: int, dx: float, ell: float) -> np.ndarray:
    """OpenCV's packed real DFT (CCS, float64, read-only) of a Pasternak support's influence
    coefficients (unit stiffness) on the zero-padded (padded_size(ny), padded_size(nx)) grid.

    A Pasternak layer ``k w - k l^2 lap w = p`` spreads a point load as
    ``K0(r / l) / (2 pi l^2 k)``: coefficient (i, j) is that at the pixel offset times the
    pixel area, the centre the exact integral over a disk of one pixel's area
    (``1 - X K1(X)``, X = dx / (sqrt(pi) l)). The weights sum to 1 (uniform load: w = p / k).
    """
    r = np.hypot(wrapped_offsets(ny, padded_size(ny), dx)[:, None], wrapped_offsets(nx, padded_size(nx), dx)[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(r > 0, k0(np.maximum(r, 1e-300) / ell), 0.0) * (dx * dx / (2 * math.pi * ell * ell))
    x0 = dx / (math.sqrt(math.pi) * ell)
    c[0, 0] = 1.0 - x0 * float(k1(x0))
    return _readonly(cv2.dft(c))


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False  # shared through the caches
    return a


class Operator:
    """u = K * p on an (ny, nx) window of cell size ``dx`` mm, plus what lies under the object.

    ``support_compliance`` = 1 / k_s (mm/MPa) of a layer under the object (0: rigid) and
    ``support_len`` (mm) its Pasternak shear length (0 or None: a Winkler layer, ``p / k_s``
    point by point); ``winkler_compliance`` (mm/MPa) adds a pointwise layer on top of it (a
    fabric's yarn crowns). ``__call__`` gives the total closure (gel + supports), :meth:`gel`
    the gel's displacement alone.

    The convolutions are zero-padded real DFTs by OpenCV (packed CCS spectra, ``cv2.mulSpectrums``):
    on the macro solve's 48x64 grid one costs about 2/3 of scipy.fft's rfft2/irfft2 pair, most of
    the difference being the latter's per-call Python overhead. The pointwise (Winkler) compliance
    is a kernel of weight ``cw`` at offset 0, a constant ``cw`` in the spectrum, and the inverse
    DFT's 1 / (my mx) is folded into the spectra too: a call is one DFT, one product, one inverse.
    An operator keeps its zero-padded input buffer: use one from one thread at a time.
    """

    def __init__(self, shape: tuple[int, int], dx: float, gel, support_compliance: float = 0.0,
                 support_len: float | None = None, winkler_compliance: float = 0.0, dtype=np.float64):
        self.dtype = np.dtype(dtype).type
        self.ny, self.nx = shape
        self.s = (padded_size(self.ny), padded_size(self.nx))
        # Single precision: half the DFT cost, ample for a 1e-3 solve.
        self.kf_gel = _scaled(kernel_spectrum, (self.ny, self.nx, float(dx), float(gel.young_modulus_mpa),
                                                float(gel.poisson_ratio), float(gel.thickness_mm)), self.dtype)
        self.kf = self.kf_gel
        cs = float(support_compliance)
        self.pasternak = bool(cs) and support_len is not None and support_len > 0.5 * dx
        if self.pasternak:  # (the packed spectra are linear in the coefficients: they add)
            sup = _scaled(support_kernel_spectrum, (self.ny, self.nx, float(dx), float(support_len)), self.dtype)
            self.kf = cv2.scaleAdd(sup, cs, self.kf)
        self.cw = float(winkler_compliance) + (0.0 if self.pasternak else cs)
        if self.cw:
            self.kf = cv2.scaleAdd(_scaled(_unit_spectrum, self.s, self.dtype), self.cw, self.kf)
        self._buf = np.zeros(self.s, self.dtype)  # zero beyond the (ny, nx) corner, which each call fills

    def _conv(self, p: np.ndarray, kf: np.ndarray) -> np.ndarray:
        """(ny, nx) view of a fresh (padded) array: K * p for the scaled packed spectrum ``kf``."""
        self._buf[: self.ny, : self.nx] = p
        spec = cv2.dft(self._buf)
        cv2.mulSpectrums(spec, kf, 0, spec)
        return cv2.idft(spec, flags=cv2.DFT_REAL_OUTPUT)[: self.ny, : self.nx]

    def gel(self, p: np.ndarray) -> np.ndarray:
        """The gel's surface displacement (mm) under ``p`` (MPa)."""
        return self._conv(p, self.kf_gel)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """The total closure (mm: gel, cloth and yarn crowns) under ``p`` (MPa)."""
        return self._conv(p, self.kf)


@functools.lru_cache(maxsize=32)
def _unit_spectrum(my: int, mx: int) -> np.ndarray:
    """Packed DFT of a unit impulse at offset 0 on an (my, mx) grid (1 in every real part), float64."""
    e = np.zeros((my, mx))
    e[0, 0] = 1.0
    return _readonly(cv2.dft(e))


@functools.lru_cache(maxsize=64)
def _scaled(spectrum, args: tuple, dtype) -> np.ndarray:
    """``spectrum(*args)`` times the unscaled inverse DFT's 1 / (my mx), in ``dtype``, read-only (cached:
    an operator is built a few times per frame, each for a new cloth stiffness on the same grid)."""
    s = spectrum(*args)
    return _readonly((s * (1.0 / s.size)).astype(dtype))


def pk_solve(op: Operator, h: np.ndarray, area: float, *, force: float | None = None,
             delta: float | None = None, p0: np.ndarray, tol: float = CG_TOL,
             maxit: int = CG_MAXIT) -> tuple[np.ndarray, float, int]:
    """Polonsky-Keer constrained conjugate gradients.

    h: object surface relative to its first touch (P - P_max, mm, <= 0), (ny, nx).
    area: cell area, mm^2. Force control (``force``, N) or approach control (``delta``, mm).
    p0: initial pressure (MPa), e.g. the previous frame's. tol: stop when the pressure
    changes by less than this (relative L1) in one iteration.
    Returns (pressure MPa, approach mm, iterations). The arithmetic is in the operator's dtype
    (the contact set enters as a 0/1 mask: no gathers on the small grids this runs on).
    """
    dtype = getattr(op, "dtype", np.float64)
    force_ctl = force is not None
    target = (h if force_ctl else h + delta).astype(dtype, copy=False)
    p = p0.astype(dtype, copy=True)
    if force_ctl:
        s = float(p.sum())
        if s <= 0:
            p = (h >= h.max() - 1e-12).astype(dtype)
            s = float(p.sum())
        p *= dtype(force / (area * s))
    t = np.zeros_like(p)
    icf = np.empty_like(p)
    p_old = np.empty_like(p)
    g_old, d = 1.0, 0.0
    it = 0
    for it in range(1, maxit + 1):
        np.greater(p, 0, out=icf)
        n = float(icf.sum())
        if n == 0:
            break
        g = op(p) - target
        if force_ctl:
            g -= dtype(float(np.vdot(g, icf)) / n)
        gm = g * icf
        gg = float(np.vdot(gm, gm))
        if d:  # t = gm + beta t, t kept on the contact
            t *= icf
            t = cv2.scaleAdd(t, d * gg / g_old, gm)
        else:  # (a restart: beta = 0)
            t = gm.copy()
        g_old = max(gg, 1e-300)
        r = op(t)
        if force_ctl:
            r = r - dtype(float(np.vdot(r, icf)) / n)
        den = float(np.vdot(r, t))  # t is zero off the contact
        if den == 0.0:
            # The current contact set is solved exactly (e.g. a few cells of equal height with the
            # uniform start): let the cells that overlap the object join, or stop if none do.
            iol = (p == 0) & (g < 0)
            if not iol.any():
                break
            p = np.where(iol, dtype(float(p.sum()) / n), p)
            if force_ctl:
                p *= dtype(force / (area * float(p.sum())))
            t[:] = 0
            d = 0.0
            continue
        tau = float(np.vdot(g, t)) / den
        np.copyto(p_old, p)
        cv2.scaleAdd(t, -tau, p, dst=p)
        np.maximum(p, 0, out=p)
        iol = g < 0
        iol &= p == 0
        grew = bool(iol.any())
        if grew:
            d = 0.0
            np.subtract(p, dtype(tau) * g, out=p, where=iol)
        else:
            d = 1.0
        s = float(p.sum())
        if s <= 0:
            break
        if force_ctl:
            p *= dtype(force / (area * s))
            s = force / area
        # Converged when the pressure no longer moves and no overlapping cell joined the contact this
        # step (a small first contact set can otherwise "converge" after one tiny step).
        if cv2.norm(p, p_old, cv2.NORM_L1) / s < tol and not grew:
            break
    p = p.astype(np.float64)
    if force_ctl:
        ic = p > 0
        u = op(p) - h
        delta = float(u[ic].mean()) if ic.any() else 0.0
    return p, float(delta), it


# --------------------------------------------------------------------------------------
# Mean compliance of the layer under a uniformly loaded disk
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
