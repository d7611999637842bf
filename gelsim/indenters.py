"""Indenters other than fabrics: sphere, cylinder and any triangle mesh, as protrusion maps.

A *protrusion* map says how far the object's surface stands out towards the gel, in mm,
on the sensor's image grid (``float32 (H, W)``): ``>= 0``, largest where the object
touches first, 0 where the object is absent. Only differences from the maximum matter
to :func:`gelsim.gel.press`. Grids follow the sensor frame (origin at the image centre,
``x`` along columns, ``y`` down the rows, mm); ``scale`` computes on a grid of
``scale`` times the image resolution over the same field of view.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from .errors import GelsimError
from .scene import positive_mm as _positive


def _on_field(obj, profile, scale: float) -> np.ndarray:
    from .scene import field_heights

    return field_heights(obj, profile, scale=scale)


def sphere(diameter_mm: float, profile, *, center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """A rigid sphere of ``diameter_mm`` over the point ``center_mm`` (x, y) of the gel.

    Protrusion ``sqrt(R^2 - r^2)`` inside its outline, 0 outside: float32 (H, W), mm.
    """
    from .scene import Sphere

    return _on_field(Sphere(_positive("diameter_mm", diameter_mm), tuple(center_mm)), profile, scale)


def cylinder(diameter_mm: float, profile, *, length_mm: float | None = None, angle_deg: float = 0.0,
             center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """A rigid cylinder lying on its side (axis parallel to the gel), flat ends.

    The axis runs through ``center_mm`` at ``angle_deg`` from +x towards +y; ``length_mm``
    None means longer than the field of view. Protrusion ``sqrt(R^2 - d^2)`` with ``d`` the
    distance from the axis, 0 beyond the ends: float32 (H, W), mm.
    """
    from .scene import Cylinder

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
    from .scene import Mesh

    load_mesh(path)  # a bad file fails here, with its own message
    return _on_field(Mesh(str(path), tuple(center_mm)), profile, scale)


@functools.lru_cache(maxsize=8)
def _load_mesh_cached(path: str, mtime_ns: int):
    import trimesh

    try:
        m = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many kinds of errors on bad files
        raise GelsimError(f"cannot read mesh {path} ({e}); give a valid .stl/.obj file") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise GelsimError(f"mesh {path} has no triangles; give a mesh with faces")
    return m


def load_mesh(path: str | Path):
    """The mesh at ``path`` (trimesh.Trimesh, units mm), read once per file version."""
    path = Path(path)
    if not path.is_file():
        raise GelsimError(f"indenter mesh {path} not found; give an existing .stl/.obj file")
    return _load_mesh_cached(str(path), path.stat().st_mtime_ns)


def mesh_heights(m, xs: np.ndarray, ys: np.ndarray, rotation_deg: float = 0.0) -> np.ndarray:
    """How far the lower surface of mesh ``m`` stands below its top (``z_max - z_bottom``) over the
    grid ``xs`` x ``ys`` (mm, relative to the mesh's x-y bounding-box centre; the mesh turned by
    ``rotation_deg``), 0 outside its footprint: float32 (len(ys), len(xs))."""
    (x0, y0, z0), (x1, y1, z1) = m.bounds
    tri = np.array(m.triangles, dtype=np.float64)  # (T, 3, 3), a writable copy
    tri[:, :, 0] -= (x0 + x1) / 2.0
    tri[:, :, 1] -= (y0 + y1) / 2.0
    if rotation_deg:
        c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
        x, y = tri[:, :, 0].copy(), tri[:, :, 1].copy()
        tri[:, :, 0], tri[:, :, 1] = c * x - s * y, s * x + c * y
    zb = _zbuffer_min(tri, np.asarray(xs, np.float64), np.asarray(ys, np.float64))
    return np.where(np.isfinite(zb), z1 - zb, 0.0).astype(np.float32)


def _zbuffer_min(tri: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Lowest z of the triangles over each pixel centre (inf where none): (len(ys), len(xs)).

    Vectorised rasteriser (no ray-tracing library needed): every triangle is tested
    against the pixel centres inside its bounding box, in chunks to bound memory.
    """
    h, w = ys.size, xs.size
    dx = xs[1] - xs[0] if w > 1 else 1.0
    zb = np.full(h * w, np.inf)
    # Project out triangles seen edge-on from below (zero area in x-y).
    e1 = tri[:, 1, :2] - tri[:, 0, :2]
    e2 = tri[:, 2, :2] - tri[:, 0, :2]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    tri, det = tri[np.abs(det) > 1e-15], det[np.abs(det) > 1e-15]
    c0 = np.clip(np.ceil((tri[:, :, 0].min(1) - xs[0]) / dx), 0, w).astype(np.int64)
    c1 = np.clip(np.floor((tri[:, :, 0].max(1) - xs[0]) / dx) + 1, 0, w).astype(np.int64)
    r0 = np.clip(np.ceil((tri[:, :, 1].min(1) - ys[0]) / dx), 0, h).astype(np.int64)
    r1 = np.clip(np.floor((tri[:, :, 1].max(1) - ys[0]) / dx) + 1, 0, h).astype(np.int64)
    nw, nh = np.maximum(c1 - c0, 0), np.maximum(r1 - r0, 0)
    npix = nw * nh
    keep = np.flatnonzero(npix > 0)
    chunk = 2_000_000  # pixel-triangle pairs per batch: about 100 MB of temporaries
    start = 0
    while start < keep.size:
        stop = start
        total = 0
        while stop < keep.size and (total == 0 or total + npix[keep[stop]] <= chunk):
            total += npix[keep[stop]]
            stop += 1
        ids = keep[start:stop]
        start = stop
        cnt = npix[ids]
        t = np.repeat(ids, cnt)
        k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        col = c0[t] + k % nw[t]
        row = r0[t] + k // nw[t]
        px, py = xs[col], ys[row]
        v0 = tri[t, 0]
        ax, ay = px - v0[:, 0], py - v0[:, 1]
        ee1, ee2, dd = tri[t, 1, :2] - v0[:, :2], tri[t, 2, :2] - v0[:, :2], det[t]
        b1 = (ax * ee2[:, 1] - ay * ee2[:, 0]) / dd
        b2 = (ee1[:, 0] * ay - ee1[:, 1] * ax) / dd
        inside = (b1 >= -1e-9) & (b2 >= -1e-9) & (b1 + b2 <= 1 + 1e-9)
        z = v0[:, 2] + b1 * (tri[t, 1, 2] - v0[:, 2]) + b2 * (tri[t, 2, 2] - v0[:, 2])
        np.minimum.at(zb, (row * w + col)[inside], z[inside])
    return zb.reshape(h, w)


def load_indenter(name_or_path: str, profile, *, diameter_mm: float | None = None, length_mm: float | None = None,
                  angle_deg: float = 0.0, center_mm=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """``"sphere"`` or ``"cylinder"`` (need ``diameter_mm``) or a mesh file path, as a protrusion map
    (:func:`gelsim.scene.indenter` names the object; ``length_mm`` and ``angle_deg`` apply to the
    cylinder only): float32 (H, W) mm at ``scale`` times the profile's resolution."""
    import dataclasses

    from .scene import indenter

    obj = indenter(name_or_path, diameter_mm=diameter_mm, length_mm=length_mm, angle_deg=angle_deg)
    return _on_field(dataclasses.replace(obj, center_mm=tuple(center_mm)), profile, scale)
