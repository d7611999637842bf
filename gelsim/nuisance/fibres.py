"""Loose fibres of a hairy fabric denting the gel before the fabric itself touches it.

A fabric with catalog ``hairiness`` > 0 has fibres standing proud of its face. Where the gap between the
gel and the fabric is shorter than a fibre, the fibre's tip pushes into the gel until the fibre buckles
(Euler, clamped at the fabric, free at the tip: ``F = pi^2 E I / (4 L^2)``, ``I = pi d^4 / 64``). The gel
answers as an elastic half-space under a flat punch of the fibre's radius ``a = d / 2``: it sinks
``delta = F (1 - nu^2) / (2 a E_gel)`` and, around it, ``(2 / pi) delta arcsin(a / r)`` (Boussinesq).
A fibre's dent is ``min(L - gap, delta_buckling, max_depth_over_diameter d)``: it grows as the gap closes,
and more fibres reach the gel as it does (a gradual onset of sparse marks). Where the gap is <= 0 the
fabric itself is in contact and its imprint holds the fibres flat: no dent is drawn there.

Fibres stand at fixed points of the sensor's field (before contact the hand moves the sensor along the
normal; sideways by 0.1 mm a frame or less). :func:`draw_fibres` draws them per sequence;
:func:`fibre_dents_mm` turns them and a frame's gap map into a depth map (mm, float32 ``(H, W)``) that
adds to the imprint's depth before shading; :func:`gap_map_mm` and :func:`approach_gap_mm` give the gap
from the sensor's pose. Numpy only: the imprint is computed on the CPU for every optics backend.
Numbers and their sources: ``gelsim/assets/nuisance.toml``, ``[stages.fibres]``; docs/nuisance.md.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import GelsimError
from ..fabrics.catalog import Fabric
from .params import MAX_SEVERITY, FibreParams, check_severity

#: The catalog's largest hairiness (its declared upper bound): the density in the data file is for it.
HAIRINESS_MAX = next(f.metadata["hi"] for f in dataclasses.fields(Fabric) if f.name == "hairiness")
#: Sub-samples per pixel side when drawing a dent (a fibre is about one 960x720 pixel wide).
SUPERSAMPLE = 4


@dataclass(frozen=True)
class Fibres:
    """Standing fibres of one sequence, float64 arrays of shape (N,): position in the sensor's field
    relative to its centre (``x_mm`` along image columns, ``y_mm`` along rows), free length, diameter (mm)
    and Young's modulus (GPa)."""
    x_mm: np.ndarray
    y_mm: np.ndarray
    length_mm: np.ndarray
    diameter_mm: np.ndarray
    modulus_gpa: np.ndarray

    def __len__(self) -> int:
        return int(self.x_mm.shape[0])


def draw_fibres(rng: np.random.Generator, field_mm: tuple[float, float], hairiness: float, p: FibreParams,
                severity: float) -> Fibres:
    """The standing fibres under a sensor whose field is ``field_mm`` (width, height) mm, on a fabric of
    catalog ``hairiness`` (0 to HAIRINESS_MAX), at ``severity`` (0 to MAX_SEVERITY).

    Their number is Poisson with mean ``p.density_per_mm2 x hairiness / HAIRINESS_MAX x severity x area``;
    lengths are exponential (mean ``p.length_mean_mm``), diameters and moduli uniform in their ranges.
    The draws do not depend on ``severity``: candidates are drawn at MAX_SEVERITY and each kept when its own
    uniform falls under ``severity / MAX_SEVERITY``, so a larger severity keeps a superset of the fibres."""
    s = check_severity(severity)
    w, h = (float(v) for v in field_mm)
    if not (math.isfinite(w) and math.isfinite(h) and w > 0 and h > 0):
        raise GelsimError(f"field {field_mm} mm must be two positive widths")
    if isinstance(hairiness, bool) or not (math.isfinite(hairiness) and 0.0 <= hairiness <= HAIRINESS_MAX):
        raise GelsimError(f"hairiness {hairiness!r} must be in [0, {HAIRINESS_MAX}] (the fabric catalog's range)")
    lam = p.density_per_mm2 * hairiness / HAIRINESS_MAX * MAX_SEVERITY * w * h
    n = int(rng.poisson(lam))
    x = rng.uniform(-w / 2, w / 2, n)
    y = rng.uniform(-h / 2, h / 2, n)
    length = rng.exponential(p.length_mean_mm, n)
    diameter = rng.uniform(p.diameter_mm[0], p.diameter_mm[1], n)
    modulus = rng.uniform(p.modulus_gpa[0], p.modulus_gpa[1], n)
    keep = rng.uniform(0.0, 1.0, n) < s / MAX_SEVERITY
    return Fibres(x[keep], y[keep], length[keep], diameter[keep], modulus[keep])


def buckling_dent_mm(length_mm, diameter_mm, modulus_gpa, gel_modulus_mpa: float, gel_poisson: float) -> np.ndarray:
    """How deep a fibre sinks into the gel when it buckles, mm: its Euler load (clamped-free) on a flat
    punch of its radius on the gel's half-space. Arrays broadcast; lengths must be > 0."""
    L = np.asarray(length_mm, np.float64) * 1e-3
    d = np.asarray(diameter_mm, np.float64) * 1e-3
    ef = np.asarray(modulus_gpa, np.float64) * 1e9
    force = math.pi ** 2 * ef * (math.pi * d ** 4 / 64.0) / (4.0 * L ** 2)
    return force * (1.0 - gel_poisson ** 2) / (2.0 * (d / 2.0) * gel_modulus_mpa * 1e6) * 1e3


def dent_depths_mm(fibres: Fibres, gap_at_fibre_mm, gel_modulus_mpa: float, gel_poisson: float,
                   p: FibreParams) -> np.ndarray:
    """Each fibre's dent depth, mm (N,): ``min(L - gap, buckling dent, max_depth_over_diameter x d)`` where
    its length exceeds the gap ``gap_at_fibre_mm`` (N,) at its foot and the gap is > 0; 0 elsewhere."""
    gap = np.asarray(gap_at_fibre_mm, np.float64)
    if gap.shape != (len(fibres),):
        raise GelsimError(f"gap at the fibres has shape {gap.shape}; give ({len(fibres)},)")
    over = fibres.length_mm - gap
    touching = (gap > 0.0) & (over > 0.0)
    depth = np.zeros(len(fibres))
    if touching.any():
        i = np.flatnonzero(touching)
        buckle = buckling_dent_mm(fibres.length_mm[i], fibres.diameter_mm[i], fibres.modulus_gpa[i],
                                  gel_modulus_mpa, gel_poisson)
        depth[i] = np.minimum(np.minimum(over[i], buckle), p.max_depth_over_diameter * fibres.diameter_mm[i])
    return depth


def _check_gap(gap_mm: np.ndarray) -> np.ndarray:
    g = np.asarray(gap_mm)
    if g.ndim != 2 or not np.issubdtype(g.dtype, np.floating) or not np.all(np.isfinite(g)):
        raise GelsimError(f"gap map must be a finite float (H, W) array, mm; got {g.dtype} {g.shape}")
    return g


def fibre_depths_mm(fibres: Fibres, gap_mm: np.ndarray, mm_per_px: float, gel_modulus_mpa: float,
                    gel_poisson: float, p: FibreParams) -> np.ndarray:
    """Each fibre's dent depth in this frame, float64 (N,) mm (0: not touching, or outside the image), from the
    gap map ``gap_mm`` (float (H, W) mm, <= 0 where the fabric is in contact) read at the fibre's pixel (pixel
    (i, j) is at ``x = (j - (W - 1) / 2) mm_per_px``, ``y = (i - (H - 1) / 2) mm_per_px``)."""
    g = _check_gap(gap_mm)
    if not (math.isfinite(mm_per_px) and mm_per_px > 0):
        raise GelsimError(f"mm_per_px {mm_per_px} must be a positive number")
    H, W = g.shape
    if len(fibres) == 0:
        return np.zeros(0)
    col = np.clip(np.rint(fibres.x_mm / mm_per_px + (W - 1) / 2.0), 0, W - 1).astype(np.int64)
    row = np.clip(np.rint(fibres.y_mm / mm_per_px + (H - 1) / 2.0), 0, H - 1).astype(np.int64)
    inside = (np.abs(fibres.x_mm) <= (W / 2.0) * mm_per_px) & (np.abs(fibres.y_mm) <= (H / 2.0) * mm_per_px)
    depth = dent_depths_mm(fibres, g[row, col].astype(np.float64), gel_modulus_mpa, gel_poisson, p)
    return np.where(inside, depth, 0.0)


def draw_dents_mm(fibres: Fibres, depth_mm: np.ndarray, shape: tuple[int, int], mm_per_px: float,
                  p: FibreParams) -> np.ndarray:
    """The gel's depth from the fibres' dents of depths ``depth_mm`` (N,) mm, float32 ``shape`` (H, W) mm, to add
    to the imprint's depth. Each dent is a flat punch profile out to ``p.tail_radii`` fibre radii (lowered so
    that it ends at 0 and rescaled to keep its depth), area-averaged over SUPERSAMPLE^2 points per pixel;
    dents add."""
    H, W = (int(v) for v in shape)
    out = np.zeros((H, W), np.float32)
    sub = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5          # sub-sample offsets, px
    for k in np.flatnonzero(np.asarray(depth_mm) > 0):
        a = fibres.diameter_mm[k] / 2.0
        reach = p.tail_radii * a
        cx = fibres.x_mm[k] / mm_per_px + (W - 1) / 2.0                # fibre centre, px
        cy = fibres.y_mm[k] / mm_per_px + (H - 1) / 2.0
        rp = int(math.ceil(reach / mm_per_px)) + 1
        j0, j1 = max(0, int(math.floor(cx)) - rp), min(W, int(math.floor(cx)) + rp + 2)
        i0, i1 = max(0, int(math.floor(cy)) - rp), min(H, int(math.floor(cy)) + rp + 2)
        if j0 >= j1 or i0 >= i1:
            continue
        xs = ((np.arange(j0, j1)[:, None] + sub[None, :]).ravel() - cx) * mm_per_px   # (nx * S,)
        ys = ((np.arange(i0, i1)[:, None] + sub[None, :]).ravel() - cy) * mm_per_px
        r = np.hypot(ys[:, None], xs[None, :])
        edge = (2.0 / math.pi) * math.asin(1.0 / p.tail_radii)         # the profile's value at `reach`, / depth
        prof = np.where(r <= a, 1.0, (2.0 / math.pi) * np.arcsin(np.minimum(1.0, a / np.maximum(r, 1e-12))))
        prof = np.where(r <= reach, (prof - edge) / (1.0 - edge), 0.0)
        patch = prof.reshape(i1 - i0, SUPERSAMPLE, j1 - j0, SUPERSAMPLE).mean(axis=(1, 3))
        out[i0:i1, j0:j1] += (depth_mm[k] * patch).astype(np.float32)
    return out


def fibre_dents_mm(fibres: Fibres, gap_mm: np.ndarray, mm_per_px: float, gel_modulus_mpa: float,
                   gel_poisson: float, p: FibreParams) -> np.ndarray:
    """The gel's depth from the fibres' dents, float32 ``(H, W)`` mm (``gap_mm``'s shape), to add to the
    imprint's depth: :func:`draw_dents_mm` of :func:`fibre_depths_mm`."""
    depth = fibre_depths_mm(fibres, gap_mm, mm_per_px, gel_modulus_mpa, gel_poisson, p)
    return draw_dents_mm(fibres, depth, np.shape(gap_mm), mm_per_px, p)


def gap_map_mm(shape: tuple[int, int], mm_per_px: float, apex_gap_mm: float, dome_radius_mm: float = 0.0,
               tilt_deg: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The gap between the gel and a flat fabric at each pixel, float32 ``(H, W)`` mm, when the gel's point
    nearest the fabric is ``apex_gap_mm`` from it (negative: pressed that far past first touch). The gel is
    a sphere cap of radius ``dome_radius_mm`` (0: flat; its sag taken as r^2 / 2R) tilted by ``tilt_deg`` =
    (roll, pitch): the gel is lower (nearer the fabric) at +y for roll > 0 and at +x for pitch > 0."""
    H, W = (int(v) for v in shape)
    if H < 1 or W < 1:
        raise GelsimError(f"shape {shape} must be (H, W) with H, W >= 1")
    for name, v in (("mm_per_px", mm_per_px), ("apex_gap_mm", apex_gap_mm), ("dome_radius_mm", dome_radius_mm)):
        if not math.isfinite(v):
            raise GelsimError(f"{name} {v} must be finite")
    if mm_per_px <= 0 or dome_radius_mm < 0:
        raise GelsimError("mm_per_px must be > 0 and dome_radius_mm >= 0")
    x = (np.arange(W) - (W - 1) / 2.0) * mm_per_px
    y = (np.arange(H) - (H - 1) / 2.0) * mm_per_px
    roll, pitch = (math.radians(float(t)) for t in tilt_deg)
    s = -x[None, :] * math.tan(pitch) - y[:, None] * math.tan(roll)
    if dome_radius_mm > 0:
        s = s + (x[None, :] ** 2 + y[:, None] ** 2) / (2.0 * dome_radius_mm)
    return (apex_gap_mm + s - s.min()).astype(np.float32)


def approach_gap_mm(frame: int, precontact_frames: int, contact_phase: float, speed_mm_s: float,
                    fps_hz: float) -> float:
    """Gap (mm) between the gel's nearest point and the fabric at frame ``frame`` < ``precontact_frames``
    of a motion (gelsim.motion.Motion: the first contact comes ``contact_phase`` of a frame period before
    frame ``precontact_frames``), approaching at ``speed_mm_s``: ``speed (P - phase - frame) / fps``."""
    if not (isinstance(frame, (int, np.integer)) and 0 <= frame < precontact_frames):
        raise GelsimError(f"frame {frame} is not before the first contact frame {precontact_frames}; "
                          "the approach gap exists only before contact")
    if not (0.0 < contact_phase < 1.0 and speed_mm_s > 0 and fps_hz > 0):
        raise GelsimError("contact_phase must be in (0, 1), speed_mm_s and fps_hz > 0")
    return float(speed_mm_s * (precontact_frames - contact_phase - frame) / fps_hz)
