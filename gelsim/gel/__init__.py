"""The gel imprint: how far an object pressed into the elastomer pushes its surface in.

:func:`press` takes the object's *protrusion* map in the sensor frame (``float32 (H, W)``, mm,
largest where the object touches first, see :mod:`gelsim.indenters`; relative to a flat plane
through the gel's apex: a domed gel's sag is subtracted here) and the normal force (N) or the
rigid-body approach (mm), and returns an :class:`Imprint`: the depth the gel surface is pushed in
(``>= 0``, 0 where untouched), the contact mask, approach, force and contact area.

Three models, chosen by ``fidelity.imprint_model`` and computed on a grid of
``fidelity.imprint_scale`` times the image resolution (then resampled):

``"twoscale"`` (fast and balanced levels, :mod:`.twoscale`)
    Exact layer elasticity on a coarse grid of the object's crown envelope (contact patch, force,
    smooth displacement, local pressure), Johnson's sinusoidal contact at the local pressure for
    the texture below the crowns (:mod:`.johnson`).
``"elastic"`` (reference, :mod:`.elastic`)
    Polonsky-Keer contact with the elastic layer at every pixel: exact at every scale, seconds.
``"pyramid"`` (:mod:`.pyramid`, after Taxim)
    Gaussian-pyramid spreading with a force law fitted to the elastic model; blind to
    texture-scale elasticity (kept for comparison).

A fabric adds its compliance (:class:`FabricSupport`: cloth compression and yarn flattening,
:mod:`.support`) and its texture scale (``texture_mm``). All models clip the approach at
``gel.max_indentation_mm`` (the pad bottoms out; ``bottomed_out`` is set) and work over the
touched region only unless ``window="full"``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import cv2
import numpy as np

from ..errors import GelsimError
from .elastic import press_elastic
from .layer import disk_layer_factor, effective_modulus_mpa  # noqa: F401  (public)
from .pyramid import ImprintLaw, imprint_law, press_pyramid  # noqa: F401  (public)
from .support import FabricSupport
from .twoscale import MacroState, press_twoscale
from .util import bbox, membrane_blur, resize

__all__ = ["Imprint", "FabricSupport", "press", "hertz", "measure_contact_radius_mm", "effective_modulus_mpa",
           "disk_layer_factor", "ImprintLaw", "imprint_law", "gel_sag_mm"]


@dataclass(frozen=True)
class Imprint:
    """The gel's response to one pressed object, at image resolution.

    depth_mm: float32 (H, W), how far the gel surface is pushed in, mm, >= 0, 0 where untouched.
    contact_mask: bool (H, W), object and gel in contact.
    indentation_mm: rigid-body approach of the object into the gel, mm (past the first touch).
    normal_force_n: normal force carried by the gel, N (below the request if bottomed out).
    contact_area_mm2: area in contact, mm^2.
    bottomed_out: the approach reached ``gel.max_indentation_mm`` and was clipped there.
    state: the model's solution (two-scale: its macro solve, which warm-starts the next frame,
        ``press(warm=)``; elastic: its pressure), or None.

    Its boxes, :attr:`depth_extent` (the optics') and :attr:`touched_extent` (the markers'), are found on first
    use and kept: one pass over the frame for both. The arrays are not to be modified once the imprint is made.
    """
    depth_mm: np.ndarray
    contact_mask: np.ndarray
    indentation_mm: float
    normal_force_n: float
    contact_area_mm2: float
    bottomed_out: bool
    state: Any = None

    @functools.cached_property
    def depth_extent(self) -> tuple[int, int, int, int] | None:
        """``(row0, row1, col0, col1)``, end exclusive, of the pixels where ``depth_mm > 0``; None if there are
        none (:func:`gelsim.optics.ops.box.imprint_extent` of ``depth_mm``, found once)."""
        return bbox(np.asarray(self.depth_mm) > 0)

    @functools.cached_property
    def touched_extent(self) -> tuple[int, int, int, int] | None:
        """``(row0, row1, col0, col1)``, end exclusive, of the pixels where ``depth_mm > 0`` or in
        ``contact_mask`` (the markers' window); None if there are none. Found once, in the same pass as
        :attr:`depth_extent` when that is not known yet (the first pass over the frame pays for bringing it into
        the cache: a second one is cheap)."""
        touched = np.asarray(self.depth_mm) > 0
        if "depth_extent" not in self.__dict__:
            self.__dict__["depth_extent"] = bbox(touched)     # (as functools.cached_property keeps it)
        touched |= np.asarray(self.contact_mask)
        return bbox(touched)

    def pressure_mpa(self) -> np.ndarray | None:
        """The contact pressure at the image's resolution (MPa, float32, shaped like depth_mm): the
        elastic model's at every pixel, the two-scale model's local mean (its macro solve's); None
        for the pyramid model."""
        field = getattr(self.state, "pressure_field", None)
        return None if field is None else resize(field(), self.depth_mm.shape)


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


def gel_sag_mm(profile, shape: tuple[int, int] | None = None) -> np.ndarray | None:
    """The undeformed gel surface's depth below its apex on a grid of ``shape`` (default the
    profile's image) over the profile's field, float32 mm, read-only (cached: every frame of a
    sequence needs the same one); None for a flat gel."""
    if not profile.gel.dome_radius_mm:
        return None
    h, w = shape or profile.shape
    fw, fh = profile.field_mm
    return _sag_grid(float(profile.gel.dome_radius_mm), float(fw), float(fh), int(h), int(w))


@functools.lru_cache(maxsize=8)
def _sag_grid(dome_radius_mm: float, fw: float, fh: float, h: int, w: int) -> np.ndarray:
    from ..sensor import GelSpec

    x = ((np.arange(w, dtype=np.float32) + 0.5) / w - 0.5) * np.float32(fw)
    y = ((np.arange(h, dtype=np.float32) + 0.5) / h - 0.5) * np.float32(fh)
    sag = GelSpec.sag_mm_of(dome_radius_mm, x[None, :], y[:, None]).astype(np.float32)
    sag.flags.writeable = False
    return sag


def _check_inputs(protrusion_mm, force_n, depth_mm, texture_mm, valley_mm=None):
    if (force_n is None) == (depth_mm is None):
        raise GelsimError("give exactly one of force_n and depth_mm to press()")
    for name, val in (("force_n", force_n), ("depth_mm", depth_mm), ("texture_mm", texture_mm),
                      ("valley_mm", valley_mm)):
        if val is not None and not (math.isfinite(val) and val >= 0):
            raise GelsimError(f"{name} = {val} is negative or not finite; give a finite value >= 0")
    p = np.asarray(protrusion_mm)
    if p.ndim != 2:
        raise GelsimError(f"protrusion map has shape {p.shape}; give a 2-D (H, W) array in mm")
    if p.size == 0 or not (math.isfinite(float(p.max())) and math.isfinite(float(p.min()))):
        raise GelsimError("protrusion map has NaN or Inf values; give finite heights in mm")
    return p


def gel_capacity_n(profile) -> float:
    """An upper bound on the normal force, N, the gel of ``profile`` can carry within its travel: its whole
    field pressed flat to ``max_indentation_mm``, in confined compression (the stiffest a bonded layer
    responds: modulus E (1 - nu) / ((1 + nu) (1 - 2 nu))). Any object, dome or cloth carries less at
    full travel, so a larger request bottoms the pad out whatever it presses; inf for nu = 0.5."""
    gel = profile.gel
    nu = gel.poisson_ratio
    if nu >= 0.5:
        return math.inf
    modulus = gel.young_modulus_mpa * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    fw, fh = profile.field_mm
    return fw * fh * modulus * gel.max_indentation_mm / gel.thickness_mm


def work_shape(profile, scale: float) -> tuple[int, int]:
    """The imprint grid of ``profile`` at ``scale`` times its image resolution (at least 8x8)."""
    h, w = profile.shape
    return max(8, round(h * scale)), max(8, round(w * scale))


def _no_contact(profile) -> Imprint:
    return Imprint(np.zeros(profile.shape, np.float32), np.zeros(profile.shape, bool), 0.0, 0.0, 0.0, False)


def press(protrusion_mm: np.ndarray, profile, fidelity, *, force_n: float | None = None,
          depth_mm: float | None = None, support: FabricSupport | None = None, texture_mm: float | None = None,
          window: str = "touched", warm: Imprint | None = None,
          envelope_mm: np.ndarray | Callable[..., np.ndarray] | None = None,
          valley_mm: float | None = None) -> Imprint:
    """Press an object into the gel.

    protrusion_mm: (H, W) protrusion map in mm at the profile's image resolution, or already at
        ``fidelity.imprint_scale`` times it (same field of view), relative to a plane through the
        gel's apex (the profile's dome, if any, is accounted for here).
    force_n: normal force, N (0 = no contact); or depth_mm: approach past first touch, mm.
    support: a fabric's compliance (cloth compression, yarn flattening); None = a rigid object.
    texture_mm: the object's texture scale, mm (a weave's largest pitch; the two-scale model
        splits crowns from valleys over it); None = a smooth object.
    window: "touched" computes over the touched region only (default); "full" over the whole
        frame (for checking the former).
    warm: the previous frame's Imprint of the same object, to warm-start the two-scale model's
        macro solve (same result within its tolerance, a few times fewer iterations).
    envelope_mm: the object's crown envelope seen as ``protrusion_mm`` sees the object (same shape and
        pose; two-scale model, with ``texture_mm``), or a function ``envelope_mm(box=None)`` that gives
        it, or only its rows r0:r1 and columns c0:c1 for ``box`` = (r0, r1, c0, c1) (only the touched
        region is read; e.g. :meth:`gelsim.scene.HeightPatch.sample` with the frame's pose). A sequence
        takes it once on the object (:func:`gelsim.sequence.render_sequence`). None: taken here, over the
        touched region of the object's own heights (before the dome's sag).
    valley_mm: the narrowest valley of the object's crown envelope, mm (``macro_valley_mm`` of a
        :class:`gelsim.scene.TouchedObject`: a corduroy's gap between wales); the two-scale model's
        contact-scale grid takes at least ``fidelity.macro_cells_per_valley`` cells across it. None: none.
    Returns an :class:`Imprint` at the profile's image resolution (float32 depth).
    """
    from ..fidelity import get_fidelity

    fidelity = get_fidelity(fidelity)
    prot = _check_inputs(protrusion_mm, force_n, depth_mm, texture_mm, valley_mm)
    if support is not None and not isinstance(support, FabricSupport):
        raise GelsimError(f"support must be a FabricSupport or None, got {type(support).__name__}; "
                          "use fabric.support() for a catalog fabric")
    if (force_n is not None and force_n == 0) or (depth_mm is not None and depth_mm == 0):
        return _no_contact(profile)
    gel = profile.gel
    beyond = ((force_n is not None and force_n > gel_capacity_n(profile))
              or (depth_mm is not None and depth_mm > gel.max_indentation_mm))
    if beyond:
        # More than the gel can carry at full travel (1e20 N overflowed the float32 solve into NaN), or an
        # approach past the travel (the cloth solve has no case for one): the pad bottoms out whatever it
        # presses, so press it to its travel (the same bottomed imprint).
        force_n, depth_mm = None, gel.max_indentation_mm
    ws = work_shape(profile, fidelity.imprint_scale)
    if prot.shape == profile.shape:
        work = resize(np.ascontiguousarray(prot, dtype=np.float32), ws, cv2.INTER_AREA)
    elif prot.shape == ws:
        work = np.ascontiguousarray(prot, dtype=np.float32)
    else:
        raise GelsimError(f"protrusion map is {prot.shape}; give {profile.shape} (the profile's image) "
                          f"or {ws} (its imprint grid)")
    env = None
    if envelope_mm is not None and texture_mm is not None and fidelity.imprint_model in ("twoscale", "elastic"):
        env = _envelope_reader(envelope_mm, prot.shape, ws)
    sag = gel_sag_mm(profile, ws)
    own = work   # the object's own heights, before the dome's sag
    if sag is not None:
        work = work - sag
    dx = profile.image.mm_per_px * profile.shape[1] / ws[1]
    model = fidelity.imprint_model
    state = None
    if model == "twoscale" or model == "elastic":
        ts = press_twoscale(work, dx, gel, force_n=force_n, depth_mm=depth_mm, support=support,
                            texture_mm=texture_mm, window=window, macro_cells=fidelity.macro_cells,
                            warm=warm.state if (warm is not None and isinstance(warm.state, MacroState)) else None,
                            sag=sag, envelope=env, own=own,
                            valley_mm=valley_mm if texture_mm is not None else None,
                            cells_per_valley=fidelity.macro_cells_per_valley)
        depth_w, mask_w, delta, force, bottomed, state = ts
        if model == "elastic":
            depth_w, mask_w, delta, force, bottomed, state = press_elastic(
                work, dx, gel, force_n=force_n, depth_mm=depth_mm, support=support, window=window,
                guess_mm=max(delta, 1e-4), texture_mm=texture_mm)
    elif model == "pyramid":
        ks = None
        if support is not None:  # the cloth's secant stiffness at a typical hand-press pressure
            ks = support.secant_stiffness_kpa_per_mm(_PYRAMID_SUPPORT_KPA) * 1e-3
            ks = ks if math.isfinite(ks) else None  # an incompressible cloth is a rigid support
        depth_w, mask_w, delta, force, bottomed = press_pyramid(
            work, dx, gel, force_n, depth_mm, ks, window, None if support is None else support.shear_length_mm)
    else:
        raise GelsimError(f"unknown imprint model {model!r}; use twoscale, elastic or pyramid")
    depth_w = membrane_blur(depth_w, gel.membrane_smoothing_mm / dx)
    depth = resize(depth_w, profile.shape)
    mask = mask_w if mask_w.shape == profile.shape else resize(mask_w.astype(np.float32), profile.shape) >= 0.5
    depth = depth.astype(np.float32, copy=False)  # finite and >= 0 by construction
    if not (math.isfinite(force) and math.isfinite(delta) and math.isfinite(float(depth.max()))):
        # checked in the solve's own precision (float32), never handed on as NaN
        raise GelsimError(f"the imprint solve did not converge to finite values (force {force} N, approach "
                          f"{delta} mm); press with a force within the gel's range, below "
                          f"{gel_capacity_n(profile):.0f} N")
    area = float(np.count_nonzero(mask_w)) * dx * dx
    return Imprint(depth, mask, float(delta), float(force), area, bool(bottomed or beyond), state)


def _envelope_reader(envelope_mm, prot_shape, ws) -> Callable[[tuple[int, int, int, int]], np.ndarray]:
    """``press``'s ``envelope_mm`` as a function of a box of the imprint grid ``ws`` (float32 mm): read
    as asked when the protrusion map is on that grid, else whole and resampled as that map is."""
    if callable(envelope_mm) and prot_shape == ws:
        return envelope_mm
    env = np.asarray(envelope_mm() if callable(envelope_mm) else envelope_mm)
    if env.shape != prot_shape:
        raise GelsimError(f"envelope_mm is {env.shape}, the protrusion map {prot_shape}; give both on the same grid")
    env = resize(np.ascontiguousarray(env, dtype=np.float32), ws, cv2.INTER_AREA)
    return lambda box: env[box[0]:box[1], box[2]:box[3]]


# The pyramid model takes one linear stiffness for a fabric: its secant at 10 kPa (a 3 N press
# over a third of the pad), the middle of a hand press's range.
_PYRAMID_SUPPORT_KPA = 10.0
