"""Tests of gelsim.optics: both rendering backends and the shared compositing."""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.optics import Renderer, available_backends, check_depth, render
from gelsim.optics.field import led_position_mm

SMALL_W = 320  # 320x240: the same sensor at a third of the resolution, for speed


@pytest.fixture(scope="module")
def small(vitac):
    return vitac.with_resolution(SMALL_W)


def replace(profile, **sections):
    """Profile with some fields of some sections replaced: replace(p, shading={"gain_dn": 5})."""
    changes = {name: dataclasses.replace(getattr(profile, name), **fields) for name, fields in sections.items()}
    return dataclasses.replace(profile, **changes)


def sphere_dent(profile, radius_mm=3.0, depth_mm=0.5, center_mm=(0.0, 0.0), smooth_px=0.0):
    """Imprint of a sphere: max(0, sqrt(R^2 - r^2) - (R - d)), float32 (H, W) mm."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    x = (np.arange(w) - (w - 1) / 2) * mm - center_mm[0]
    y = (np.arange(h) - (h - 1) / 2) * mm - center_mm[1]
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    d = np.maximum(0.0, np.sqrt(np.maximum(radius_mm ** 2 - r2, 0.0)) - (radius_mm - depth_mm)).astype(np.float32)
    if smooth_px > 0:
        d = cv2.GaussianBlur(d, (0, 0), smooth_px)
    return d


def marker_grid(profile, offset_px=(0.0, 0.0)):
    """Square markers of the profile's size on its pitch: float32 (N, 4, 2) corner pixels."""
    mm = profile.image.mm_per_px
    pitch, size = profile.markers.pitch_mm / mm, profile.markers.size_mm / mm
    h, w = profile.shape
    cx = np.arange(pitch / 2, w - size, pitch) + offset_px[0]
    cy = np.arange(pitch / 2, h - size, pitch) + offset_px[1]
    centres = np.array([(x, y) for y in cy for x in cx], np.float32)
    half = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32) * size / 2
    return centres[:, None, :] + half[None], centres


@pytest.fixture(scope="module")
def gl_backend():
    if "pyrender" not in available_backends():
        pytest.skip("no headless OpenGL context (install libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libosmesa6)")
    return "pyrender"


# ---------------------------------------------------------------- flat gel, noise

def test_flat_gel_is_background_plus_profile_noise(vitac):
    # vitac borrows the R1.5's measured noise (no shot term); a shot term makes the test see both
    vitac = replace(vitac, noise={"shot_gain": 0.03})
    r = Renderer(vitac, seed=3)
    bg = r.background_float()
    frame = r.render(None, seed=11).astype(np.float64)
    diff = frame - bg
    assert abs(diff.mean()) < 0.3, "noise must be zero-mean over the frame"
    n = vitac.noise
    expected_var = n.read_sigma_dn ** 2 + n.shot_gain * bg
    # quantisation adds 1/12 DN^2 of variance
    ratio = (diff ** 2).mean() / (expected_var.mean() + 1.0 / 12.0)
    assert 0.9 < ratio < 1.1
    # shot noise: brighter pixels are noisier by the profile's shot gain
    bright, dark = bg > np.percentile(bg, 80), bg < np.percentile(bg, 20)
    slope = ((diff[bright] ** 2).mean() - (diff[dark] ** 2).mean()) / (bg[bright].mean() - bg[dark].mean())
    assert slope == pytest.approx(n.shot_gain, rel=0.35)


def test_noise_off_and_background_match(small):
    r = Renderer(small)
    np.testing.assert_array_equal(r.render(None, noise=False), r.background())


def test_same_seed_same_frame_different_seed_different_noise(small):
    r = Renderer(small, seed=1)
    d = sphere_dent(small, 2.0, 0.3)
    a, b, c = r.render(d, seed=5), r.render(d, seed=5), r.render(d, seed=6)
    np.testing.assert_array_equal(a, b)
    assert np.mean(a != c) > 0.3
    g1, g2 = r.render(d, seed=np.random.default_rng(9)), r.render(d, seed=np.random.default_rng(9))
    np.testing.assert_array_equal(g1, g2)
    # a fresh renderer with the same seed reproduces the frame; another seed changes the background
    np.testing.assert_array_equal(Renderer(small, seed=1).render(d, seed=5), a)
    assert not np.array_equal(Renderer(small, seed=2).background(), r.background())


def test_noise_differs_over_many_seeds(small):
    r = Renderer(small)
    frames = {r.render(None, seed=s).tobytes() for s in range(40)}
    assert len(frames) == 40


# ---------------------------------------------------------------- background field

def test_background_mean_led_tint_and_vignetting(vitac):
    plain = replace(vitac, background={"nonuniformity_dn": 0.0}, camera={"vignetting": 0.0, "blur_sigma_px": 0.0})
    bg = Renderer(plain).background_float()
    np.testing.assert_allclose(bg.reshape(-1, 3).astype(np.float64).mean(axis=0), plain.background.rgb_dn, atol=0.05)
    h, w = plain.shape
    # each LED's colour is brighter near its own rim than on the opposite side
    for light in plain.lights:
        a = math.radians(light.azimuth_deg)
        u = np.array([math.cos(a), math.sin(a)])
        near = (np.array([w / 2, h / 2]) + u * np.array([w, h]) * 0.45).astype(int)
        far = (np.array([w / 2, h / 2]) - u * np.array([w, h]) * 0.45).astype(int)
        ch = int(np.argmax(light.color_rgb))
        assert bg[near[1], near[0], ch] - bg[far[1], far[0], ch] > 0.3 * plain.background.led_tint_dn
    vig = replace(plain, background={"led_tint_dn": 0.0}, camera={"vignetting": 0.2})
    bgv = Renderer(vig).background_float()
    assert bgv[h // 2, w // 2, 0] == pytest.approx(vig.background.rgb_dn[0], rel=1e-3)
    assert bgv[0, 0, 0] == pytest.approx(vig.background.rgb_dn[0] * 0.8, rel=1e-2)


def test_random_field_has_profile_amplitude(vitac):
    p = replace(vitac, background={"led_tint_dn": 0.0, "nonuniformity_dn": 6.0},
                camera={"vignetting": 0.0, "blur_sigma_px": 0.0})
    bg = Renderer(p, seed=4).background_float()[..., 0]
    assert bg.std() == pytest.approx(6.0, rel=0.02)
    # smooth: neighbouring pixels differ by far less than the field's amplitude
    assert np.abs(np.diff(bg, axis=1)).max() < 0.1 * 6.0


# ---------------------------------------------------------------- shading

def _check_led_sides(profile, frame, bg, radius_mm, depth_mm):
    """On the dent's slope facing each LED, that LED's dominant colour channel gains most."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    a_contact = math.sqrt(radius_mm ** 2 - (radius_mm - depth_mm) ** 2)
    diff = frame.astype(np.float64) - bg
    for light in profile.lights:
        p = led_position_mm(light, profile)
        u = p[:2] / np.hypot(p[0], p[1])
        cx, cy = (w - 1) / 2 + u[0] * 0.7 * a_contact / mm, (h - 1) / 2 + u[1] * 0.7 * a_contact / mm
        patch = diff[int(cy) - 2:int(cy) + 3, int(cx) - 2:int(cx) + 3].reshape(-1, 3).mean(axis=0)
        assert int(np.argmax(patch)) == int(np.argmax(light.color_rgb)), (light.name, patch)
        assert patch.max() > 10.0, (light.name, patch)
        # the opposite slope turns away from this LED: its colour darkens there
        ox, oy = (w - 1) - cx, (h - 1) - cy
        opp = diff[int(oy) - 2:int(oy) + 3, int(ox) - 2:int(ox) + 3].reshape(-1, 3).mean(axis=0)
        assert opp[int(np.argmax(light.color_rgb))] < patch[int(np.argmax(light.color_rgb))] - 10.0


def test_sphere_press_lights_each_side_in_its_led_colour_fast(vitac):
    r = Renderer(vitac)
    d = sphere_dent(vitac, 3.0, 0.5)
    _check_led_sides(vitac, r.render(d, noise=False), r.background_float(), 3.0, 0.5)


def test_shading_follows_light_azimuths_from_the_profile(vitac):
    """Phong shading: rotate all LEDs by 180 degrees and the colours on the dent swap sides
    (the calibrated table of vitac ignores [[lights]], so the phong model is selected here)."""
    phong = replace(vitac, shading={"model": "phong"})
    rotated = dataclasses.replace(phong, lights=tuple(dataclasses.replace(li, azimuth_deg=li.azimuth_deg + 180)
                                                      for li in phong.lights))
    r = Renderer(rotated)
    d = sphere_dent(rotated, 3.0, 0.5)
    _check_led_sides(rotated, r.render(d, noise=False), r.background_float(), 3.0, 0.5)


@pytest.mark.gl
def test_sphere_press_lights_each_side_in_its_led_colour_pyrender(small, gl_backend):
    r = Renderer(small, gl_backend)
    try:
        d = sphere_dent(small, 3.0, 0.5)
        _check_led_sides(small, r.render(d, noise=False), r.background_float(), 3.0, 0.5)
    finally:
        r.close()


@pytest.mark.gl
def test_backends_agree_on_a_smooth_dent(small, gl_backend):
    """Both backends shade a smooth dent alike from the same lights: correlation of the shading
    change > 0.98 and mean abs difference < 3 DN where it shows (at 960x720 we measured 0.997 and
    1.5 DN; the fast phong model has no shadows and Phong rather than GGX highlights, which make
    the rest). vitac's fast backend shades from the R1.5 table, so the phong model is selected."""
    small = replace(small, shading={"model": "phong"})
    d = sphere_dent(small, 3.0, 0.5, smooth_px=8.0 * SMALL_W / 960)
    out = {}
    for b in ("fast", gl_backend):
        r = Renderer(small, b)
        try:
            out[b] = r.render_float(d) - r.background_float()
        finally:
            r.close()
    a, b = out["fast"], out[gl_backend]
    m = np.abs(a).sum(axis=-1) > 1.0
    assert m.sum() > 1000
    corr = np.corrcoef(a[m].ravel(), b[m].ravel())[0, 1]
    assert corr > 0.98
    assert np.abs(a - b)[m].mean() < 3.0
    # outside the imprint both are exactly the background
    far = np.zeros(small.shape, bool)
    far[:20] = True
    assert np.abs(b[far]).max() < 0.5


@pytest.mark.gl
def test_pyrender_casts_shadows_behind_a_steep_bump(small, gl_backend):
    """A 0.8 mm block lit by the profile's first LED alone: behind it, away from the LED, both
    backends darken that LED's colour (pyrender by its shadow map at the light's elevation, the
    fast backend by the calibrated table's soft shadow for that LED); in front of it, as far on
    the LED's side, pyrender changes nothing and the fast backend far less. Directions and lengths
    come from the profile and its table."""
    from gelsim.optics.lut import load_table, table_path

    one = dataclasses.replace(small, lights=(small.lights[0],))
    light = one.lights[0]
    ch = int(np.argmax(light.color_rgb))
    tab = load_table(table_path(one))
    k = int(np.argmin(np.abs((tab["shadow_dirs_deg"] - light.azimuth_deg + 180.0) % 360.0 - 180.0)))
    assert abs((tab["shadow_dirs_deg"][k] - light.azimuth_deg + 180.0) % 360.0 - 180.0) < 1.0
    h, w = one.shape
    mm = one.image.mm_per_px
    half = 25                                                        # block half-width, px
    d = np.zeros(one.shape, np.float32)
    d[h // 2 - half:h // 2 + half, w // 2 - half:w // 2 + half] = 0.8  # raised towards the camera
    d = cv2.GaussianBlur(d, (0, 0), 1.0)
    # shadow lengths: 0.8 mm over each backend's grazing slope; sample a third of the shorter one behind
    tan_e = min(math.tan(math.radians(light.elevation_deg)), float(tab["shadow_tan"][k]))
    dist = half + 0.33 * 0.8 / tan_e / mm
    a = math.radians(light.azimuth_deg)                              # the light comes from this side
    u = np.array([math.cos(a), math.sin(a)])
    behind = (np.array([w // 2, h // 2]) - dist * u).round().astype(int)
    front = (np.array([w // 2, h // 2]) + dist * u).round().astype(int)
    assert 5 <= behind.min() and behind[0] < w - 5 and behind[1] < h - 5

    def patch(img, xy):
        return img[xy[1] - 3:xy[1] + 4, xy[0] - 3:xy[0] + 4, ch].mean()

    # the fast shadow's depth at full occlusion: the table's colour for this LED, saturated at 0.8 mm
    fast_full = float(tab["shadow_rgb"][k, ch]) * 0.8 / (0.8 + float(tab["shadow_sat_mm"]))
    assert fast_full < -5.0
    for b in ("fast", gl_backend):
        r = Renderer(one, b)
        try:
            diff = r.render_float(d) - r.background_float()
        finally:
            r.close()
        if b == gl_backend:
            assert abs(patch(diff, front)) < 2.0 and patch(diff, behind) < -20.0
        else:
            # the table shades with all the R1.5's LEDs: the others' shadows tint the front a little
            assert patch(diff, behind) < patch(diff, front) + 0.5 * fast_full


def test_supersampling_agrees_with_plain_rendering(small):
    d = sphere_dent(small, 3.0, 0.5, smooth_px=2.0)
    corners, _ = marker_grid(small)
    a = Renderer(small).render_float(d, corners)
    b = Renderer(small, supersample=2).render_float(d, corners)
    assert np.abs(a - b).mean() < 1.0
    assert np.abs(a - b).max() < 40.0


# ---------------------------------------------------------------- markers

def test_markers_have_profile_size_and_pitch(vitac):
    p = replace(vitac, camera={"blur_sigma_px": 0.0})
    r = Renderer(p)
    corners, centres = marker_grid(p, offset_px=(0.37, 0.61))
    img = r.render(None, corners, noise=False).astype(np.float64)
    bg = r.background_float()
    coverage = ((bg - img) / (bg * p.markers.darkness)).mean(axis=-1)
    n, labels, stats, cents = cv2.connectedComponentsWithStats((coverage > 0.5).astype(np.uint8))
    assert n - 1 == len(centres)
    mm = p.image.mm_per_px
    size_px, pitch_px = p.markers.size_mm / mm, p.markers.pitch_mm / mm
    sides, got = [], []
    for i in range(1, n):
        x, y, bw, bh, _ = stats[i]
        patch = coverage[y - 2:y + bh + 2, x - 2:x + bw + 2].clip(0, 1)
        sides.append(math.sqrt(patch.sum()))
        yy, xx = np.mgrid[y - 2:y + bh + 2, x - 2:x + bw + 2]
        got.append(((patch * xx).sum() / patch.sum(), (patch * yy).sum() / patch.sum()))
    assert np.median(sides) == pytest.approx(size_px, rel=0.02)
    # coverage-weighted centroids measured from the image sit on the drawn centres (sub-pixel)
    got = np.array(got)
    dist = np.linalg.norm(got[:, None] - centres[None], axis=-1)
    assert dist.min(axis=1).max() < 0.1
    nn = np.sort(np.linalg.norm(got[:, None] - got[None], axis=-1), axis=1)[:, 1]
    assert np.median(nn) == pytest.approx(pitch_px, rel=0.005)


def test_markers_follow_subpixel_motion(small):
    """Shifting markers by a third of a pixel moves the image's dark centroid by a third of a pixel."""
    r = Renderer(small)
    c0, _ = marker_grid(small)
    bg = r.background_float()
    xs = []
    for dx in (0.0, 1.0 / 3.0):
        img = r.render_float(None, c0 + np.array([dx, 0.0], np.float32))
        dark = (bg - img).mean(axis=-1)
        cols = np.arange(small.shape[1])
        xs.append((dark.sum(axis=0) * cols).sum() / dark.sum())
    assert xs[1] - xs[0] == pytest.approx(1.0 / 3.0, abs=0.03)


def test_markers_accept_object_with_corners(small):
    corners, _ = marker_grid(small)

    class M:
        corners_px = corners
    r = Renderer(small)
    np.testing.assert_array_equal(r.render(None, M(), noise=False), r.render(None, corners, noise=False))
    assert not np.array_equal(r.render(None, corners, noise=False), r.background())
    off = replace(small, markers={"enabled": False})
    ro = Renderer(off)
    np.testing.assert_array_equal(ro.render(None, corners, noise=False), ro.background())


# ---------------------------------------------------------------- range, bad input

@pytest.mark.parametrize("setting", ["bright", "dark"])
def test_no_wraparound_or_nan_at_extremes(vitac, setting):
    # specular and shininess belong to the phong model (the calibrated table has no highlight); the
    # LEDs at full intensity, so that the extremes do not depend on the calibrated intensities
    vitac = replace(vitac, shading={"model": "phong"})
    vitac = dataclasses.replace(vitac, lights=tuple(dataclasses.replace(lt, intensity=1.0) for lt in vitac.lights))
    if setting == "bright":
        p = replace(vitac, shading={"gain_dn": 1000.0, "specular": 10.0, "shininess": 2.0},
                    background={"rgb_dn": (250.0, 250.0, 250.0), "led_tint_dn": 255.0},
                    noise={"read_sigma_dn": 50.0, "shot_gain": 5.0})
    else:
        p = replace(vitac, shading={"gain_dn": 1000.0}, background={"rgb_dn": (1.0, 1.0, 1.0)},
                    markers={"darkness": 1.0}, noise={"read_sigma_dn": 50.0, "shot_gain": 5.0})
    d = sphere_dent(p, 2.0, 1.0) * 5.0        # deep and steep
    corners, _ = marker_grid(p)
    r = Renderer(p)
    f = r.render_float(d, corners)
    assert np.isfinite(f).all()
    assert f.max() > 300 or f.min() < -50     # the settings really leave 0-255
    img = r.render(d, corners, noise=False)
    np.testing.assert_array_equal(img, np.clip(np.rint(f), 0, 255).astype(np.uint8))
    noisy = r.render(d, corners, seed=1).astype(int)
    # far beyond the range, noise of sigma <= 80 DN cannot bring a pixel back: a wrap-around would
    assert (f > 700).any() or (f < -400).any()
    assert np.all(noisy[f > 700] == 255) and np.all(noisy[f < -400] == 0)


def test_bad_input_raises(small):
    with pytest.raises(GelsimError, match="backend"):
        Renderer(small, "raytracer")
    with pytest.raises(GelsimError, match="supersample"):
        Renderer(small, supersample=0)
    r = Renderer(small)
    with pytest.raises(GelsimError, match="shape"):
        r.render(np.zeros((10, 10), np.float32))
    d = sphere_dent(small)
    d[5, 5] = np.nan
    with pytest.raises(GelsimError, match="NaN"):
        r.render(d)
    with pytest.raises(GelsimError, match="negative"):
        r.render(-sphere_dent(small))
    with pytest.raises(GelsimError, match="corners"):
        r.render(None, np.zeros((3, 5, 2), np.float32))
    # tiny negatives from float error are clipped, not refused
    assert check_depth(np.full(small.shape, -1e-6, np.float32), small.shape).min() == 0.0


def test_convenience_render_and_backends(small):
    d = sphere_dent(small)
    img = render(d, None, small, seed=2)
    assert img.dtype == np.uint8 and img.shape == (*small.shape, 3)
    np.testing.assert_array_equal(img, Renderer(small, seed=2).render(d, seed=2))
    assert available_backends()[0] == "fast"


def test_background_image_replaces_parametric_field(tmp_path, small):
    """A profile's background PNG (path relative to the profile file) becomes the flat gel."""
    h, w = small.shape
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(60, 200, (h // 2, w // 2, 3)).astype(np.uint8), (0, 0), 3)
    cv2.imwrite(str(tmp_path / "flat.png"), img[..., ::-1])         # stored as RGB -> BGR on disk
    p = dataclasses.replace(replace(small, background={"image": "flat.png"}, camera={"vignetting": 0.0,
                                                                                      "blur_sigma_px": 0.0}),
                            source=str(tmp_path / "sensor.toml"))
    bg = Renderer(p).background()
    want = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(bg, want)
    missing = dataclasses.replace(p, background=dataclasses.replace(p.background, image="nope.png"))
    with pytest.raises(GelsimError, match="nope.png"):
        Renderer(missing)
# ---------------------------------------------------------------- optimised LUT path vs a plain reference

def _reference_lut_frame(renderer, depth):
    """The calibrated shading computed the straightforward way, in float64: Sobel slopes, the unit
    normal, a bilinear lookup of the 9-channel table with the exact per-pixel [1, xn, yn] weights,
    the camera blur; shadows on their grid (f x f blocks, ShadowSpec.grid_factor) by a brute-force max
    over every step s = 1, 2, ... along each LED's direction (bilinear samples, 0 outside), o / (o + sat), a
    Gaussian penumbra (camera blur folded in), mixed to colour and interpolated back bilinearly. No tiles, bands,
    window doubling or fixed-point maps. Returns float32 (H, W, 3) DN without markers."""
    from scipy import ndimage

    from gelsim.optics.field import pixel_grid_mm
    from gelsim.optics.ops.filters import gaussian_blur

    prof, sh = renderer.profile, renderer.shader
    h, w = prof.shape
    mm = prof.image.mm_per_px
    d = depth.astype(np.float64)
    gx = cv2.Sobel(d, cv2.CV_64F, 1, 0, ksize=3, scale=1 / (8 * mm), borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(d, cv2.CV_64F, 0, 1, ksize=3, scale=1 / (8 * mm), borderType=cv2.BORDER_REPLICATE)
    norm = np.sqrt(1 + gx * gx + gy * gy)
    nb = sh.nb
    u, v = (-gx / norm + 1) * (nb - 1) / 2, (-gy / norm + 1) * (nb - 1) / 2     # column (nx), row (ny) bins
    i0, j0 = np.clip(np.floor(v).astype(int), 0, nb - 2), np.clip(np.floor(u).astype(int), 0, nb - 2)
    fv, fu = (v - i0)[..., None], (u - j0)[..., None]
    t = sh.table.astype(np.float64)
    val = ((1 - fv) * (1 - fu) * t[i0, j0] + (1 - fv) * fu * t[i0, j0 + 1]
           + fv * (1 - fu) * t[i0 + 1, j0] + fv * fu * t[i0 + 1, j0 + 1])           # (H, W, 9)
    x, y = pixel_grid_mm(prof)
    fw, fh = prof.field_mm
    xn = np.broadcast_to(x / (fw / 2), (h, w))[..., None]
    yn = np.broadcast_to(y / (fh / 2), (h, w))[..., None]
    table = val[..., 0:3] + xn * val[..., 3:6] + yn * val[..., 6:9]
    table[depth.max() == 0] = 0.0
    frame = renderer.background_float().astype(np.float64) + gaussian_blur(table.astype(np.float32),
                                                                            prof.camera.blur_sigma_px)
    s = sh.shadow
    # f x f block means (zero-padded), grid pixel x' centred on full-resolution f x' + (f - 1) / 2
    g = s.grid_factor(mm)
    hp = np.zeros((g * -(-h // g), g * -(-w // g)))
    hp[:h, :w] = d
    hg = hp.reshape(hp.shape[0] // g, g, hp.shape[1] // g, g).mean(axis=(1, 3))
    yy, xx = np.mgrid[0:hg.shape[0], 0:hg.shape[1]].astype(np.float64)
    cols = []
    for phi, tan_e in zip(s.dirs_deg, s.tan):
        rise = float(tan_e) * mm * g
        best = np.full(hg.shape, -np.inf)
        for step in range(1, int(np.ceil(hg.max() / rise)) + 2):
            sx = xx + step * math.cos(math.radians(float(phi)))
            sy = yy + step * math.sin(math.radians(float(phi)))
            samp = ndimage.map_coordinates(hg, [sy, sx], order=1, mode="constant", cval=0.0)
            best = np.maximum(best, samp - step * rise)
        o = np.maximum(best - hg, 0.0)
        cols.append(o / (o + s.sat_mm))
    f = np.stack(cols, axis=-1) @ s.mix.T.astype(np.float64)
    sigma = math.hypot(s.soft_mm / mm, prof.camera.blur_sigma_px) / g
    f = np.stack([ndimage.gaussian_filter(f[..., c], sigma, mode="constant", truncate=4.0) for c in range(3)], -1)
    up = cv2.resize(f.astype(np.float32), (hg.shape[1] * g, hg.shape[0] * g), interpolation=cv2.INTER_LINEAR)
    return (frame + up[:h, :w] + _reference_coarse_terms(renderer, depth)).astype(np.float32)


def _reference_coarse_terms(renderer, depth):
    """The table's depth and halo terms, computed plainly: block means on the coarse grid (zero-padded),
    scipy's Gaussian filters and Sobel (replicated borders), the spill and its gate, the features'
    colours, bilinear back to full resolution, nothing where no pixel changes by COARSE_SKIP_DN."""
    from scipy import ndimage

    from gelsim.optics.lut import load_table, table_path
    from gelsim.optics.ops.coarse import COARSE_SKIP_DN, coarse_factor

    prof = renderer.profile
    t = load_table(table_path(prof))
    h, w = prof.shape
    mm = prof.image.mm_per_px
    f = coarse_factor(mm)
    hs, ws = -(-h // f), -(-w // f)
    hp = np.zeros((hs * f, ws * f))
    hp[:h, :w] = depth
    hg = hp.reshape(hs, f, ws, f).mean(axis=(1, 3))
    gmm = mm * f
    fw, fh = prof.field_mm
    xn = (f * (np.arange(ws) + 0.5) - 0.5 - (w - 1) / 2) * mm / (fw / 2)
    yn = (f * (np.arange(hs) + 0.5) - 0.5 - (h - 1) / 2) * mm / (fh / 2)
    gain = prof.shading.gain_dn / t["gain_dn"]
    change = np.zeros((hs, ws, 3))
    if "depth_rgb" in t:
        d = t["depth_rgb"].astype(np.float64) * gain
        change += hg[..., None] * (d[0] + xn[None, :, None] * d[1] + yn[:, None, None] * d[2])
    if "halo_rgb" in t:
        b = ndimage.gaussian_filter(hg, t["halo_sigma_mm"] / gmm, mode="nearest", truncate=4.0)
        b0 = ndimage.gaussian_filter(hg, t["halo_base_mm"] / gmm, mode="nearest", truncate=4.0)
        spill = np.maximum(b - b0, 0.0)
        gate = np.minimum(spill / t["halo_gate_mm"], 1.0)
        gx = ndimage.sobel(b, axis=1, mode="nearest") / (8 * gmm)
        gy = ndimage.sobel(b, axis=0, mode="nearest") / (8 * gmm)
        hr = t["halo_rgb"].astype(np.float64) * gain
        change += (gate * gx)[..., None] * hr[0] + (gate * gy)[..., None] * hr[1] + spill[..., None] * hr[2]
    if np.abs(change).max() < COARSE_SKIP_DN:
        return np.zeros((h, w, 3), np.float32)
    up = cv2.resize(change.astype(np.float32), (ws * f, hs * f), interpolation=cv2.INTER_LINEAR)
    return up[:h, :w]


def _weave(profile, base_mm, amp_mm):
    """A woven-like relief over the whole frame (every pixel touched): float32 (H, W) mm."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    yy, xx = np.mgrid[0:h, 0:w] * mm
    return (base_mm + amp_mm * np.sin(2 * np.pi * xx / 0.6) * np.cos(2 * np.pi * yy / 0.9)).astype(np.float32)


# Stated tolerance of the optimised LUT path against the plain float64 computation, in DN of the
# noiseless frame: measured mean 0.002-0.09 and max 0.36-0.55 at 320x240 and 960x720 (tile
# centres for the spatial terms, 1/32-bin fixed-point remap coordinates, bilinear window doubling
# for the shadows). Against the previous renderer (9-channel remap, rotated shadows) the frames
# differ by a mean of 0.003-0.11 DN and at most 0.70 DN, 1 DN after quantisation.
# With 30 x 24 tiles (lut.MOSAIC_TILES) the steepest scene, a weave with shadows, differs by a
# mean of 0.17 DN and at most 0.91 DN: below one 8-bit step and the camera's 0.92 DN read noise.
LUT_MEAN_TOL_DN, LUT_MAX_TOL_DN = 0.25, 1.0


@pytest.mark.parametrize("scene", ["sphere", "steep sphere", "weave with shadows", "gentle weave"])
def test_lut_path_matches_plain_reference(small, scene):
    from gelsim.optics.ops.shadows import shadow_grid

    r = Renderer(small, seed=2)
    depth = {"sphere": lambda: sphere_dent(small, 2.0, 0.5, smooth_px=1.0),
             "steep sphere": lambda: sphere_dent(small, 1.0, 0.6, center_mm=(1.3, -0.7)),
             "weave with shadows": lambda: _weave(small, 0.12, 0.1),
             "gentle weave": lambda: _weave(small, 0.03, 0.02)}[scene]()
    ref = _reference_lut_frame(r, depth)
    out = r.render_float(depth)
    change = np.abs(ref - r.background_float())
    assert change.max() > 10.0                      # the scene is seen
    err = np.abs(out - ref)
    assert err.mean() < LUT_MEAN_TOL_DN and err.max() < LUT_MAX_TOL_DN, (err.mean(), err.max())
    if scene != "sphere":
        # the steep scenes cast shadows (so the shadow path is compared too); the gentle weave casts none
        grid = shadow_grid(depth, r.shader.shadow, small.image.mm_per_px, small.camera.blur_sigma_px)
        assert (grid is not None) == (scene != "gentle weave")


@pytest.mark.parametrize("width", [320, 640, 960])
def test_shadow_grid_is_as_coarse_as_the_penumbra_allows(width, monkeypatch):
    """The shadows' grid (ShadowSpec.grid_factor) on the steepest shadows, a 1 mm ball 0.6 mm deep and a
    steep weave: on the chosen grid they are within SHADOW_GRID_TOL_DN of the full-resolution ones, on the
    next coarser grid they are not (the rule is about as coarse as the tolerance allows, and no coarser)."""
    from gelsim.optics.lut import table_model
    from gelsim.optics.ops import shadows
    from gelsim.optics.ops.resample import upsample
    from gelsim.sensor import load_profile

    prof = load_profile("vitac").with_resolution(width)
    spec, mm = table_model(prof).shadows, prof.image.mm_per_px
    f = spec.grid_factor(mm)
    assert spec.soft_mm / mm / f >= shadows.SHADOW_GRID_MIN_SIGMA
    assert (f == 1) == (width == 320) and (f >= 4) == (width == 960)   # finer frames, finer grids

    def term(d, factor):
        monkeypatch.setattr(shadows.ShadowSpec, "grid_factor", lambda self, mm_per_px: factor)
        g = shadows.shadow_grid(d, spec, mm, prof.camera.blur_sigma_px)
        return np.zeros(d.shape + (3,), np.float32) if g is None else upsample(g[0], g[1], d.shape)

    chosen_err, coarser_err = 0.0, 0.0
    for d in (sphere_dent(prof, 1.0, 0.6, center_mm=(1.3, -0.7)), _weave(prof, 0.12, 0.1)):
        exact = term(d, 1)
        assert np.abs(exact).max() > 1.5                                # both cast shadows
        chosen_err = max(chosen_err, float(np.abs(term(d, f) - exact).max()))
        coarser_err = max(coarser_err, float(np.abs(term(d, 2 * f) - exact).max()))
    assert chosen_err <= shadows.SHADOW_GRID_TOL_DN < coarser_err, (chosen_err, coarser_err)


def test_banded_pass_equals_one_pass_over_the_box(small, monkeypatch):
    """Row bands with the blur's and the gradient's extra rows reproduce one pass over the box."""
    from gelsim.optics.lut import LutShader
    from gelsim.optics.ops.filters import gaussian_blur

    r = Renderer(small, seed=0)
    d = sphere_dent(small, 2.5, 0.4, center_mm=(0.5, 0.3))
    whole = r.render_float(d)
    monkeypatch.setattr(LutShader, "BAND_ROWS", 7)
    banded = r.render_float(d)
    np.testing.assert_allclose(banded, whole, atol=2e-4)
    # and the one pass is background + blurred table + shadows + depth and halo terms, in that order
    (roi, table, blurred), *terms = r.shader.parts(d, 2, small.camera.blur_sigma_px)
    assert not blurred and len(terms) == 2 and all(t[2] for t in terms)     # both terms are part of this press
    ref = r.background_float()
    ref[roi] += gaussian_blur(table.copy(), small.camera.blur_sigma_px)
    for box, change, _ in terms:
        ref[box] += change
    np.testing.assert_allclose(whole, ref, atol=2e-4)


def test_no_shadow_shortcut_is_exact():
    """The slope bound that skips a direction gives what the full window-doubling max gives."""
    from gelsim.optics.ops.shadows import grid_slopes, occlusion_grid

    rng = np.random.default_rng(4)
    for amp in (0.01, 0.05, 0.3):
        hg = cv2.GaussianBlur(rng.random((60, 80)).astype(np.float32), (0, 0), 2.0) * amp * 10
        slopes = grid_slopes(hg)
        for phi in (0.0, 37.0, -117.2, 127.8, 200.0):
            a = occlusion_grid(hg, phi, 0.02, slopes)
            b = occlusion_grid(hg, phi, 0.02, None)
            np.testing.assert_array_equal(a, b)
    assert occlusion_grid(hg, 0.0, 0.02).max() > 0.01          # the steepest case does cast shadows


def test_constant_sigma_noise_pass_matches_general_formula(small):
    """With no shot noise the one-pass noise equals frame + read_sigma * z, rounded and saturated."""
    r = Renderer(small, seed=1)
    h, w = small.shape
    ramp = np.linspace(-20.0, 280.0, w, dtype=np.float32)          # reaches both ends of uint8
    frame = np.ascontiguousarray(np.broadcast_to(ramp[None, :, None], (h, w, 3)))
    z = r.optics.noise.pick(9)
    expect = np.clip(np.rint(frame.astype(np.float64) + small.noise.read_sigma_dn * z), 0, 255)
    got = r.optics.noise.apply(frame, 9).astype(np.float64)
    assert (got == 0).any() and (got == 255).any()
    assert np.abs(got - expect).max() <= 1.0 and (got != expect).mean() < 1e-3


@pytest.mark.parametrize("factor", [1, 2, 5, 6])
def test_upsampled_rows_equal_those_of_the_whole_upsampling(factor):
    """A band's rows of a grid's bilinear upsampling, computed from the grid rows they read only, are
    bit for bit those of the whole grid's (the renderer adds the shadows and the depth and halo terms
    band by band this way)."""
    from gelsim.optics.ops.resample import upsample_rows

    rng = np.random.default_rng(factor)
    for hs, ws in ((23, 31), (120, 160)):
        grid = (rng.standard_normal((hs, ws, 3)) * 20).astype(np.float32)
        whole = cv2.resize(grid, (ws * factor, hs * factor), interpolation=cv2.INTER_LINEAR) if factor > 1 else grid
        width = ws * factor - factor // 2                          # a box cut short of the last grid column
        for a in sorted({0, 1, factor, 7, hs * factor // 2, hs * factor - 3}):
            for b in {a + 1, a + 7, a + 96, hs * factor}:
                b = min(b, hs * factor)
                if b > a:
                    np.testing.assert_array_equal(upsample_rows(grid, factor, a, b, width), whole[a:b, :width])


def test_a_renderer_reused_over_a_sequence_draws_what_fresh_ones_draw(small):
    """The markers' factors and the flat gel under markers at rest are reused between frames; a sequence
    rendered with one Renderer equals each frame rendered by a fresh one, bit for bit."""
    corners, _ = marker_grid(small)
    moved = corners + np.float32(0.4)
    d = sphere_dent(small, 2.5, 0.3)
    frames = [(None, corners), (None, corners), (d, corners), (None, corners), (None, moved), (None, moved),
              (d, None), (None, corners), (np.zeros_like(d), corners), (None, corners)]
    r = Renderer(small, seed=3)
    for i, (depth, mk) in enumerate(frames):
        fresh = Renderer(small, seed=3)
        np.testing.assert_array_equal(r.render_float(depth, mk), fresh.render_float(depth, mk))
        np.testing.assert_array_equal(r.render(depth, mk, seed=i), fresh.render(depth, mk, seed=i))


@pytest.mark.parametrize("shot_gain", [0.0, 0.03])
@pytest.mark.parametrize("band_rows", [7, 96])
def test_frames_finished_band_by_band_equal_the_whole_frame_passes(small, monkeypatch, shot_gain, band_rows):
    """render() darkens the markers, adds the noise and quantises each band of a pressed frame as it is
    composed (in a band-sized buffer): bit for bit the whole-frame passes over render_float's frame,
    for presses at the frame's edges and in its middle (rows above and below the shaded box), markers
    at rest and moved, with and without noise."""
    from gelsim.optics.lut import LutShader
    from gelsim.optics.ops.readout import to_uint8

    monkeypatch.setattr(LutShader, "BAND_ROWS", band_rows)
    prof = replace(small, noise={"shot_gain": shot_gain})
    r = Renderer(prof, seed=2)
    banded = []                                       # whether each compose wrote bands only (no frame)
    compose = r.shader.compose
    monkeypatch.setattr(r.shader, "compose", lambda frame, *a: banded.append(frame is None) or compose(frame, *a))
    corners, _ = marker_grid(prof)
    rng = np.random.default_rng(band_rows)
    fw, fh = prof.field_mm
    n_banded = 0
    for i, centre in enumerate([(0.0, 0.0), (0.3 * fw, -0.45 * fh), (-0.4 * fw, 0.5 * fh), (0.1, 0.2)]):
        d = sphere_dent(prof, 1.5 + i, 0.2 + 0.1 * i, center_mm=centre)
        mk = corners if i % 2 == 0 else corners + rng.normal(0, 1.5, corners.shape).astype(np.float32)
        want = r.render_float(d, mk)
        np.testing.assert_array_equal(r.render(d, mk, seed=i), r.optics.noise.apply(want, i))
        n_banded += banded[-1]
        np.testing.assert_array_equal(r.render(d, mk, noise=False), to_uint8(want))
        n_banded += banded[-1]
    assert n_banded == 8 and banded.count(False) == 4             # every render took the banded path


def test_lut_compose_hands_every_row_to_finish_once_in_order(small, monkeypatch):
    """LutShader.compose's finish sees each frame row once, in order, with the values that the frame
    gets without finish, whether the bands are the frame's own rows or a band buffer (frame None)."""
    from gelsim.optics.lut import LutShader
    from gelsim.optics.ops.filters import blur_radius_px, gaussian_blur

    monkeypatch.setattr(LutShader, "BAND_ROWS", 11)
    r = Renderer(small, seed=0)
    sh, bg = r.shader, r.background_float()
    sigma = small.camera.blur_sigma_px
    d = sphere_dent(small, 2.0, 0.4, center_mm=(1.0, -0.5))
    whole = np.zeros_like(bg)
    assert sh.compose(whole, bg, d, blur_radius_px(sigma), sigma, gaussian_blur)
    for frame in (np.zeros_like(bg), None):
        seen, got = [], np.full_like(bg, np.nan)

        def finish(rows, y0, y1):
            assert rows.shape == (y1 - y0,) + bg.shape[1:]
            seen.append((y0, y1))
            got[y0:y1] = rows

        assert sh.compose(frame, bg, d, blur_radius_px(sigma), sigma, gaussian_blur, finish)
        assert [a for a, _ in seen] == [0] + [b for _, b in seen[:-1]] and seen[-1][1] == bg.shape[0]
        assert len(seen) > bg.shape[0] // 11                      # rows above, in and below the box
        np.testing.assert_array_equal(got, whole)


@pytest.mark.parametrize("f", [2, 3, 6])
def test_area_mean_over_the_imprint_box_equals_the_whole_frame(f):
    """resample.area_mean_box averages only the blocks that meet the box outside which the frame is 0: the
    same float32 values as area_mean of the whole frame, blocks cut by the bottom and right edges included."""
    from gelsim.optics.ops.resample import area_mean, area_mean_box

    rng = np.random.default_rng(f)
    h, w = 6 * f + 1, 9 * f + f - 1                              # not whole blocks
    for extent in ((f + 1, 3 * f + 2, 2, 5 * f), (2, h, 3 * f - 1, w), (0, 1, 0, 1)):
        x = np.zeros((h, w), np.float32)
        r0, r1, c0, c1 = extent
        x[r0:r1, c0:c1] = rng.uniform(0.0, 0.3, (r1 - r0, c1 - c0)).astype(np.float32)
        ref = area_mean(x, f)
        assert ref.any() and area_mean_box(x, f, extent).tobytes() == ref.tobytes()
    assert area_mean_box(x, f, None).tobytes() == ref.tobytes()
