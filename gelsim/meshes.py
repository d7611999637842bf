"""Triangle meshes as height maps: read a mesh file once per version, rasterise its lower surface.

The rigid :class:`gelsim.scene.Mesh` object and :func:`gelsim.indenters.mesh` stand on these.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from .errors import GelsimError


@functools.lru_cache(maxsize=8)
def _load_mesh_cached(path: str, mtime_ns: int):
    import trimesh

    try:
        m = trimesh.load(path, force="mesh")
    except ImportError:
        # A file that is neither a binary nor a plain-text mesh sends trimesh to guess its text encoding with
        # an optional package: whatever that guess, the file is no mesh (it named the missing package).
        raise GelsimError(f"cannot read mesh {path}: it is neither a binary nor a text mesh; give a valid "
                          ".stl/.obj file") from None
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
