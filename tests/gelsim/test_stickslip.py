"""gelsim.mujoco.stickslip: the pad's contact history (anchor, slip) as a public object, stepped per frame."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from gelsim.mujoco.rays import MM  # noqa: E402
from gelsim.mujoco.stickslip import GelSprings, StickSlip  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402

SPRINGS = GelSprings(k_shear_n_mm=2.0, k_tors_nmm_rad=50.0, r_eff_mm=3.0)
EYE = np.eye(3)


def rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_springs_of_a_profile_are_positive():
    s = GelSprings.of(load_profile("vitac"))
    assert s.k_shear_n_mm > 0 and s.k_tors_nmm_rad > 0 and s.r_eff_mm > 0


def test_stuck_gel_follows_the_load_and_the_pads_motion_over_the_body():
    h = StickSlip()
    body = (np.zeros(3), EYE)
    shear, twist, slip = h.step(SPRINGS, 1, (np.zeros(3), EYE), body, 10.0, np.array([0.2, 0.0]), 0.0, 1.0)
    np.testing.assert_allclose(shear, [0.1, 0.0])                     # tang / k
    assert twist == 0.0 and not slip and h.anchor[0] == 1
    # the pad moves 0.05 mm along +x over the (still) body: the gel, stuck to it, shears the other way
    shear, twist, slip = h.step(SPRINGS, 1, (np.array([0.05 * MM, 0, 0]), EYE), body, 10.0, np.zeros(2), 0.0, 1.0)
    np.testing.assert_allclose(shear, [-0.05, 0.0], atol=1e-12)
    # turned by 2 degrees: twisted back by as much
    _, twist, _ = h.step(SPRINGS, 1, (np.zeros(3), rot_z(2.0)), body, 10.0, np.zeros(2), 0.0, 1.0)
    assert twist == pytest.approx(-2.0)


def test_past_coulombs_limit_the_gel_slips_and_remembers_it():
    h = StickSlip()
    body = (np.zeros(3), EYE)
    h.step(SPRINGS, 1, (np.zeros(3), EYE), body, 1.0, np.zeros(2), 0.0, 0.5)
    lim = 0.5 * 1.0 / SPRINGS.k_shear_n_mm                         # mu N / k, mm
    shear, _, slip = h.step(SPRINGS, 1, (np.array([1.0 * MM, 0, 0]), EYE), body, 1.0, np.zeros(2), 0.0, 0.5)
    assert slip and np.hypot(*shear) == pytest.approx(lim)
    np.testing.assert_allclose(h.slip_mm, [1.0 - lim, 0.0])
    # back where it started: the gel, stuck where it slipped to, is pulled the other way past the limit
    shear, _, slip = h.step(SPRINGS, 1, (np.zeros(3), EYE), body, 1.0, np.zeros(2), 0.0, 0.5)
    assert slip and shear[0] == pytest.approx(lim)
    np.testing.assert_allclose(h.slip_mm, [lim, 0.0])
    # released, then touched again: a fresh anchor and no slip
    h.release()
    shear, _, _ = h.step(SPRINGS, 1, (np.array([1.0 * MM, 0, 0]), EYE), body, 1.0, np.zeros(2), 0.0, 0.5)
    np.testing.assert_allclose(shear, [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(h.slip_mm, 0.0)
