"""End-to-end tests of `gelsim render`."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from gelsim.cli import main
from gelsim.params import dump_toml, to_dict
from gelsim.sensor import load_profile


@pytest.fixture(scope="module")
def small_profile(tmp_path_factory):
    """The ViTac sensor at 320x240, written as a profile file (exercises --profile PATH)."""
    data = to_dict(load_profile("vitac").with_resolution(320))
    data.pop("source")
    path = tmp_path_factory.mktemp("prof") / "vitac320.toml"
    path.write_text(dump_toml(data))
    return path


def _expected_contrast(prof, box, radius_mm, depth_mm):
    """Mean |colour change| (DN) over ``box`` (rows y0, y1, columns x0, x1) that the profile's LEDs
    predict, to first order in the tilt, for a centred sphere cap: each LED changes its colour by
    gain_dn x intensity x cos(elevation) per unit of the normal's in-plane component towards it (for
    a calibrated profile these lights are fitted to the table's response near flat, so the fast
    backend's table shades alike; the gel's spread around the cap is ignored)."""
    import math

    h, w = prof.shape
    mm = prof.image.mm_per_px
    yy, xx = np.mgrid[box[0]:box[1], box[2]:box[3]]
    x, y = (xx - (w - 1) / 2) * mm, (yy - (h - 1) / 2) * mm
    inside = x ** 2 + y ** 2 <= 2 * radius_mm * depth_mm - depth_mm ** 2
    nx, ny = np.where(inside, x / radius_mm, 0.0), np.where(inside, y / radius_mm, 0.0)
    change = np.zeros(x.shape + (3,))
    for li in prof.lights:
        g = prof.shading.gain_dn * li.intensity * math.cos(math.radians(li.elevation_deg))
        a = math.radians(li.azimuth_deg)
        change += np.multiply.outer(g * (nx * math.cos(a) + ny * math.sin(a)), np.asarray(li.color_rgb))
    return float(np.abs(change).mean())


def _run(capsys, *argv):
    code = main(["render", *map(str, argv)])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def _read(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None
    return img[..., ::-1]


def test_render_sphere_json_and_png(tmp_path, capsys, small_profile):
    out = tmp_path / "sphere.png"
    code, stdout, _ = _run(capsys, "--out", out, "--indenter", "sphere", "--diameter-mm", 4, "--depth-mm", 0.4,
                           "--profile", small_profile, "--seed", 3, "--json")
    assert code == 0
    info = json.loads(stdout)
    assert info["backend"] == "fast" and info["shape_hw"] == [240, 320]
    assert info["imprint"]["indentation_mm"] == pytest.approx(0.4, rel=1e-3)
    assert info["imprint"]["max_depth_mm"] > 0.2
    assert set(info["stages_ms"]) >= {"object", "imprint", "markers", "render", "write_png"}
    assert all(v >= 0 for v in info["stages_ms"].values())
    img = _read(out)
    assert img.shape == (240, 320, 3)
    # against the flat gel (same seed: same background, markers and noise) only the dent changed
    flat = tmp_path / "flat.png"
    _run(capsys, "--out", flat, "--depth-mm", 0, "--profile", small_profile, "--seed", 3)
    diff = np.abs(img.astype(float) - _read(flat))
    # the profile's LEDs predict 8.9 DN for vitac (10.8 rendered: the gel's spread adds slope around the cap)
    expected = _expected_contrast(load_profile(small_profile), (90, 150, 130, 190), radius_mm=2.0, depth_mm=0.4)
    assert 0.75 * expected < diff[90:150, 130:190].mean() < 2.0 * expected
    assert diff[:40, :40].mean() < 0.5
    # same seed, same PNG
    out2 = tmp_path / "again.png"
    _run(capsys, "--out", out2, "--depth-mm", 0.4, "--profile", small_profile, "--seed", 3)
    np.testing.assert_array_equal(_read(out2), img)
    assert not list(tmp_path.glob(".*.partial-*"))


def test_render_fabric_by_force(tmp_path, capsys, small_profile):
    from gelsim.fabrics import load_catalog
    fid = load_catalog().ids[0]
    out = tmp_path / "fabric.png"
    code, stdout, _ = _run(capsys, "--out", out, "--fabric", fid, "--force-n", 1.5, "--profile", small_profile,
                           "--json")
    assert code == 0
    info = json.loads(stdout)
    assert info["object"]["fabric"] == fid
    assert info["imprint"]["normal_force_n"] == pytest.approx(1.5, rel=0.05)
    assert _read(out).shape == (240, 320, 3)


def test_a_force_the_gel_cannot_carry_is_said_on_stderr_and_the_json_stays_valid(tmp_path, capsys, small_profile):
    """`--force-n 1e20 --json` printed a NaN force (not JSON) and exited 0 silently (#42)."""
    code, stdout, err = _run(capsys, "--out", tmp_path / "x.png", "--fabric", 21, "--force-n", 1e20,
                             "--profile", small_profile, "--json")
    assert code == 0
    info = json.loads(stdout, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert info["imprint"]["bottomed_out"] and 0 < info["imprint"]["normal_force_n"] < 1e3
    assert err.count("\n") == 1 and err.startswith("gelsim render: warning: the gel bottomed out")
    assert "of the 1e+20 N asked" in err
    code, _, err = _run(capsys, "--out", tmp_path / "y.png", "--fabric", 21, "--force-n", 1, "--profile", small_profile)
    assert code == 0 and err == ""                                       # within range: nothing said


@pytest.mark.gl
def test_render_pyrender_backend(tmp_path, capsys, small_profile):
    from gelsim.optics import available_backends
    if "pyrender" not in available_backends():
        pytest.skip("no headless OpenGL context")
    out = tmp_path / "gl.png"
    code, stdout, _ = _run(capsys, "--out", out, "--depth-mm", 0.4, "--profile", small_profile,
                           "--backend", "pyrender", "--json")
    assert code == 0 and json.loads(stdout)["backend"] == "pyrender"
    assert _read(out).shape == (240, 320, 3)


@pytest.mark.parametrize("argv, needle", [
    (["--out", "x.jpg"], ".png"),
    (["--out", "no/such/folder/x.png"], "does not exist"),
    (["--out", "x.png", "--profile", "nosuch"], "unknown sensor profile"),
    (["--out", "x.png", "--depth-mm", "nan"], "finite"),
    (["--out", "x.png", "--indenter", "cone"], "unknown indenter"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch, argv, needle):
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(capsys, *argv)
    assert code == 2
    assert needle in err and err.count("\n") == 1 and err.startswith("gelsim: error:")


def test_unknown_backend_rejected(capsys):
    with pytest.raises(SystemExit) as e:
        main(["render", "--out", "x.png", "--backend", "raytracer"])
    assert e.value.code == 2
