"""Fast imprint models against the elastic reference on fabric textures, and the fabric support.

Each case presses a 256 x 192 px patch of a catalog fabric (the ViTac pixel, 0.0197 mm/px:
5.0 x 3.8 mm) over the whole patch at the mean pressure of 2 N on the full 18.9 x 14.2 mm
pad (7.5 kPa, a firm press by hand), rigid or on the fabric's support (Pasternak: stiffness
compressive modulus / thickness, shear length the thickness), with the "balanced" and
"fast" levels' imprint settings and with the elastic reference. Agreement is measured away
from the patch's edge (0.6 mm), on what the camera sees of the texture:

- texture correlation: Pearson correlation of the depth maps after removing a 0.5 mm blur;
- slope ratio: RMS slope of the depth map, fast model over reference;
- contact ratio: fraction of the area in contact, fast over reference;
- approach ratio: indentation for the same force, fast over reference.

Tolerances are set from the measured spread (docs/imprint.md) with some margin; the
corduroy on its support is a known miss (too much texture: the support's share is
linearised for full contact, and corduroy touches on 5% of its area), kept as a strict xfail.
"""
import dataclasses
import functools
import math

import cv2
import numpy as np
import pytest

from gelsim.fabrics import heightfield, load_catalog
from gelsim.fidelity import get_fidelity
from gelsim.gel import disk_layer_factor, effective_modulus_mpa, press
from gelsim.sensor import load_profile

ELASTIC = dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0)
LEVELS = {"balanced": get_fidelity("balanced"), "fast": get_fidelity("fast")}
FULL_PAD_MM2 = 18.912 * 14.184  # the ViTac field, 960 x 720 px at 0.0197 mm/px
PRESSURE_MPA = 2.0 / FULL_PAD_MM2
# One of each family the task names: plain weave, twill, knit, corduroy, felt, leather, mesh.
FABRICS = {"plain": 1, "twill": 21, "knit": 47, "corduroy": 65, "felt": 78, "leather": 86, "mesh": 95}
EDGE_MM = 0.6      # the patch's rim feels its edge, not the texture
TEXTURE_MM = 0.5   # blur removed before comparing textures: the yarn scale stays
TOL = {"corr": 0.90, "slope": (0.55, 1.7), "contact": (0.45, 2.0), "approach": (0.8, 1.4)}
KNOWN_MISSES = {("corduroy", True)}
# Cases whose elastic reference converges in a few seconds: in the default suite.
QUICK = {True: ("corduroy", "leather", "mesh"), False: ("corduroy", "mesh")}


def patch_profile():
    p = load_profile("vitac")
    return dataclasses.replace(p, image=dataclasses.replace(p.image, width_px=256, height_px=192, mm_per_px=0.0197))


PATCH = patch_profile()
FORCE_N = PRESSURE_MPA * PATCH.field_mm[0] * PATCH.field_mm[1]


@functools.cache
def fabric(name):
    fab = load_catalog()[FABRICS[name]]
    h, w = PATCH.shape
    mm = PATCH.image.mm_per_px
    prot = heightfield(fab, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                       mm_per_px=mm, seed=0)
    return fab, prot


def support_of(fab, supported):
    if not supported:
        return {}
    return {"support_stiffness_kpa_per_mm": fab.compressive_modulus_kpa / fab.thickness_mm,
            "support_length_mm": fab.thickness_mm}


@functools.cache
def imprint(name, supported, level):
    fab, prot = fabric(name)
    fid = ELASTIC if level == "elastic" else LEVELS[level]
    return press(prot, PATCH, fid, force_n=FORCE_N, **support_of(fab, supported))


def inner(a):
    m = int(round(EDGE_MM / PATCH.image.mm_per_px))
    return a[m:-m, m:-m]


def texture(depth):
    d = depth.astype(np.float64)
    return inner(d - cv2.GaussianBlur(d, (0, 0), TEXTURE_MM / PATCH.image.mm_per_px))


def slope_rms(depth):
    gy, gx = np.gradient(inner(depth.astype(np.float64)), PATCH.image.mm_per_px)
    return float(np.sqrt(np.mean(gx * gx + gy * gy)))


def agreement(fast, ref) -> dict:
    ta, tb = texture(fast.depth_mm), texture(ref.depth_mm)
    return {"corr": float(np.corrcoef(ta.ravel(), tb.ravel())[0, 1]),
            "slope": slope_rms(fast.depth_mm) / slope_rms(ref.depth_mm),
            "contact": float(inner(fast.contact_mask).mean()) / float(inner(ref.contact_mask).mean()),
            "approach": fast.indentation_mm / ref.indentation_mm}


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
            marks = [pytest.mark.xfail(strict=True, reason="support share linearised for full contact")] \
                if (name, supported) in KNOWN_MISSES else []
            if name not in QUICK[supported]:
                marks.append(pytest.mark.slow)  # the elastic reference takes 2-30 s for these
            out.append(pytest.param(name, level, marks=marks, id=f"{name}-{level}"))
    return out


@pytest.mark.parametrize("name, level", cases(True))
def test_supported_fabric_matches_elastic(name, level):
    check(name, True, level)


@pytest.mark.parametrize("name, level", cases(False))
def test_rigid_fabric_matches_elastic(name, level):
    check(name, False, level)


@pytest.mark.parametrize("level", list(LEVELS))
def test_fast_models_touch_only_the_crowns(level):
    # The old pyramid touched 94-100% of a fabric; the elastic model touches 5-60%.
    for name in ("knit", "mesh"):
        im = imprint(name, True, level)
        assert 0.02 < float(inner(im.contact_mask).mean()) < 0.5
        assert float(texture(im.depth_mm).std()) > 1e-3  # texture of a micrometre or more stays


@pytest.mark.parametrize("model", ["elastic", "balanced"])
def test_pasternak_support_keeps_texture_that_winkler_flattens(model):
    # Same fabric, force and stiffness: spreading the support's load over the yarns
    # (shear length = thickness) keeps the crowns; point-by-point springs flatten them.
    fab, prot = fabric("mesh")
    ks = fab.compressive_modulus_kpa / fab.thickness_mm
    fid = ELASTIC if model == "elastic" else LEVELS[model]
    past = press(prot, PATCH, fid, force_n=FORCE_N, support_stiffness_kpa_per_mm=ks,
                 support_length_mm=fab.thickness_mm)
    wink = press(prot, PATCH, fid, force_n=FORCE_N, support_stiffness_kpa_per_mm=ks, support_length_mm=0.0)
    rigid = imprint("mesh", False, "elastic" if model == "elastic" else model)
    assert texture(wink.depth_mm).std() < 0.5 * texture(past.depth_mm).std()
    assert texture(past.depth_mm).std() > 0.4 * texture(rigid.depth_mm).std()
    # The support compresses by about p / k_s: the approach grows by that much.
    extra = past.indentation_mm - rigid.indentation_mm
    assert extra == pytest.approx(PRESSURE_MPA / (ks * 1e-3), rel=0.35)


@pytest.mark.parametrize("level", list(LEVELS))
def test_stiffer_support_leaves_more_texture(level):
    fab, prot = fabric("twill")
    stds = [float(texture(press(prot, PATCH, LEVELS[level], force_n=FORCE_N, support_stiffness_kpa_per_mm=k,
                                support_length_mm=fab.thickness_mm).depth_mm).std()) for k in (5.0, 50.0, 500.0)]
    assert stds[0] < stds[1] < stds[2]


def test_uniform_pressure_on_whole_pad_follows_disk_layer_factor():
    # The law's layer factor R: mean displacement under a uniform pressure on a disk of
    # the pad's area, 16 p a R / (3 pi E*). The elastic model pressing a plane over the
    # whole (rectangular) pad should give that within 10%.
    prof = load_profile("vitac").with_resolution(160)
    im = press(np.zeros(prof.shape, np.float32), prof, ELASTIC, force_n=2.0)
    area = prof.field_mm[0] * prof.field_mm[1]
    a = math.sqrt(area / math.pi)
    r = float(disk_layer_factor(np.array(a / prof.gel.thickness_mm), prof.gel.poisson_ratio))
    expect = 16 * (2.0 / area) * a * r / (3 * math.pi * effective_modulus_mpa(prof.gel))
    assert float(im.depth_mm.mean()) == pytest.approx(expect, rel=0.10)
    assert float(disk_layer_factor(np.array(1e-3), 0.48)) == pytest.approx(1.0, abs=1e-3)
    rs = disk_layer_factor(np.geomspace(0.01, 100, 30), 0.48)
    assert np.all(np.diff(rs) < 0)


def test_support_length_validation():
    from gelsim.errors import GelsimError

    fab, prot = fabric("plain")
    with pytest.raises(GelsimError):
        press(prot, PATCH, LEVELS["fast"], force_n=FORCE_N, support_stiffness_kpa_per_mm=50.0,
              support_length_mm=-1.0)
