"""Contact simulation: press, slip, twist physics, determinism, errors."""
from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest

from gelsim.contact import ContactFrames, Surface, _check_stable, gel_stiffness, simulate
from gelsim.errors import GelsimError
from gelsim.fidelity import get_fidelity
from gelsim.motion import Motion, sample_motion
from gelsim.scene import FabricObject, physics_surface
from gelsim.sensor import load_profile

PROFILE = load_profile("vitac")
FAST = get_fidelity("fast")
BALANCED = get_fidelity("balanced")
MU = 0.7


def woven_surface(half_mm: float = 30.0, cell: float = 0.2, seed: int = 0, mu: float = MU) -> Surface:
    n = int(2 * half_mm / cell) + 1
    yy, xx = np.mgrid[0:n, 0:n] * cell
    rng = np.random.default_rng(seed)
    z = 0.03 * (np.sin(2 * np.pi * xx / 0.5) * np.sin(2 * np.pi * yy / 0.5) + 1) + 0.01 * rng.random((n, n))
    return Surface(z.astype(np.float32), cell, (-half_mm, -half_mm), mu)


SURFACE = woven_surface()


def base_motion(action: str, **kw) -> Motion:
    args = dict(action=action, num_frames=36, precontact_frames=4, start_xy_mm=(0.5, -0.5),
                fabric_rotation_deg=0.0, approach_speed_mm_s=10.0, peak_force_n=2.5, tilt_deg=(0.0, 0.0),
                tremor_amplitude_mm=0.0, tremor_force_fraction=0.0, contact_phase=0.5,
                rise_fraction=0.2, hold_fraction=0.4, release_fraction=0.3, settle_fraction=0.1,
                end_fraction=0.05)
    args.update(kw)
    return Motion(**args)


def contact_u(cf: ContactFrames, motion: Motion) -> np.ndarray:
    """Fraction of the in-contact time at each frame (the plan's clock)."""
    dur = cf.time_s[-1] - cf.contact_time_s
    return (cf.time_s - cf.contact_time_s) / dur


@pytest.fixture(scope="module")
def press():
    m = base_motion("press")
    return m, simulate(m, SURFACE, PROFILE, BALANCED)


@pytest.fixture(scope="module")
def slip():
    m = base_motion("slip", slip_direction_deg=30.0, slip_distance_mm=4.0, peak_force_n=2.0,
                    rise_fraction=0.2, settle_fraction=0.1, end_fraction=0.1)
    return m, simulate(m, SURFACE, PROFILE, BALANCED)


@pytest.fixture(scope="module")
def twist():
    m = base_motion("twist", twist_deg=25.0, peak_force_n=2.0)
    return m, simulate(m, SURFACE, PROFILE, BALANCED)


def test_shapes_and_dict(press):
    m, cf = press
    T = m.num_frames
    d = cf.to_dict()
    for name, shape in [("time_s", (T,)), ("position_mm", (T, 3)), ("yaw_deg", (T,)), ("tilt_deg", (T, 2)),
                        ("normal_force_n", (T,)), ("tangential_force_n", (T, 2)), ("in_contact", (T,)),
                        ("slipping", (T,)), ("shear_mm", (T, 2)), ("twist_deg", (T,))]:
        assert d[name].shape == shape, name
        assert np.all(np.isfinite(d[name].astype(float))), name
    assert len(d) == 10 and all(v.shape[0] == T for v in d.values())
    assert np.allclose(np.diff(cf.time_s), 1 / PROFILE.image.fps_hz)
    assert np.all(cf.normal_force_n >= 0)


def test_press_precontact_then_contact(press):
    m, cf = press
    P = m.precontact_frames
    assert not cf.in_contact[:P].any()
    assert np.all(cf.normal_force_n[:P] == 0)
    assert cf.in_contact[P]
    assert cf.first_contact_frame == P
    # Contact happens contact_phase of a frame before frame P.
    assert cf.time_s[P] - cf.contact_time_s == pytest.approx(m.contact_phase / PROFILE.image.fps_hz, abs=2e-3)
    # The sensor descends at the approach speed before contact.
    vz = np.diff(cf.position_mm[:P, 2]) * PROFILE.image.fps_hz
    assert np.allclose(vz, -m.approach_speed_mm_s, rtol=0.05)


def test_press_force_rises_holds_releases(press):
    m, cf = press
    u = contact_u(cf, m)
    hold = (u > m.rise_fraction + 0.03) & (u < m.rise_fraction + m.hold_fraction - 0.03)
    assert hold.sum() >= 5
    # Tolerance: 5 % of the target during the hold (force control on a bumpy fabric).
    assert np.all(np.abs(cf.normal_force_n[hold] - m.peak_force_n) < 0.05 * m.peak_force_n)
    rising = cf.normal_force_n[m.precontact_frames:np.argmax(hold)]
    assert np.all(np.diff(rising) > -0.05 * m.peak_force_n)
    assert rising[0] < 0.5 * m.peak_force_n
    # Release: the force falls and the sensor lifts off at the end.
    assert cf.normal_force_n[-1] == 0 and not cf.in_contact[-1]
    after = cf.normal_force_n[np.argmax(hold) + hold.sum():]
    assert after.max() <= m.peak_force_n * 1.05 and after.min() == 0.0
    assert cf.position_mm[-1, 2] > cf.position_mm[hold][:, 2].max()
    # Without slip or twist commanded, the gel barely shears.
    assert np.abs(cf.shear_mm).max() < 0.05 and np.abs(cf.twist_deg).max() < 0.2


def test_slip_moves_along_direction_with_opposing_friction(slip):
    m, cf = slip
    d = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    P = m.precontact_frames
    disp = cf.position_mm[-1, :2] - cf.position_mm[P, :2]
    assert np.linalg.norm(disp) == pytest.approx(m.slip_distance_mm, rel=0.05)
    assert np.degrees(np.arccos(disp @ d / np.linalg.norm(disp))) < 2.0
    yaw = np.radians(cf.yaw_deg)
    fx, fy = cf.tangential_force_n[:, 0], cf.tangential_force_n[:, 1]
    f_world = np.stack([np.cos(yaw) * fx - np.sin(yaw) * fy, np.sin(yaw) * fx + np.cos(yaw) * fy], 1)
    sl = cf.slipping & cf.in_contact
    assert sl.sum() >= 5
    # Sliding: friction opposes the motion and equals mu N (15 %).
    along = f_world[sl] @ d
    assert np.all(along < 0)
    ratio = np.linalg.norm(f_world[sl], axis=1) / (MU * cf.normal_force_n[sl])
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    assert np.all(np.abs(ratio - 1) < 0.25)
    # Shear points against the motion, saturated at mu N / k.
    k, _, _ = gel_stiffness(PROFILE)
    shear_lim = MU * cf.normal_force_n[sl] / k * 1e3
    s_along = cf.shear_mm[sl] @ d  # yaw is 0 in a slip
    assert np.all(s_along < 0)
    assert np.median(-s_along / shear_lim) == pytest.approx(1.0, abs=0.15)


def test_slip_sticks_before_it_slips(slip):
    m, cf = slip
    u = contact_u(cf, m)
    d = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    start = m.rise_fraction + m.settle_fraction
    first_slip = int(np.argmax(cf.slipping & (u > start)))
    assert u[first_slip] > start
    moving = np.where((u > start) & (np.arange(len(u)) < first_slip))[0]
    assert len(moving) >= 1, "no stick phase between the start of the slide and the first slip"
    s = -(cf.shear_mm[moving] @ d)
    assert s[-1] > 0.02                      # the gel shears while the pad sticks...
    assert np.all(np.diff(s) > 0)            # ...and the shear grows with the hand's travel
    assert not cf.slipping[moving].any()
    # Before the slide the pad sticks (shear small, no slipping) once the force is up.
    settled = (u > m.rise_fraction) & (u < start)
    assert settled.any() and not cf.slipping[settled].any()


def test_twist_rotates_and_torsion_saturates(twist):
    m, cf = twist
    assert cf.yaw_deg[-1] == pytest.approx(m.twist_deg, abs=1.0)
    assert np.all(np.sign(cf.yaw_deg[np.abs(cf.yaw_deg) > 0.5]) == np.sign(m.twist_deg))
    # twist_deg is the contact surface relative to the base: it lags the commanded rotation.
    rotating = np.abs(cf.yaw_deg) > 2.0
    assert np.all(np.sign(cf.twist_deg[rotating]) == -np.sign(m.twist_deg))
    _, kt, r_eff = gel_stiffness(PROFILE)
    limit = np.degrees(MU * cf.normal_force_n * r_eff / kt)
    sl = cf.slipping & rotating
    assert sl.sum() >= 5
    assert np.all(np.abs(np.abs(cf.twist_deg[sl]) / limit[sl] - 1) < 0.2)
    # Saturation: torsion stops growing while the rotation continues.
    assert np.ptp(np.abs(cf.twist_deg[sl])) < 0.3 * np.abs(cf.twist_deg[sl]).mean()
    assert np.ptp(cf.yaw_deg[sl]) > 5.0
    assert np.abs(cf.shear_mm).max() < 0.05


def test_same_seed_identical():
    m = sample_motion("slip", 7)
    a = simulate(m, SURFACE, PROFILE, FAST).to_dict()
    b = simulate(m, SURFACE, PROFILE, FAST).to_dict()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("action", ["press", "slip", "twist"])
def test_sampled_motions_with_tilt_and_tremor(action):
    m = sample_motion(action, 11)
    assert m.tilt_deg != (0.0, 0.0) and m.tremor_amplitude_mm > 0
    cf = simulate(m, SURFACE, PROFILE, FAST)
    P = m.precontact_frames
    assert cf.first_contact_frame == P and not cf.in_contact[:P].any()
    held = cf.in_contact & (contact_u(cf, m) > m.rise_fraction + 0.05)
    if action != "press":
        # Tremor modulates the force by up to 5 % and fibres bump a sliding pad: median within 5 %,
        # all frames but one within 20 % and none beyond 35 % (the crisp 5 % hold is tested without tremor
        # above). The one: a stick-slip release spikes the normal force for a frame, 23-30 % in 5 of 24
        # sampled slip/twist motions (seeds 0-11, 2026-11-28; here twist at seed 11 once its late start
        # went, docs/nuisance.md section 1); the other 19 motions stayed within 14 %.
        f = cf.normal_force_n[held]
        dev = np.abs(f - m.peak_force_n) / m.peak_force_n
        assert abs(np.median(f) - m.peak_force_n) < 0.05 * m.peak_force_n
        assert np.sum(dev >= 0.2) <= 1 and np.all(dev < 0.35), dev
    assert np.array_equal(cf.tilt_deg[0], np.array(m.tilt_deg))
    # Undeformed gel height: near the fabric top while pressing (soft contact stand-off < 1 mm).
    assert np.all(np.abs(cf.position_mm[held, 2] - 0.06) < 1.0)


def test_absurd_timestep_names_parameter():
    bad = dataclasses.replace(FAST, physics_dt_s=0.02)
    with pytest.raises(GelsimError, match="physics_dt_s"):
        simulate(base_motion("press"), SURFACE, PROFILE, bad)


def test_mujoco_warning_becomes_error():
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body><joint type='slide' name='px'/>"
                                           "<joint type='slide' name='py'/><geom size='0.1'/></body></worldbody></mujoco>")
    data = mujoco.MjData(model)
    qa = {"px": 0, "py": 1}
    _check_stable(model, data, 0.1, [int(mujoco.mjtWarning.mjWARN_BADQACC)], qa, PROFILE)  # fine
    data.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)].number = 1
    with pytest.raises(GelsimError, match=r"t=0\.410 s.*physics_dt_s.*young_modulus_mpa"):
        _check_stable(model, data, 0.41, [int(mujoco.mjtWarning.mjWARN_BADQACC)], qa, PROFILE)


def test_surface_validation_and_coverage():
    with pytest.raises(GelsimError):
        Surface(np.full((10, 10), -1.0, np.float32), 0.2, (0.0, 0.0), 0.5)
    with pytest.raises(GelsimError):
        Surface(np.zeros((10, 10), np.float32), 0.2, (0.0, 0.0), 0.0)
    small = woven_surface(half_mm=8.0)
    with pytest.raises(GelsimError, match="does not cover"):
        simulate(base_motion("press"), small, PROFILE, FAST)


def test_surface_height_at_bilinear():
    h = np.array([[0, 1], [2, 3]], np.float32)
    s = Surface(h, 0.5, (1.0, 2.0), 0.5)
    assert s.height_at(np.array(1.25), np.array(2.25)) == pytest.approx(1.5)
    assert s.height_at(np.array(1.5), np.array(2.0)) == pytest.approx(1.0)


def test_physics_surface_covers_travel_and_simulates():
    from gelsim.fabrics import load_catalog

    fabric = next(iter(load_catalog()))
    m = sample_motion("slip", 3)
    surf = physics_surface(FabricObject(fabric), m, PROFILE, seed=1)
    assert surf.heights_mm.dtype == np.float32 and surf.heights_mm.min() >= 0
    assert surf.friction == fabric.friction
    xmin, ymin, xmax, ymax = m.travel_bounds_mm()
    sx0, sy0, sx1, sy1 = surf.extent_mm
    r = 0.5 * math.hypot(*PROFILE.field_mm)
    assert sx0 <= xmin - r and sy0 <= ymin - r and sx1 >= xmax + r and sy1 >= ymax + r
    cf = simulate(m, surf, PROFILE, FAST)
    assert cf.first_contact_frame == m.precontact_frames
