"""gelsim.mujoco: a GelSight sensor on a pad of a user's MuJoCo scene (#14)."""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from gelsim import frame
from gelsim.contact import gel_stiffness
from gelsim.errors import GelsimError
from gelsim.mujoco import GelSightSensor, attach
from gelsim.mujoco.grasp import press_scene
from gelsim.scene import Sphere
from gelsim.stats import fit_marker_motion

MM = 1e-3


def twist_scene(profile: str):
    """A pad facing -z on a force-driven slide and a position-driven hinge about z, above a static
    box whose contact with the pad is frictionless in MuJoCo (the gel's friction is the sensor's:
    Coulomb's mu of the pair as MuJoCo combines it, the larger of the two geoms', here 0.6)."""
    spec = mujoco.MjSpec()
    spec.option.gravity = [0, 0, 0]
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.03, 0.005],
                            pos=[0, 0, -0.005], condim=1, friction=[0.6, 0.005, 0.0001])
    hand = spec.worldbody.add_body(name="hand", pos=[0, 0, 0.0005])
    hand.add_joint(name="z", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1], damping=20.0)
    # the wrist's inertia (as gelsim.contact's SENSOR_YAW_INERTIA_KGM2) keeps the servo resolvable
    hand.add_joint(name="yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], armature=1e-3)
    hand.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.002], mass=0.05, contype=0, conaffinity=0)
    attach(spec, "hand", "pad", facing=(0, 0, -1), x_axis=(1, 0, 0), profile=profile, condim=1)
    spec.add_actuator(name="press", target="z", trntype=mujoco.mjtTrn.mjTRN_JOINT, gainprm=[1] + [0] * 9)
    spec.add_actuator(name="turn", target="yaw", trntype=mujoco.mjtTrn.mjTRN_JOINT, gainprm=[1.0] + [0] * 9,
                      biastype=mujoco.mjtBias.mjBIAS_AFFINE, biasprm=[0, -1.0, -0.07] + [0] * 7)
    m = spec.compile()
    return m, mujoco.MjData(m)


@pytest.fixture(scope="module")
def pressed_ball():
    return press_scene(1.0, 8.0, profile="vitac")


def test_sphere_press_matches_gelsim_press(pressed_ball):
    """The same sphere at the same force as `gelsim press` (frame.press_object): the force is
    MuJoCo's, the imprint within 5% in depth and 8% in area (the rays sample the ball every 0.2 mm,
    the press evaluates it per pixel)."""
    m, d = pressed_ball
    s = GelSightSensor(m, d, "pad", profile="vitac", fidelity="fast", resolution=(320, 240), noise=False)
    f = s.render()
    assert f.in_contact and f.normal_force_n == pytest.approx(1.0, rel=0.01)
    assert np.abs(f.tangential_force_n).max() < 1e-6
    ref = frame.press_object(Sphere(8.0), s.profile, "fast", force_n=1.0)
    assert f.depth_mm.max() == pytest.approx(float(ref.depth_mm.max()), rel=0.05)
    assert f.contact_mask.sum() == pytest.approx(ref.contact_mask.sum(), rel=0.08)
    assert float(np.abs(f.depth_mm - ref.depth_mm).mean()) < 0.02 * float(ref.depth_mm.max())
    # the imprint sits where the ball is: centred (the ball is on the pad's axis)
    ys, xs = np.nonzero(f.contact_mask)
    h, w = s.shape
    assert abs(xs.mean() - (w - 1) / 2) < 1.0 and abs(ys.mean() - (h - 1) / 2) < 1.0
    # markers dilate outwards from the press, no shear or twist
    assert np.allclose(f.shear_mm, 0) and f.twist_deg == 0.0
    moved = np.linalg.norm(f.markers_xy_px - f.markers_rest_px, axis=1)
    assert moved.max() > 0.3


def test_offset_ball_lands_at_its_place_in_the_image():
    """Image columns follow the pad's +x, rows its +y: a ball 3 mm along +x and 2 mm along +y."""
    m, d = press_scene(0.5, 6.0, profile="gelsight-mini", offset_mm=(3.0, 2.0))
    s = GelSightSensor(m, d, "pad", profile="gelsight-mini", resolution=(320, 240), noise=False)
    f = s.render()
    ys, xs = np.nonzero(f.contact_mask)
    mm = s.profile.image.mm_per_px
    h, w = s.shape
    assert (xs.mean() - (w - 1) / 2) * mm == pytest.approx(3.0, abs=0.1)
    assert (ys.mean() - (h - 1) / 2) * mm == pytest.approx(2.0, abs=0.1)


def test_frames_before_contact_are_the_background_and_runs_repeat():
    m, d = twist_scene("vitac")
    s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(160, 120), noise=False)
    f = s.render()
    assert not f.in_contact and f.normal_force_n == 0.0 and not f.contact_mask.any()
    np.testing.assert_array_equal(f.rgb, s.background())
    np.testing.assert_array_equal(f.markers_xy_px, f.markers_rest_px)

    def run():
        m, d = twist_scene("vitac")
        s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(160, 120), seed=3)
        d.ctrl[:] = (-2.0, math.radians(0.3))
        out = []
        for i in range(300):
            mujoco.mj_step(m, d)
            if i % 50 == 49:
                out.append(s.render())
        return out

    a, b = run(), run()
    assert any(f.in_contact for f in a)
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.markers_xy_px, fb.markers_xy_px)
        assert fa.normal_force_n == fb.normal_force_n and fa.twist_deg == fb.twist_deg


def test_pure_twist_rotates_the_markers_by_the_pads_turn():
    """The pad, facing down on a flat box, turns by 0.3 degrees about the world's +z, i.e. by -0.3
    degrees about its own +z (the gel's normal points down): the gel surface sticks to the box, so
    relative to the pad, and in the image, it turns by +0.3 degrees, below the friction limit; the
    markers in the contact turn with it."""
    m, d = twist_scene("vitac")
    s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(320, 240), noise=False)
    d.ctrl[:] = (-2.0, 0.0)
    for _ in range(600):
        mujoco.mj_step(m, d)
    f0 = s.render()
    assert f0.in_contact and f0.normal_force_n == pytest.approx(2.0, rel=0.02)
    turn = 0.3
    _, k_tors, r_eff = gel_stiffness(s.profile)
    assert math.degrees(0.6 * 2.0 * r_eff / k_tors) > turn   # still sticking at this turn
    d.ctrl[1] = math.radians(turn)
    for _ in range(1500):
        mujoco.mj_step(m, d)
        s.render() if _ % 100 == 0 else None
    f = s.render()
    assert not f.slipping
    turned = math.degrees(d.qpos[m.joint("yaw").qposadr[0]])
    assert turned == pytest.approx(turn, rel=0.05)
    assert f.twist_deg == pytest.approx(turned, rel=0.02)
    assert np.hypot(*f.shear_mm) < 0.005
    fit = fit_marker_motion(f.markers_rest_px, f.markers_xy_px, s.profile.image.mm_per_px, f.contact_mask[
        np.clip(np.rint(f.markers_rest_px[:, 1]).astype(int), 0, s.shape[0] - 1),
        np.clip(np.rint(f.markers_rest_px[:, 0]).astype(int), 0, s.shape[1] - 1)])
    assert fit.rotation_deg == pytest.approx(turned, rel=0.1)


def test_twist_past_the_friction_limit_slips():
    m, d = twist_scene("vitac")
    s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(160, 120), noise=False)
    d.ctrl[:] = (-1.0, 0.0)
    for _ in range(600):
        mujoco.mj_step(m, d)
    s.render()
    d.ctrl[1] = math.radians(10.0)
    frames = []
    for i in range(2000):
        mujoco.mj_step(m, d)
        if i % 50 == 0:
            frames.append(s.render())
    f = s.render()
    _, k_tors, r_eff = gel_stiffness(s.profile)
    limit = math.degrees(0.6 * f.normal_force_n * r_eff / k_tors)
    # it slips while the pad turns, and the gel stays twisted at Coulomb's limit once the pad stops
    assert sum(fr.slipping for fr in frames) >= 5 and not f.slipping
    assert f.twist_deg == pytest.approx(limit, rel=1e-3)
    assert math.degrees(d.qpos[m.joint("yaw").qposadr[0]]) > 5 * limit


def test_bad_input_is_one_clear_error(pressed_ball):
    m, d = pressed_ball
    with pytest.raises(GelsimError, match="no geom named 'nope'.*pad"):
        GelSightSensor(m, d, "nope")
    with pytest.raises(GelsimError, match="unknown sensor profile 'gelsight-9000'"):
        GelSightSensor(m, d, "pad", profile="gelsight-9000")
    spec = mujoco.MjSpec()
    spec.worldbody.add_geom(name="ball_pad", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.01])
    spec.worldbody.add_geom(name="lonely", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.01, 0.01, 0.001],
                            contype=0, conaffinity=0)
    m2 = spec.compile()
    d2 = mujoco.MjData(m2)
    with pytest.raises(GelsimError, match="is a sphere.*box or cylinder"):
        GelSightSensor(m2, d2, "ball_pad")
    with pytest.raises(GelsimError, match="no geom of the model can ever touch pad 'lonely'.*contype"):
        GelSightSensor(m2, d2, "lonely")
    with pytest.raises(GelsimError, match="resolution"):
        GelSightSensor(m, d, "pad", resolution="big")
    spec = mujoco.MjSpec()
    with pytest.raises(GelsimError, match="no body named 'finger'"):
        attach(spec, "finger", "pad")


def _pad_scene(half_mm: tuple[float, float], kind=mujoco.mjtGeom.mjGEOM_BOX):
    spec = mujoco.MjSpec()
    size = [half_mm[0] * MM, half_mm[1] * MM, 0.001]
    spec.worldbody.add_geom(name="pad", type=kind, size=size)
    ball = spec.worldbody.add_body(name="ball", pos=[0, 0, 0.02])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.005], mass=0.01)
    m = spec.compile()
    return m, mujoco.MjData(m)


def test_a_pad_that_does_not_match_the_field_is_refused_in_one_line():
    """A 5x5 mm pad and a 60x60 mm pad used to give the same 20x15 mm image (#42)."""
    from gelsim.mujoco.attach import pad_size_m

    for half in ((2.5, 2.5), (30.0, 30.0)):
        m, d = _pad_scene(half)
        with pytest.raises(GelsimError, match=r"pad 'pad' is .* but the gelsight-mini profile sees 20\.\d+ x 15\.\d+ mm"
                                              r".*half-sizes 0\.010\d+ 0\.007\d+ m") as e:
            GelSightSensor(m, d, "pad", warmup=False)
        assert "\n" not in str(e.value)
    hx, hy, _ = pad_size_m("gelsight-mini")
    m, d = _pad_scene((round(hx / MM, 3), round(hy / MM, 3)))     # the size attach gives, to MJCF's digits
    GelSightSensor(m, d, "pad", warmup=False)


def test_a_fractional_resolution_is_refused_not_truncated(pressed_ball):
    m, d = pressed_ball
    for bad in ((320.7, 240), (320, 240.5), (True, 240), (320,), "320x240"):
        with pytest.raises(GelsimError, match="whole px"):
            GelSightSensor(m, d, "pad", profile="vitac", resolution=bad, warmup=False)
    s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(np.int64(160), 120.0), warmup=False)
    assert s.shape == (120, 160)


def test_render_runs_on_one_thread_and_gives_the_callers_threading_back(pressed_ball):
    """numpy's OpenBLAS and OpenCV are limited to one thread inside render() only (#42)."""
    import cv2
    from threadpoolctl import threadpool_info, threadpool_limits

    m, d = pressed_ball
    s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(160, 120), noise=False)
    seen = []
    inner = s.renderer.render_input

    def spy(*a, **k):
        seen.append(([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"], cv2.getNumThreads()))
        return inner(*a, **k)

    s.renderer.render_input = spy
    old_cv = cv2.getNumThreads()
    with threadpool_limits(limits=2, user_api="blas"):
        cv2.setNumThreads(2)
        try:
            assert s.render().in_contact
            after = ([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"], cv2.getNumThreads())
        finally:
            cv2.setNumThreads(old_cv)
    blas_inside, cv_inside = seen[0]
    assert blas_inside and set(blas_inside) == {1} and cv_inside == 1
    assert set(after[0]) == {2} and after[1] == 2                       # the caller's settings, given back
    unlimited = GelSightSensor(m, d, "pad", profile="vitac", resolution=(160, 120), noise=False, threads=None,
                               warmup=False)
    unlimited.renderer.render_input = spy
    cv2.setNumThreads(2)
    try:
        unlimited.render()
        assert seen[-1][1] == 2                                             # threads=None: left alone
    finally:
        cv2.setNumThreads(old_cv)
    with pytest.raises(GelsimError, match="threads 0 is not a thread count"):
        GelSightSensor(m, d, "pad", profile="vitac", threads=0)


def test_warm_up_at_construction_changes_no_frame(pressed_ball):
    m, d = pressed_ball
    frames = []
    for warm in (False, True):
        s = GelSightSensor(m, d, "pad", profile="vitac", resolution=(160, 120), seed=4, warmup=warm)
        frames.append([s.render().rgb for _ in range(3)])
    for a, b in zip(*frames):
        np.testing.assert_array_equal(a, b)
