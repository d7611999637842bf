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
    assert diff[90:150, 130:190].mean() > 10
    assert diff[:40, :40].mean() < 0.5
    # same seed, same PNG
    out2 = tmp_path / "again.png"
    _run(capsys, "--out", out2, "--depth-mm", 0.4, "--profile", small_profile, "--seed", 3)
    np.testing.assert_array_equal(_read(out2), img)
    assert not list(tmp_path.glob(".*.tmp"))


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
