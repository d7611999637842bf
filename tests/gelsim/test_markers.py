"""Markers: grid geometry, dilation, shear, twist, determinism, dtypes."""
import dataclasses

import numpy as np
import pytest

from gelsim import indenters
from gelsim.errors import GelsimError
from gelsim.fidelity import get_fidelity
from gelsim.gel import press
from gelsim.markers import Markers, displace, marker_grid, rest_markers
from gelsim.sensor import load_profile

BASE = get_fidelity("balanced")
FIDS = [dataclasses.replace(BASE, marker_model="gaussian"), dataclasses.replace(BASE, marker_model="elastic")]
ids = lambda f: f.marker_model  # noqa: E731


def no_jitter(profile, **kw):
    return dataclasses.replace(profile, markers=dataclasses.replace(profile.markers, jitter_mm=0.0, **kw))


@pytest.fixture(scope="module")
def imprint(vitac):
    return press(indenters.sphere(6.0, vitac, center_mm=(0.8, -0.4)), vitac, BASE, force_n=0.2)


def test_square_grid_size_and_pitch_in_pixels(vitac):
    p = no_jitter(vitac)
    grid = marker_grid(p)
    pitch_px = p.markers.pitch_mm / p.image.mm_per_px
    d = np.diff(np.unique(np.round(grid[:, 0], 3)))
    assert np.allclose(d, pitch_px, atol=1e-3)
    m = rest_markers(p)
    side = np.linalg.norm(m.corners_px[:, 1] - m.corners_px[:, 0], axis=1)
    assert np.allclose(side, p.markers.size_mm / p.image.mm_per_px, atol=1e-3)
    h, w = p.shape
    assert grid[:, 0].min() >= 0 and grid[:, 0].max() <= w - 1 and grid[:, 1].max() <= h - 1
    assert len(grid) == 11 * 9  # the 11x9 grid of 1.6 mm over 18.9 x 14.2 mm


def test_hex_layout(vitac):
    p = no_jitter(vitac, layout="hex")
    grid = marker_grid(p)
    rows = np.unique(np.round(grid[:, 1], 3))
    pitch_px = p.markers.pitch_mm / p.image.mm_per_px
    assert np.allclose(np.diff(rows), pitch_px * np.sqrt(3) / 2, atol=1e-3)
    # Nearest neighbours are one pitch apart in every direction.
    d = np.linalg.norm(grid[:, None] - grid[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert np.allclose(d.min(axis=1), pitch_px, atol=1e-3)


def test_jitter_is_seeded(vitac):
    a, b, c = marker_grid(vitac, seed=1), marker_grid(vitac, seed=1), marker_grid(vitac, seed=2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    sigma = vitac.markers.jitter_mm / vitac.image.mm_per_px
    assert 0 < np.abs(a - marker_grid(no_jitter(vitac))).max() < 6 * sigma


def test_disabled_markers_are_empty():
    p = load_profile("gelsight-r15")
    assert marker_grid(p).shape == (0, 2)
    assert len(rest_markers(p)) == 0


@pytest.mark.parametrize("fid", FIDS, ids=ids)
def test_rest_equals_displace_without_imprint(vitac, fid):
    r = rest_markers(vitac, seed=3)
    d = displace(vitac, fid, None, shear_mm=(0.3, 0.1), twist_deg=4.0, seed=3)
    for x, y in ((r.rest_px, d.rest_px), (r.xy_px, d.xy_px), (r.corners_px, d.corners_px)):
        assert np.array_equal(x, y)
    assert r.xy_px.dtype == r.corners_px.dtype == np.float32


def radial(m, centre):
    v = m.rest_px - centre
    u = m.xy_px - m.rest_px
    return (u * v).sum(1) / np.linalg.norm(v, axis=1)


def centre_px(vitac, cmm):
    h, w = vitac.shape
    return np.array([(w - 1) / 2 + cmm[0] / vitac.image.mm_per_px, (h - 1) / 2 + cmm[1] / vitac.image.mm_per_px])


@pytest.mark.parametrize("fid", FIDS, ids=ids)
def test_press_dilates_outward(vitac, imprint, fid):
    m = displace(vitac, fid, imprint)
    c = centre_px(vitac, (0.8, -0.4))
    rad = radial(m, c)
    near = np.linalg.norm(m.rest_px - c, axis=1) < 3 * vitac.gel.thickness_mm / vitac.image.mm_per_px
    assert rad[near].mean() > 0.2  # px, outward
    assert rad.mean() > 0
    # A harder press moves them further.
    deeper = press(indenters.sphere(6.0, vitac, center_mm=(0.8, -0.4)), vitac, BASE, force_n=0.6)
    assert radial(displace(vitac, fid, deeper), c)[near].mean() > rad[near].mean()


@pytest.mark.parametrize("fid", FIDS, ids=ids)
def test_shear_follows_direction_and_decays(vitac, imprint, fid):
    s = np.array([0.15, -0.1])
    base = displace(vitac, fid, imprint)
    m = displace(vitac, fid, imprint, shear_mm=tuple(s))
    u = (m.xy_px - base.xy_px).astype(np.float64)
    mean = u.mean(0)
    assert np.dot(mean, s) > 0.9 * np.linalg.norm(mean) * np.linalg.norm(s)  # same direction
    mag = np.linalg.norm(u, axis=1)
    dist = np.linalg.norm(m.rest_px - centre_px(vitac, (0.8, -0.4)), axis=1)
    s_px = np.linalg.norm(s) / vitac.image.mm_per_px
    assert mag[np.argmin(dist)] > 0.5 * s_px  # the marker nearest the contact moves most of it
    assert mag[dist > dist.max() * 0.8].max() < 0.1 * s_px  # and far ones barely


def curl(m):
    """Mean of (r x u) over |r|^2 about the markers' mean: > 0 for +x -> +y rotation."""
    c = m.rest_px.mean(0)
    r = (m.rest_px - c).astype(np.float64)
    u = (m.xy_px - m.rest_px).astype(np.float64)
    return float(((r[:, 0] * u[:, 1] - r[:, 1] * u[:, 0]) / (np.linalg.norm(r, axis=1) ** 2 + 1.0)).sum())


@pytest.mark.parametrize("fid", FIDS, ids=ids)
@pytest.mark.parametrize("twist", [6.0, -6.0])
def test_twist_curl_has_the_twist_sign(vitac, fid, twist):
    imp = press(indenters.sphere(10.0, vitac), vitac, BASE, force_n=0.5)
    base = displace(vitac, fid, imp)
    m = displace(vitac, fid, imp, twist_deg=twist)
    rot = Markers(base.xy_px, m.xy_px, m.corners_px)
    assert np.sign(curl(rot)) == np.sign(twist)
    # Corners turn with the squares: the top edge tilts by the twist near the centre.
    i = int(np.argmin(np.linalg.norm(m.rest_px - centre_px(vitac, (0, 0)), axis=1)))
    e = m.corners_px[i, 1] - m.corners_px[i, 0]
    assert np.sign(np.degrees(np.arctan2(e[1], e[0]))) == np.sign(twist)


@pytest.mark.parametrize("fid", FIDS, ids=ids)
def test_deterministic_and_float32(vitac, imprint, fid):
    a = displace(vitac, fid, imprint, shear_mm=(0.1, 0.0), twist_deg=2.0, seed=5)
    b = displace(vitac, fid, imprint, shear_mm=(0.1, 0.0), twist_deg=2.0, seed=5)
    assert np.array_equal(a.xy_px, b.xy_px) and np.array_equal(a.corners_px, b.corners_px)
    assert a.xy_px.dtype == np.float32 and a.corners_px.shape == (len(a), 4, 2)
    assert np.isfinite(a.corners_px).all()


@pytest.mark.parametrize("fid", FIDS, ids=ids)
def test_float64_depth_bounded_difference(vitac, imprint, fid):
    d64 = dataclasses.replace(imprint, depth_mm=imprint.depth_mm.astype(np.float64))
    a = displace(vitac, fid, imprint)
    b = displace(vitac, fid, d64)
    assert np.abs(a.xy_px - b.xy_px).max() < 1e-3  # px


def test_custom_rest_and_bad_input(vitac, imprint):
    rest = np.array([[100.0, 100.0], [480.0, 360.0]], np.float32)
    m = displace(vitac, BASE, imprint, rest=rest)
    assert m.rest_px.shape == (2, 2) and np.array_equal(m.rest_px, rest)
    with pytest.raises(GelsimError):
        displace(vitac, BASE, imprint, rest=np.zeros((3, 3)))
    with pytest.raises(GelsimError):
        displace(vitac, BASE, imprint, shear_mm=(np.nan, 0.0))
    with pytest.raises(GelsimError):
        displace(vitac.with_resolution(480), BASE, imprint)


def test_cell_means_over_the_touched_box_equal_the_whole_window(vitac, imprint):
    """The block means are taken over the touched box's cells only: the same float32 values as OpenCV's
    INTER_AREA over the whole window (the mask's from block counts), the margin's cells 0."""
    import cv2

    from gelsim.markers import _cell_means, field_window

    depth, mask = imprint.depth_mm, imprint.contact_mask
    box = cv2.boundingRect(((depth > 0) | mask).view(np.uint8))
    f, r0, c0, hc, wc = field_window(vitac, box)
    win = (slice(r0, r0 + hc * f), slice(c0, c0 + wc * f))
    got = _cell_means(depth, mask, box, (f, r0, c0, hc, wc))
    for k, full in enumerate((depth[win].astype(np.float32), mask[win].astype(np.float32))):
        ref = cv2.resize(full, (wc, hc), interpolation=cv2.INTER_AREA)
        assert ref.any() and ref.tobytes() == got[k].tobytes()
    assert (got[:, 0] == 0).all() and (got[:, :, 0] == 0).all()   # the margin (a sphere well inside the image)
