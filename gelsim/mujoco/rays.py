"""What lies in front of a gel pad in a user's MuJoCo scene, by MuJoCo's own ray casts.

:class:`PadRays` casts one ray per cell of a grid over the pad's face, parallel to the pad's
normal, out of the gel, and returns how far the nearest surface is from the gel plane: the gap
map, ``float32 (H, W)`` mm, negative where an object has sunk into the (rigid) pad geom, ``inf``
where a ray hits nothing.

How: MuJoCo's ``rangefinder`` sensor attached to an orthographic camera casts exactly this batch
of parallel rays in C (``data="depth"``). The sensor cannot live in the user's model (mj_step
would then cast every ray at every physics step, about 100x the cost of a small scene's step), so
a private *ray scene* is compiled once, when the sensor is made: a copy of every geom that can
touch the pad (primitives, meshes, height fields; their sizes, vertices and elevations copied from
the compiled model) plus the camera and its rangefinder. Per frame only poses are copied: the
user's ``geom_xpos``/``geom_xmat`` into the ray scene's, the pad's pose into the camera's, then
``mj_sensorPos`` casts the rays. Nothing is rebuilt per frame.

Only geoms that MuJoCo would let collide with the pad are copied (``contype``/``conaffinity``
bits, not the pad's own body, not its parent unless that is the world: MuJoCo filters
parent-child contacts), so the finger behind the pad can never appear in front of it.
"""
from __future__ import annotations

import math

import mujoco
import numpy as np

from ..errors import GelsimError

MM = 1e-3  # metres per mm

# Geom types the ray scene copies; flex and SDF geoms are skipped (MuJoCo's rangefinder does not
# see flexes, and an SDF geom needs its plugin instance).
_COPYABLE = {int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD), int(mujoco.mjtGeom.mjGEOM_SPHERE),
             int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_ELLIPSOID),
             int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_MESH)}


def touching_candidates(model: mujoco.MjModel, pad_geom: int) -> list[int]:
    """Geoms MuJoCo may put in contact with ``pad_geom``: contype/conaffinity compatible, on another
    body than the pad's, not on its parent body (unless the parent is the world), copyable."""
    body = int(model.geom_bodyid[pad_geom])
    parent = int(model.body_parentid[body])
    filter_parent = not (model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT))
    ct, ca = int(model.geom_contype[pad_geom]), int(model.geom_conaffinity[pad_geom])
    out = []
    for g in range(model.ngeom):
        b = int(model.geom_bodyid[g])
        if g == pad_geom or b == body or (filter_parent and parent != 0 and b == parent):
            continue
        if not ((ct & int(model.geom_conaffinity[g])) or (int(model.geom_contype[g]) & ca)):
            continue
        if int(model.geom_type[g]) in _COPYABLE:
            out.append(g)
    return out


class PadRays:
    """Parallel rays over a pad's face (see the module docstring).

    ``model``: the user's compiled model; ``pad_geom``: the pad's geom id; ``face_offset_m``: the
    gel plane's distance from the geom's centre along its +z, m; ``field_mm``: (width, height) of
    the sensor's field on the gel, mm; ``cell_mm``: ray spacing, mm; ``standoff_mm``: how far
    behind the gel plane the rays start, mm (objects sunk into the pad by less are still seen).

    Attributes: ``shape`` (H, W) of the gap map; ``cell_mm``; ``origin_mm``: the pad-frame (x, y)
    of cell (0, 0)'s centre, mm (cell (i, j) at ``origin + (j, i) * cell_mm``, x along the pad's
    +x, y along its +y; centred on the face).
    """

    def __init__(self, model: mujoco.MjModel, pad_geom: int, face_offset_m: float, field_mm: tuple[float, float],
                 cell_mm: float, standoff_mm: float):
        self.model = model
        self.pad = int(pad_geom)
        self.face_offset_m = float(face_offset_m)
        self.cell_mm = float(cell_mm)
        self.standoff_mm = float(standoff_mm)
        fw, fh = field_mm
        w, h = int(math.ceil(fw / cell_mm)), int(math.ceil(fh / cell_mm))
        # Same parity on both sides, so that the crop below keeps the square grid's centre.
        w, h = (w, h + (w - h) % 2) if w >= h else (w + (h - w) % 2, h)
        self.shape = (h, w)
        self.origin_mm = (-(w - 1) / 2.0 * cell_mm, -(h - 1) / 2.0 * cell_mm)
        # MuJoCo's orthographic rangefinder spans fovy along both image axes (measured: a 101x76
        # camera spaced its columns fovy/101 apart), so the rays are cast on a square grid of the
        # longer side and the rows (or columns) outside the field are cropped.
        n = max(w, h)
        self._n = n
        self._rows = slice((n - h) // 2, (n - h) // 2 + h)
        self._cols = slice((n - w) // 2, (n - w) // 2 + w)
        self.geoms = np.array(touching_candidates(model, self.pad), dtype=np.int64)
        self._build(n)

    def _build(self, n: int) -> None:
        m = self.model
        spec = mujoco.MjSpec()
        cam_body = spec.worldbody.add_body(name="gelsim_pad_camera")
        cam_body.add_camera(name="gelsim_rays", proj=int(mujoco.mjtProjection.mjPROJ_ORTHOGRAPHIC),
                            fovy=n * self.cell_mm * MM, resolution=[n, n])
        for k, g in enumerate(self.geoms):
            t = int(m.geom_type[g])
            # alpha 1: the rangefinder ignores invisible geoms, and a user's invisible collider still touches
            kw = dict(type=mujoco.mjtGeom(t), size=m.geom_size[g].tolist(), rgba=[1.0, 1.0, 1.0, 1.0])
            if t == int(mujoco.mjtGeom.mjGEOM_MESH):
                i = int(m.geom_dataid[g])
                va, vn = int(m.mesh_vertadr[i]), int(m.mesh_vertnum[i])
                fa, fn = int(m.mesh_faceadr[i]), int(m.mesh_facenum[i])
                spec.add_mesh(name=f"mesh{k}", uservert=m.mesh_vert[va:va + vn].ravel().tolist(),
                              userface=m.mesh_face[fa:fa + fn].ravel().tolist())
                kw["meshname"] = f"mesh{k}"
            elif t == int(mujoco.mjtGeom.mjGEOM_HFIELD):
                i = int(m.geom_dataid[g])
                a, nr, nc = int(m.hfield_adr[i]), int(m.hfield_nrow[i]), int(m.hfield_ncol[i])
                spec.add_hfield(name=f"hfield{k}", size=m.hfield_size[i].tolist(), nrow=nr, ncol=nc,
                                userdata=m.hfield_data[a:a + nr * nc].tolist())
                kw["hfieldname"] = f"hfield{k}"
            spec.worldbody.add_geom(**kw)
        spec.add_sensor(name="gelsim_rays", type=mujoco.mjtSensor.mjSENS_RANGEFINDER,
                        objtype=mujoco.mjtObj.mjOBJ_CAMERA, objname="gelsim_rays",
                        intprm=[1 << int(mujoco.mjtRayDataField.mjRAYDATA_DEPTH), 0, 0])
        try:
            self._m = spec.compile()
        except ValueError as e:
            raise GelsimError(f"could not build the pad's ray scene ({e}); check the geoms near the pad") from None
        self._d = mujoco.MjData(self._m)
        # Compiling may move a mesh's frame (MuJoCo re-centres meshes on their centroid): the copy's
        # pose relative to the user's geom frame, applied per frame (identity for primitives).
        ng = self._m.ngeom
        self._off_pos = self._m.geom_pos.copy()
        mats = np.zeros((ng, 9))
        for i in range(ng):
            mujoco.mju_quat2Mat(mats[i], self._m.geom_quat[i])
        self._off_mat = mats.reshape(ng, 3, 3)
        self._has_offset = bool(np.any(self._off_pos) or np.any(self._off_mat != np.eye(3)))

    def gaps_mm(self, data: mujoco.MjData) -> np.ndarray:
        """Gap between the gel plane and the nearest surface in front of it along each ray,
        ``float32 self.shape`` mm (negative: sunk into the pad; inf: nothing in front)."""
        m, pd = self.model, self._d
        if self.geoms.size:
            xpos = data.geom_xpos[self.geoms]
            xmat = data.geom_xmat[self.geoms].reshape(-1, 3, 3)
            if self._has_offset:
                xpos = xpos + np.einsum("nij,nj->ni", xmat, self._off_pos)
                xmat = xmat @ self._off_mat
            pd.geom_xpos[:] = xpos
            pd.geom_xmat[:] = xmat.reshape(-1, 9)
        R = data.geom_xmat[self.pad].reshape(3, 3)
        z = R[:, 2]
        pd.cam_xpos[0] = data.geom_xpos[self.pad] + z * (self.face_offset_m - self.standoff_mm * MM)
        # A camera looks along its -z and its image's rows run along its -y: camera axes (x, -y, -z)
        # of the pad put image columns along the pad's +x, rows along its +y, rays along its +z.
        pd.cam_xmat[0] = np.column_stack([R[:, 0], -R[:, 1], -z]).ravel()
        mujoco.mj_sensorPos(self._m, pd)
        raw = pd.sensordata.reshape(self._n, self._n)[self._rows, self._cols]
        gap = (raw - self.standoff_mm * MM) / MM
        return np.where(raw >= 0, gap, np.inf).astype(np.float32)
