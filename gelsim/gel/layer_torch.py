"""The gel layer's operator and Polonsky-Keer's solve in torch, for a batch of coarse grids (the twin of
:mod:`gelsim.gel.layer`: :func:`gelsim.gel.layer.kernel_spectrum`, :class:`gelsim.gel.layer.Operator`,
:func:`gelsim.gel.layer.pk_solve`).

Each frame has its own coarse grid (its cell size, its grid's shape); the batch's grids share one array of the
largest shape, each frame's in its top-left corner and a ``valid`` mask over it. The layer's operator is a linear
convolution: one zero-padded FFT grid of at least twice the largest shape serves every frame, each with its own
kernel (its cell size, its cloth's stiffness), so a frame's convolution is the numpy path's, up to rounding.
Polonsky-Keer's conjugate gradients (:func:`pk_solve`) run every frame of the batch in step, each stopping by the
numpy path's own rule (a frame that has stopped is carried unchanged). Parity with the numpy kernels:
``tests/gelsim/test_gel_kernels.py``.
"""
from __future__ import annotations

import functools
import math

import numpy as np
from scipy.special import k0, k1

from .. import batch_ops as ops
from .layer import layer_correction_table, love_influence, padded_size, wrapped_offsets


# ---------------------------------------------------------------- kernels on a common grid

def rho_max(ny: int, nx: int, dx: float, h_mm: float) -> float:
    """The layer-correction table's range for an (ny, nx) grid of ``dx`` mm cells, as
    :func:`gelsim.gel.layer.kernel_spectrum` takes it for that grid."""
    rho_needed = float(np.hypot(ny * dx, nx * dx) / h_mm) * 1.01 + 1e-6
    return 2.0 ** math.ceil(math.log2(max(rho_needed, 1.0)))


@functools.lru_cache(maxsize=256)
def layer_coefficients(n: tuple[int, int], m: tuple[int, int], dx: float, e_mpa: float, nu: float, h_mm: float,
                       rho: float) -> np.ndarray:
    """The layer's influence coefficients (:func:`gelsim.gel.layer.kernel_spectrum`'s, mm per MPa) at the
    wrapped offsets of signals up to ``n`` (ny, nx) cells on a zero-padded ``m`` grid, float64 (read-only)."""
    y, x = np.meshgrid(wrapped_offsets(n[0], m[0], dx), wrapped_offsets(n[1], m[1], dx), indexing="ij")
    a = dx / 2
    love = love_influence(x + a, y + a) - love_influence(x + a, y - a) - love_influence(x - a, y + a) + love_influence(x - a, y - a)
    r = np.hypot(x, y)
    rr, g = layer_correction_table(nu, rho)
    corr = np.interp(r / h_mm, rr, g) / h_mm * dx * dx
    k = (1.0 - nu * nu) / (math.pi * e_mpa) * (love + corr)
    k.flags.writeable = False
    return k


@functools.lru_cache(maxsize=256)
def pasternak_coefficients(n: tuple[int, int], m: tuple[int, int], dx: float, ell: float) -> np.ndarray:
    """A Pasternak support's coefficients (unit stiffness; :func:`gelsim.gel.layer.support_kernel_spectrum`'s)
    on the grid of :func:`layer_coefficients`, float64 (read-only)."""
    r = np.hypot(wrapped_offsets(n[0], m[0], dx)[:, None], wrapped_offsets(n[1], m[1], dx)[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(r > 0, k0(np.maximum(r, 1e-300) / ell), 0.0) * (dx * dx / (2 * math.pi * ell * ell))
    x0 = dx / (math.sqrt(math.pi) * ell)
    c[0, 0] = 1.0 - x0 * float(k1(x0))
    c.flags.writeable = False
    return c


_SPECTRA: dict = {}


def _spectrum(kind: str, args: tuple, device):
    """The rfft2 of a cached coefficient array (``kind`` "layer" or "pasternak"), complex64 on ``device``
    (cached: a batch's frames mostly share their cell size)."""
    torch = ops.torch_module()
    key = (kind, args, str(device))
    s = _SPECTRA.get(key)
    if s is None:
        coef = layer_coefficients(*args) if kind == "layer" else pasternak_coefficients(*args)
        s = torch.as_tensor(np.fft.rfft2(coef), device=device).to(torch.complex64)
        if len(_SPECTRA) > 512:
            _SPECTRA.clear()
        _SPECTRA[key] = s
    return s


class BatchOperator:
    """``u = K_b * p_b`` for every frame b of a batch of ``(B, cy, cx)`` grids (each frame's data in the
    top-left corner of the batch's shape ``shape``): one zero-padded real FFT on an ``m`` grid, each frame's
    own spectrum ``kf`` (complex64 ``(B, m0, m1 // 2 + 1)``)."""

    def __init__(self, kf, shape: tuple[int, int], m: tuple[int, int]):
        self.kf, self.shape, self.m = kf, shape, m

    def __call__(self, p):
        torch = ops.torch_module()
        spec = torch.fft.rfft2(p, s=self.m)
        return torch.fft.irfft2(spec * self.kf, s=self.m)[:, :self.shape[0], :self.shape[1]]


def grid_for(shape: tuple[int, int]) -> tuple[int, int]:
    """The zero-padded FFT grid for linear convolutions of signals up to ``shape``."""
    return padded_size(shape[0]), padded_size(shape[1])


def gel_operator(cells: list[tuple[int, int]], dx: list[float], gel, shape: tuple[int, int], device) -> BatchOperator:
    """The bare layer's operator for frames whose grids are ``cells[b]`` (ny, nx) cells of ``dx[b]`` mm, in a
    batch array of ``shape``."""
    torch = ops.torch_module()
    m = grid_for(shape)
    e, nu, h = float(gel.young_modulus_mpa), float(gel.poisson_ratio), float(gel.thickness_mm)
    kf = torch.stack([_spectrum("layer", (shape, m, float(d), e, nu, h, rho_max(c[0], c[1], float(d), h)), device)
                      for c, d in zip(cells, dx)])
    return BatchOperator(kf, shape, m)


def cloth_operator(cells, dx, gel, supports, ks, shape, device) -> BatchOperator:
    """:func:`gelsim.gel.twoscale.cloth_operator` for each frame: the layer with the cloth ``supports[b]``
    (None: rigid) in series at its secant stiffness ``ks[b]`` (kPa/mm, inf: none) and the yarn crowns'
    Winkler compliance."""
    base = gel_operator(cells, dx, gel, shape, device)
    m = base.m
    extra = []
    any_support = False
    for b, sup in enumerate(supports):
        if sup is None:
            extra.append(None)
            continue
        any_support = True
        d = float(dx[b])
        cs = 1e3 / ks[b] if math.isfinite(ks[b]) else 0.0
        ell = sup.shear_length_mm
        pasternak = bool(cs) and ell is not None and ell > 0.5 * d
        cw = 1.0 / sup.yarn_stiffness_mpa_per_mm + (0.0 if pasternak else cs)
        extra.append((pasternak, cs, ell, cw))
    if not any_support:
        return base
    torch = ops.torch_module()
    dev = base.kf.device
    cs = torch.as_tensor([x[1] if x is not None and x[0] else 0.0 for x in extra], device=dev, dtype=torch.float32)
    cw = torch.as_tensor([x[3] if x is not None else 0.0 for x in extra], device=dev, dtype=torch.float32)
    kf = base.kf + cw[:, None, None]
    past = [b for b, x in enumerate(extra) if x is not None and x[0]]
    if past:
        zero = torch.zeros_like(base.kf[0])
        kp = torch.stack([_spectrum("pasternak", (shape, m, float(dx[b]), float(extra[b][2])), dev)
                          if (extra[b] is not None and extra[b][0]) else zero for b in range(len(extra))])
        kf = kf + cs[:, None, None] * kp
    return BatchOperator(kf, shape, m)


# ---------------------------------------------------------------- Polonsky-Keer, batched

def _sum(x):
    """Each frame's sum of ``(B, h, w)`` ``x``, accumulated in float64: ``(B,)`` float64."""
    return x.sum(dim=(1, 2), dtype=ops.torch_module().float64)


# How often (iterations) the batched solve asks the device whether every frame has stopped: each question waits
# for the device's queue to drain; a frame that has stopped is carried unchanged meanwhile, so asking less often
# costs only a few idle iterations.
CHECK_EVERY = {"cpu": 1, "cuda": 4}


def pk_solve(op: BatchOperator, h, valid, area, *, force=None, delta=None, p0, tol: float, maxit: int):
    """:func:`gelsim.gel.layer.pk_solve` in single precision for every frame of the batch, in step: each frame
    stops by the numpy path's rule and is carried unchanged after.

    h: float64 ``(B, cy, cx)`` object surface below its top, mm (any value off ``valid``); valid: bool, the
    frame's own grid; area: float64 ``(B,)`` cell area mm^2; ``force`` (N) or ``delta`` (mm): float64 ``(B,)``;
    p0: the start, MPa. Returns (pressure float32 MPa, approach float64 mm (B,) -- ``delta`` under approach
    control). (Dot products: float32 products summed in float64.)"""
    torch = ops.torch_module()
    force_ctl = force is not None
    target = (h if force_ctl else h + delta[:, None, None]).float()
    p = torch.where(valid, p0, 0.0).float()
    if force_ctl:
        s = _sum(p)
        empty = s <= 0
        if bool(empty.any()):
            hmax = torch.where(valid, h, -math.inf).amax(dim=(1, 2))
            top = ((h >= (hmax - 1e-12)[:, None, None]) & valid).float()
            p = torch.where(empty[:, None, None], top, p)
            s = _sum(p)
        p = p * (force / (area * s)).float()[:, None, None]
    b = p.shape[0]
    t = torch.zeros_like(p)
    g_old = torch.ones(b, dtype=torch.float64, device=p.device)
    conj = torch.zeros(b, dtype=torch.bool, device=p.device)          # d: the last step kept the contact set
    done = torch.zeros(b, dtype=torch.bool, device=p.device)
    every = CHECK_EVERY.get(p.device.type, 1)
    for it in range(maxit):
        icf = (p > 0) & valid
        icf_f = icf.float()
        n = _sum(icf_f)
        done = done | (n == 0)
        act = ~done
        if it % every == 0 and not bool(act.any()):
            break
        nn = torch.where(n > 0, n, 1.0)
        g = op(p) - target
        if force_ctl:
            g = g - (_sum(g * icf_f) / nn).float()[:, None, None]
        gm = g * icf_f
        gg = _sum(gm * gm)
        beta = (gg / g_old).float()[:, None, None]
        t = torch.where(conj[:, None, None], (t * icf_f) * beta + gm, gm)
        g_old = torch.where(act, gg.clamp(min=1e-300), g_old)
        r = op(t)
        if force_ctl:
            r = r - (_sum(r * icf_f) / nn).float()[:, None, None]
        den = _sum(r * t)
        # den == 0: the contact set is solved exactly; the cells that overlap the object join (a restart), or the
        # frame stops if none do (computed for every frame: a question to the device per step costs more)
        zero_den = act & (den == 0)
        iol0 = (p == 0) & (g < 0) & valid
        has = iol0.any(dim=(1, 2))
        done = done | (zero_den & ~has)
        restart = (zero_den & has)[:, None, None]
        pr = torch.where(iol0, (_sum(p) / nn).float()[:, None, None], p)
        if force_ctl:
            pr = pr * (force / (area * _sum(pr).clamp(min=1e-300))).float()[:, None, None]
        p = torch.where(restart, pr, p)
        t = torch.where(restart, 0.0, t)
        conj = conj & ~restart[:, 0, 0]
        step = act & (den != 0)
        tau = (_sum(g * t) / torch.where(den != 0, den, 1.0)).float()[:, None, None]
        p_new = torch.clamp(p - tau * t, min=0.0)
        iol = (g < 0) & (p_new == 0) & valid
        grew = iol.any(dim=(1, 2))
        p_new = torch.where(iol, p_new - tau * g, p_new)
        s = _sum(p_new)
        empty = s <= 0
        if force_ctl:
            p_new = p_new * (force / (area * torch.where(empty, 1.0, s))).float()[:, None, None]
            s = torch.where(empty, s, force / area)
        change = _sum((p_new - p).abs()) / torch.where(empty, 1.0, s)
        stop = empty | ((change < tol) & ~grew)
        p = torch.where(step[:, None, None], p_new, p)
        conj = torch.where(step, ~grew, conj)
        done = done | (step & stop)
    if force_ctl:
        ic = (p > 0) & valid
        u = (op(p).double() - h)
        cnt = _sum(ic.double())
        delta = torch.where(cnt > 0, (u * ic).sum(dim=(1, 2)) / cnt.clamp(min=1), 0.0)
    return p, delta
