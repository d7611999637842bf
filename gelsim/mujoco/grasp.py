"""A parallel gripper with a GelSight pad on each finger, over a table with one object to grasp.

Shared by ``examples/grasp.py`` and :class:`gelsim.envs.GraspEnv`. The hand hangs from a vertical
slide (position servo); two fingers on horizontal slides along world y close on the object with a
force (motors: the grip force is the command, N); :func:`gelsim.mujoco.attach` puts a pad on
each finger, facing the other. Objects (:data:`OBJECTS`): a sphere, a cube turned 45 degrees about
the vertical so that the pads meet two of its edges, and a hexagonal bolt head built as a mesh in
code (its flats face the pads, its shank points up). SI units, as MuJoCo's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from ..errors import GelsimError
from .attach import attach, pad_size_m

OBJECTS = ("sphere", "box_edge", "bolt")
# Scene sizes, m. The objects are sized to the pads (a GelSight Mini's field is 20 x 15 mm).
SPHERE_RADIUS_M = 0.015
CUBE_HALF_M = 0.012
BOLT_ACROSS_FLATS_M = 0.024     # an M16 bolt's head (ISO 4017: 24 mm across flats, 10 mm high)
BOLT_HEAD_HEIGHT_M = 0.010
BOLT_SHANK_RADIUS_M = 0.008
BOLT_SHANK_LENGTH_M = 0.030
OBJECT_MASS_KG = 0.05
# The hand's travel: it starts this high above the grasp height, m.
APPROACH_M = 0.04
FINGER_OPEN_M = 0.035           # each finger's rest distance from the hand's axis, m
FINGER_DAMPING_NS_M = 20.0      # the fingers close at grip / damping, about 0.1-0.4 m/s
HAND_KP_N_M = 2000.0            # the arm's stiffness along z (it holds the 50 g object within 0.3 mm)
PAD_CLEARANCE_M = 0.001         # the pads' lower edge above the table at the grasp height, m


@dataclass(frozen=True)
class GraspScene:
    """The compiled scene: ``model``, ``data``, the pads' geom names (left, right), the object's body
    name, the height of the pads' centres above the table when the hand's actuator target (its
    slide's position) is 0, m, and the actuator ids (hand z position, left and right grip force)."""
    model: mujoco.MjModel
    data: mujoco.MjData
    pads: tuple[str, str]
    object_body: str
    grasp_z_m: float
    act_hand: int
    act_left: int
    act_right: int


def hex_prism(across_flats_m: float, height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A hexagonal prism's vertices (12, 3) m, centred, axis along z, two flats facing +-y, and its
    triangles (20, 3), outward-wound."""
    r = across_flats_m / math.sqrt(3.0)         # corner radius
    ang = np.radians(np.arange(6) * 60.0)       # corners at 0, 60, ... degrees: flats face +-y
    ring = np.column_stack([r * np.cos(ang), r * np.sin(ang)])
    verts = np.vstack([np.column_stack([ring, np.full(6, -height_m / 2)]),
                       np.column_stack([ring, np.full(6, height_m / 2)])])
    faces = []
    for i in range(6):
        j = (i + 1) % 6
        faces += [[i, j, 6 + j], [i, 6 + j, 6 + i]]
    faces += [[0, i + 1, i] for i in range(1, 5)]       # bottom cap, facing -z
    faces += [[6, 6 + i, 6 + i + 1] for i in range(1, 5)]  # top cap, facing +z
    return verts, np.asarray(faces, dtype=np.int32)


def _add_object(spec: mujoco.MjSpec, kind: str) -> tuple[str, float]:
    """The object on the table; returns its body name and the height of its grasp centre, m."""
    body = spec.worldbody.add_body(name="object")
    body.add_freejoint(name="object_free")
    if kind == "sphere":
        body.pos = [0, 0, SPHERE_RADIUS_M]
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[SPHERE_RADIUS_M], mass=OBJECT_MASS_KG,
                      rgba=[0.8, 0.3, 0.2, 1])
        return "object", SPHERE_RADIUS_M
    if kind == "box_edge":
        body.pos = [0, 0, CUBE_HALF_M]
        body.quat = [math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)]   # 45 degrees about z
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[CUBE_HALF_M] * 3, mass=OBJECT_MASS_KG,
                      rgba=[0.2, 0.5, 0.8, 1])
        return "object", CUBE_HALF_M
    if kind == "bolt":
        verts, faces = hex_prism(BOLT_ACROSS_FLATS_M, BOLT_HEAD_HEIGHT_M)
        spec.add_mesh(name="bolt_head", uservert=verts.ravel().tolist(), userface=faces.ravel().tolist())
        body.pos = [0, 0, BOLT_HEAD_HEIGHT_M / 2]
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname="bolt_head", mass=OBJECT_MASS_KG * 0.6,
                      rgba=[0.6, 0.6, 0.65, 1])
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[BOLT_SHANK_RADIUS_M, BOLT_SHANK_LENGTH_M / 2],
                      pos=[0, 0, BOLT_HEAD_HEIGHT_M / 2 + BOLT_SHANK_LENGTH_M / 2], mass=OBJECT_MASS_KG * 0.4,
                      rgba=[0.6, 0.6, 0.65, 1])
        return "object", BOLT_HEAD_HEIGHT_M / 2
    raise GelsimError(f"unknown object {kind!r}; choose one of {', '.join(OBJECTS)}")


def build_grasp_scene(kind: str = "sphere", *, profile: str = "gelsight-mini") -> GraspScene:
    """The gripper over ``kind`` (one of :data:`OBJECTS`), compiled, at rest with the hand up."""
    spec = mujoco.MjSpec()
    spec.option.timestep = 0.002
    spec.option.noslip_iterations = 3   # no creep of the pinched object between the pads
    spec.worldbody.add_light(pos=[0, -0.3, 0.5], dir=[0, 0.5, -1])
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.3, 0.3, 0.01],
                            rgba=[0.35, 0.35, 0.3, 1])
    obj_body, centre_z = _add_object(spec, kind)
    hx, hy, hz = pad_size_m(profile)
    grasp_z = max(centre_z, hy + PAD_CLEARANCE_M)   # the pads' lower edge stays off the table
    hand = spec.worldbody.add_body(name="hand", pos=[0, 0, grasp_z])
    hand.add_joint(name="hand_z", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1], damping=40.0)
    hand.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.05, 0.008], pos=[0, 0, 0.045], mass=0.3,
                  rgba=[0.25, 0.25, 0.28, 1], contype=0, conaffinity=0)
    sides = (("left", 1.0), ("right", -1.0))
    for side, sgn in sides:
        f = hand.add_body(name=f"{side}_finger", pos=[0, sgn * FINGER_OPEN_M, 0])
        f.add_joint(name=f"{side}_slide", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, -sgn, 0],
                    range=[0, FINGER_OPEN_M - 0.002], damping=FINGER_DAMPING_NS_M)
        f.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx + 0.002, 0.004, hy + 0.02], pos=[0, sgn * 0.004, 0.02],
                   mass=0.05, rgba=[0.3, 0.3, 0.33, 1], contype=0, conaffinity=0)
        # the pad faces the other finger; image rows run down the finger (world -z)
        attach(spec, f"{side}_finger", f"{side}_pad", facing=(0, -sgn, 0), x_axis=(-sgn, 0, 0), profile=profile)
    spec.add_actuator(name="hand", target="hand_z", trntype=mujoco.mjtTrn.mjTRN_JOINT,
                      gainprm=[HAND_KP_N_M] + [0] * 9, biastype=mujoco.mjtBias.mjBIAS_AFFINE,
                      biasprm=[0, -HAND_KP_N_M, 0] + [0] * 7)
    for side, _ in sides:
        spec.add_actuator(name=f"{side}_grip", target=f"{side}_slide", trntype=mujoco.mjtTrn.mjTRN_JOINT,
                          gainprm=[1.0] + [0] * 9, ctrlrange=[-20, 20], ctrllimited=True)
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[model.joint("hand_z").qposadr[0]] = APPROACH_M
    data.ctrl[model.actuator("hand").id] = APPROACH_M
    data.ctrl[model.actuator("left_grip").id] = -1.0
    data.ctrl[model.actuator("right_grip").id] = -1.0
    mujoco.mj_forward(model, data)
    return GraspScene(model, data, ("left_pad", "right_pad"), obj_body, grasp_z, model.actuator("hand").id,
                      model.actuator("left_grip").id, model.actuator("right_grip").id)


def scripted_controls(t_s: float, grip_n: float = 4.0, lift_m: float = 0.04) -> tuple[float, float]:
    """The example's grasp: (hand z target m relative to the grasp height, grip force N) at time
    ``t_s``: descend (0-0.5 s), close (0.5-0.9 s), lift (0.9-1.5 s), hold (after)."""
    def ramp(a, b):
        u = min(max((t_s - a) / (b - a), 0.0), 1.0)
        return 0.5 - 0.5 * math.cos(math.pi * u)
    z = APPROACH_M * (1.0 - ramp(0.0, 0.5)) + lift_m * ramp(0.9, 1.5)
    grip = -1.0 + (grip_n + 1.0) * ramp(0.5, 0.9)
    return z, grip


def press_scene(force_n: float, diameter_mm: float, *, profile: str = "gelsight-mini",
                offset_mm: tuple[float, float] = (0.0, 0.0), settle_steps: int = 2500):
    """A test rig: a pad ``pad`` facing +z at the origin and a sphere of ``diameter_mm`` on a slide
    joint pushed into it with ``force_n`` N (no gravity), ``offset_mm`` off the pad's axis (pad
    frame x, y), stepped until it settles. Returns ``(model, data)``."""
    spec = mujoco.MjSpec()
    spec.option.gravity = [0, 0, 0]
    spec.worldbody.add_body(name="base")
    attach(spec, "base", "pad", facing=(0, 0, 1), x_axis=(1, 0, 0), profile=profile)
    r = diameter_mm / 2 * 1e-3
    ball = spec.worldbody.add_body(name="ball", pos=[offset_mm[0] * 1e-3, offset_mm[1] * 1e-3, r + 2e-4])
    ball.add_joint(name="z", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1], damping=2.0)
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r], mass=0.01)
    spec.add_actuator(name="push", target="z", trntype=mujoco.mjtTrn.mjTRN_JOINT, gainprm=[1] + [0] * 9)
    m = spec.compile()
    d = mujoco.MjData(m)
    d.ctrl[0] = -force_n
    for _ in range(settle_steps):
        mujoco.mj_step(m, d)
    return m, d
