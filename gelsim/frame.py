"""One frame: press a touched object into the gel and render what the camera sees, or report the press.

The single-frame counterpart of :mod:`gelsim.sequence` (no motion, no physics: the object is centred
under the sensor and pressed straight in), used by ``gelsim render`` and ``gelsim press``:

* :func:`press_object`: the object (any :class:`gelsim.scene.TouchedObject`) over the sensor's field,
  pressed with a normal force (N) or to a depth (mm past first touch) -> :class:`gelsim.gel.Imprint`;
* :func:`render_frame`: that imprint, its markers and the camera -> ``uint8 (H, W, 3)`` RGB frame and a
  record of what was rendered, with each stage's time in ms (the one-frame function of every caller,
  :func:`gelsim.stream.make_frames`);
* :func:`press_report`: the press against Hertz's rigid sphere on an elastic half-space (spheres; on a
  domed gel with the dome's curvature added): contact radius and indentation, mm.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from .errors import GelsimError
from .fidelity import Fidelity, get_fidelity
from .scene import Cylinder, FabricObject, Mesh, Sphere, TouchedObject, as_object, field_heights, press_properties
from .sensor import SensorProfile, load_profile

#: Force used when neither a force nor a depth is given: a light press by hand (the ViTac data were
#: pressed by hand; about 1 N makes a clear imprint on a 0.2 MPa gel).
DEFAULT_FORCE_N = 1.0


def _profile(profile: str | Path | SensorProfile) -> SensorProfile:
    return profile if isinstance(profile, SensorProfile) else load_profile(profile)


def press_object(obj: TouchedObject, profile: SensorProfile, fidelity: str | Fidelity, *,
                 force_n: float | None = None, depth_mm: float | None = None, seed: int = 0,
                 protrusion_mm: np.ndarray | None = None):
    """``obj`` centred under the sensor pressed into the gel with ``force_n`` N or to ``depth_mm`` mm
    past first touch, with the object's own compliance (``obj.support()``) and texture scale: a
    :class:`gelsim.gel.Imprint` at the profile's resolution. ``seed``: the object's irregularities (a
    fabric's); ``protrusion_mm``: its heights over the field when already computed
    (:func:`gelsim.scene.field_heights`, float32 (H, W) mm)."""
    from .gel import press

    obj = as_object(obj)
    prot = field_heights(obj, profile, seed=seed) if protrusion_mm is None else protrusion_mm
    return press(prot, profile, get_fidelity(fidelity), force_n=force_n, depth_mm=depth_mm, **press_properties(obj))


def describe(obj: TouchedObject) -> dict:
    """What ``gelsim render --json`` says the object was: a fabric's id, name and family, or an
    indenter's name (sphere, cylinder or the mesh's path) and diameter (mm; None for a mesh)."""
    if isinstance(obj, FabricObject):
        return {"fabric": obj.fabric.id, "name": obj.fabric.name, "family": obj.fabric.family}
    if isinstance(obj, (Sphere, Cylinder)):
        return {"indenter": "sphere" if isinstance(obj, Sphere) else "cylinder", "diameter_mm": obj.diameter_mm}
    if isinstance(obj, Mesh):
        return {"indenter": obj.path, "diameter_mm": None}
    return {"object": obj.name}


def render_frame(obj: TouchedObject, profile: str | Path | SensorProfile = "vitac",
                 fidelity: str | Fidelity = "balanced", *, force_n: float | None = None,
                 depth_mm: float | None = None, backend: str | None = None, seed: int = 0,
                 device: str | None = None) -> tuple[np.ndarray, dict]:
    """One camera frame of ``obj`` pressed into the gel (see :func:`press_object`).

    ``force_n`` (N) or ``depth_mm`` (mm past first touch), DEFAULT_FORCE_N when neither is given;
    ``backend``: the renderer (default: the fidelity level's); ``device``: where the torch backend
    renders (default the CPU; for no other backend); ``seed``: the object's irregularities,
    the background field, the marker jitter and the camera noise.
    Returns ``(rgb, info)``: ``uint8 (H, W, 3)`` RGB and a dict with the inputs, the imprint
    (indentation mm, force N, contact area mm^2, deepest point mm), the marker count and
    ``stages_ms`` (wall time per stage, ms).
    """
    from .engines import NumpyEngine
    from .optics import Renderer
    from .stream import FrameRequest, FrameSetup, StageTimer, Touch, make_frames

    timer = StageTimer(time.perf_counter)   # wall time: `gelsim render` reports what the user waits for
    prof = _profile(profile)
    fid = get_fidelity(fidelity)
    backend = backend or fid.render_backend
    if force_n is None and depth_mm is None:
        force_n = DEFAULT_FORCE_N
    for name, v in (("--force-n", force_n), ("--depth-mm", depth_mm)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise GelsimError(f"{name} {v} must be a finite number >= 0")
    obj = as_object(obj)
    timer.lap("setup")
    info: dict = {"profile": prof.name, "shape_hw": list(prof.shape), "backend": backend, "fidelity": fid.name,
                  "seed": seed, "object": describe(obj)}
    if device is not None:
        info["device"] = device
    touch = Touch(field_heights(obj, prof, seed=seed), force_n=force_n, depth_mm=depth_mm,
                  properties=press_properties(obj))
    timer.lap("object")
    renderer = Renderer(prof, backend, supersample=fid.supersample, seed=seed, device=device)
    timer.lap("renderer_setup")
    try:
        made = make_frames([FrameRequest(touch, seed)], FrameSetup.make(prof, fid, sensor_seed=seed, renderer=renderer),
                           NumpyEngine(clock=time.perf_counter))
    finally:
        renderer.close()
    imprint, markers, rgb = made.parts[0].imprint, made.parts[0].markers, made.parts[0].frame
    # the optics stage is what `gelsim render` has always called "render"
    times = {("render" if k == "optics" else k): round(v * 1e3, 2) for k, v in {**timer.take(), **made.seconds}.items()}
    info["imprint"] = {"indentation_mm": imprint.indentation_mm, "normal_force_n": imprint.normal_force_n,
                       "contact_area_mm2": imprint.contact_area_mm2, "bottomed_out": imprint.bottomed_out,
                       "max_depth_mm": float(imprint.depth_mm.max())}
    info["markers"] = 0 if markers is None else len(markers)
    info["stages_ms"] = times
    return rgb, info


def hertz_for(obj: TouchedObject, force_n: float, gel) -> tuple[float, float] | None:
    """Hertz's contact radius and indentation (mm) for ``obj`` pressed with ``force_n`` N into ``gel``
    (a profile's gel section), or None for anything but a sphere. A domed gel adds its curvature to
    the sphere's: ``1/R = 1/R_sphere + 1/R_dome``."""
    from .gel import hertz

    if not isinstance(obj, Sphere):
        return None
    dome = gel.dome_radius_mm
    d = obj.diameter_mm
    d_eff = d if not dome else 2.0 / (2.0 / d + 1.0 / dome)
    return hertz(d_eff, force_n, gel)


def press_report(obj: TouchedObject, force_n: float, *, profile: str | Path | SensorProfile = "vitac",
                 fidelity: str | Fidelity = "reference", resolution_px: int | None = None) -> dict:
    """Press ``obj`` with ``force_n`` N and return the report ``gelsim press --json`` prints: the
    simulated contact radius (from the contact area) and indentation beside Hertz's (spheres only,
    else None), their ratios, the contact area (mm^2), the force the gel carries (N), the deepest
    point, the gel's parameters and the time taken (ms). Lengths in mm. ``resolution_px``: image
    width, px, over the same field (default: the profile's)."""
    from .gel import measure_contact_radius_mm

    if not (isinstance(force_n, (int, float)) and math.isfinite(force_n) and force_n > 0):
        raise GelsimError(f"--force-n {force_n} is not a positive force; give a force > 0 N")
    prof = _profile(profile)
    if resolution_px is not None:
        prof = prof.with_resolution(resolution_px)
    from .gel import gel_capacity_n

    capacity = gel_capacity_n(prof)
    if force_n > capacity:
        # Beyond it the pad bottoms out whatever presses, and Hertz's figures for that force describe
        # nothing the gel could show: a comparison of nothing.
        raise GelsimError(f"--force-n {force_n:g} is more than the {prof.name} gel can carry ({capacity:.0f} N with its "
                          "whole field pressed to its travel); give a smaller force")
    fid = get_fidelity(fidelity)
    obj = as_object(obj)
    t0 = time.perf_counter()
    imp = press_object(obj, prof, fid, force_n=force_n)
    elapsed = time.perf_counter() - t0
    a = measure_contact_radius_mm(imp, prof.image.mm_per_px)
    what = describe(obj)
    out = {
        "indenter": what.get("indenter", obj.name),
        "diameter_mm": what.get("diameter_mm"),
        "force_n": force_n,
        "model": fid.imprint_model,
        "fidelity": fid.name,
        "profile": prof.name,
        "resolution_px": list(prof.shape[::-1]),
        "mm_per_px": prof.image.mm_per_px,
        "contact_radius_mm": a,
        "indentation_mm": imp.indentation_mm,
        "hertz_contact_radius_mm": None,
        "hertz_indentation_mm": None,
        "contact_radius_ratio": None,
        "indentation_ratio": None,
        "contact_area_mm2": imp.contact_area_mm2,
        "gel_force_n": imp.normal_force_n,
        "max_depth_mm": float(imp.depth_mm.max()),
        "bottomed_out": imp.bottomed_out,
        "gel_thickness_mm": prof.gel.thickness_mm,
        "gel_dome_radius_mm": prof.gel.dome_radius_mm or None,
        "young_modulus_mpa": prof.gel.young_modulus_mpa,
        "poisson_ratio": prof.gel.poisson_ratio,
        "contact_radius_over_thickness": a / prof.gel.thickness_mm,
        "elapsed_ms": round(elapsed * 1000.0, 1),
    }
    h = hertz_for(obj, force_n, prof.gel)
    if h is not None:
        ha, hd = h
        out.update(hertz_contact_radius_mm=ha, hertz_indentation_mm=hd,
                   contact_radius_ratio=a / ha, indentation_ratio=imp.indentation_mm / hd)
    return out
