"""A GelSight sensor on a gel pad of any MuJoCo scene: one tactile frame per ``render()``.

The user names a ``box`` or ``cylinder`` geom of their model as the gel pad. The gel's surface is
the geom's +z face (the face at ``+size[2]`` of a box, the cap at ``+size[1]`` of a cylinder) and
the gel looks along the geom's +z: the sensor frame is the geom's frame moved onto that face, image
columns along the geom's +x, rows along its +y (``docs/mujoco.md``). Per frame:

1. **Forces** from MuJoCo's contacts on the pad (``mj_contactForce``): the normal force pressing the
   gel and the in-plane force of the objects on it, N, sensor frame.
2. **Geometry** from MuJoCo's ray casts (:class:`gelsim.mujoco.rays.PadRays`): the gap between the
   gel plane and whatever lies in front of it, on the physics grid of the dataset pipeline
   (:data:`gelsim.scene.PHYSICS_MM_PER_PX`), resampled to the imprint grid.
3. **Imprint** by the pipeline's gel model (:func:`gelsim.gel.press`) at MuJoCo's normal force.
4. **Shear and twist** of the gel surface relative to the pad, the dataset pipeline's stick/slip
   model (:mod:`gelsim.contact`): the gel's shear and torsion springs (:func:`gelsim.contact.gel_stiffness`)
   carry the tangential load MuJoCo puts on the pad plus the pad's motion relative to the touched
   object since first contact, up to Coulomb's limit ``mu N`` (``mu N r_eff`` in torsion); past it
   the gel slips and stays at the limit.
5. **Markers** (:func:`gelsim.markers.displace`) and the **camera image** (:class:`gelsim.optics.Renderer`).

Steps 3 and 5 are the frame pipeline (:func:`gelsim.stream.make_frames`, a batch of one on the numpy engine), the
one that ``gelsim render`` and every dataset frame run too.

Frames without a contact force on the pad skip steps 2-4: they are the flat gel (exactly
:meth:`GelSightSensor.background` without noise). MuJoCo runs in SI units; everything the sensor
returns is in mm, N, degrees and px, like the rest of gelsim.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from ..errors import GelsimError
from ..fidelity import Fidelity, get_fidelity
from ..gel import Imprint, gel_sag_mm, work_shape
from ..markers import marker_grid
from ..optics import Renderer
from ..runtime import ThreadLimit
from ..scene import PHYSICS_MM_PER_PX, HeightPatch
from ..sensor import SensorProfile, load_profile
from ..stream import FrameRequest, FrameSetup, StageTimer, Touch, make_frame, make_frames
from .rays import MM, PadRays
from .stickslip import GelSprings, StickSlip

#: Geom types that can be a gel pad, with the distance of their flat +z face from the geom's centre
#: (index into ``geom_size``).
SUPPORTED_PAD_TYPES = {"box": 2, "cylinder": 1}
# How deep below the first touch the ray scene's heights are kept, beyond the gel's own reach
# (max_indentation_mm plus the dome's sag): deeper surface cannot reach the gel; two ray cells of
# slack keep the cut off the imprint's edge.
_REACH_SLACK_CELLS = 2.0


@dataclass(frozen=True)
class TactileFrame:
    """One tactile frame. Sensor frame: x along image columns, y along rows, z out of the gel.

    rgb: uint8 (H, W, 3) camera image. markers_xy_px, markers_rest_px: float32 (N, 2) marker centres,
    px (x = column, y = row; N = 0 for a profile without markers). normal_force_n: force pressing the
    gel, N (>= 0). tangential_force_n: float64 (2,) in-plane force of the objects on the gel, N.
    contact_mask: bool (H, W). depth_mm: float32 (H, W) imprint, mm (>= 0). shear_mm: float64 (2,)
    gel surface displacement relative to the pad, mm. twist_deg: its rotation, degrees (+x towards
    +y). in_contact: a contact force acts on the pad. slipping: the gel reached Coulomb's limit and
    slides. time_s: MuJoCo's ``data.time``, s.
    """
    rgb: np.ndarray
    markers_xy_px: np.ndarray
    markers_rest_px: np.ndarray
    normal_force_n: float
    tangential_force_n: np.ndarray
    contact_mask: np.ndarray
    depth_mm: np.ndarray
    shear_mm: np.ndarray
    twist_deg: float
    in_contact: bool
    slipping: bool
    time_s: float


def _geom_names(model: mujoco.MjModel, limit: int = 12) -> str:
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in range(model.ngeom)]
    names = [n for n in names if n]
    more = f" (+{len(names) - limit} more)" if len(names) > limit else ""
    return (", ".join(names[:limit]) + more) if names else "none: the model's geoms have no names"


def find_pad(model: mujoco.MjModel, pad: str) -> tuple[int, float]:
    """The pad geom's id and the distance of its gel face from its centre, m; GelsimError for a
    name the model lacks or a geom type without a flat +z face."""
    if not isinstance(pad, str) or not pad:
        raise GelsimError(f"pad {pad!r} is not a geom name; give the name of the gel pad's geom in the model")
    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, pad)
    if gid < 0:
        raise GelsimError(f"no geom named {pad!r} in the model; name one of its geoms as the pad "
                          f"({_geom_names(model)}), or add one with gelsim.mujoco.attach")
    gtype = mujoco.mjtGeom(int(model.geom_type[gid])).name.removeprefix("mjGEOM_").lower()
    if gtype not in SUPPORTED_PAD_TYPES:
        raise GelsimError(f"pad geom {pad!r} is a {gtype}; a gel pad needs a flat face: make it a "
                          f"{' or '.join(SUPPORTED_PAD_TYPES)} geom (its +z face is the gel)")
    return gid, float(model.geom_size[gid][SUPPORTED_PAD_TYPES[gtype]])


#: How far a pad's face may differ from the profile's field of view, as a fraction of the field
#: (MJCF sizes are written to a few digits: attach's half-sizes 0.010144 m round 20.288 mm by 0.001%).
PAD_FIELD_TOLERANCE = 0.02


def whole_px(resolution) -> tuple[int, int]:
    """``(width, height)`` px from ``resolution``: two whole numbers (320.0 is 320; 320.7 is refused,
    not truncated)."""
    try:
        w, h = resolution
        if not all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                   and math.isfinite(v) and float(v).is_integer() for v in (w, h)):
            raise ValueError
    except (TypeError, ValueError):
        raise GelsimError(f"resolution {resolution!r} is not (width, height) in whole px; give e.g. (320, 240)") from None
    return int(w), int(h)


def check_pad_size(model: mujoco.MjModel, pad_id: int, pad: str, profile: SensorProfile) -> None:
    """GelsimError unless the pad's gel face matches ``profile``'s field of view (see GelSightSensor)."""
    fw, fh = profile.field_mm
    size_mm = model.geom_size[pad_id] / MM
    gtype = mujoco.mjtGeom(int(model.geom_type[pad_id])).name.removeprefix("mjGEOM_").lower()
    if gtype == "box":
        face = (2 * float(size_mm[0]), 2 * float(size_mm[1]))
        ok = abs(face[0] - fw) <= PAD_FIELD_TOLERANCE * fw and abs(face[1] - fh) <= PAD_FIELD_TOLERANCE * fh
        shown = f"{face[0]:.2f} x {face[1]:.2f} mm"
    else:
        diag = math.hypot(fw, fh)
        face = (2 * float(size_mm[0]),)
        ok = abs(face[0] - diag) <= PAD_FIELD_TOLERANCE * diag
        shown = f"a cylinder {face[0]:.2f} mm across (the field's diagonal is {diag:.2f} mm)"
    if not ok:
        raise GelsimError(
            f"pad {pad!r} is {shown} but the {profile.name} profile sees {fw:.2f} x {fh:.2f} mm, so the sensor "
            f"would image beyond the pad or only part of it; give the box pad half-sizes {fw / 2 * MM:.6f} "
            f"{fh / 2 * MM:.6f} m in x and y (gelsim.mujoco.attach makes such a pad), or pick a profile of its size")


def with_thread_limit(render):
    """``render`` run under its sensor's ThreadLimit (``threads=`` of GelSightSensor)."""
    @functools.wraps(render)
    def limited(self):
        with self._threads:
            return render(self)
    return limited


class GelSightSensor:
    """A GelSight sensor on the geom ``pad`` of ``model`` (see the module docstring).

    ``profile``: a shipped profile name (``gelsim sensors list``), a .toml path or a SensorProfile;
    ``fidelity``: ``fast``, ``balanced`` or ``reference`` (imprint model, markers, renderer);
    ``resolution``: (width, height) px of the images (default the profile's; same field in mm);
    ``seed``: the sensor's background, marker jitter and camera-noise stream; ``noise``: camera
    noise on (True) or off. Frames depend only on the scene's state, the calls made so far since the
    last :meth:`reset` and these arguments: the same run gives the same frames.

    ``threads``: how many threads numpy's BLAS and OpenCV may use inside :meth:`render` (default 1: one
    frame is too small to share, and a BLAS thread left spinning doubled the CPU time per frame); the
    caller's own settings are given back when ``render`` returns. ``None`` leaves them alone.
    ``warmup``: the constructor renders one contact frame and throws it away, so that the one-off costs
    (compiling the imprint's kernels, 0.4-0.6 s in a new process, and filling the renderer's tables)
    are paid here, not by the first frame in contact; frames do not depend on it.

    The pad must match the profile's field of view (``profile.field_mm``): a box whose +z face is that
    rectangle (:func:`gelsim.mujoco.attach` makes one; :func:`gelsim.mujoco.attach.pad_size_m` gives its
    half-sizes), or a cylinder whose cap holds it inscribed (diameter = the field's diagonal), within
    :data:`PAD_FIELD_TOLERANCE`; any other pad is refused, since the sensor would see beyond it or only
    part of it.

    The sensor reads ``data`` at each :meth:`render`; it never changes the model or the data.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, pad: str, *,
                 profile: str | Path | SensorProfile = "gelsight-mini", fidelity: str | Fidelity = "fast",
                 resolution: tuple[int, int] | None = None, seed: int = 0, noise: bool = True,
                 threads: int | None = 1, warmup: bool = True):
        if not isinstance(model, mujoco.MjModel) or not isinstance(data, mujoco.MjData):
            raise GelsimError("GelSightSensor needs a mujoco.MjModel and its mujoco.MjData; "
                              "pass (model, data) of the running simulation")
        self._threads = ThreadLimit(threads)
        self.model, self.data, self.pad_name = model, data, pad
        self.pad_id, self.face_offset_m = find_pad(model, pad)
        prof = profile if isinstance(profile, SensorProfile) else load_profile(profile)
        if resolution is not None:
            w, h = whole_px(resolution)
            prof = prof.with_resolution(w, h)
        self.profile = prof
        self.fidelity = get_fidelity(fidelity)
        self.seed, self.noise = int(seed), bool(noise)
        # Rays start at the pad's back face: anything sunk into the pad (MuJoCo's soft contact) is seen.
        thickness_mm = 2.0 * self.face_offset_m / MM
        self.rays = PadRays(model, self.pad_id, self.face_offset_m, prof.field_mm, PHYSICS_MM_PER_PX, thickness_mm)
        if self.rays.geoms.size == 0:
            raise GelsimError(f"no geom of the model can ever touch pad {pad!r} (contype/conaffinity bits, "
                              "parent-child filtering), so the sensor would see no contact at all; give the pad "
                              "and the objects matching contype/conaffinity (MuJoCo's default 1/1 does)")
        check_pad_size(model, self.pad_id, pad, prof)
        self.renderer = Renderer(prof, self.fidelity.render_backend, supersample=self.fidelity.supersample,
                                 seed=self.seed)
        #: The printed markers' rest centres, float32 (N, 2) px (N = 0 without markers).
        self.rest_px = marker_grid(prof, seed=self.seed) if prof.markers.enabled else np.zeros((0, 2), np.float32)
        self._setup = FrameSetup.make(prof, self.fidelity, sensor_seed=self.seed, renderer=self.renderer)
        self._background = self.renderer.render(None, self._setup.flat_markers, noise=False)
        self.springs = GelSprings.of(prof)
        sag = gel_sag_mm(prof)
        self._reach_mm = (prof.gel.max_indentation_mm + (0.0 if sag is None else float(sag.max()))
                          + _REACH_SLACK_CELLS * PHYSICS_MM_PER_PX)
        self._work = work_shape(prof, self.fidelity.imprint_scale)
        self.timings_ms: dict[str, float] = {}
        if warmup:
            with self._threads:
                self._warm_up()
        self.reset()

    def _warm_up(self) -> None:
        """Press a 4 mm ball into the gel and render it (discarded): the first contact frame's one-off
        costs, paid at construction. Nothing of it is kept but what every frame rebuilds alike."""
        h, w = self._work
        fw, fh = self.profile.field_mm
        x = (np.arange(w) + 0.5) * (fw / w) - fw / 2
        y = (np.arange(h) + 0.5) * (fh / h) - fh / 2
        r2 = x[None, :] ** 2 + y[:, None] ** 2
        ball_mm = 2.0                                      # radius of the ball pressed (any small one would do)
        prot = np.sqrt(np.maximum(ball_mm ** 2 - r2, 0.0)).astype(np.float32)
        make_frame(Touch(prot, force_n=0.5), self._setup, seed=np.random.default_rng(0), noise=self.noise)

    # -- state -------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the contact history (stick anchor, slip, warm start) and restart the noise stream."""
        self.stick_slip = StickSlip()
        self._prev: Imprint | None = None
        self._frame = 0

    def background(self) -> np.ndarray:
        """The flat gel with its markers at rest, no noise: uint8 (H, W, 3) (a copy)."""
        return self._background.copy()

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (H, W), px."""
        return self.profile.shape

    # -- contacts ----------------------------------------------------------------------------------
    def pad_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """The pad's gel-face centre (m, world) and rotation (3x3, columns = sensor x, y, z in world)."""
        R = self.data.geom_xmat[self.pad_id].reshape(3, 3)
        return self.data.geom_xpos[self.pad_id] + R[:, 2] * self.face_offset_m, R

    def contact_forces(self):
        """MuJoCo's contacts on the pad: ``(normal_n, tangential_n (2,), torque_nmm, mu, body)`` with
        the force and the torque about the normal (N mm, about the contacts' force-weighted centre)
        that the touching objects exert on the gel, sensor frame; ``body`` the body pressing
        hardest. None when nothing presses the pad."""
        m, d = self.model, self.data
        n = d.ncon
        if n == 0:
            return None
        geom = d.contact.geom[:n]
        idx = np.flatnonzero((geom[:, 0] == self.pad_id) | (geom[:, 1] == self.pad_id))
        if idx.size == 0:
            return None
        face, R = self.pad_frame()
        f6 = np.zeros(6)
        forces = np.zeros((idx.size, 3))
        torsion = np.zeros(3)                          # torsional friction on the gel, world, N m
        for k, i in enumerate(idx):
            mujoco.mj_contactForce(m, d, int(i), f6)
            frame = d.contact.frame[i].reshape(3, 3)
            fw = frame.T @ f6[:3]                      # on geom2, world
            sign = 1.0 if geom[i, 1] == self.pad_id else -1.0
            forces[k] = sign * fw
            if d.contact.dim[i] >= 4:                  # torsional friction: a torque about the normal
                torsion += sign * f6[3] * frame[0]
        local = forces @ R                             # sensor frame
        normal = -local[:, 2]                          # the objects push into the gel, along -z
        total = float(normal.sum())
        if not total > 0.0:
            return None
        pos = (d.contact.pos[idx] - face) @ R / MM     # contact points, sensor frame, mm
        w = np.maximum(normal, 0.0)
        centre = (w[:, None] * pos).sum(0) / max(float(w.sum()), 1e-12)
        rel = pos - centre
        torque = float((rel[:, 0] * local[:, 1] - rel[:, 1] * local[:, 0]).sum()) + float(torsion @ R[:, 2]) / MM
        other = np.where(geom[idx, 0] == self.pad_id, geom[idx, 1], geom[idx, 0])
        body = int(m.geom_bodyid[other[int(np.argmax(normal))]])
        mu = float(d.contact.friction[idx[int(np.argmax(normal))], 0])
        return total, local[:, :2].sum(0), torque, mu, body

    def shear_twist(self, history: StickSlip, body: int, normal_n: float, tang_n: np.ndarray, torque_nmm: float,
                    mu: float) -> tuple[np.ndarray, float, bool]:
        """Gel shear (mm, (2,)) and twist (degrees) with the stick/slip model (see the module docstring), from
        the pad's and ``body``'s poses in ``data`` now; ``history``: the pad's :class:`StickSlip` (updated)."""
        d = self.data
        return history.step(self.springs, body, self.pad_frame(), (d.xpos[body], d.xmat[body].reshape(3, 3)),
                            normal_n, tang_n, torque_nmm, mu)

    # -- the frame ---------------------------------------------------------------------------------
    def protrusion_mm(self, gaps_mm: np.ndarray) -> np.ndarray:
        """The imprint grid's protrusion map (float32, :func:`gelsim.gel.work_shape`, mm) from a ray
        gap map: how far each point stands out towards the gel relative to a plane ``reach`` below
        the first touch (deeper surface cannot reach the gel)."""
        g = np.where(np.isfinite(gaps_mm), gaps_mm, np.float32(np.inf))
        top = float(g.min())
        prot = np.maximum(np.float32(top + self._reach_mm) - g, 0.0).astype(np.float32)
        patch = HeightPatch(prot, self.rays.origin_mm, self.rays.cell_mm)
        h, w = self._work
        fw = self.profile.field_mm[0]
        return np.maximum(patch.sample((h, w), fw / w, 0.0, 0.0, 0.0), 0.0)

    @with_thread_limit
    def render(self) -> TactileFrame:
        """The tactile frame of the scene's current state (``data`` as it is now)."""
        timer = StageTimer()
        t0 = timer.clock()
        prof = self.profile
        rng = np.random.default_rng([self.seed, self._frame])
        self._frame += 1
        found = self.contact_forces()
        timer.lap("forces")
        gaps = None
        if found is not None:
            gaps = self.rays.gaps_mm(self.data)
            timer.lap("rays")
            if not np.isfinite(gaps).any():   # pressed by something outside the field: no imprint
                found = None
        touch, slipping = None, False
        if found is None:
            self.stick_slip.release()
        else:
            normal, tang, torque, mu, body = found
            prot = self.protrusion_mm(gaps)
            shear, twist, slipping = self.shear_twist(self.stick_slip, body, normal, tang, torque, mu)
            touch = Touch(prot, force_n=normal, shear_mm=tuple(shear), twist_deg=twist, warm=self._prev)
            timer.lap("geometry")
        timer.restart()
        made = make_frames([FrameRequest(touch, rng, self.noise)], self._setup)
        imprint, markers, rgb = made.parts[0].imprint, made.parts[0].markers, made.parts[0].frame
        self._prev = imprint
        # (the optics stage has always been "render" here)
        self.timings_ms = {("render" if k == "optics" else k): v * 1e3 for k, v in {**timer.take(), **made.seconds}.items()}
        self.timings_ms["total"] = (timer.clock() - t0) * 1e3
        xy = self.rest_px.copy() if markers is None or imprint is None else markers.xy_px
        if imprint is None:
            h, w = prof.shape
            return TactileFrame(rgb, xy, self.rest_px.copy(), 0.0, np.zeros(2), np.zeros((h, w), bool),
                                np.zeros((h, w), np.float32), np.zeros(2), 0.0, False, False, float(self.data.time))
        return TactileFrame(rgb, xy, self.rest_px.copy(), float(normal), np.asarray(tang, float), imprint.contact_mask,
                            imprint.depth_mm, np.asarray(shear, float), float(twist), True, bool(slipping),
                            float(self.data.time))

    def close(self) -> None:
        """Free the renderer's resources (a GL context for the pyrender backend)."""
        self.renderer.close()
