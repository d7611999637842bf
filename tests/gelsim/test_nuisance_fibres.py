"""gelsim.nuisance.fibres: loose fibres of hairy fabrics denting the gel before the main contact."""
import math

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from gelsim.errors import GelsimError
from gelsim.nuisance import (Fibres, approach_gap_mm, buckling_dent_mm, dent_depths_mm, draw_fibres, fibre_dents_mm,
                             gap_map_mm, load_nuisance, stage_rng)
from gelsim.nuisance.fibres import HAIRINESS_MAX
from gelsim.sensor import load_profile

P = load_nuisance().stages.fibres
PROF = load_profile("vitac")
FIELD = PROF.field_mm
GEL = (PROF.gel.young_modulus_mpa, PROF.gel.poisson_ratio)
MMPP = PROF.image.mm_per_px


def fibres(seed=1, hairiness=0.45, severity=1.0):
    return draw_fibres(stage_rng(seed, "fibres"), FIELD, hairiness, P, severity)


def test_no_fibres_without_hairiness_or_severity():
    assert len(fibres(hairiness=0.0)) == 0 and len(fibres(severity=0.0)) == 0
    assert len(fibres()) > 0
    gap = gap_map_mm(PROF.shape, MMPP, 0.1, PROF.gel.dome_radius_mm)
    assert not fibre_dents_mm(fibres(hairiness=0.0), gap, MMPP, *GEL, P).any()


def test_larger_severity_keeps_a_superset_and_the_count_follows_the_density():
    def keys(f):
        return set(zip(f.x_mm.round(9), f.y_mm.round(9)))
    a, b, c = fibres(severity=0.5), fibres(severity=1.0), fibres(severity=3.0)
    assert keys(a) <= keys(b) <= keys(c) and len(a) < len(c)
    counts = [len(fibres(seed=s, hairiness=0.3)) for s in range(300)]
    expected = P.density_per_mm2 * 0.3 / HAIRINESS_MAX * FIELD[0] * FIELD[1]
    assert np.mean(counts) == pytest.approx(expected, rel=0.05)          # 300 draws: sd of the mean ~1.6%


def test_buckling_dent_matches_the_hand_computation():
    # 25 um wool fibre (2 GPa), 1 mm free length, on the 0.2 MPa, nu 0.48 gel:
    # F = pi^2 E (pi d^4 / 64) / (4 L^2) = 94.6 uN; delta = F (1 - nu^2) / (2 a E_gel) = 14.56 um
    d = 0.025e-3
    force = math.pi ** 2 * 2e9 * (math.pi * d ** 4 / 64) / (4 * 1e-3 ** 2)
    assert force == pytest.approx(94.6e-6, rel=1e-3)
    assert buckling_dent_mm(1.0, 0.025, 2.0, 0.2, 0.48) == pytest.approx(force * (1 - 0.48 ** 2) / (2 * d / 2 * 0.2e6) * 1e3)
    assert float(buckling_dent_mm(1.0, 0.025, 2.0, 0.2, 0.48)) == pytest.approx(0.01456, rel=1e-3)


def test_dent_depth_is_the_smallest_of_its_three_caps_and_zero_when_not_touching():
    f = Fibres(*(np.array(v, float) for v in ([0, 0, 0, 0, 0], [0] * 5, [0.5, 1.0, 3.0, 0.2, 1.0],
                                                [0.025] * 5, [2.0] * 5)))
    gap = np.array([0.49, 0.3, 0.3, 0.3, 0.0])
    depth = dent_depths_mm(f, gap, *GEL, P)
    buckle = buckling_dent_mm(f.length_mm, f.diameter_mm, f.modulus_gpa, *GEL)
    assert depth[0] == pytest.approx(0.01)                                # just touching: L - gap
    assert depth[1] == pytest.approx(min(0.7, buckle[1], P.max_depth_over_diameter * 0.025))
    assert depth[2] == pytest.approx(buckle[2])                           # long fibre: it buckles early
    assert depth[3] == 0.0 and depth[4] == 0.0                            # shorter than the gap; in contact
    assert np.all(depth <= P.max_depth_over_diameter * f.diameter_mm + 1e-15)


def test_marks_appear_as_the_gap_closes_and_never_where_the_fabric_touches():
    f = fibres(seed=4, hairiness=0.5, severity=2.0)
    touched = []
    for apex in (5.0, 1.5, 0.6, 0.3, 0.05):
        gap = gap_map_mm(PROF.shape, MMPP, apex, PROF.gel.dome_radius_mm, (0.0, 0.0))
        d = fibre_dents_mm(f, gap, MMPP, *GEL, P)
        assert d.dtype == np.float32 and d.shape == PROF.shape and d.min() >= 0
        touched.append(int((d > 1e-4).sum()))
    assert touched[0] == 0 or touched[0] < touched[-1]
    assert all(a <= b for a, b in zip(touched, touched[1:])) and touched[-1] > 0
    # in contact: no dent inside the region where the gap is <= 0, dents around it (the domed gel's rim)
    gap = gap_map_mm(PROF.shape, MMPP, -0.3, PROF.gel.dome_radius_mm)
    d = fibre_dents_mm(f, gap, MMPP, *GEL, P)
    reach = int(math.ceil(P.tail_radii * P.diameter_mm[1] / 2 / MMPP)) + 2
    core = gap <= 0
    inner = distance_transform_edt(core) > reach                          # farther than a dent's reach from the rim
    assert inner.sum() > 1000
    assert not d[inner].any() and d[~core].any()


def test_a_dent_sits_on_its_fibre_and_ends_at_its_tail():
    f = Fibres(np.array([0.0]), np.array([0.0]), np.array([1.0]), np.array([0.03]), np.array([2.0]))
    gap = np.full((101, 101), 0.3, np.float32)
    d = fibre_dents_mm(f, gap, 0.01, *GEL, P)
    assert d[50, 50] == d.max() > 0
    r_px = P.tail_radii * 0.015 / 0.01
    yy, xx = np.mgrid[:101, :101]
    assert not d[np.hypot(yy - 50, xx - 50) > r_px + 1].any()
    assert d.max() <= dent_depths_mm(f, np.array([0.3]), *GEL, P)[0] + 1e-7
    assert np.array_equal(d, fibre_dents_mm(f, gap, 0.01, *GEL, P))       # deterministic


def test_gap_map_dome_and_tilt():
    flat = gap_map_mm((5, 7), 1.0, 0.4)
    assert np.allclose(flat, 0.4)
    dome = gap_map_mm((5, 7), 1.0, 0.4, 80.0)
    assert dome.min() == pytest.approx(0.4) and dome[2, 3] == pytest.approx(0.4)
    assert dome[0, 0] == pytest.approx(0.4 + (3 ** 2 + 2 ** 2) / 160, rel=1e-6)
    tilted = gap_map_mm((5, 7), 1.0, 0.4, 0.0, (0.0, 2.0))                # pitch > 0: the gel lower at +x
    assert tilted[2, 6] < tilted[2, 0] and tilted.min() == pytest.approx(0.4)
    rolled = gap_map_mm((5, 7), 1.0, 0.4, 0.0, (2.0, 0.0))                # roll > 0: lower at +y
    assert rolled[4, 3] < rolled[0, 3]


def test_approach_gap():
    assert approach_gap_mm(0, 1, 0.25, 12.0, 30.0) == pytest.approx(12.0 * 0.75 / 30.0)
    assert approach_gap_mm(0, 3, 0.5, 12.0, 30.0) > approach_gap_mm(2, 3, 0.5, 12.0, 30.0) > 0
    with pytest.raises(GelsimError, match="before the first contact frame"):
        approach_gap_mm(1, 1, 0.5, 12.0, 30.0)


@pytest.mark.parametrize("call", [
    lambda: draw_fibres(stage_rng(0, "fibres"), FIELD, 0.7, P, 1.0),
    lambda: draw_fibres(stage_rng(0, "fibres"), FIELD, 0.3, P, -1.0),
    lambda: draw_fibres(stage_rng(0, "fibres"), (0.0, 5.0), 0.3, P, 1.0),
    lambda: fibre_dents_mm(fibres(), np.zeros((4, 4), np.int32), MMPP, *GEL, P),
    lambda: fibre_dents_mm(fibres(), np.full((4, 4), np.nan), MMPP, *GEL, P),
    lambda: fibre_dents_mm(fibres(), np.ones((4, 4)), 0.0, *GEL, P),
    lambda: dent_depths_mm(fibres(), np.ones(3), *GEL, P),
    lambda: gap_map_mm((4, 4), -1.0, 0.3),
])
def test_bad_values_are_refused_in_one_line(call):
    with pytest.raises(GelsimError) as e:
        call()
    assert "\n" not in str(e.value)
