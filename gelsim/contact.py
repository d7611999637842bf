"""Contact simulation of a hand-held GelSight on a fabric, in MuJoCo.

The scene, built in code for each sequence (compiling it costs about 2 ms):

* the fabric: a MuJoCo heightfield of the coarse :class:`Surface` (0.1-0.25 mm cells), max-pooled
  to ``PHYSICS_CELL_MM`` cells (0.4 mm) for speed;
* the sensor base B, driven by the hand along the :class:`~gelsim.motion.Motion`: slide joints
  x, y (position servos: the hand is stiff in the plane), z (a force-controlled drive: descend at
  the approach speed, then press to the target force, hold, release, lift) and a yaw hinge (position
  servo) carrying the rigid pad box that touches the heightfield (the hand's small tilt is applied by
  tilting the fabric the other way, see simulate);
* the gel's contact surface P, carried by B on compliant in-plane joints (x, y, yaw) whose springs
  are the gel's shear stiffness ``G A / t`` and torsional stiffness ``G J / t``
  (``G = E / (2 (1 + nu))``, ``A`` the pad area, ``J`` its polar moment, ``t`` the thickness).

Friction between the gel and the fabric acts on P's motion relative to the fabric as MuJoCo dry
friction (``frictionloss`` on two fixed tendons, P's world x and y, and on P's yaw), with limits
``mu N`` and ``mu N r_eff`` (``r_eff`` the mean distance of the pad's points from its centre, i.e.
uniform pressure) updated every step from the simulated normal force, and made rigid by MuJoCo's
noslip pass. Why not MuJoCo's own contact friction: heightfield contacts are capped at 50 per geom
pair and MuJoCo finds them in row order, so on a flat-pressed pad all of them lie along one edge
(measured: every contact within 1 mm of the pad's first row). Translation friction would still be
``mu N``, but torsion would get the wrong lever arms and a spurious sideways force; splitting the
pad into 3x3 sub-boxes fixes that at 25x the cost (3.4 s per simulated second, measured). The
heightfield contact itself is frictionless and gives the normal force, the first touch and the
stand-off height.

P lags the base while the friction holds (stick: the gel shears), then slides once the spring force
exceeds the friction limit (slip). The offset of P from B is the gel's shear (``shear_mm``) and
torsion (``twist_deg``). MuJoCo's soft contact stops the pad at the surface (a few tenths of a mm
at a few N): the gel imprint is computed from geometry downstream (:mod:`gelsim.gel`), not from
this penetration.

The pad is a flat box although the vitac gel is a shallow dome (``GelSpec.dome_radius_mm``): MuJoCo's
curved geoms (ellipsoid, mesh) against a heightfield cost 11-38x the box's step time (measured), and
the physics needs only the force, the first touch and the shear, which a dome of 80 mm radius changes
by less than the tilt does. The dome's sag enters the imprint downstream (:func:`gelsim.gel.press`).

Units: inputs and outputs in mm, N, degrees and s; MuJoCo runs in SI units (m, kg, N, s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import mujoco
import numpy as np

from .errors import GelsimError
from .fidelity import Fidelity
from .motion import Motion
from .sensor import SensorProfile

MM = 1e-3  # metres per mm

# Effective moving mass of sensor and hand along the normal, kg. A GelSight body weighs ~0.1-0.2 kg
# and the hand adds to it; with the contact time constant below it also sets the contact stiffness
# (m / tau^2 = 12 kN/m: 0.25 mm of stand-off compression at 3 N, like the gel's own indentation).
SENSOR_MASS_KG = 0.3
# Yaw inertia of sensor and hand, kg m^2: the wrist turns the sensor, so this is far above the
# sensor's own ~1e-5; it keeps the yaw servo's natural frequency (~140 rad/s) resolvable at dt 2 ms.
SENSOR_YAW_INERTIA_KGM2 = 1e-3
# Natural period of the gel's shear and torsion springs with the pad's inertia, s. The real gel layer
# (~0.6 g) would ring at ~4 kHz, far faster than any physics step: at stick-slip events the pad then
# overshot by half its shear within one 1 ms step (measured). The pad's inertia is set so that it
# relaxes over 10 ms instead: resolvable at every fidelity's step, yet a third of a camera frame.
GEL_PERIOD_S = 0.01
# Hand stiffness in the plane, N/m and N m/rad: a position servo stiff enough that 5 N of friction
# lags it by 0.25 mm (the hand does follow the intended path); critically damped with the mass above.
HAND_KP_N_M = 2.0e4
HAND_KP_YAW_NM_RAD = 20.0
# Damping of the normal drive, N s/m: the approach runs at v = force / damping, and this damping
# makes the first touch gentle (0.05-0.2 N at 5-20 mm/s) without slowing force changes
# (damping / contact stiffness = 1 ms).
Z_DAMPING_NS_M = 10.0
# Damping ratio of the gel's shear and torsion springs: silicone is lossy; 0.5 stops ringing after slip.
GEL_DAMPING_RATIO = 1.0
# MuJoCo contact time constant, s: the stiffness of the pad-fabric contact (see SENSOR_MASS_KG).
# MuJoCo raises it to 2 dt when the step is coarser, which only softens the contact.
CONTACT_TIMECONST_S = 0.005
# MuJoCo contact impedance (solimp d0, dwidth, width m): nearly constant and high, so the stand-off
# depth is proportional to force.
CONTACT_SOLIMP = (0.95, 0.99, 0.001)
# Thickness of the rigid pad box and of the heightfield's base slab, mm: thick enough that no
# penetration at a few newtons can tunnel through either.
PAD_BOX_MM = 2.0
HFIELD_BASE_MM = 3.0
# A pad point moving faster than this over the fabric is slipping, mm/s. Tremor moves the hand at up
# to 2 pi f A ~ 4 mm/s, but a sticking pad stays put (the gel shear absorbs it); noslip leaves a sticking
# pad at < 0.01 mm/s (measured), a slipping one moves at the hand's speed (several mm/s).
SLIP_SPEED_MM_S = 0.5
# MuJoCo noslip iterations (post-pass that removes soft-friction creep): 0, because the friction
# constraints below are made nearly rigid instead, and noslip tripled the cost (measured).
NOSLIP_ITERATIONS = 0
# Softness of the gel-fabric dry friction (MuJoCo solref/solimp of the frictionloss constraints).
# MuJoCo friction is a regularised constraint that lets a sticking pad creep at a speed proportional
# to (1 - d) / d; d = 0.9999 keeps that creep below 0.01 mm/s (measured) so stick is real stick.
FRICTION_SOLREF = (0.005, 1.0)
FRICTION_SOLIMP = (0.9999, 0.9999, 0.001)
# Cell size of the heightfield MuJoCo sees, mm. MuJoCo tests every cell under the pad for contact,
# so the cost grows with the cell count: at 0.2 mm a step took 3x longer than at 0.4 mm, with the same
# normal force, stand-off and torsion (measured, within 1.5 %). Finer surfaces are max-pooled to this
# size: the highest fibre in each cell is kept, so the first touch and the stand-off are unchanged.
# The fine texture is the gel model's business.
PHYSICS_CELL_MM = 0.4
# Camera exposure, s: a frame's forces are averaged, and its contact flag OR-ed, over the steps of
# the exposure. assumed: a 30 Hz webcam exposes for a good part of its frame; 8 ms is short enough to
# keep motion sharp. It also bridges the one-step losses of contact a rigid pad has on a bumpy
# surface when the highest fibre under it leaves its edge (a soft gel would stay in touch).
EXPOSURE_S = 0.008
# The camera must see each frame at a distinct physics step with room to resolve a touch between two frames.
MIN_STEPS_PER_FRAME = 8


@dataclass(frozen=True)
class Surface:
    """What the physics needs of the touched object (fabric frame, mm).

    ``heights_mm``: float32 (H, W) heights >= 0 above the fabric's base plane; pixel (i, j) (row,
    column) lies at ``(x, y) = origin_mm + (j, i) * mm_per_px``. ``friction``: gel-fabric Coulomb mu.
    """
    heights_mm: np.ndarray
    mm_per_px: float
    origin_mm: tuple[float, float]
    friction: float

    def __post_init__(self) -> None:
        h = self.heights_mm
        if not isinstance(h, np.ndarray) or h.ndim != 2 or min(h.shape) < 2:
            raise GelsimError("Surface.heights_mm must be a 2-D array of at least 2x2 cells; pass a heightfield")
        if not np.all(np.isfinite(h)) or float(h.min()) < 0:
            raise GelsimError("Surface.heights_mm must be finite and >= 0 mm; shift the heightfield up")
        if not self.mm_per_px > 0:
            raise GelsimError(f"Surface.mm_per_px {self.mm_per_px} must be > 0")
        if not 0 < self.friction <= 5:
            raise GelsimError(f"Surface.friction {self.friction} must be in (0, 5]; check the fabric's friction")
        object.__setattr__(self, "heights_mm", np.ascontiguousarray(h, dtype=np.float32))

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) covered by the pixel centres, mm."""
        H, W = self.heights_mm.shape
        x0, y0 = self.origin_mm
        return (x0, y0, x0 + (W - 1) * self.mm_per_px, y0 + (H - 1) * self.mm_per_px)

    def height_at(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Bilinear height (mm) at fabric-frame points; points outside take the edge value."""
        H, W = self.heights_mm.shape
        u = np.clip((np.asarray(x_mm) - self.origin_mm[0]) / self.mm_per_px, 0, W - 1)
        v = np.clip((np.asarray(y_mm) - self.origin_mm[1]) / self.mm_per_px, 0, H - 1)
        j0 = np.minimum(np.floor(u).astype(int), W - 2)
        i0 = np.minimum(np.floor(v).astype(int), H - 2)
        fu, fv = u - j0, v - i0
        h = self.heights_mm
        return ((1 - fv) * ((1 - fu) * h[i0, j0] + fu * h[i0, j0 + 1])
                + fv * ((1 - fu) * h[i0 + 1, j0] + fu * h[i0 + 1, j0 + 1]))


@dataclass(frozen=True)
class ContactFrames:
    """One row per camera frame (T = motion.num_frames). Fabric frame for positions, sensor frame
    (x, y of the image, rotated by yaw from the fabric's) for forces and gel deformation."""
    time_s: np.ndarray             # (T,) camera time, frame 0 at 0
    position_mm: np.ndarray        # (T, 3) sensor centre, fabric frame; z = undeformed gel surface height
    yaw_deg: np.ndarray            # (T,) sensor rotation about the normal (+: from +x towards +y)
    tilt_deg: np.ndarray           # (T, 2) roll, pitch (gel lower at +y, +x)
    normal_force_n: np.ndarray     # (T,) >= 0, force pressing the gel
    tangential_force_n: np.ndarray # (T, 2) in-plane force of the fabric on the gel, sensor frame
    in_contact: np.ndarray         # (T,) bool
    slipping: np.ndarray           # (T,) bool, the gel surface slides over the fabric
    shear_mm: np.ndarray           # (T, 2) contact surface displacement relative to the sensor base, sensor frame
    twist_deg: np.ndarray          # (T,) contact surface rotation relative to the sensor base
    first_contact_frame: int = -1  # index of the first in-contact frame (= motion.precontact_frames)
    contact_time_s: float = float("nan")  # camera time of the first touch

    def to_dict(self) -> dict[str, np.ndarray]:
        """The per-frame arrays (leading dimension T); the two scalars stay attributes."""
        return {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)
                if f.name not in ("first_contact_frame", "contact_time_s")}


def gel_stiffness(profile: SensorProfile) -> tuple[float, float, float]:
    """(shear N/m, torsion N m/rad, r_eff m) of the gel pad of ``profile``.

    Shear of an elastic layer bonded to a rigid backing: ``G A / t``; torsion ``G J / t`` with
    ``J = A (w^2 + h^2) / 12`` the rectangle's polar moment; r_eff the mean distance of its points
    from the centre (the friction torque arm under uniform pressure).
    """
    g = profile.gel
    G = g.young_modulus_mpa * 1e6 / (2 * (1 + g.poisson_ratio))
    w, h = (v * MM for v in profile.field_mm)
    A, t = w * h, g.thickness_mm * MM
    J = A * (w * w + h * h) / 12
    u = (np.arange(64) + 0.5) / 64 - 0.5
    r_eff = float(np.mean(np.hypot(u[None, :] * w, u[:, None] * h)))
    return G * A / t, G * J / t, r_eff


def build_model(surface: Surface, profile: SensorProfile, fidelity: Fidelity,
                friction_axis_deg: float = 0.0) -> mujoco.MjModel:
    """Compile the MuJoCo scene for ``surface`` (see the module docstring); the pad is level.

    MuJoCo's dry friction acts per tendon, so the friction limit is a box, not a disk, in the plane:
    ``friction_axis_deg`` aligns the box with the main sliding direction (a slip's direction), where
    it is exact; across it the limit is the same mu N.
    """
    ca, sa = math.cos(math.radians(friction_axis_deg)), math.sin(math.radians(friction_axis_deg))
    H, W = surface.heights_mm.shape
    x0, y0, x1, y1 = surface.extent_mm
    elev = max(float(surface.heights_mm.max()), 1e-4)  # MuJoCo needs a positive elevation
    k_shear, k_tors, _ = (float(v) for v in gel_stiffness(profile))
    fw, fh = (v * MM / 2 for v in profile.field_mm)
    w2 = (GEL_PERIOD_S / (2 * math.pi)) ** 2
    m_pad = k_shear * w2
    i_pad = k_tors * w2
    c_shear = 2 * GEL_DAMPING_RATIO * math.sqrt(k_shear * m_pad)
    c_tors = 2 * GEL_DAMPING_RATIO * math.sqrt(k_tors * i_pad)
    hand_kv = 2 * math.sqrt(HAND_KP_N_M * SENSOR_MASS_KG)
    hand_kv_yaw = 2 * math.sqrt(HAND_KP_YAW_NM_RAD * SENSOR_YAW_INERTIA_KGM2)
    bt = PAD_BOX_MM * MM / 2
    dt = fidelity.physics_dt_s
    fric_ref = f"{FRICTION_SOLREF[0]} {FRICTION_SOLREF[1]}"
    fric_imp = " ".join(str(v) for v in FRICTION_SOLIMP)
    xml = f"""<mujoco model="gelsim-contact">
  <compiler angle="radian" autolimits="true"/>
  <size memory="8M"/>
  <option timestep="{dt!r}" gravity="0 0 0" integrator="discrete" cone="elliptic" solver="Newton"
          noslip_iterations="{NOSLIP_ITERATIONS}"/>
  <asset>
    <hfield name="fabric" nrow="{H}" ncol="{W}"
            size="{(x1 - x0) / 2 * MM!r} {(y1 - y0) / 2 * MM!r} {elev * MM!r} {HFIELD_BASE_MM * MM!r}"/>
  </asset>
  <worldbody>
    <geom name="fabric" type="hfield" hfield="fabric" pos="{(x0 + x1) / 2 * MM!r} {(y0 + y1) / 2 * MM!r} 0"
          condim="1" solref="{CONTACT_TIMECONST_S} 1" solimp="{CONTACT_SOLIMP[0]} {CONTACT_SOLIMP[1]} {CONTACT_SOLIMP[2]}"/>
    <body name="base">
      <joint name="bx" type="slide" axis="1 0 0"/>
      <joint name="by" type="slide" axis="0 1 0"/>
      <joint name="bz" type="slide" axis="0 0 1" damping="{Z_DAMPING_NS_M}"/>
      <inertial pos="0 0 0" mass="{SENSOR_MASS_KG}" diaginertia="1e-4 1e-4 1e-4"/>
      <body name="sensor">
        <joint name="yaw" type="hinge" axis="0 0 1"/>
        <inertial pos="0 0 0" mass="1e-3" diaginertia="{SENSOR_YAW_INERTIA_KGM2} {SENSOR_YAW_INERTIA_KGM2} {SENSOR_YAW_INERTIA_KGM2}"/>
        <geom name="pad" type="box" size="{fw!r} {fh!r} {bt!r}" pos="0 0 {bt!r}" mass="0" condim="1"
              solref="{CONTACT_TIMECONST_S} 1" solimp="{CONTACT_SOLIMP[0]} {CONTACT_SOLIMP[1]} {CONTACT_SOLIMP[2]}"/>
      </body>
      <body name="gel">
        <joint name="px" type="slide" axis="1 0 0" stiffness="{k_shear!r}" damping="{c_shear!r}"/>
        <joint name="py" type="slide" axis="0 1 0" stiffness="{k_shear!r}" damping="{c_shear!r}"/>
        <joint name="pyaw" type="hinge" axis="0 0 1" solreffriction="{fric_ref}" solimpfriction="{fric_imp}"/>
        <inertial pos="0 0 0" mass="{m_pad!r}" diaginertia="{i_pad!r} {i_pad!r} {i_pad!r}"/>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="gel_x" solreffriction="{fric_ref}" solimpfriction="{fric_imp}">
      <joint joint="bx" coef="{ca!r}"/><joint joint="px" coef="{ca!r}"/><joint joint="by" coef="{sa!r}"/><joint joint="py" coef="{sa!r}"/>
    </fixed>
    <fixed name="gel_y" solreffriction="{fric_ref}" solimpfriction="{fric_imp}">
      <joint joint="bx" coef="{-sa!r}"/><joint joint="px" coef="{-sa!r}"/><joint joint="by" coef="{ca!r}"/><joint joint="py" coef="{ca!r}"/>
    </fixed>
    <fixed name="gel_twist" stiffness="{k_tors!r}" damping="{c_tors!r}" springlength="0">
      <joint joint="pyaw" coef="1"/><joint joint="yaw" coef="-1"/>
    </fixed>
  </tendon>
  <actuator>
    <position name="hand_x" joint="bx" kp="{HAND_KP_N_M}" kv="{hand_kv!r}"/>
    <position name="hand_y" joint="by" kp="{HAND_KP_N_M}" kv="{hand_kv!r}"/>
    <motor name="hand_z" joint="bz"/>
    <position name="hand_yaw" joint="yaw" kp="{HAND_KP_YAW_NM_RAD}" kv="{hand_kv_yaw!r}"/>
  </actuator>
</mujoco>"""
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as e:  # mujoco reports compile errors as ValueError
        raise GelsimError(f"MuJoCo could not build the contact scene ({e}); check the sensor profile and surface") from None
    model.hfield_data[:] = (surface.heights_mm / elev).ravel()
    return model


def _smooth_ramp(u: np.ndarray) -> np.ndarray:
    """0 -> 1 with zero slope at both ends (half cosine), for u in [0, 1] (clipped)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(u, 0.0, 1.0))


_WARNINGS = ("mjWARN_BADQACC", "mjWARN_BADQVEL", "mjWARN_BADQPOS")


def _unstable(where_t: float, what: str) -> GelsimError:
    return GelsimError(f"physics became unstable at t={where_t:.3f} s ({what}); lower physics_dt_s (fidelity) "
                       "or the gel's young_modulus_mpa (sensor profile)")


def simulate(motion: Motion, surface: Surface, profile: SensorProfile, fidelity: Fidelity) -> ContactFrames:
    """Simulate one hand-held motion on ``surface``; one row per camera frame (profile.image.fps_hz).

    The camera clock is set so that the first touch falls ``motion.contact_phase`` of a frame period
    before frame ``motion.precontact_frames``: that frame is the first in contact, exactly.
    Deterministic: the same inputs give identical outputs. Raises GelsimError if the physics becomes
    unstable (naming the parameter to change) or the surface does not cover the sensor's travel.
    """
    dt = float(fidelity.physics_dt_s)
    fps = float(profile.image.fps_hz)
    frame_s = 1.0 / fps
    if dt * MIN_STEPS_PER_FRAME > frame_s:
        raise GelsimError(f"physics_dt_s {dt} is too coarse for a {fps:g} Hz camera (a frame needs at least "
                          f"{MIN_STEPS_PER_FRAME} physics steps); lower physics_dt_s (fidelity) below "
                          f"{frame_s / MIN_STEPS_PER_FRAME:.4f} s")
    _check_coverage(motion, surface, profile)
    k_shear, k_tors, r_eff = gel_stiffness(profile)
    # Tilt: the hand holds the sensor a few degrees off the fabric's normal. MuJoCo's heightfield
    # collision tests every cell under a tilted box when fewer than 50 cells touch (measured 1.6 s
    # instead of 0.08 s per sequence), so the scene is rotated instead: the pad stays level and the
    # fabric gets the opposite tilt (a plane added to its heights). The hand then presses along the
    # sensor's axis and slides in the sensor's plane, as it does; in-plane lengths differ from the
    # fabric's by cos(tilt) > 0.998 at 3 degrees.
    surface, plane = _tilted(_pooled(surface, PHYSICS_CELL_MM), motion)
    fric_axis = motion.slip_direction_deg if motion.action == "slip" else 0.0
    model = build_model(surface, profile, fidelity, fric_axis)
    data = mujoco.MjData(model)
    mu = surface.friction
    P, T, phi = motion.precontact_frames, motion.num_frames, motion.contact_phase
    v_app = motion.approach_speed_mm_s * MM
    jid = {n: model.joint(n).id for n in ("bx", "by", "bz", "yaw", "px", "py", "pyaw")}
    qa = {n: int(model.jnt_qposadr[i]) for n, i in jid.items()}
    va = {n: int(model.jnt_dofadr[i]) for n, i in jid.items()}
    ten_x, ten_y = model.tendon("gel_x").id, model.tendon("gel_y").id
    dof_pyaw = va["pyaw"]
    pad_geom = model.geom("pad").id
    warn_ids = [int(getattr(mujoco.mjtWarning, w)) for w in _WARNINGS]

    # Where the pad first meets the fabric: its lowest point relative to the fabric under it.
    x_start, y_start = motion.start_xy_mm
    top_mm = _top_under_pad(surface, profile, x_start, y_start)
    A, f_tr = motion.tremor_amplitude_mm * MM, motion.tremor_frequency_hz
    ph = motion.tremor_phase_rad

    def tremor(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = 2 * np.pi * f_tr * t
        return A * np.sin(w + ph[0]), A * np.sin(w + ph[1])

    margin_s = 0.5 * frame_s
    max_steps = int(math.ceil(((P + 2) * frame_s + 1.0 + T * frame_s) / dt)) + 2
    qlog = np.zeros((max_steps, model.nq))
    vlog = np.zeros((max_steps, model.nv))
    flog = np.zeros((max_steps, model.nv))   # constraint forces per dof (contact + friction)
    clog = np.zeros(max_steps, dtype=bool)   # pad touching
    bz_dof = va["bz"]
    ten_fl = model.tendon_frictionloss
    dof_fl = model.dof_frictionloss
    check_every = max(1, int(round(frame_s / dt)))
    for _attempt in range(3):
        lead_s = (P - phi) * frame_s + margin_s  # planned time of the first touch
        max_approach = int(math.ceil((lead_s + 0.5) / dt))  # 0.5 s: a generous allowance for estimate errors
        if max_approach + T * frame_s / dt + 2 > max_steps:
            max_steps = int(max_approach + T * frame_s / dt + 2)
            qlog = np.zeros((max_steps, model.nq))
            vlog = np.zeros((max_steps, model.nv))
            flog = np.zeros((max_steps, model.nv))
            clog = np.zeros(max_steps, dtype=bool)
        mujoco.mj_resetData(model, data)
        tx0, ty0 = tremor(np.array(0.0))
        data.qpos[qa["bx"]] = x_start * MM + tx0
        data.qpos[qa["by"]] = y_start * MM + ty0
        data.qpos[qa["bz"]] = top_mm * MM + v_app * lead_s
        data.qvel[va["bz"]] = -v_app
        ten_fl[:] = 0.0
        dof_fl[:] = 0.0
        # Free approach: hand follows start + tremor, the drive descends at v_app.
        i_contact = -1
        for i in range(max_approach):
            tx, ty = tremor(np.array((i + 1) * dt))
            data.ctrl[:] = (x_start * MM + tx, y_start * MM + ty, -Z_DAMPING_NS_M * v_app, 0.0)
            qlog[i] = data.qpos
            vlog[i] = data.qvel
            mujoco.mj_step(model, data)
            if data.ncon:
                i_contact = i
                flog[i] = data.qfrc_constraint
                clog[i] = True
                break
            if i % check_every == 0:
                _check_stable(model, data, i * dt, warn_ids, qa, profile)
        if i_contact < 0:
            raise GelsimError(f"the sensor never touched the fabric within {max_approach * dt:.2f} s; check the "
                              "surface heights and the approach speed")
        t_c = i_contact * dt
        if t_c - (P - phi) * frame_s >= -0.25 * dt:
            break
        margin_s *= 3  # touched earlier than planned (tremor over a tall fibre): start higher
    else:
        raise GelsimError("the sensor touched the fabric before its pre-contact frames could be recorded; "
                          "lower precontact_frames or the approach speed")

    # Camera frames relative to the first touch; frame P lies phi of a period after it.
    frame_t = t_c + (np.arange(T) - P + phi) * frame_s
    frame_step = np.rint(frame_t / dt).astype(np.int64)
    frame_step[P:] = np.maximum(frame_step[P:], i_contact)
    frame_step[:P] = np.minimum(frame_step[:P], i_contact - 1)
    n_steps = int(frame_step[-1]) + 1
    ctrl = _plan(motion, dt, n_steps, i_contact, frame_t[-1] - t_c, x_start, y_start, v_app, tremor)

    # The loop's Python runs 33 times a frame around a 30 us step: MjData's arrays are bound once (each
    # attribute read makes a new numpy view), and the state is logged only at the steps the frames read
    # (qlog and vlog are read at frame_step alone; flog and clog at every step, by the exposure windows).
    step, d_ctrl, d_qpos, d_qvel, d_qfrc = mujoco.mj_step, data.ctrl, data.qpos, data.qvel, data.qfrc_constraint
    logged = np.zeros(n_steps, dtype=bool)
    logged[frame_step] = True
    logged = logged.tolist()
    rows = list(ctrl)                        # (row views: indexing a list is cheaper than the array)
    last = n_steps - 1
    n_prev = max(0.0, float(d_qfrc[bz_dof]))
    for i in range(i_contact + 1, n_steps):
        d_ctrl[:] = rows[i]
        f_lim = mu * n_prev
        ten_fl[ten_x] = f_lim
        ten_fl[ten_y] = f_lim
        dof_fl[dof_pyaw] = f_lim * r_eff
        if logged[i]:
            qlog[i] = d_qpos
            vlog[i] = d_qvel
        step(model, data)
        flog[i] = d_qfrc
        clog[i] = data.ncon > 0
        f_n = float(d_qfrc[bz_dof])
        n_prev = f_n if f_n > 0.0 else 0.0   # max(0.0, f_n), NaN and -0.0 included, without the call
        if i % check_every == 0 or i == last:
            _check_stable(model, data, i * dt, warn_ids, qa, profile)

    # Exposure window of each frame: the steps (i_k - w, i_k], none before the first touch for
    # in-contact frames (so the first in-contact frame is exactly P) and none after it for the others.
    w = max(1, int(round(EXPOSURE_S / dt)))
    csum = np.concatenate([[0], np.cumsum(clog[:n_steps])])
    fsum = np.concatenate([np.zeros((1, model.nv)), np.cumsum(flog[:n_steps], axis=0)])
    hi = frame_step + 1
    lo = np.maximum(hi - w, 0)
    lo[P:] = np.maximum(lo[P:], i_contact)
    out_ncon = (csum[hi] - csum[lo]) > 0
    out_ncon[:P] = False
    fmean = (fsum[hi] - fsum[lo]) / (hi - lo)[:, None]
    # Force of the fabric on the gel, world axes: normal = contact force on the drive's z; friction
    # on the gel's x, y; in-plane push of sloped fibres on the pad = what x, y carry beyond friction.
    out_force = np.stack([fmean[:, va["bx"]], fmean[:, va["by"]], fmean[:, bz_dof]], axis=1)

    q = qlog[frame_step]
    v = vlog[frame_step]
    yaw = q[:, qa["yaw"]]
    c, s = np.cos(yaw), np.sin(yaw)
    # The scene's z is the sensor's axis; rotate the in-plane force into the sensor frame by yaw.
    fx, fy = out_force[:, 0], out_force[:, 1]
    normal = np.where(out_ncon, np.maximum(0.0, out_force[:, 2]), 0.0)
    t_sx = c * fx + s * fy
    t_sy = -s * fx + c * fy
    px, py = q[:, qa["px"]], q[:, qa["py"]]
    shear_x = (c * px + s * py) / MM
    shear_y = (-s * px + c * py) / MM
    twist = np.degrees(q[:, qa["pyaw"]] - yaw)
    vpx = v[:, va["bx"]] + v[:, va["px"]]
    vpy = v[:, va["by"]] + v[:, va["py"]]
    slip_speed = (np.hypot(vpx, vpy) + np.abs(v[:, va["pyaw"]]) * r_eff) / MM
    slipping = out_ncon & (slip_speed > SLIP_SPEED_MM_S)
    pos = np.stack([q[:, qa["bx"]], q[:, qa["by"]], q[:, qa["bz"]]], axis=1) / MM
    pos[:, 2] -= plane(pos[:, 0], pos[:, 1])  # height above the fabric's own base plane
    t0 = frame_t[0]
    return ContactFrames(
        time_s=frame_t - t0, position_mm=pos, yaw_deg=np.degrees(yaw),
        tilt_deg=np.tile(np.asarray(motion.tilt_deg, dtype=float), (T, 1)),
        normal_force_n=normal, tangential_force_n=np.where(out_ncon[:, None], np.stack([t_sx, t_sy], 1), 0.0),
        in_contact=out_ncon, slipping=slipping, shear_mm=np.stack([shear_x, shear_y], 1), twist_deg=twist,
        first_contact_frame=int(np.argmax(out_ncon)) if out_ncon.any() else -1, contact_time_s=float(t_c - t0))


def _pooled(surface: Surface, cell_mm: float) -> Surface:
    """``surface`` max-pooled to cells of about ``cell_mm`` (unchanged if already that coarse)."""
    f = int(round(cell_mm / surface.mm_per_px))
    if f <= 1:
        return surface
    h = surface.heights_mm
    H, W = h.shape
    H2, W2 = -(-H // f), -(-W // f)
    padded = np.pad(h, ((0, H2 * f - H), (0, W2 * f - W)), mode="edge")
    pooled = padded.reshape(H2, f, W2, f).max(axis=(1, 3))
    shift = (f - 1) / 2 * surface.mm_per_px  # a pooled cell sits at the centre of the cells it covers
    return Surface(pooled, surface.mm_per_px * f, (surface.origin_mm[0] + shift, surface.origin_mm[1] + shift),
                   surface.friction)


def _tilted(surface: Surface, motion: Motion):
    """The surface seen by a level pad when the sensor is tilted by ``motion.tilt_deg``, and the
    function (x_mm, y_mm) -> height (mm) of the fabric's base plane in that scene."""
    roll, pitch = (math.tan(math.radians(a)) for a in motion.tilt_deg)
    xs0, ys0 = motion.start_xy_mm
    H, W = surface.heights_mm.shape
    x = surface.origin_mm[0] + np.arange(W) * surface.mm_per_px
    y = surface.origin_mm[1] + np.arange(H) * surface.mm_per_px
    # pitch > 0 lowers the gel at +x: relative to a level gel, the fabric rises towards +x.
    ramp = pitch * (x[None, :] - xs0) + roll * (y[:, None] - ys0)
    offset = -float(ramp.min())

    def plane(xq, yq):
        return offset + pitch * (np.asarray(xq) - xs0) + roll * (np.asarray(yq) - ys0)

    if roll == 0 and pitch == 0:
        return surface, plane
    heights = (surface.heights_mm + ramp + offset).astype(np.float32)
    return Surface(heights, surface.mm_per_px, surface.origin_mm, surface.friction), plane


def _top_under_pad(surface: Surface, profile: SensorProfile, x_mm: float, y_mm: float) -> float:
    """Highest point (mm) of the surface under the level pad centred at (x, y): where it touches first."""
    fw, fh = profile.field_mm
    step = surface.mm_per_px / 2
    xs = np.linspace(x_mm - fw / 2, x_mm + fw / 2, max(2, int(fw / step) + 1))
    ys = np.linspace(y_mm - fh / 2, y_mm + fh / 2, max(2, int(fh / step) + 1))
    X, Y = np.meshgrid(xs, ys)
    return float(np.max(surface.height_at(X, Y)))


def _check_coverage(motion: Motion, surface: Surface, profile: SensorProfile) -> None:
    xmin, ymin, xmax, ymax = motion.travel_bounds_mm()
    r = 0.5 * math.hypot(*profile.field_mm)
    sx0, sy0, sx1, sy1 = surface.extent_mm
    if xmin - r < sx0 or ymin - r < sy0 or xmax + r > sx1 or ymax + r > sy1:
        raise GelsimError(f"the surface ({sx0:.1f}..{sx1:.1f} x {sy0:.1f}..{sy1:.1f} mm) does not cover the sensor's "
                          f"travel ({xmin - r:.1f}..{xmax + r:.1f} x {ymin - r:.1f}..{ymax + r:.1f} mm); build it "
                          "with gelsim.scene.physics_surface or enlarge it")


def _plan(motion: Motion, dt: float, n_steps: int, i_contact: int, dur_s: float, x_start: float,
          y_start: float, v_app: float, tremor) -> np.ndarray:
    """Hand commands per step, (n_steps, 4): x, y (m), z force (N, negative presses), yaw (rad)."""
    t = np.arange(n_steps) * dt
    s = t - i_contact * dt                      # time since the first touch
    u = s / max(dur_s, dt)                      # fraction of the in-contact time
    tx, ty = tremor(t + dt)                     # target for the end of the step
    f_touch = Z_DAMPING_NS_M * v_app            # the drive force during the approach
    peak = motion.peak_force_n
    rise = _smooth_ramp(u / max(motion.rise_fraction, 1e-6))
    force = f_touch + (peak - f_touch) * rise
    x = np.full(n_steps, x_start * MM) + tx
    y = np.full(n_steps, y_start * MM) + ty
    yaw = np.zeros(n_steps)
    lift = np.zeros(n_steps, dtype=bool)
    if motion.action == "press":
        r0 = motion.rise_fraction + motion.hold_fraction
        r1 = r0 + motion.release_fraction
        rel = _smooth_ramp((u - r0) / max(r1 - r0, 1e-6))
        force = np.where(u > r0, peak * (1 - rel), force)
        lift = u >= r1
    else:
        m0 = motion.rise_fraction + motion.settle_fraction
        m1 = max(m0 + 1e-3, 1.0 - motion.end_fraction)
        prog = _smooth_ramp((u - m0) / (m1 - m0))
        if motion.action == "slip":
            dx, dy = motion.slip_vector_mm()
            x += prog * dx * MM
            y += prog * dy * MM
        else:
            yaw = prog * math.radians(motion.twist_deg)
    w = 2 * np.pi * motion.tremor_frequency_hz * t
    force = force * (1 + motion.tremor_force_fraction * np.sin(w + motion.tremor_phase_rad[2]))
    fz = np.where(s < 0, -f_touch, np.where(lift, Z_DAMPING_NS_M * v_app, -force))
    return np.stack([x, y, fz, yaw], axis=1)


def _check_stable(model, data, t: float, warn_ids, qa, profile: SensorProfile) -> None:
    if any(data.warning[w].number for w in warn_ids):
        raise _unstable(t, "MuJoCo reported a bad acceleration, velocity or position")
    if not np.all(np.isfinite(data.qpos)):
        raise _unstable(t, "non-finite state")
    shear = math.hypot(data.qpos[qa["px"]], data.qpos[qa["py"]]) / MM
    if shear > 0.5 * min(profile.field_mm):
        raise _unstable(t, f"gel shear {shear:.1f} mm exceeds half the pad")
