"""The edges of every documented parameter range, across gel, markers, optics, contact,
fabrics and whole sequences: no NaN or Inf, no uint8 wrap-around, a bounded float32/float64
difference; property-based tests (hypothesis) inside the ranges and a clear GelsimError
outside them.
"""
from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gelsim import indenters
from gelsim.contact import Surface, simulate
from gelsim.errors import GelsimError
from gelsim.fabrics import heightfield, load_catalog
from gelsim.fabrics.catalog import Fabric
from gelsim.fidelity import Fidelity, get_fidelity
from gelsim.gel import FabricSupport, press
from gelsim.gel.twoscale import MIN_TEXTURE_PX
from gelsim.markers import displace, marker_grid
from gelsim.motion import ForceRanges, Motion, load_motion_ranges, sample_motion
from gelsim.optics import Renderer
from gelsim.params import build
from gelsim.sensor import GelSpec, ImageSpec, MarkerSpec, load_profile
from gelsim.sequence import PHYSICS_MM_PER_PX, render_sequence
from gelsim.sinks import KeepFrames, drain
from gelsim.texture import texture_budget

FAST = get_fidelity("fast")
BAL = get_fidelity("balanced")
ELASTIC = dataclasses.replace(BAL, imprint_model="elastic")
PYRAMID = dataclasses.replace(BAL, imprint_model="pyramid")
# derandomize: the default suite stays reproducible (set it False locally to explore further)
PROPS = settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def small():
    # A flat gel: the marker tests below press the whole frame (the dome has its own edges test).
    p = load_profile("vitac").with_resolution(96, 72)
    return dataclasses.replace(p, gel=dataclasses.replace(p.gel, dome_radius_mm=0.0))


def with_gel(profile, **kw):
    return dataclasses.replace(profile, gel=dataclasses.replace(profile.gel, **kw))


def check_imprint(im, profile):
    d = im.depth_mm
    assert d.dtype == np.float32 and d.shape == profile.shape
    assert np.isfinite(d).all() and d.min() >= 0
    assert math.isfinite(im.indentation_mm) and math.isfinite(im.normal_force_n)
    assert math.isfinite(im.contact_area_mm2) and im.contact_area_mm2 >= 0
    # the gel surface never goes deeper than the pad's travel (the membrane blur only smooths)
    assert d.max() <= profile.gel.max_indentation_mm * (1 + 1e-4) + 1e-6


# ------------------------------------------------------------------------------ gel
@pytest.mark.parametrize("fid", [BAL, ELASTIC, PYRAMID], ids=["twoscale", "elastic", "pyramid"])
class TestGelEdges:
    def test_no_contact(self, small, fid):
        im = press(indenters.sphere(6.0, small), small, fid, force_n=0.0)
        assert im.depth_mm.max() == 0 and not im.contact_mask.any() and im.indentation_mm == 0

    def test_grazing_contact(self, small, fid):
        im = press(indenters.sphere(6.0, small), small, fid, force_n=1e-7)
        check_imprint(im, small)
        assert 0 <= im.indentation_mm < 1e-3 and not im.bottomed_out

    def test_bottoming_out(self, small, fid):
        im = press(indenters.sphere(6.0, small), small, fid, force_n=50.0)
        check_imprint(im, small)
        assert im.bottomed_out and im.indentation_mm == pytest.approx(small.gel.max_indentation_mm)
        assert im.normal_force_n <= 50.0

    @pytest.mark.parametrize("modulus", [1e-3, 100.0])
    def test_very_soft_and_very_stiff_gel(self, small, fid, modulus):
        p = with_gel(small, young_modulus_mpa=modulus)
        im = press(indenters.sphere(6.0, p), p, fid, force_n=1.0)
        check_imprint(im, p)
        assert im.bottomed_out == (modulus < 1)   # 1 N bottoms out a 1 kPa gel; 100 MPa barely dents
        if modulus > 1:   # Hertz: 0.022 mm for a 6 mm ball at 1 N on E* = 130 MPa
            assert 0.005 < im.indentation_mm < 0.05

    # The catalog's ranges: thickness 0.05-6 mm, compressibility 0-0.9, surface modulus 0.01-1000 MPa.
    @pytest.mark.parametrize("soft", [True, False], ids=["softest", "stiffest"])
    def test_very_soft_and_very_stiff_fabric(self, small, fid, soft):
        prot = indenters.sphere(6.0, small)
        support = FabricSupport(6.0, 0.9, 0.01) if soft else FabricSupport(0.05, 0.0, 1000.0)
        im = press(prot, small, fid, force_n=0.3, support=support)
        check_imprint(im, small)
        rigid = press(prot, small, fid, force_n=0.3)
        if not soft:         # a stiff fabric is nearly rigid
            assert im.depth_mm.max() == pytest.approx(rigid.depth_mm.max(), rel=0.05)
        elif fid.imprint_model == "pyramid":  # its springs-in-series law softens less (0.80 measured)
            assert im.depth_mm.max() < 0.9 * rigid.depth_mm.max()
        else:                # a soft fabric gives way: the gel is hardly pushed in
            assert im.depth_mm.max() < 0.5 * rigid.depth_mm.max()

    @pytest.mark.parametrize("dome", [5.0, 1e5], ids=["tight-dome", "flat-dome"])
    def test_dome_edges(self, small, fid, dome):
        # A 5 mm dome (steeper than any GelSight) and a practically flat one, on a flat object.
        p = with_gel(small, dome_radius_mm=dome)
        im = press(np.zeros(small.shape, np.float32), p, fid, force_n=0.3)
        check_imprint(im, p)
        assert im.contact_mask.any() and im.normal_force_n == pytest.approx(0.3, rel=1e-3)

    def test_steep_texture(self, small, fid):
        prot = np.zeros(small.shape, np.float32)
        prot[:, small.shape[1] // 2:] = 1.0       # a 1 mm cliff between neighbouring pixels
        prot[10, 10] = 1.5                        # a one-pixel spike above it
        im = press(prot, small, fid, force_n=0.5)
        check_imprint(im, small)
        assert im.contact_mask.any()

    def test_subpixel_texture(self, small, fid):
        h, w = small.shape
        checker = (np.indices((h, w)).sum(0) % 2).astype(np.float32) * 0.02   # Nyquist: 2 px period
        prot = checker + indenters.sphere(20.0, small)
        im = press(prot, small, fid, force_n=0.5)
        check_imprint(im, small)


def test_tiny_and_large_images():
    for w, h in ((22, 16), (1920, 1440)):  # 22 px: the smallest vitac image within mm_per_px <= 1
        p = load_profile("vitac").with_resolution(w, h)
        im = press(indenters.sphere(6.0, p), p, BAL, force_n=0.5)
        check_imprint(im, p)
        assert im.indentation_mm > 0.05
        frame = Renderer(p, "fast").render(im.depth_mm, displace(p, BAL, im))
        assert frame.dtype == np.uint8 and frame.shape == (h, w, 3)


@pytest.mark.parametrize("fid", [BAL, ELASTIC, PYRAMID], ids=["twoscale", "elastic", "pyramid"])
def test_float32_float64_difference_bounded(small, fid):
    """Heights far from 0 (an object 100 mm up) lose float32 precision: the imprint moves by
    less than 1e-3 mm, and float64 input gives the same imprint as float32 input."""
    prot = indenters.sphere(6.0, small).astype(np.float64)
    base = press(prot, small, fid, force_n=0.3)
    f32 = press(prot.astype(np.float32), small, fid, force_n=0.3)
    far = press(prot + 100.0, small, fid, force_n=0.3)
    np.testing.assert_allclose(f32.depth_mm, base.depth_mm, atol=1e-6)
    assert abs(far.indentation_mm - base.indentation_mm) < 1e-3
    assert np.abs(far.depth_mm - base.depth_mm).max() < 1e-3


# ------------------------------------------------------------------------------ markers
def flat_punch(profile, depth=0.2):
    """An imprint covering the whole frame: every marker is in contact (weight 1)."""
    return press(np.zeros(profile.shape, np.float32), profile, BAL, depth_mm=depth)


def test_ninety_degree_twist_rotates_contact(small):
    im = flat_punch(small)
    rest = marker_grid(small)
    mk = displace(small, BAL, im, twist_deg=90.0, rest=rest)
    assert np.isfinite(mk.xy_px).all() and np.isfinite(mk.corners_px).all()
    dilated = displace(small, BAL, im, rest=rest).xy_px   # the punch's edges also push markers out
    cx, cy = (small.shape[1] - 1) / 2, (small.shape[0] - 1) / 2
    # uniform contact, centroid at the image centre: (x, y) -> (cx - (y - cy), cy + (x - cx))
    want = np.stack([cx - (rest[:, 1] - cy), cy + (rest[:, 0] - cx)], axis=1)
    np.testing.assert_allclose(mk.xy_px - dilated + rest, want, atol=0.05)


def test_fast_slip_shear(small):
    im = flat_punch(small)
    mk = displace(small, BAL, im, shear_mm=(5.0, -3.0))
    dilated = displace(small, BAL, im).xy_px
    moved = (mk.xy_px - dilated) * small.image.mm_per_px
    assert np.isfinite(moved).all()
    np.testing.assert_allclose(moved, np.broadcast_to([5.0, -3.0], moved.shape), atol=1e-3)


def test_markers_float64_rest_matches_float32(small):
    im = press(indenters.sphere(6.0, small), small, BAL, force_n=0.3)
    rest = marker_grid(small)
    a = displace(small, BAL, im, shear_mm=(0.1, 0.0), twist_deg=3.0, rest=rest)
    b = displace(small, BAL, im, shear_mm=(0.1, 0.0), twist_deg=3.0, rest=rest.astype(np.float64))
    assert np.abs(a.xy_px - b.xy_px).max() < 1e-4


# ------------------------------------------------------------------------------ optics
def assert_no_wraparound(renderer, depth, markers=None):
    """uint8 output is the saturated float frame: 255 where it overflows, 0 where it underflows."""
    f = renderer.render_float(depth, markers)
    u = renderer.render(depth, markers, noise=False)
    assert np.isfinite(f).all() and u.dtype == np.uint8
    assert np.abs(u.astype(np.float32) - np.clip(f, 0, 255)).max() <= 0.5 + 1e-3
    return f


@pytest.mark.parametrize("backend", ["fast", pytest.param("pyrender", marks=pytest.mark.gl)])
def test_deepest_steepest_imprint_saturates_without_wrapping(small, backend):
    from gelsim.optics import available_backends

    if backend not in available_backends():
        pytest.skip("no OpenGL context")
    p = dataclasses.replace(small, shading=dataclasses.replace(small.shading, gain_dn=1000.0))
    depth = np.zeros(p.shape, np.float32)
    depth[20:50, 30:60] = p.gel.max_indentation_mm   # the pad bottomed out with vertical walls
    r = Renderer(p, backend)
    try:
        f = assert_no_wraparound(r, depth, displace(p, BAL, flat_punch(p, 1.0)))
    finally:
        r.close()
    assert f.max() > 255 and f.min() < 0        # the case does leave 0-255 on both sides


def test_supersampled_tiny_frame():
    p = load_profile("vitac").with_resolution(22, 16)
    r = Renderer(p, "fast", supersample=4)
    im = press(indenters.sphere(6.0, p), p, BAL, force_n=0.5)
    assert_no_wraparound(r, im.depth_mm, displace(p, BAL, im))


# ------------------------------------------------------------------------------ contact
def flat_surface(motion, profile, friction=0.8):
    x0, y0, x1, y1 = motion.travel_bounds_mm()
    r = 0.5 * math.hypot(*profile.field_mm) + 1.0
    w = int((x1 - x0 + 2 * r) / PHYSICS_MM_PER_PX) + 2
    h = int((y1 - y0 + 2 * r) / PHYSICS_MM_PER_PX) + 2
    return Surface(np.zeros((h, w), np.float32), PHYSICS_MM_PER_PX, (x0 - r, y0 - r), friction)


def check_contact(c, motion):
    for k, v in c.to_dict().items():
        assert len(v) == motion.num_frames, k
        if v.dtype != bool:
            assert np.isfinite(v).all(), k
    assert (c.normal_force_n >= 0).all()


def simulate_flat(motion, profile):
    """``motion`` simulated on a flat surface at the fast level, its frames checked (check_contact)."""
    c = simulate(motion, flat_surface(motion, profile), profile, FAST)
    check_contact(c, motion)
    return c


def base_motion(action, **kw):
    m = sample_motion(action, 3, frames=(12, 12), precontact=(2, 2))
    return dataclasses.replace(m, **kw)


def test_fast_long_slip(small):
    m = base_motion("slip", slip_distance_mm=50.0, approach_speed_mm_s=200.0, slip_direction_deg=30.0)
    c = simulate_flat(m, small)
    assert c.slipping.any()
    travel = np.hypot(*(c.position_mm[-1, :2] - c.position_mm[m.precontact_frames, :2]))
    assert travel > 30.0


def test_ninety_degree_twist_motion(small):
    m = base_motion("twist", twist_deg=90.0)
    c = simulate_flat(m, small)
    assert abs(c.yaw_deg[-1] - c.yaw_deg[0]) > 60.0


def test_largest_force(small):
    m = base_motion("press", peak_force_n=50.0)
    c = simulate_flat(m, small)
    assert c.normal_force_n.max() > 25.0


def test_long_sequence(small):
    simulate_flat(sample_motion("press", 5, frames=(150, 150), precontact=(8, 8)), small)


# ------------------------------------------------------------------------------ fabrics
@pytest.mark.parametrize("changes", [
    dict(relief_mm=0.005), dict(relief_mm=2.0, thickness_mm=6.0),
    dict(warp_pitch_mm=0.021, weft_pitch_mm=0.021, warp_width_mm=0.02, weft_width_mm=0.02),  # sub-pixel weave
    dict(warp_pitch_mm=20.0, weft_pitch_mm=20.0, warp_width_mm=20.0, weft_width_mm=20.0),
    dict(compressibility=0.0, surface_modulus_mpa=0.01), dict(compressibility=0.9, surface_modulus_mpa=1000.0),
])
def test_fabric_extremes(changes):
    fabric = dataclasses.replace(load_catalog()[1], **changes)
    h = heightfield(fabric, x0_mm=-5, y0_mm=-5, width_px=120, height_px=90, mm_per_px=0.08, seed=1)
    assert h.dtype == np.float32 and np.isfinite(h).all() and h.min() >= 0
    assert h.max() <= 1.5 * fabric.relief_mm + 1e-6


# ------------------------------------------------------------------------------ texture edges
# The edges the texture work adds: pitches near the pixel pitch, relief near zero and near the gel's
# travel, the motion range's extreme forces, texture below the two-scale model's 4 px per period.
# Each gives finite output within the pad's travel, or a clear GelsimError outside the documented
# ranges (the catalog's relief 0.005-2 mm and pitch > 0.02 mm, motions.toml's forces).
HIRES = load_profile("vitac")                        # 960x720, 0.0197 mm per px: the dataset's
TEX = load_profile("vitac").with_resolution(160, 120)  # 0.118 mm per px


def fabric_with(fid, **changes):
    """A catalog fabric with ``changes``, validated as a catalog entry."""
    return build(Fabric, {**load_catalog()[fid].to_dict(), **changes}, where="test")


def pad_heights(fabric, profile, seed=0):
    h, w = profile.shape
    mm = profile.image.mm_per_px
    return heightfield(fabric, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                       mm_per_px=mm, seed=seed, rotation_deg=fabric.orientation_deg)


def press_fabric(fabric, profile, fid, force_n, **kw):
    return press(pad_heights(fabric, profile), profile, fid, force_n=force_n, support=fabric.support(),
                 texture_mm=fabric.texture_mm, **kw)


def check_budget(b):
    for k in ("fabric_relief_mm", "gel_relief_mm", "kept", "gel_slope_rms", "image_dn", "noise_dn", "snr"):
        v = getattr(b, k)
        assert math.isfinite(v) and v >= 0, k


@pytest.mark.parametrize("pitch_px", [1.07, 2.0, 4.0])
@pytest.mark.parametrize("fid", [FAST, BAL, PYRAMID], ids=["twoscale-0.5", "twoscale-1.0", "pyramid"])
def test_pitch_near_the_pixel_pitch(fid, pitch_px):
    """A plain weave whose pitch is 1-4 pixels of the 960x720 camera (0.021 mm: just above the
    catalog's 0.02 mm floor): the imprint stays finite and within the travel; the texture budget's
    band (half the pitch: below a pixel) still measures finite numbers."""
    pitch = pitch_px * HIRES.image.mm_per_px
    fab = fabric_with(2, warp_pitch_mm=pitch, weft_pitch_mm=pitch, warp_width_mm=0.8 * pitch,
                      weft_width_mm=0.8 * pitch, relief_mm=0.01)
    im = press_fabric(fab, HIRES, fid, 2.5)
    check_imprint(im, HIRES)
    assert im.contact_mask.any() and im.normal_force_n == pytest.approx(2.5, rel=0.02)
    if fid is BAL:
        check_budget(texture_budget(fab, 2.5, HIRES, fid, codec=False))


def test_texture_below_four_px_per_period_skips_the_texture_stage():
    """Below MIN_TEXTURE_PX pixels per period on the imprint grid the two-scale model presses the
    area-averaged surface: exactly as for an object without texture. The fast level's half-scale
    grid at 960x720 (0.039 mm per px) puts that threshold at 0.158 mm: a 0.15 mm texture is skipped
    there and kept at balanced's full scale; 0.17 mm is kept by both."""
    prot = pad_heights(load_catalog()[14], HIRES)   # silk organza, 0.16 mm
    sup = load_catalog()[14].support()
    dx_fast = HIRES.image.mm_per_px / FAST.imprint_scale
    assert 0.15 < MIN_TEXTURE_PX * dx_fast < 0.17

    def run(fid, tex):
        return press(prot, HIRES, fid, force_n=2.0, support=sup, texture_mm=tex)

    smooth = run(FAST, None)
    skipped = run(FAST, 0.15)
    np.testing.assert_array_equal(skipped.depth_mm, smooth.depth_mm)
    np.testing.assert_array_equal(skipped.contact_mask, smooth.contact_mask)
    assert skipped.indentation_mm == smooth.indentation_mm
    kept = run(FAST, 0.17)
    check_imprint(kept, HIRES)
    assert np.abs(kept.depth_mm - smooth.depth_mm).max() > 1e-4      # the texture stage ran
    full = run(BAL, 0.15)
    assert np.abs(full.depth_mm - run(BAL, None).depth_mm).max() > 1e-4
    for tex in (-0.1, float("nan"), float("inf")):
        with pytest.raises(GelsimError, match="texture_mm"):
            run(BAL, tex)


@pytest.mark.parametrize("fid", [FAST, BAL, ELASTIC, PYRAMID], ids=["twoscale-0.5", "twoscale-1.0", "elastic",
                                                                     "pyramid"])
def test_relief_near_zero(fid):
    """The catalog's least relief (0.005 mm) on a fine weave: a nearly smooth cloth; the gel keeps at
    most the cloth's relief and the texture budget stays finite."""
    fab = fabric_with(2, relief_mm=0.005)
    im = press_fabric(fab, TEX, fid, 2.5)
    check_imprint(im, TEX)
    assert im.normal_force_n == pytest.approx(2.5, rel=0.02)
    b = texture_budget(fab, 2.5, TEX, fid, codec=False)
    check_budget(b)
    assert b.gel_relief_mm <= 2 * b.fabric_relief_mm


def test_relief_outside_the_catalog_range_is_a_clear_error():
    for v in (0.004, 2.01):
        with pytest.raises(GelsimError, match="relief_mm"):
            fabric_with(2, relief_mm=v)
    with pytest.raises(GelsimError, match="warp_pitch_mm"):
        fabric_with(2, warp_pitch_mm=0.02)


@pytest.mark.parametrize("relief", [1.0, 2.0], ids=["travel", "catalog-max"])
@pytest.mark.parametrize("fid", [FAST, BAL, ELASTIC, PYRAMID], ids=["twoscale-0.5", "twoscale-1.0", "elastic",
                                                                     "pyramid"])
def test_relief_near_the_gels_limit(fid, relief):
    """A corduroy whose wales stand as deep as the pad's travel (1 mm) or twice it (the catalog's
    2 mm), on its thickest cloth, pressed at the motion range's top force: finite, and the gel
    surface never deeper than its travel."""
    fab = fabric_with(64, relief_mm=relief, thickness_mm=6.0)
    im = press_fabric(fab, TEX, fid, 4.0)
    check_imprint(im, TEX)
    assert im.contact_mask.any()
    check_budget(texture_budget(fab, 4.0, TEX, fid, codec=False))


def _force_edges():
    f = load_motion_ranges().force
    return f.peak_force_n[0] * f.slip_force_scale[0], f.peak_force_n[1]


@pytest.mark.parametrize("fabric_id", [2, 50, 64], ids=["fine-weave", "coarse-knit", "pile"])
def test_forces_at_the_motion_range_edges(fabric_id):
    """Whole sequences at the lightest force a motion can have (a slip at half the least press,
    0.5 N) and the heaviest press (4 N): finite labels and frames, the gel within its travel, a
    contact in every pressing frame, and the heavier press deeper and wider."""
    fabric = load_catalog()[fabric_id]
    labels = []
    for action, force in zip(("slip", "press"), _force_edges()):
        m = base_motion(action, peak_force_n=force)
        keep = KeepFrames()
        lab, _ = drain(render_sequence(fabric, m, TEX, BAL, seed=2), [keep])
        frames = keep.frames
        assert all(f.dtype == np.uint8 and f.shape == (120, 160, 3) for f in frames)
        pressing = lab["in_contact"] & (lab["normal_force_n"] > 0)
        assert pressing.any() and (lab["contact_area_mm2"][pressing] > 0).all()
        for k, v in lab.items():
            if k in ("contact_centroid_px", "contact_bbox_px"):
                assert np.isfinite(v[pressing]).all(), k
            elif v.dtype != bool:
                assert np.isfinite(v).all(), k
        # the two-scale approach adds the crowns' sink below the macro solve's (bounded by the travel)
        assert lab["indentation_mm"].max() <= TEX.gel.max_indentation_mm * 1.1
        labels.append(lab)
    light, heavy = labels
    assert heavy["normal_force_n"].max() > 2 * light["normal_force_n"].max()
    assert heavy["contact_area_mm2"].max() > light["contact_area_mm2"].max()
    assert heavy["indentation_mm"].max() > light["indentation_mm"].max()


def test_forces_outside_the_motion_range_are_a_clear_error():
    with pytest.raises(GelsimError, match="peak_force_n"):
        build(ForceRanges, {"peak_force_n": [0.01, 4.0]}, where="motions.force")
    with pytest.raises(GelsimError, match="peak_force_n"):
        build(ForceRanges, {"peak_force_n": [1.0, 60.0]}, where="motions.force")


# ------------------------------------------------------------------------------ whole sequence
@pytest.mark.parametrize("fabric_id, motion_kw", [
    (64, dict(action="slip", slip_distance_mm=50.0, approach_speed_mm_s=200.0)),    # corduroy, fast slip
    (1, dict(action="twist", twist_deg=90.0)),
    (1, dict(action="press", peak_force_n=50.0)),
])
def test_sequence_extremes(fabric_id, motion_kw):
    profile = load_profile("vitac").with_resolution(64, 48)
    fabric = load_catalog()[fabric_id]
    m = base_motion(**motion_kw)
    keep = KeepFrames()
    labels, _ = drain(render_sequence(fabric, m, profile, FAST, seed=2), [keep])
    frames, out = keep.frames, SimpleNamespace(labels=labels)
    assert len(frames) == m.num_frames
    assert all(f.dtype == np.uint8 and f.shape == (48, 64, 3) for f in frames)
    touched = out.labels["contact_area_mm2"] > 0
    for k, v in out.labels.items():
        if k in ("contact_centroid_px", "contact_bbox_px"):  # NaN by definition in frames without contact
            assert np.isfinite(v[touched]).all() and np.isnan(v[~touched]).all(), k
        elif v.dtype != bool:
            assert np.isfinite(v).all(), k
    assert out.labels["indentation_mm"].max() <= profile.gel.max_indentation_mm + 1e-6


# ------------------------------------------------------------------------------ properties
GEL_RANGES = dict(thickness_mm=(0.1, 20.0), young_modulus_mpa=(1e-3, 100.0), poisson_ratio=(0.0, 0.5),
                  max_indentation_mm=(0.01, 20.0), membrane_smoothing_mm=(0.0, 5.0))


def _log_uniform(lo, hi):
    # exp(log(hi)) may round above hi: clamp into the range
    return st.floats(math.log(lo), math.log(hi)).map(lambda v: min(max(math.exp(v), lo), hi))


@PROPS
@given(thickness=_log_uniform(0.1, 20.0), modulus=_log_uniform(1e-3, 100.0), nu=st.floats(0.0, 0.5),
       travel=_log_uniform(0.01, 20.0), smooth=st.floats(0.0, 5.0), f1=_log_uniform(1e-6, 50.0),
       ratio=st.floats(1.0, 10.0), diameter=_log_uniform(0.5, 40.0))
def test_press_properties(thickness, modulus, nu, travel, smooth, f1, ratio, diameter):
    base = load_profile("vitac").with_resolution(64, 48)
    gel = build(GelSpec, dict(thickness_mm=thickness, young_modulus_mpa=modulus, poisson_ratio=nu,
                              max_indentation_mm=travel, membrane_smoothing_mm=smooth))
    p = dataclasses.replace(base, gel=gel)
    prot = indenters.sphere(diameter, p)
    a = press(prot, p, BAL, force_n=f1)
    b = press(prot, p, BAL, force_n=f1 * ratio)
    check_imprint(a, p)
    check_imprint(b, p)
    assert b.indentation_mm >= a.indentation_mm - 1e-6     # more force, deeper (or bottomed out)
    assert a.indentation_mm <= travel + 1e-9


@PROPS
@given(sx=st.floats(-10, 10), sy=st.floats(-10, 10), twist=st.floats(-180, 180), depth=_log_uniform(1e-4, 1.0),
       diameter=_log_uniform(1.0, 30.0), model=st.sampled_from(["gaussian", "elastic"]))
def test_marker_properties(sx, sy, twist, depth, diameter, model):
    p = load_profile("vitac").with_resolution(64, 48)
    fid = dataclasses.replace(BAL, marker_model=model)
    im = press(indenters.sphere(diameter, p), p, fid, depth_mm=depth)
    mk = displace(p, fid, im, shear_mm=(sx, sy), twist_deg=twist)
    assert np.isfinite(mk.xy_px).all() and np.isfinite(mk.corners_px).all()
    # no marker moves further than the shear plus the twist's arc across the image plus dilation
    bound = (math.hypot(sx, sy) / p.image.mm_per_px + abs(math.radians(twist)) * math.hypot(*p.shape)
             + 5 * p.gel.thickness_mm / p.image.mm_per_px)
    assert np.linalg.norm(mk.xy_px - mk.rest_px, axis=1).max() <= bound


@PROPS
@given(depth=_log_uniform(1e-4, 1.0), diameter=_log_uniform(0.5, 40.0), seed=st.integers(0, 2 ** 31 - 1),
       gain=st.floats(0.0, 1000.0), ss=st.integers(1, 2))
def test_render_properties(depth, diameter, seed, gain, ss):
    base = load_profile("vitac").with_resolution(48, 36)
    p = dataclasses.replace(base, shading=dataclasses.replace(base.shading, gain_dn=gain))
    im = press(indenters.sphere(diameter, p), p, BAL, depth_mm=depth)
    r = Renderer(p, "fast", supersample=ss, seed=seed % 7)
    assert_no_wraparound(r, im.depth_mm, displace(p, BAL, im))
    noisy = r.render(im.depth_mm, None, seed=seed)
    assert noisy.dtype == np.uint8 and noisy.shape == (36, 48, 3)


# ------------------------------------------------------------------------------ outside the ranges
def _ranged_fields(cls):
    out = []
    for f in dataclasses.fields(cls):
        lo, hi = f.metadata.get("lo"), f.metadata.get("hi")
        if lo is not None or hi is not None:
            out.append((cls, f.name, lo, hi))
    return out


VALID = {
    GelSpec: dict(thickness_mm=2.0, young_modulus_mpa=0.2, poisson_ratio=0.48, max_indentation_mm=1.0),
    ImageSpec: dict(width_px=320, height_px=240, mm_per_px=0.05),
    MarkerSpec: {},
    Fidelity: dict(name="x", physics_dt_s=0.001, imprint_model="pyramid", imprint_scale=1.0,
                   marker_model="gaussian", render_backend="fast", supersample=1, macro_cells=64),
}
RANGED = [r for cls in VALID for r in _ranged_fields(cls)]


@pytest.mark.parametrize("cls, name, lo, hi", RANGED, ids=[f"{r[0].__name__}.{r[1]}" for r in RANGED])
@pytest.mark.parametrize("side", ["below", "above"])
def test_outside_documented_range_is_a_clear_error(cls, name, lo, hi, side):
    bound = lo if side == "below" else hi
    if bound is None:
        pytest.skip("no bound on this side")
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    is_int = f.type in (int, "int")
    step = 1 if is_int else max(abs(bound) * 0.01, 1e-6)
    value = bound - step if side == "below" else bound + step
    with pytest.raises(GelsimError, match=name):
        build(cls, {**VALID[cls], name: value}, where="t")
    # the bound itself is accepted
    if not (side == "below" and f.metadata.get("lo_open")):
        build(cls, {**VALID[cls], name: bound}, where="t")


@pytest.mark.parametrize("call, match", [
    (lambda p: press(np.zeros(p.shape), p, BAL, force_n=-1.0), "negative"),
    (lambda p: press(np.zeros(p.shape), p, BAL, force_n=float("nan")), "not finite"),
    (lambda p: press(np.full(p.shape, np.inf), p, BAL, force_n=1.0), "NaN or Inf"),
    (lambda p: displace(p, BAL, None, shear_mm=(float("inf"), 0.0)), "not finite"),
    (lambda p: Renderer(p, "fast", supersample=5), "supersample"),
    (lambda p: Renderer(p, "fast").render(np.full(p.shape, np.nan, np.float32)), "NaN"),
    (lambda p: Renderer(p, "fast").render(np.full(p.shape, -1.0, np.float32)), "negative"),
    (lambda p: p.with_resolution(8, 8), "out of range for"),
    (lambda p: get_fidelity("ultra"), "unknown fidelity"),
    (lambda p: base_motion("press", peak_force_n=-1.0), "positive"),
    (lambda p: sample_motion("press", 0, frames=(4, 4), precontact=(3, 3)), "fewer than 3"),
])
def test_bad_inputs_raise_gelsim_error(small, call, match):
    with pytest.raises(GelsimError, match=match):
        call(small)


def test_with_resolution_keeps_mm_per_px_in_range():
    with pytest.raises(GelsimError):
        load_profile("vitac").with_resolution(16, 16)


def test_motion_twist_outside_range():
    with pytest.raises(GelsimError):
        base_motion("twist", twist_deg=720.0)



def test_textured_contact_on_the_frames_edge():
    """A twist whose contact reaches the frame's edge at 320x240 left the two-scale contact window
    one pixel wide, which OpenCV's arithmetic reads as a scalar (sequence f009-s0004 of the cpu
    preset); every frame now renders."""
    profile = load_profile("vitac").with_resolution(320, 240)
    motion = sample_motion("twist", 88805309, frames=(34, 34), precontact=None)
    frames = [r.frame for r in render_sequence(load_catalog()[9], motion, profile, BAL, seed=88805309)]
    assert len(frames) == 34 and all(np.isfinite(f).all() for f in frames)
