"""Indenters other than fabrics: sphere, cylinder and any triangle mesh, as protrusion maps.

A *protrusion* map says how far the object's surface stands out towards the gel, in mm,
on the sensor's image grid (``float32 (H, W)``): ``>= 0``, largest where the object
touches first, 0 where the object is absent. Only differences from the maximum matter
to :func:`gelsim.gel.press`. Grids follow the sensor frame (origin at the image centre,
``x`` along columns, ``y`` down the rows, mm); ``scale`` computes on a grid of
``scale`` times the image resolution over the same field of view.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import GelsimError
from .meshes import load_mesh, mesh_heights  # noqa: F401 (mesh_heights: for callers)
from .scene import Cylinder, Mesh, Sphere, field_heights, indenter
from .scene import positive_mm as _positive


def _on_field(obj, profile, scale: float) -> np.ndarray:
    return field_heights(obj, profile, scale=scale)


def sphere(diameter_mm: float, profile, *, center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """A rigid sphere of ``diameter_mm`` over the point ``center_mm`` (x, y) of the gel.

    Protrusion ``sqrt(R^2 - r^2)`` inside its outline, 0 outside: float32 (H, W), mm.
    """
    return _on_field(Sphere(_positive("diameter_mm", diameter_mm), tuple(center_mm)), profile, scale)


def cylinder(diameter_mm: float, profile, *, length_mm: float | None = None, angle_deg: float = 0.0,
             center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """A rigid cylinder lying on its side (axis parallel to the gel), flat ends.

    The axis runs through ``center_mm`` at ``angle_deg`` from +x towards +y; ``length_mm``
    None means longer than the field of view. Protrusion ``sqrt(R^2 - d^2)`` with ``d`` the
    distance from the axis, 0 beyond the ends: float32 (H, W), mm.
    """
    if not math.isfinite(angle_deg):
        raise GelsimError(f"angle_deg = {angle_deg} is not finite; give an angle in degrees")
    obj = Cylinder(_positive("diameter_mm", diameter_mm), None if length_mm is None else
                   _positive("length_mm", length_mm), float(angle_deg), tuple(center_mm))
    return _on_field(obj, profile, scale)


def mesh(path: str | Path, profile, *, center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """Any mesh trimesh can read (units mm), approaching the gel along -z (its lowest side first).

    The mesh's x-y bounding-box centre is placed over ``center_mm``. Protrusion is the
    height of the mesh's lower surface below its top, ``z_max - z_bottom(x, y)``, 0 outside
    its footprint: float32 (H, W), mm (triangles rasterised at pixel centres).
    """
    load_mesh(path)  # a bad file fails here, with its own message
    return _on_field(Mesh(str(path), tuple(center_mm)), profile, scale)


def load_indenter(name_or_path: str, profile, *, diameter_mm: float | None = None, length_mm: float | None = None,
                  angle_deg: float = 0.0, center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """``"sphere"`` or ``"cylinder"`` (need ``diameter_mm``) or a mesh file path, as a protrusion map
    (:func:`gelsim.scene.indenter` names the object; ``length_mm`` and ``angle_deg`` apply to the
    cylinder only): float32 (H, W) mm at ``scale`` times the profile's resolution."""
    import dataclasses

    obj = indenter(name_or_path, diameter_mm=diameter_mm, length_mm=length_mm, angle_deg=angle_deg)
    return _on_field(dataclasses.replace(obj, center_mm=tuple(center_mm)), profile, scale)
