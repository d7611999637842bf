"""gelsim.stats: the marker-field fit, the label-vs-image check, per-sequence statistics, the crop."""
from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from gelsim import indenters
from gelsim.errors import GelsimError
from gelsim.fidelity import get_fidelity
from gelsim.gel import press
from gelsim.markers import displace, marker_grid
from gelsim.sensor import load_profile
from gelsim.labels import contact_location
from gelsim.stats import (AGREEMENT_TOLERANCE, MIN_REGION_MARKERS, STAM_CPU_CROP, check_crop, contact_region,
                          crop_box_px, fit_marker_motion, key_frames, label_agreement, sequence_stats)

ROOT = Path(__file__).resolve().parents[2]
MMPP = 0.0591  # the cpu preset's scale, mm/px


def grid(n=9, pitch=27.0, origin=(40.0, 30.0)):
    j, i = np.meshgrid(np.arange(n), np.arange(n))
    return np.column_stack([origin[0] + j.ravel() * pitch, origin[1] + i.ravel() * pitch])


def similarity(pts, theta_deg, t_px, scale=1.0, about=None):
    """Rotate by theta (+x towards +y) and scale about ``about`` (default the centroid), then translate."""
    c = pts.mean(0) if about is None else np.asarray(about, float)
    th = math.radians(theta_deg)
    r = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    return c + scale * (pts - c) @ r.T + np.asarray(t_px, float)


@pytest.mark.parametrize("theta, t_px, scale", [(1.0, (0.0, 0.0), 1.0), (-2.5, (1.7, -0.4), 1.0),
                                                 (30.0, (-5.0, 3.0), 1.03), (0.0, (0.2, 0.1), 0.98)])
def test_fit_recovers_a_known_similarity(theta, t_px, scale):
    rest = grid()
    fit = fit_marker_motion(rest, similarity(rest, theta, t_px, scale), MMPP)
    assert fit.rotation_deg == pytest.approx(theta, abs=1e-9)
    np.testing.assert_allclose(fit.translation_mm, np.asarray(t_px) * MMPP, atol=1e-12)
    assert fit.dilation == pytest.approx(scale - 1.0, abs=1e-12)
    assert fit.rms_residual_mm < 1e-10
    assert fit.n_markers == len(rest)


def test_fit_is_exact_at_large_angles_where_the_small_angle_form_is_not():
    rest = grid()
    moved = similarity(rest, 30.0, (0, 0))
    fit = fit_marker_motion(rest, moved, MMPP)
    a, d = rest - rest.mean(0), moved - rest
    small = math.degrees((a[:, 0] * d[:, 1] - a[:, 1] * d[:, 0]).sum() / (a * a).sum())
    assert fit.rotation_deg == pytest.approx(30.0, abs=1e-9)
    assert abs(small - 30.0) > 1.0  # sin(30 deg) in radians: 28.6 deg


def test_rotation_about_another_point_is_the_same_rotation_plus_a_translation():
    rest = grid()
    about = (300.0, -50.0)
    moved = similarity(rest, 1.5, (0, 0), about=about)
    fit = fit_marker_motion(rest, moved, MMPP)
    assert fit.rotation_deg == pytest.approx(1.5, abs=1e-9)
    np.testing.assert_allclose(fit.translation_mm, (moved.mean(0) - rest.mean(0)) * MMPP, atol=1e-12)
    assert np.hypot(*fit.translation_mm) > 0.1


def test_fit_with_noise_stays_close():
    rng = np.random.default_rng(3)
    rest = grid(n=11)
    moved = similarity(rest, 0.8, (0.5, -0.3), 1.01) + rng.normal(0, 0.05, rest.shape)
    fit = fit_marker_motion(rest, moved, MMPP)
    assert fit.rotation_deg == pytest.approx(0.8, abs=0.02)
    assert fit.dilation == pytest.approx(0.01, abs=5e-4)
    assert fit.rms_residual_mm == pytest.approx(0.05 * math.sqrt(2) * MMPP, rel=0.2)


def test_region_restricts_the_fit_and_whole_pad_fit_dilutes_a_local_twist():
    """A patch that twists by 1 deg in a field at rest: the region fit recovers it, the whole field
    does not (the loss issue #17 measured on the dataset)."""
    rest = grid(n=11)
    inside = np.hypot(*(rest - rest[60]).T) <= 40.0  # the centre marker and its neighbours
    moved = rest.copy()
    moved[inside] = similarity(rest[inside], 1.0, (0.3, 0.0), about=rest[60])
    region = fit_marker_motion(rest, moved, MMPP, inside)
    whole = fit_marker_motion(rest, moved, MMPP)
    assert region.n_markers == inside.sum() >= MIN_REGION_MARKERS
    assert region.rotation_deg == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(region.translation_mm, [0.3 * MMPP, 0.0], atol=1e-12)
    assert abs(whole.rotation_deg) < 0.2
    # weights: zero weight is the same as leaving the marker out
    w = inside.astype(float) * 2.0
    assert fit_marker_motion(rest, moved, MMPP, w).rotation_deg == pytest.approx(1.0, abs=1e-9)


def test_fit_rejects_bad_input_and_returns_none_when_underdetermined():
    rest = grid(n=3)
    with pytest.raises(GelsimError, match="shapes"):
        fit_marker_motion(rest, rest[:-1], MMPP)
    with pytest.raises(GelsimError, match="weights"):
        fit_marker_motion(rest, rest, MMPP, -np.ones(len(rest)))
    with pytest.raises(GelsimError, match="mm_per_px"):
        fit_marker_motion(rest, rest, 0.0)
    one = np.zeros(len(rest), bool)
    one[4] = True
    assert fit_marker_motion(rest, rest, MMPP, one) is None
    same = np.zeros((4, 2))
    assert fit_marker_motion(same, same, MMPP) is None


def test_contact_region_is_the_area_disc_widened_to_the_nearest_markers():
    rest = grid()  # pitch 27 px = 1.6 mm
    centre = rest[40]
    # a disc of radius 1.1 pitches holds the centre marker and its 4 neighbours
    r_mm = 1.1 * 27 * MMPP
    sel = contact_region(rest, centre, math.pi * r_mm ** 2, MMPP)
    assert sel.sum() == 5 and sel[40]
    tiny = contact_region(rest, centre, 0.01, MMPP)
    assert tiny.sum() == MIN_REGION_MARKERS and tiny[40]
    assert not contact_region(rest, [np.nan, np.nan], 10.0, MMPP).any()
    assert not contact_region(rest, centre, 0.0, MMPP).any()


def _labels(rest, moved, twist_deg, shear_mm, centroid, area_mm2):
    """One-frame labels as a sequence writes them."""
    return {"markers_rest_px": rest.astype(np.float32), "markers_xy_px": moved[None].astype(np.float32),
            "twist_deg": np.array([twist_deg], np.float32), "shear_mm": np.array([shear_mm], np.float32),
            "contact_centroid_px": np.array([centroid], np.float32),
            "contact_area_mm2": np.array([area_mm2], np.float32)}


def test_label_agreement_on_a_field_that_follows_the_labels():
    rest = grid(n=11)
    c = rest[60]
    r_mm = 2.2 * 27 * MMPP
    inside = np.hypot(*(rest - c).T) * MMPP <= r_mm
    moved = rest.copy()
    moved[inside] = similarity(rest[inside], 1.2, np.array([0.08, -0.02]) / MMPP, about=c)
    ag = label_agreement(_labels(rest, moved, 1.2, (0.08, -0.02), c, math.pi * r_mm ** 2), 0, MMPP)
    assert ag["contact"]["rotation_ratio"] == pytest.approx(1.0, abs=1e-3)
    assert ag["contact"]["translation_ratio"] == pytest.approx(1.0, abs=1e-3)
    assert ag["all"]["rotation_ratio"] < 0.5 and ag["all"]["translation_ratio"] < 0.5
    # a field turning the other way gives a negative ratio, not an agreement
    moved[inside] = similarity(rest[inside], -1.2, (0, 0), about=c)
    ag = label_agreement(_labels(rest, moved, 1.2, (0.0, 0.0), c, math.pi * r_mm ** 2), 0, MMPP)
    assert ag["contact"]["rotation_ratio"] == pytest.approx(-1.0, abs=1e-3)
    # labels below the floors are not compared
    assert math.isnan(ag["contact"]["translation_ratio"])
    ag = label_agreement(_labels(rest, rest, 0.01, (0.0, 0.0), c, 10.0), 0, MMPP)
    assert math.isnan(ag["contact"]["rotation_ratio"])


def test_label_agreement_with_the_marker_model_on_a_sphere_press():
    """markers.displace twists and shears the contact of a 40 mm sphere at 3 N (30 mm^2, the cpu
    preset's median contact): the fit in the contact region recovers the labels within the
    tolerance, the whole pad does not."""
    prof = load_profile("vitac").with_resolution(320, 240)
    prof = dataclasses.replace(prof, gel=dataclasses.replace(prof.gel, dome_radius_mm=0.0))  # the marker fit alone
    fid = get_fidelity("balanced")
    mmpp = prof.image.mm_per_px
    im = press(indenters.sphere(40.0, prof, center_mm=(3.0, 2.0)), prof, fid, force_n=3.0)
    assert 20 < im.contact_area_mm2 < 60
    rest = marker_grid(prof)
    shear = (0.06, -0.03)
    mk = displace(prof, fid, im, shear_mm=shear, twist_deg=1.0, rest=rest)
    cen, _ = contact_location(im.contact_mask)
    ag = label_agreement(_labels(rest, mk.xy_px, 1.0, shear, cen, im.contact_area_mm2), 0, mmpp)
    assert ag["contact"]["n_markers"] >= 2 * MIN_REGION_MARKERS
    assert abs(ag["contact"]["rotation_ratio"] - 1) <= AGREEMENT_TOLERANCE
    assert abs(ag["contact"]["translation_ratio"] - 1) <= AGREEMENT_TOLERANCE
    assert ag["all"]["rotation_ratio"] < 1 - AGREEMENT_TOLERANCE
    assert ag["all"]["translation_ratio"] < 1 - AGREEMENT_TOLERANCE


def _sequence_labels(T=6, n=9):
    rest = grid(n=n, pitch=30.0, origin=(40.0, 0.0)).astype(np.float32)
    force = np.array([0, 0.5, 2.0, 3.0, 2.5, 0], np.float32)
    twist = np.array([0, 0.2, 0.9, 0.5, 1.4, 3.0], np.float32)  # frame 5 has no contact: not the peak
    shear = np.zeros((T, 2), np.float32)
    shear[3] = (0.05, 0.0)
    cen = np.full((T, 2), np.nan, np.float32)
    box = np.full((T, 4), np.nan, np.float32)
    cen[1:5] = (160.0, 120.0)
    box[1:5] = (100.0, 80.0, 220.0, 160.0)
    cen[3] = (20.0, 20.0)  # the peak-force frame's patch sits in a corner, outside the crop
    box[3] = (0.0, 0.0, 60.0, 40.0)
    return {"normal_force_n": force, "in_contact": force > 0, "twist_deg": twist, "shear_mm": shear,
            "contact_area_mm2": np.where(force > 0, 20.0, 0.0).astype(np.float32),
            "indentation_mm": np.array([0, 0.2, 0.6, 1.0, 0.8, 0], np.float32),
            "markers_rest_px": rest, "markers_xy_px": np.repeat(rest[None], T, 0),
            "contact_centroid_px": cen, "contact_bbox_px": box}


def test_key_frames_and_sequence_stats():
    lab = _sequence_labels()
    assert key_frames(lab) == {"peak_force": 3, "peak_shear": 3, "peak_twist": 4}
    row = sequence_stats(lab, "twist", MMPP, 320, 240, max_indentation_mm=1.0)
    assert row["frame_key"] == 4
    assert row["frames_in_contact"] == 4
    assert row["normal_force_n"] == pytest.approx(3.0)
    assert row["contact_share_of_pad_pct"] == pytest.approx(100 * 20.0 / (320 * 240 * MMPP ** 2), rel=1e-6)
    assert row["bottomed_out_pct"] == 100.0
    assert row["twist_deg"] == pytest.approx(1.4)
    assert row["shear_mm"] == pytest.approx(0.05)
    # markers at rest: no rotation, ratio 0 against a 1.4 degree label
    assert row["marker_rotation_contact_deg"] == pytest.approx(0.0, abs=1e-9)
    assert row["rotation_ratio_contact"] == pytest.approx(0.0, abs=1e-9)
    # crop (99.5..219.5, 59.5..179.5): out at the peak-force frame, in at the other three
    assert row["centroid_in_crop_pct"] == 0.0
    assert row["centroid_in_crop_frames_pct"] == pytest.approx(75.0)
    assert row["bbox_share_in_crop"] == 0.0
    assert row["centroid_offset_mm"] == pytest.approx(math.hypot(159.5 - 20, 119.5 - 20) * MMPP, rel=1e-6)
    row = sequence_stats(lab, "press", MMPP, 320, 240, max_indentation_mm=2.0)
    assert row["frame_key"] == 3 and row["bottomed_out_pct"] == 0.0
    with pytest.raises(GelsimError, match="action"):
        sequence_stats(lab, "rub", MMPP, 320, 240)


def test_sequence_without_contact_gives_nan_not_an_error():
    lab = _sequence_labels()
    lab["normal_force_n"] = np.zeros(6, np.float32)
    lab["in_contact"] = np.zeros(6, bool)
    row = sequence_stats(lab, "slip", MMPP, 320, 240)
    assert row["frame_key"] == -1 and row["frames_in_contact"] == 0
    assert math.isnan(row["contact_area_mm2"]) and math.isnan(row["marker_rotation_all_deg"])


def test_crop_matches_stam():
    """The crop gelsim measures is the one stam's cpu preset feeds its models."""
    from stam.data import centre_square

    cfg = tomllib.loads((ROOT / "stam" / "configs" / "cpu.toml").read_text())
    assert cfg["train"]["crop"] == STAM_CPU_CROP
    for w, h in ((320, 240), (960, 720), (97, 61)):
        ys, xs = np.mgrid[0:h, 0:w]
        frame = np.stack([xs, ys, np.zeros_like(xs)], -1)
        kept = centre_square(frame, STAM_CPU_CROP)
        x0, y0, x1, y1 = crop_box_px(w, h, STAM_CPU_CROP)
        assert (kept[0, 0, 0], kept[0, 0, 1]) == (x0 + 0.5, y0 + 0.5)
        assert (kept[-1, -1, 0], kept[-1, -1, 1]) == (x1 - 0.5, y1 - 0.5)
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(GelsimError, match="crop"):
            check_crop(bad)


@pytest.mark.parametrize("action", ["slip", "twist"])
def test_labels_agree_with_the_marker_field_in_the_contact_on_generated_sequences(action):
    """Issue #17's label-vs-image check on simulated sequences (the fabrics it measured): in the
    contact region the fitted marker rotation follows twist_deg and the translation follows shear_mm
    within AGREEMENT_TOLERANCE, at the action's key frame, for every label large enough to compare."""
    from gelsim.fabrics import load_catalog
    from gelsim.motion import sample_motion
    from gelsim.sequence import SequenceOptions, render_sequence
    from gelsim.sinks import drain

    prof = load_profile("vitac").with_resolution(320, 240)
    fid = get_fidelity("balanced")
    catalog = load_catalog()
    compared = 0
    for fabric_id in (8, 21, 50):
        for seed in range(3):
            motion = sample_motion(action, seed, frames=(12, 12), precontact=(1, 1))
            labels, _ = drain(render_sequence(catalog[fabric_id], motion, prof, fid, seed=seed,
                                              options=SequenceOptions(outputs={"markers"})))
            row = sequence_stats(labels, action, prof.image.mm_per_px, prof.image.width_px,
                                 prof.image.height_px)
            for what in ("rotation", "translation"):
                ratio = row[f"{what}_ratio_contact"]
                if math.isfinite(ratio):
                    compared += 1
                    assert abs(ratio - 1) <= AGREEMENT_TOLERANCE, (fabric_id, seed, what, ratio)
    assert compared >= 9  # every sequence compared its action's own label
