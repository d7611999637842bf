"""`gelsim press`: JSON keys and values, table output, bad input exits 2."""
import json
import re

import pytest

from gelsim.cli import main
from gelsim.gel import hertz
from gelsim.sensor import SENSORS_DIR, load_profile

KEYS = {"contact_radius_mm", "indentation_mm", "hertz_contact_radius_mm", "hertz_indentation_mm", "force_n", "model"}


@pytest.fixture(scope="module")
def thick_profile(tmp_path_factory):
    """The vitac sensor with a 20 mm gel: a half-space for millinewton presses."""
    text = (SENSORS_DIR / "vitac.toml").read_text()
    text, n = re.subn(r"(?m)^thickness_mm\s*=.*$", "thickness_mm = 20.0", text)
    assert n == 1
    path = tmp_path_factory.mktemp("prof") / "thick.toml"
    path.write_text(text)
    return path


def run_json(capsys, *argv):
    rc = main(["press", *argv, "--json"])
    out = capsys.readouterr().out
    assert rc == 0
    return json.loads(out)


def test_json_keys_and_hertz_values(capsys, thick_profile):
    rep = run_json(capsys, "--indenter", "sphere", "--diameter-mm", "4", "--force-n", "0.02",
                   "--profile", str(thick_profile), "--fidelity", "reference", "--resolution-px", "480")
    assert KEYS <= set(rep)
    assert rep["model"] == "elastic" and rep["force_n"] == 0.02
    gel = load_profile(thick_profile).gel
    # The gel is domed: Hertz with the sphere's and the dome's curvatures added (1/R = 1/2 + 1/R_dome).
    a, d = hertz(2.0 / (2.0 / 4.0 + 1.0 / gel.dome_radius_mm), 0.02, gel)
    assert rep["hertz_contact_radius_mm"] == pytest.approx(a)
    assert rep["hertz_indentation_mm"] == pytest.approx(d)
    assert rep["contact_radius_mm"] == pytest.approx(a, rel=0.10)
    assert rep["indentation_mm"] == pytest.approx(d, rel=0.10)
    assert rep["bottomed_out"] is False


def test_twoscale_and_cylinder(capsys):
    rep = run_json(capsys, "--force-n", "0.05", "--fidelity", "balanced", "--resolution-px", "320")
    assert rep["model"] == "twoscale" and rep["indentation_mm"] > 0 and rep["contact_radius_mm"] > 0
    cyl = run_json(capsys, "--indenter", "cylinder", "--diameter-mm", "3", "--length-mm", "5",
                   "--force-n", "0.05", "--fidelity", "fast", "--resolution-px", "320")
    assert cyl["hertz_contact_radius_mm"] is None and cyl["indentation_mm"] > 0


def test_mesh_indenter(capsys, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=2.0).export(path)
    rep = run_json(capsys, "--indenter", str(path), "--force-n", "0.05", "--fidelity", "balanced",
                   "--resolution-px", "320")
    ref = run_json(capsys, "--indenter", "sphere", "--diameter-mm", "4", "--force-n", "0.05",
                   "--fidelity", "balanced", "--resolution-px", "320")
    assert rep["indentation_mm"] == pytest.approx(ref["indentation_mm"], rel=0.05)


def test_table_output(capsys):
    assert main(["press", "--force-n", "0.05", "--fidelity", "fast", "--resolution-px", "320"]) == 0
    out = capsys.readouterr().out
    assert "contact radius (mm)" in out and "indentation (mm)" in out and "Hertz" in out


@pytest.mark.parametrize("argv", [
    ["--diameter-mm", "0", "--force-n", "0.1"],
    ["--diameter-mm", "-2", "--force-n", "0.1"],
    ["--force-n", "0"],
    ["--force-n", "-1"],
    ["--indenter", "/nonexistent/ball.stl", "--force-n", "0.1"],
    ["--indenter", "pyramid", "--force-n", "0.1"],
])
def test_bad_input_exits_2_with_one_line(capsys, argv):
    assert main(["press", *argv, "--resolution-px", "160"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("gelsim: error:") and "\n" not in err


def test_an_overflowing_force_is_refused_and_a_bottomed_press_said_on_stderr(capsys):
    """`--force-n 1e39` overflowed float32 with a RuntimeWarning and said nothing (#42); 1e20 printed a garbled
    table with exit 0 (#50). More than the gel can carry at all is one line and status 2 (Hertz's figures
    for it describe nothing); a force that bottoms the pad out is pressed to its travel, said on stderr."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc = main(["press", "--indenter", "sphere", "--diameter-mm", "4", "--force-n", "1e39", "--fidelity", "fast",
                   "--resolution-px", "320", "--json"])
        cap = capsys.readouterr()
        assert rc == 2 and cap.out == "" and cap.err.count("\n") == 1
        assert "is more than the vitac gel can carry" in cap.err and "give a smaller force" in cap.err
        rc = main(["press", "--indenter", "sphere", "--diameter-mm", "4", "--force-n", "200", "--fidelity", "fast",
                   "--resolution-px", "320"])
    cap = capsys.readouterr()
    assert rc == 0 and "BOTTOMED OUT" in cap.out
    assert cap.err.startswith("gelsim press: warning: the gel bottomed out") and cap.err.count("\n") == 1
    # the table's columns stay apart whatever the figures' size
    rows = [line for line in cap.out.splitlines() if line.startswith(("contact radius", "indentation"))]
    assert len(rows) == 2 and all(len([float(v) for v in r[22:].split()]) == 3 for r in rows), rows
