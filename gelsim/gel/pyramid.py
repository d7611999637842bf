"""The pyramid imprint (after Taxim, Si and Yuan 2022): fast, but blind to texture-scale elasticity.

The object's penetration ``I = max(P - (P_max - delta), 0)`` is spread by a Gaussian pyramid
(coarse to fine, each level clamped to stay at or above ``I``: the gel never passes through the
object), then the membrane blur. The approach for a force comes from a law fitted to the elastic
model, ``F = c E* V / sqrt(A) / R(kappa a / h)^beta`` (V the volume under the pyramid's gel
surface, A the apparent contact area, R the layer's mean compliance under a disk), with the
constants in ``gelsim/assets/imprint_law.toml`` (fitted by ``tools/fit_pyramid_law.py``). The contact is
where the last clamp holds and the penetration exceeds ``contact_fraction`` of its peak.

It was gelsim's default until the texture study (docs/imprint.md): on a texture the pyramid's
spans do not depend on the pressure, so its contact stays at about a quarter of a wave whatever
the force, where Johnson's theory (and the elastic reference) reach complete contact. It remains
as a fidelity knob (``imprint_model = "pyramid"``) for that comparison. A fabric's support enters
as the cloth's secant stiffness in series (springs at the contact's scale); yarn flattening is
not modelled here.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ive, kve

from ..params import ASSETS_DIR, build, load_toml, param
from .layer import disk_layer_factor, effective_modulus_mpa
from .util import membrane_blur, pen_window

LAW_FILE = ASSETS_DIR / "imprint_law.toml"


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
    """The pyramid model's force-law constants from ``gelsim/assets/imprint_law.toml``."""
    return build(ImprintLaw, load_toml(LAW_FILE).get("law", {}), where="imprint_law.law")




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
                   ratio: float = 1.0, law: ImprintLaw | None = None) -> np.ndarray:
    """Pyramid-model force per penetration volume, N/mm^3, for apparent contact area (mm^2).

    The law holds for the volume under the pyramid's gel surface, ``ratio`` times the
    penetration volume. A support (``ks`` MPa/mm, shear length ``ell`` mm) acts in series.
    """
    law = law or imprint_law()
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


class LawSamples:
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

    def __init__(self, v: np.ndarray, dx: float, gel, vmax: float, law: ImprintLaw | None = None):
        law = self.law = law or imprint_law()
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
            self._hist = (key, edges, vol, c_app * self.cell_area, _law_stiffness(c_app * self.cell_area, gel, None, law=self.law))
        _, edges, vol, area_app, k1 = self._hist
        if not ks:  # the gel alone: force proportional to the volume ratio
            return edges, np.maximum.accumulate(k1 * (ratio * vol))
        f = _law_stiffness(area_app, gel, ks, ell, ratio, self.law) * vol
        return edges, np.maximum.accumulate(f)

    def at(self, delta: float) -> tuple[float, float]:
        """(penetration volume mm^3, apparent area mm^2) at approach ``delta`` (mm)."""
        m = self.v < delta
        return (float((delta - self.v[m]).sum()) * self.cell_area,
                float(np.count_nonzero(self.va < delta)) * self.cell_area)

    def force(self, delta: float, gel, ks, ell=None, ratio: float = 1.0) -> float:
        vol, app = self.at(delta)
        return float(_law_stiffness(np.array(app), gel, ks, ell, ratio, self.law) * vol)




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



# Volume under the pyramid's surface over the penetration volume: about 2 for smooth
# objects at the fitted blur (a starting guess only; each press measures its own).
_RATIO_GUESS = 2.0
# Force control: stop refining the volume ratio once it moves by less than this (the
# approach then moves by about as much, well inside the law's own error).
_RATIO_TOL = 0.01


def _pyramid_window(work, v, delta, sigma_px, window):
    margin = int(math.ceil(3 * sigma_px))  # a Gaussian is < 1.2% of its peak beyond 3 sigma
    sl = pen_window(v, delta, margin, window)
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
        kg = float(_law_stiffness(app, gel, None, None, ratio, samples.law))
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


def press_pyramid(work, dx, gel, force_n, depth_mm, ks, window, support_len=None, law: ImprintLaw | None = None):
    """Press ``work`` (protrusion mm, (ny, nx) at ``dx`` mm/px). ``ks``: a support's stiffness
    (MPa/mm) or None; ``support_len``: its Pasternak length (mm). Returns (depth mm before the
    membrane blur, contact mask, approach mm, force N, bottomed)."""
    law = law or imprint_law()
    pmax = float(work.max())
    v = pmax - work
    bottomed = False
    vmax = gel.max_indentation_mm
    samples = LawSamples(v, dx, gel, vmax, law)
    sigma_px = law.pyramid_sigma_per_thickness * gel.thickness_mm / dx
    ratio = _RATIO_GUESS
    support = None
    if ks:
        ell = law.support_length_mm if support_len is None else support_len
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


