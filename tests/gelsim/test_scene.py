"""gelsim.scene: the typed touched object and the patches built from it."""
import math

import cv2
import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.fabrics import load_catalog
from gelsim.motion import sample_motion
from gelsim.scene import (PHYSICS_MM_PER_PX, Cylinder, FabricObject, HeightPatch, Sphere, TouchedObject,
                          as_object, physics_surface, travel_patch)


@pytest.fixture(scope="module")
def fabric():
    return load_catalog()[3]


def test_fabric_wraps_and_objects_pass_through(fabric):
    obj = as_object(fabric)
    assert isinstance(obj, FabricObject) and isinstance(obj, TouchedObject)
    assert obj.friction == pytest.approx(fabric.friction)
    assert obj.texture_mm == pytest.approx(fabric.texture_mm)
    assert obj.support() is not None
    s = Sphere(4.0)
    assert as_object(s) is s and s.support() is None and s.texture_mm is None
    with pytest.raises(GelsimError, match="not something the sensor can touch"):
        as_object("cotton")


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf")])
def test_bad_diameter_names_the_fix(bad):
    with pytest.raises(GelsimError, match="give a value > 0 mm"):
        Sphere(bad)


def test_sphere_heights_are_the_cap():
    s = Sphere(4.0, center_mm=(1.0, -0.5))
    p = 0.05
    h = s.heights(-3.0, -3.0, 121, 121, p)
    assert h.dtype == np.float32 and h.shape == (121, 121)
    i, j = np.unravel_index(np.argmax(h), h.shape)
    assert (-3.0 + j * p, -3.0 + i * p) == pytest.approx((1.0, -0.5), abs=p)
    assert h.max() == pytest.approx(2.0, abs=1e-3)
    # a point 1 mm off the apex: sqrt(R^2 - 1)
    assert h[i, j + 20] == pytest.approx(math.sqrt(3.0), abs=1e-4)
    assert h.min() == 0.0


def test_heights_continuous_across_regions(fabric):
    """Two abutting regions give the same heights as one region covering both (the object has
    one frame, whatever window the sequence asks for)."""
    for obj in (FabricObject(fabric), Cylinder(3.0, angle_deg=30.0)):
        whole = obj.heights(0.0, 0.0, 80, 40, 0.05, seed=7)
        left = obj.heights(0.0, 0.0, 40, 40, 0.05, seed=7)
        right = obj.heights(40 * 0.05, 0.0, 40, 40, 0.05, seed=7)
        np.testing.assert_allclose(np.hstack([left, right]), whole, atol=1e-5)


def test_cylinder_rotation_matches_its_angle():
    a = Cylinder(2.0, angle_deg=0.0).heights(-2, -2, 81, 81, 0.05, rotation_deg=90.0)
    b = Cylinder(2.0, angle_deg=90.0).heights(-2, -2, 81, 81, 0.05)
    np.testing.assert_allclose(a, b, atol=1e-5)
    # axis along y now: constant down the columns
    assert np.ptp(b[:, 40]) < 1e-5 and np.ptp(b[40, :]) > 0.5


def test_patch_sample_translates_and_rotates():
    hp = Sphere(2.0).heights(-5.0, -5.0, 201, 201, 0.05)
    patch = HeightPatch(hp, (-5.0, -5.0), 0.05)
    img = patch.sample((61, 81), 0.05, 1.0, 0.5, 0.0)
    # the apex appears at the image point (-x, -y) from the centre: sensor at (1, 0.5) sees the
    # sphere at (0, 0) down-left of its centre
    i, j = np.unravel_index(np.argmax(img), img.shape)
    assert (j - 40, i - 30) == (-20, -10)
    # a yaw of 90 degrees about the apex leaves a sphere unchanged
    a = patch.sample((61, 81), 0.05, 0.0, 0.0, 0.0)
    b = patch.sample((61, 81), 0.05, 0.0, 0.0, 90.0)
    np.testing.assert_allclose(a[20:41, 30:51], b[20:41, 30:51], atol=2e-3)


@pytest.mark.parametrize("yaw_deg", [0.0, 1e-4, 0.5])
def test_patch_sample_is_bilinear_to_the_last_row_and_column(yaw_deg):
    """A sensor moved by a fraction of a pixel (and turned by a hand's tremor, taken as a pure
    translation, or by half a degree, warped) reads the patch bilinearly everywhere, its last row
    and column included: against the bilinear formula itself, and an edge that runs off the patch
    replicates it as OpenCV's warp does."""
    rng = np.random.default_rng(7)
    hp = rng.random((90, 120)).astype(np.float32)
    patch = HeightPatch(hp, (0.0, 0.0), 1.0)
    H, W = 61, 81
    x, y = 59.3, 44.8          # the sensor's centre, mm = px of the patch
    img = patch.sample((H, W), 1.0, x, y, yaw_deg)
    assert img.shape == (H, W) and img.dtype == np.float32 and img.flags.c_contiguous
    t = math.radians(yaw_deg)
    jj, ii = np.meshgrid(np.arange(W) - (W - 1) / 2, np.arange(H) - (H - 1) / 2)
    sx = x + math.cos(t) * jj - math.sin(t) * ii
    sy = y + math.sin(t) * jj + math.cos(t) * ii
    x0, y0 = np.floor(sx).astype(int), np.floor(sy).astype(int)
    fx, fy = sx - x0, sy - y0
    want = ((1 - fx) * (1 - fy) * hp[y0, x0] + fx * (1 - fy) * hp[y0, x0 + 1]
            + (1 - fx) * fy * hp[y0 + 1, x0] + fx * fy * hp[y0 + 1, x0 + 1])
    # The translation path neglects the turn: its corners move by at most the frame's half-diagonal
    # times the angle (8.7e-5 px at 1e-4 degrees), against the patch's slopes of at most 1 per px.
    # OpenCV's warp rounds coordinates to 1/32 px.
    turn_px = math.hypot(W, H) / 2 * t
    tol = 1e-5 + turn_px if yaw_deg < 0.01 else 1.0 / 32
    np.testing.assert_allclose(img, want, atol=tol)
    # off the patch's edge: the warp's replicated border, whichever path
    edge = patch.sample((H, W), 1.0, 80.6, 30.4, yaw_deg)
    M = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0]])
    M[:, 2] = np.array([80.6, 30.4]) - M[:, :2] @ np.array([(W - 1) / 2, (H - 1) / 2])
    ref = cv2.warpAffine(hp, M, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(edge, ref, atol=1e-6)


@pytest.mark.parametrize("yaw_deg,tilt", [(0.0, (0.0, 0.0)), (1e-4, (1.5, -2.0)), (7.0, (0.5, 0.5))],
                         ids=["shift", "tremor-tilted", "turned"])
def test_patch_sample_box_is_the_frame_cut(yaw_deg, tilt):
    """A box of the frame (what the imprint reads of a sequence's crown envelope) holds the frame's
    values there: to float rounding on its last row and column (the frame's are the filter's, the
    box's the explicit formula's), and, turned, to the warp's 1/32 px coordinates times the slope."""
    rng = np.random.default_rng(3)
    patch = HeightPatch(rng.random((90, 120)).astype(np.float32), (0.0, 0.0), 1.0)
    args = ((61, 81), 1.0, 59.3, 44.8, yaw_deg, tilt)
    frame = patch.sample(*args)
    for box in [(0, 61, 0, 81), (5, 40, 17, 80), (60, 61, 0, 1)]:
        part = patch.sample(*args, box=box)
        assert part.shape == (box[1] - box[0], box[3] - box[2]) and part.dtype == np.float32
        np.testing.assert_allclose(part, frame[box[0]:box[1], box[2]:box[3]], rtol=0,
                                   atol=1e-6 if yaw_deg < 1 else 1.0 / 32)


def test_tilt_raises_the_leaning_side():
    flat = HeightPatch(np.zeros((50, 50), np.float32), (-10.0, -10.0), 0.4)
    img = flat.sample((11, 11), 0.1, 0.0, 0.0, 0.0, tilt_deg=(0.0, 2.0))
    assert img[5, 10] - img[5, 0] == pytest.approx(math.tan(math.radians(2.0)) * 1.0, rel=1e-4)


def test_travel_patch_covers_the_motion(fabric, vitac):
    m = sample_motion("slip", 3)
    p = travel_patch(FabricObject(fabric), m, vitac, 0.1, seed=3)
    xmin, ymin, xmax, ymax = m.travel_bounds_mm()
    r = 0.5 * math.hypot(*vitac.field_mm)
    x0, y0 = p.origin_mm
    h, w = p.heights_mm.shape
    assert x0 <= xmin - r and y0 <= ymin - r
    assert x0 + (w - 1) * 0.1 >= xmax + r and y0 + (h - 1) * 0.1 >= ymax + r


def test_physics_surface_on_its_grid(fabric, vitac):
    m = sample_motion("press", 1)
    s = physics_surface(FabricObject(fabric), m, vitac, seed=1)
    ox, oy = s.origin_mm
    # snapped: the origin is a whole number of physics cells, heights >= 0
    assert ox / PHYSICS_MM_PER_PX == pytest.approx(round(ox / PHYSICS_MM_PER_PX), abs=1e-6)
    assert oy / PHYSICS_MM_PER_PX == pytest.approx(round(oy / PHYSICS_MM_PER_PX), abs=1e-6)
    assert s.heights_mm.min() >= 0.0 and s.friction == pytest.approx(fabric.friction)


@pytest.mark.parametrize("yaws", [(0.0, 0.001), (0.0, 35.0), (-20.0, 90.0)])
def test_travel_patch_from_poses_covers_every_frame_and_is_smaller(fabric, vitac, yaws):
    """Built from the frames' poses, the patch holds every pixel of every frame (two cells to spare for
    the bilinear taps), and for a press it is about half the circle-based patch's area."""
    m = sample_motion("press", 5)
    t = np.linspace(0.0, 1.0, 7)
    pos = np.stack([0.3 * t - 0.1, -0.2 * t + 0.05, 0.0 * t], axis=1)
    yaw = yaws[0] + (yaws[1] - yaws[0]) * t
    mm = vitac.image.mm_per_px
    p = travel_patch(FabricObject(fabric), m, vitac, mm, seed=3, poses=(pos, yaw))
    h_px, w_px = vitac.shape
    hp, wp = p.heights_mm.shape
    for (x, y, _), a in zip(pos, np.radians(yaw)):
        for u in (0, w_px - 1):
            for v in (0, h_px - 1):
                su, sv = (u - (w_px - 1) / 2) * mm, (v - (h_px - 1) / 2) * mm
                wx = x + math.cos(a) * su - math.sin(a) * sv
                wy = y + math.sin(a) * su + math.cos(a) * sv
                j, i = (wx - p.origin_mm[0]) / mm, (wy - p.origin_mm[1]) / mm
                assert 1.0 <= j <= wp - 2.0 and 1.0 <= i <= hp - 2.0
    if yaws[1] - yaws[0] < 1.0:
        circle = travel_patch(FabricObject(fabric), m, vitac, mm, seed=3)
        assert p.heights_mm.size < 0.6 * circle.heights_mm.size


def test_tilt_plane_is_numpys_two_passes_exactly():
    from gelsim.scene import _add_plane

    rng = np.random.default_rng(3)
    out = rng.random((37, 53), dtype=np.float32)
    xs, ys = rng.normal(size=53).astype(np.float32), rng.normal(size=37).astype(np.float32)
    ax, ay = np.float32(0.0349), np.float32(-0.0175)
    ref = out.copy()
    ref += ax * xs[None, :]
    ref += ay * ys[:, None]
    _add_plane(out, ax, xs, ay, ys)
    assert np.array_equal(out, ref)


@pytest.mark.parametrize("w", [960, 943, 12, 7])
def test_shifted_sample_is_opencvs_filter_and_numpys_fixes(w):
    """The shifted sample's one compiled pass gives what OpenCV's 2x2 filter2D, numpy's redone last row and
    column and the tilt plane gave (the frames of the datasets made before it, byte for byte), in the vector
    loop's columns and in its scalar tail (w = 943: 936 columns in 8-lane blocks, then 6)."""
    import cv2

    from llvmlite.binding import get_host_cpu_features

    from gelsim.scene import _add_plane, _shifted, _tilt_plane

    features = get_host_cpu_features()
    fused = bool(features.get("avx2") and features.get("fma"))     # OpenCV's AVX2 loop, as on this project's VM
    rng = np.random.default_rng(w)
    src = rng.random((60, w + 30), dtype=np.float32) * np.float32(2.5)
    h = 41
    for tx, ty, r0, c0 in ((3.37, 5.81, 0, 0), (10.02, 0.5, 4, 9), (0.0, 0.0, 2, 3)):
        plane = _tilt_plane((1.3, -0.7), c0, c0 + w, r0, r0 + h, (w - 1) / 2.0, 20.0, 0.0208)
        got = _shifted(src, tx, ty, h, w, r0, c0, plane)
        x0, y0 = math.floor(tx), math.floor(ty)
        fx, fy = np.float32(tx - x0), np.float32(ty - y0)
        one = np.float32(1.0)
        k = np.array([[(one - fx) * (one - fy), fx * (one - fy)], [(one - fx) * fy, fx * fy]], np.float32)
        a = src[y0 + r0:y0 + r0 + h + 1, x0 + c0:x0 + c0 + w + 1]
        ref = cv2.filter2D(a[:h, :w], -1, k, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
        ref[:, w - 1] = k[0, 0] * a[:h, w - 1] + k[0, 1] * a[:h, w] + k[1, 0] * a[1:, w - 1] + k[1, 1] * a[1:, w]
        ref[h - 1] = k[0, 0] * a[h - 1, :w] + k[0, 1] * a[h - 1, 1:] + k[1, 0] * a[h, :w] + k[1, 1] * a[h, 1:]
        flat = _shifted(src, tx, ty, h, w, r0, c0)
        tilted = ref.copy()
        _add_plane(tilted, *plane)
        assert not np.array_equal(tilted, ref)                          # the plane is seen
        for mine, theirs in ((flat, ref), (got, tilted)):
            if fused:
                np.testing.assert_array_equal(mine, theirs)
            else:   # (OpenCV's vector code without fused multiply-adds rounds each product)
                np.testing.assert_allclose(mine, theirs, rtol=0, atol=4 * np.finfo(np.float32).eps * 3.0)


def test_press_properties_carry_the_corduroys_valley_and_nothing_for_others():
    """What press() takes of an object: a corduroy's gap between wales as its envelope valley, None for
    other fabrics and rigid indenters, and None for a user's object that does not define it."""
    from gelsim.fabrics import load_catalog
    from gelsim.scene import macro_valley_mm, press_properties

    cat = load_catalog()
    cord = press_properties(FabricObject(cat[64]))
    assert cord["valley_mm"] == pytest.approx(cat[64].warp_pitch_mm - cat[64].warp_width_mm)
    assert cord["texture_mm"] == cat[64].texture_mm and cord["support"] == cat[64].support()
    gaps = [f.macro_valley_mm for f in cat if f.family == "corduroy"]
    assert len(gaps) == 5 and all(0.2 < g < 1.5 for g in gaps)
    assert all(f.macro_valley_mm is None for f in cat if f.family != "corduroy")
    assert press_properties(Sphere(4.0)) == {"support": None, "texture_mm": None, "valley_mm": None}

    class Plate:  # a user's object from before the attribute existed
        texture_mm = None

        def support(self):
            return None

    assert macro_valley_mm(Plate()) is None and press_properties(Plate())["valley_mm"] is None
