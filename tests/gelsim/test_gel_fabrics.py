"""The two-scale imprint against the elastic reference on fabric textures, and the fabric mechanics.

Each case presses a 256 x 192 px patch of a catalog fabric (the ViTac pixel, 0.0197 mm/px:
5.0 x 3.8 mm) over the whole patch at 7.5 kPa (2 N on the full 18.9 x 14.2 mm pad, a firm press
by hand) on a flat gel, rigid or on the fabric's own compliance (gelsim.gel.support: cloth
compression after Kawabata, yarn flattening), at the "balanced" and "fast" levels and with the
elastic reference (the cases and measures of gelsim.gel.agreement). Agreement is measured away from
the patch's edge (0.6 mm), on what the camera sees of the texture:

- texture correlation: Pearson correlation of the depth maps after removing a 0.5 mm blur;
- slope ratio: RMS slope of the depth map, two-scale over reference;
- contact ratio: fraction of the area in contact, two-scale over reference;
- approach ratio: indentation for the same force, two-scale over reference.

Tolerances are the measured spread (docs/imprint.md) with some margin.
"""
import dataclasses
import math

import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.gel import FabricSupport, disk_layer_factor, effective_modulus_mpa, press
from gelsim.gel.agreement import (ELASTIC, FABRICS, FORCE_N, LEVELS, PATCH, PRESSURE_MPA, agreement, fabric,
                                  imprint, inner, texture)
from gelsim.gel.support import MAX_COMPRESSION, P0_KPA, PM_KPA
from gelsim.sensor import load_profile

# Measured (7 fabrics x rigid/supported x balanced/fast, 2026-11-27, after the macro closing fix):
# correlation 0.848-0.990, slope 0.85-1.30, contact 0.53-1.95, approach 0.73-1.03. (Holding the coarse
# fields out to the frame's edge moved the mesh's correlation from 0.859-0.910 to 0.848-0.895 and the
# felt's from 0.914-0.916 to 0.933-0.948; the macro closing fix the rigid felt's from 0.907 to 0.930.)
TOL = {"corr": 0.82, "slope": (0.7, 1.35), "contact": (0.45, 2.0), "approach": (0.65, 1.25)}
# Cases whose elastic reference converges in about a second: in the default suite.
QUICK = {True: ("corduroy", "felt", "mesh"), False: ("corduroy", "mesh")}


def check(name, supported, level):
    a = agreement(imprint(name, supported, level), imprint(name, supported, "elastic"))
    assert a["corr"] >= TOL["corr"], a
    assert TOL["slope"][0] <= a["slope"] <= TOL["slope"][1], a
    assert TOL["contact"][0] <= a["contact"] <= TOL["contact"][1], a
    assert TOL["approach"][0] <= a["approach"] <= TOL["approach"][1], a


def cases(supported):
    out = []
    for name in FABRICS:
        for level in LEVELS:
            marks = [] if name in QUICK[supported] else [pytest.mark.slow]  # the reference takes 1-9 s
            out.append(pytest.param(name, level, marks=marks, id=f"{name}-{level}"))
    return out


@pytest.mark.parametrize("name, level", cases(True))
def test_supported_fabric_matches_elastic(name, level):
    check(name, True, level)


@pytest.mark.parametrize("name, level", cases(False))
def test_rigid_fabric_matches_elastic(name, level):
    check(name, False, level)


@pytest.mark.parametrize("fid", [50, 64, 80], ids=["jersey", "corduroy", "felt"])
def test_the_frame_edge_is_pressed_as_deep_as_the_reference_presses_it(fid):
    """A cloth over the whole (domed) pad, 3 N at 320x240: the deepest of the gel's outermost pixels
    (p99 of the one-pixel ring) against the elastic reference's. The contact goes on past the frame's
    edge; when the coarse grid's fields fell to zero beyond it, the cloth's compression was halved over
    the last half cell and the gel went 1.8-4.9x the reference's depth there (measured: 2.91, 1.83,
    4.88; now 1.08, 0.91, 1.05)."""
    from gelsim.fabrics import load_catalog
    from gelsim.scene import as_object, field_heights

    prof = load_profile("vitac").with_resolution(320)
    obj = as_object(load_catalog()[fid])
    heights = field_heights(obj, prof, seed=0)

    def edge_p99(level):
        d = press(heights, prof, level, force_n=3.0, support=obj.support(), texture_mm=obj.texture_mm).depth_mm
        return np.percentile(np.concatenate([d[0], d[-1], d[:, 0], d[:, -1]]), 99)

    assert 0.8 <= edge_p99("balanced") / edge_p99("reference") <= 1.25


@pytest.mark.parametrize("force_n", [1.0, 4.0])
def test_the_macro_grid_keeps_the_corduroys_wales_apart(force_n):
    """Pinwale corduroy (0.3 mm tufts on 1.6 mm wales, 0.3 mm gaps between them) over the whole pad at
    320x240: the tufts' relief the gel keeps in their band, balanced's 64 macro cells (0.3 mm) against
    192. When the macro grid's crown closing rounded up to 3 cells it filled the gaps, the pressure
    spread over them, and 64 cells kept 0.53 / 0.45 of 192 cells' relief at 1 / 4 N (now 0.74 / 0.77)."""
    from gelsim.fabrics import load_catalog
    from gelsim.texture import texture_budget

    prof = load_profile("vitac").with_resolution(320)
    fab = load_catalog()[64]
    kept = [texture_budget(fab, force_n, prof, dataclasses.replace(LEVELS["balanced"], macro_cells=n),
                           codec=False).kept for n in (64, 192)]
    assert kept[0] >= 0.65 * kept[1]


@pytest.mark.parametrize("level", list(LEVELS))
def test_texture_grows_with_pressure_as_johnson_says(level):
    # Pressing harder closes more of the valleys: contact and kept texture grow with force, for
    # both models (the old pyramid model's contact stayed at a quarter whatever the force).
    fab, prot = fabric("twill")
    out = []
    for f in (0.5, 1.0, 4.0):
        im = press(prot, PATCH, LEVELS[level], force_n=f * FORCE_N, support=fab.support(), texture_mm=fab.texture_mm)
        out.append((float(inner(im.contact_mask).mean()), float(texture(im.depth_mm).std())))
    assert out[0][0] < out[1][0] < out[2][0]
    assert out[0][1] < out[1][1] < out[2][1]


# ---------------------------------------------------------------------------- fabric mechanics
def test_kawabata_compression_law():
    sup = FabricSupport(thickness_mm=1.0, compressibility=0.4, surface_modulus_mpa=2.0)
    # EMC is the share of T0 lost between 49 Pa and 4.9 kPa.
    assert float(sup.compression_mm(PM_KPA)) == pytest.approx(0.4, rel=1e-9)
    assert float(sup.compression_mm(0.0)) == 0.0
    # Thickness about linear in log pressure (de Jong et al. 1986): equal steps per decade past p0.
    c = [float(sup.compression_mm(P0_KPA * 10 ** k)) for k in (1, 2, 3)]
    assert c[1] - c[0] == pytest.approx(c[2] - c[1], rel=0.05)
    # Capped at the fibres' own volume.
    assert float(sup.compression_mm(1e6)) == pytest.approx(MAX_COMPRESSION * 1.0)
    # The secant stiffness grows with pressure: a cloth stiffens as it compresses.
    assert sup.secant_stiffness_kpa_per_mm(1.0) < sup.secant_stiffness_kpa_per_mm(10.0) < \
        sup.secant_stiffness_kpa_per_mm(100.0)
    assert math.isinf(FabricSupport(1.0, 0.0, 2.0).secant_stiffness_kpa_per_mm(5.0))


def test_yarn_share_of_the_texture():
    e = effective_modulus_mpa(PATCH.gel)
    soft, stiff = FabricSupport(1.0, 0.3, 0.3), FabricSupport(1.0, 0.3, 300.0)
    q = np.array([2.0, 10.0, 50.0], np.float32)
    assert np.all(np.diff(soft.texture_share(q, e)) < 0)  # finer relief flattens more
    assert np.all(soft.texture_share(q, e) < stiff.texture_share(q, e))
    assert np.all(stiff.texture_share(q, e) > 0.95)       # a stiff surface keeps its relief


@pytest.mark.parametrize("model", ["elastic", "balanced"])
def test_softer_yarns_leave_less_texture_and_compressible_cloth_more_approach(model):
    fab, prot = fabric("twill")
    fid = ELASTIC if model == "elastic" else LEVELS[model]

    def run(emc, es):
        return press(prot, PATCH, fid, force_n=FORCE_N, support=FabricSupport(fab.thickness_mm, emc, es),
                     texture_mm=fab.texture_mm)
    stiff, soft_yarn, squashy = run(0.2, 50.0), run(0.2, 0.3), run(0.6, 50.0)
    # Measured: yarns of 0.3 instead of 50 MPa keep 0.74 of the texture (elastic), 0.86 (two-scale:
    # its share is that of full contact, while partial contact loads the crowns harder).
    assert texture(soft_yarn.depth_mm).std() < 0.9 * texture(stiff.depth_mm).std()
    assert squashy.indentation_mm > stiff.indentation_mm + 0.5 * float(
        FabricSupport(fab.thickness_mm, 0.4, 50.0).compression_mm(1e3 * PRESSURE_MPA))


def test_uniform_pressure_on_whole_pad_follows_disk_layer_factor():
    # R: mean displacement under a uniform pressure on a disk of the pad's area,
    # 16 p a R / (3 pi E*). The elastic model pressing a plane over the whole (rectangular) flat
    # pad should give that within 10%.
    prof = load_profile("vitac").with_resolution(160)
    prof = dataclasses.replace(prof, gel=dataclasses.replace(prof.gel, dome_radius_mm=0.0))
    im = press(np.zeros(prof.shape, np.float32), prof, ELASTIC, force_n=2.0)
    area = prof.field_mm[0] * prof.field_mm[1]
    a = math.sqrt(area / math.pi)
    r = float(disk_layer_factor(np.array(a / prof.gel.thickness_mm), prof.gel.poisson_ratio))
    expect = 16 * (2.0 / area) * a * r / (3 * math.pi * effective_modulus_mpa(prof.gel))
    assert float(im.depth_mm.mean()) == pytest.approx(expect, rel=0.10)
    assert float(disk_layer_factor(np.array(1e-3), 0.48)) == pytest.approx(1.0, abs=1e-3)
    rs = disk_layer_factor(np.geomspace(0.01, 100, 30), 0.48)
    assert np.all(np.diff(rs) < 0)


@pytest.mark.parametrize("kw, msg", [
    (dict(thickness_mm=-1.0), "thickness_mm"), (dict(compressibility=0.95), "compressibility"),
    (dict(surface_modulus_mpa=float("nan")), "surface_modulus_mpa")])
def test_support_validation(kw, msg):
    args = dict(thickness_mm=1.0, compressibility=0.3, surface_modulus_mpa=2.0) | kw
    with pytest.raises(GelsimError, match=msg):
        FabricSupport(**args)
    fab, prot = fabric("plain")
    with pytest.raises(GelsimError, match="FabricSupport"):
        press(prot, PATCH, LEVELS["fast"], force_n=FORCE_N, support=50.0)
