"""gelsim.calibrate: a synthetic data pack rendered by gelsim with known parameters is fitted back."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from gelsim.calibrate import calibrate, fit_background, fit_noise, register_heldout, register_presses
from gelsim.cli import main
from gelsim.errors import GelsimError
from gelsim.optics import Renderer
from gelsim.realism import ball_depth, check_datapack, evaluate, load_datapack
from gelsim.sensor import load_profile

TRUE_THICKNESS_MM = 3.0
TRUE_READ_SIGMA = 2.0
BALL_MM = 4.0
LIGHT_AZIMUTHS = (90.0, 210.0, 330.0)


def _truth():
    """A 160x120 phong sensor with pure-colour LEDs at known azimuths and a known gel thickness."""
    base = load_profile("vitac").with_resolution(160, 120)
    lights = tuple(dataclasses.replace(l, color_rgb=tuple(float(i == k) for i in range(3)), azimuth_deg=az)
                   for k, (l, az) in enumerate(zip(base.lights, LIGHT_AZIMUTHS)))
    return dataclasses.replace(
        base, lights=lights, shading=dataclasses.replace(base.shading, model="phong"),
        gel=dataclasses.replace(base.gel, thickness_mm=TRUE_THICKNESS_MM, membrane_smoothing_mm=0.06,
                                max_indentation_mm=2.0),
        markers=dataclasses.replace(base.markers, enabled=False),
        noise=dataclasses.replace(base.noise, read_sigma_dn=TRUE_READ_SIGMA, shot_gain=0.0),
        camera=dataclasses.replace(base.camera, blur_sigma_px=0.0))


def _pack_dict(truth, n=12, seed=0):
    """Data-pack arrays (colours stored BGR, as OpenCV writes them) of ``n`` ball presses."""
    rng = np.random.default_rng(seed)
    h, w = truth.shape
    ren = Renderer(truth, seed=seed)
    centers = np.stack([rng.uniform(35, w - 35, n), rng.uniform(35, h - 35, n)], axis=1).round()
    radii = rng.uniform(11, 15, n).round()
    imgs = np.stack([ren.render(ball_depth(truth, c, r, BALL_MM), None, seed=i)
                     for i, (c, r) in enumerate(zip(centers, radii))])
    f0 = ren.render(None, None, seed=1000)
    return {"f0": f0[..., ::-1], "imgs": imgs[..., ::-1], "touch_center": centers, "touch_radius": radii}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    truth = _truth()
    d = tmp_path_factory.mktemp("cal")
    data = _pack_dict(truth)
    np.savez(d / "pack.npz", **data)
    pack = load_datapack(d / "pack.npz")
    grid = {"thickness_mm": (1.0, TRUE_THICKNESS_MM), "membrane_smoothing_mm": (0.06,), "shadow_tan": (0.0,)}
    rep = calibrate(pack, load_profile("vitac"), d / "fit.toml", frames="even",
                    mm_per_px=truth.image.mm_per_px, ball_diameter_mm=BALL_MM, grid=grid)
    return truth, pack, rep, d


def test_calibration_recovers_gel_thickness_noise_and_light_azimuths(fitted):
    """Known thickness picked from the grid; read noise within 20%; each channel's light azimuth
    within 12 degrees of the LED that made it."""
    truth, pack, rep, d = fitted
    assert rep["best"]["thickness_mm"] == TRUE_THICKNESS_MM
    by_t = {t["thickness_mm"]: t["cv_mse"] for t in rep["trials"]}
    assert by_t[TRUE_THICKNESS_MM] < 0.7 * by_t[1.0]
    assert abs(rep["noise"]["read_sigma_dn"] - TRUE_READ_SIGMA) < 0.2 * TRUE_READ_SIGMA
    assert rep["noise"]["shot_gain"] == pytest.approx(0.0, abs=0.01)
    prof = load_profile(d / "fit.toml")
    assert prof.shading.model == "lut" and prof.gel.thickness_mm == TRUE_THICKNESS_MM
    # the base profile's unit ranges are carried over with their reasons
    assert prof.unit_variation == load_profile("vitac").unit_variation
    assert "led_intensity_frac = 0.15  # " in (d / "fit.toml").read_text()
    for light, az in zip(prof.lights, LIGHT_AZIMUTHS):
        err = (light.azimuth_deg - az + 180.0) % 360.0 - 180.0
        assert abs(err) < 12.0, (light.name, light.azimuth_deg, az)


def test_exact_annotations_are_kept(fitted):
    """The synthetic pack's centres are exact: registration finds little to gain and leaves them."""
    truth, pack, rep, d = fitted
    reg = rep["centres"]["registration"]
    assert reg["applied"] is False and reg["explained"] < 0.5
    assert np.all(np.asarray(reg["offsets_px"]) == 0.0)
    assert rep["centres"]["headline"] == rep["centres"]["fit"] == "annotated"
    np.testing.assert_array_equal(rep["centres"]["centres_px"], pack.centers_px)
    # at 0.118 mm/px the flat-point detector's disk (slope 0.1 on a 4 mm ball) is under 2 px: not used
    assert rep["centres"]["detection"]["available"] is False and "under 2 px" in rep["centres"]["detection"]["reason"]


def test_registration_recovers_shifted_centres():
    """Presses rendered with the shipped GelSight Mini table (a colour wheel that turns within a few
    pixels of the ball's lowest point) at 160x120, annotated 1-4 px off (zero mean over the fitted
    frames: registration fixes the presses relative to each other, the annotation's mean stands):
    registered back to within a pixel; with exact annotations nothing moves."""
    truth = load_profile("gelsight-mini").with_resolution(160)
    h, w = truth.shape
    mm = truth.image.mm_per_px
    n = 8
    rng = np.random.default_rng(0)
    ren = Renderer(truth, seed=0)
    centers = np.stack([rng.uniform(0.4 * w, 0.6 * w, n), rng.uniform(0.4 * h, 0.6 * h, n)], axis=1)
    radii = rng.uniform(1.1, 1.8, n) / mm
    imgs = np.stack([ren.render(ball_depth(truth, c, r, BALL_MM), None, seed=i)
                     for i, (c, r) in enumerate(zip(centers, radii))])
    f0 = ren.render(None, None, seed=99)
    ang = rng.uniform(0, 2 * np.pi, n)
    shift = np.stack([np.cos(ang), np.sin(ang)], axis=1) * (rng.uniform(0.15, 0.3, n) * radii)[:, None]
    shift[0::2] -= shift[0::2].mean(axis=0)
    pack = check_datapack({"f0": f0, "imgs": imgs, "touch_center": centers, "touch_radius": radii}, "exact", "rgb")
    moved, rep = register_presses(pack, "even", mm, BALL_MM)
    assert not rep["applied"] and moved is pack
    off = dataclasses.replace(pack, centers_px=centers + shift)
    moved, rep = register_presses(off, "even", mm, BALL_MM)
    assert rep["applied"] and rep["explained"] > 0.5
    err = np.hypot(*(moved.centers_px - centers).T)
    assert np.sqrt((shift ** 2).sum(axis=1).mean()) > 2.0 and err[0::2].max() < 1.0, err
    np.testing.assert_array_equal(moved.centers_px[1::2], off.centers_px[1::2])     # the others are left
    # each odd press registered against the table of the even ones (at their registered centres)
    cents = register_heldout(off, [0, 2, 4, 6], moved.centers_px, [1, 3, 5, 7], mm, BALL_MM)
    err = np.hypot(*(cents - centers)[1::2].T)
    assert err.max() < 1.0, err


def test_fitted_profile_reproduces_held_out_frames(fitted):
    """Fitted on even frames, the profile predicts the odd ones nearly to the noise floor."""
    truth, pack, rep, d = fitted
    prof = load_profile(d / "fit.toml")
    res = evaluate(prof, pack, "odd", ball_diameter_mm=BALL_MM)
    assert res["skill"] > 0.9
    assert res["contact"]["psnr"] > res["baseline"]["contact"]["psnr"] + 8.0
    # noise of 2 DN in both frames bounds the PSNR at about 10 log10(255^2 / 4) = 42 dB
    assert res["contact"]["psnr"] < 44.0
    # near flat the fitted table responds about as the truth does (no step, no dead zone at flat).
    # Measured 0.95 / 1.04 / 0.79: at this resolution the ball's flat top is a few pixels, and the
    # halo's directional part, radial around the press as the rim's normals are, takes a little of
    # the weakest channel's response (the fit without depth and halo terms gave 0.99 / 1.05 / 0.96)
    assert all(0.75 < g < 1.25 for g in res["small_slope"]["gain_ratio"]), res["small_slope"]


def test_background_is_smoothed_half_resolution_and_noise_fit_ignores_contacts():
    rng = np.random.default_rng(1)
    clean = np.full((60, 80, 3), 120.0)
    f0 = np.clip(clean + rng.normal(0, 3, clean.shape), 0, 255).astype(np.uint8)
    small = fit_background(f0)
    assert small.shape == (30, 40, 3) and small.dtype == np.uint8
    assert small.std() < f0.std() / 2           # smoothed
    imgs = np.clip(clean[None] + rng.normal(0, 3, (4,) + f0.shape), 0, 255).astype(np.uint8)
    imgs[:, 20:40, 30:50] = 255                 # a "contact" that the noise fit must skip
    pack = check_datapack({"f0": f0, "imgs": imgs, "touch_center": np.tile([[40.0, 30.0]], (4, 1)),
                           "touch_radius": np.full(4, 9.0)}, channel_order="rgb")
    read, shot = fit_noise(pack, [0, 1, 2, 3])
    # imgs - f0 holds two independent draws of 3 DN noise; the fit reports one frame's
    assert read == pytest.approx(3.0, rel=0.1)
    assert shot == 0.0


def test_calibrate_bad_input(tmp_path, fitted):
    truth, pack, rep, d = fitted
    with pytest.raises(GelsimError, match=r"\.toml"):
        calibrate(pack, load_profile("vitac"), tmp_path / "x.json", mm_per_px=truth.image.mm_per_px)
    with pytest.raises(GelsimError, match="does not exist"):
        calibrate(pack, load_profile("vitac"), tmp_path / "no" / "x.toml", mm_per_px=truth.image.mm_per_px)
    few = dataclasses.replace(pack, imgs=pack.imgs[:3], centers_px=pack.centers_px[:3], radii_px=pack.radii_px[:3])
    with pytest.raises(GelsimError, match="at least 4"):
        calibrate(few, load_profile("vitac"), tmp_path / "x.toml", mm_per_px=truth.image.mm_per_px)


def _write(tmp_path, data, name="p.npz"):
    np.savez(tmp_path / name, **data)
    return str(tmp_path / name)


@pytest.mark.parametrize("change, args, match", [
    (lambda d: d.update(touch_center=np.vstack([d["touch_center"][:-1], [[500.0, 20.0]]])), [], "outside"),
    (lambda d: None, ["--ball-diameter-mm", "30"], "larger than the"),
    (lambda d: None, ["--ball-diameter-mm", "1"], "exceeds the"),
    (lambda d: d.update(imgs=d["imgs"][:5], touch_center=d["touch_center"][:5], touch_radius=d["touch_radius"][:5]),
     [], "at least 4"),
    (lambda d: d.update(imgs=d["imgs"][:6], touch_center=d["touch_center"][:6], touch_radius=d["touch_radius"][:6]),
     ["--frames", "odd"], "at least 4"),
    (lambda d: d.pop("f0"), [], "lacks f0"),
    (lambda d: d.update(imgs=np.concatenate([d["imgs"][:-1], d["f0"][None]])), [], "no press there"),
    (lambda d: d.update(touch_radius=d["touch_radius"][:, None]), [], "touch_radius has shape"),
])
def test_calibrate_refuses_bad_packs_in_one_line_and_writes_nothing(fitted, tmp_path, capsys, change, args, match):
    truth, pack, rep, d = fitted
    data = dict(np.load(d / "pack.npz"))
    change(data)
    src = tmp_path / "src"
    src.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    code = main(["calibrate", _write(src, data), "--out", str(out / "p.toml"),
                 "--mm-per-px", str(truth.image.mm_per_px), *args])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and match in err, err
    assert list(out.iterdir()) == []


def test_realism_refuses_a_profile_of_another_size(fitted, capsys):
    truth, pack, rep, d = fitted
    assert main(["realism", "--profile", "gelsight-r15", "--datapack", str(d / "pack.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "640x480" in err and "160x120" in err


def test_cli_calibrate_reports_its_held_out_score(fitted, tmp_path, capsys):
    """Fitted on the even frames, the command scores the odd ones itself (JSON and text)."""
    truth, pack, rep, d = fitted
    args = ["calibrate", str(d / "pack.npz"), "--out", str(tmp_path / "c.toml"), "--mm-per-px",
            str(truth.image.mm_per_px), "--ball-diameter-mm", str(BALL_MM), "--base-profile", "vitac"]
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    held = doc["heldout"]
    assert held["frame_set"] == "odd" and held["frames"] == 6 and held["centres"] == "annotated"
    assert doc["centres"]["registration"]["applied"] is False and set(held["compare"]) == {"registered"}
    assert held["skill"] > 0.9 and held["baseline"]["skill"] == 0.0
    lo, hi = held["skill_ci95"]
    assert lo <= held["skill"] <= hi and hi - lo > 0
    # the registered poses are fitted to the fitted frames' table: they can only help (here, exact centres, little)
    assert held["compare"]["registered"]["skill"] >= held["skill"] - 0.01
    again = evaluate(load_profile(tmp_path / "c.toml"), pack, "odd", ball_diameter_mm=BALL_MM)
    assert held["skill"] == pytest.approx(again["skill"])
    assert main(args[:3] + [str(tmp_path / "c2.toml")] + args[4:] + ["--frames", "all"]) == 0
    assert "held-out score: none" in capsys.readouterr().out


def test_cli_calibrate_and_realism(fitted, tmp_path, capsys):
    truth, pack, rep, d = fitted
    bad = dict(np.load(d / "pack.npz"))
    del bad["touch_radius"]
    np.savez(tmp_path / "bad.npz", **bad)
    assert main(["calibrate", str(tmp_path / "bad.npz"), "--out", str(tmp_path / "p.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "touch_radius" in err
    out_png = tmp_path / "side.png"
    code = main(["realism", "--profile", str(d / "fit.toml"), "--datapack", str(d / "pack.npz"), "--frames", "odd",
                 "--mm-per-px", str(truth.image.mm_per_px), "--out", str(out_png), "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["crop"]) == {"ssim", "psnr", "l1"} and set(doc["contact"]) == {"ssim", "psnr", "l1"}
    assert doc["frames"] == 6 and doc["skill"] > 0.9 and doc["baseline"]["skill"] == 0.0
    assert doc["small_slope"]["pixels"] > 0 and len(doc["small_slope"]["gain_ratio"]) == 3
    import cv2
    img = cv2.imread(str(out_png))
    assert img.shape == (truth.shape[0], 3 * truth.shape[1], 3)
    # the headline (auto) is at the annotated centres here (exact, the registration leaves them); the
    # registered score (the pose fitted: an upper bound) is printed beside it
    assert doc["centres"] == "annotated" and doc["choice"]["registration"]["applied"] is False
    assert set(doc["compare"]) == {"registered"}
    assert main(["realism", "--profile", str(d / "fit.toml"), "--datapack", str(d / "pack.npz"),
                 "--mm-per-px", str(truth.image.mm_per_px), "--centres", "registered", "--json"]) == 0
    reg = json.loads(capsys.readouterr().out)
    assert reg["centres"] == "registered" and set(reg["compare"]) == {"annotated"}
    assert reg["skill"] == pytest.approx(doc["compare"]["registered"]["skill"])
    assert reg["compare"]["annotated"]["skill"] == pytest.approx(doc["skill"])
    # detected centres where the detector cannot run: one line, exit 2
    assert main(["realism", "--profile", str(d / "fit.toml"), "--datapack", str(d / "pack.npz"),
                 "--mm-per-px", str(truth.image.mm_per_px), "--centres", "detected"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "flat-point detector" in err and "--centres annotated" in err
    assert main(["realism", "--profile", str(d / "fit.toml"), "--datapack", str(d / "pack.npz"),
                 "--mm-per-px", str(truth.image.mm_per_px)]) == 0
    text = capsys.readouterr().out
    line = [ln for ln in text.splitlines() if "small slopes" in ln]
    assert len(line) == 1 and "gain sim/real R" in line[0] and "RMS" in line[0]
    assert "headline, annotated centres: skill" in text and "registered centres (pose fitted: upper bound)" in text
