"""gelsim.frame: one pressed and rendered frame, and the Hertz press report."""
from __future__ import annotations

import numpy as np
import pytest

from gelsim import frame
from gelsim.errors import GelsimError
from gelsim.fabrics import heightfield, load_catalog
from gelsim.fidelity import get_fidelity
from gelsim.gel import hertz, press
from gelsim.scene import Cylinder, FabricObject, Mesh, Sphere, field_heights, indenter, sensor_field
from gelsim.sensor import load_profile


@pytest.fixture(scope="module")
def prof():
    return load_profile("vitac").with_resolution(160)


@pytest.fixture(scope="module")
def fabric():
    return load_catalog()[5]


def test_field_is_centred_on_the_sensor(prof):
    x0, y0, w, h, dx = sensor_field(prof)
    assert (h, w) == prof.shape and dx == prof.image.mm_per_px
    assert x0 == pytest.approx(-(w - 1) / 2 * dx) and y0 == pytest.approx(-(h - 1) / 2 * dx)
    ball = field_heights(Sphere(4.0), prof)
    # even sizes: the apex (2 mm) lies between the four centre pixels, all equally high
    cy, cx = h // 2, w // 2
    centre = ball[cy - 1:cy + 1, cx - 1:cx + 1]
    assert np.ptp(centre) < 1e-6 and centre.max() == ball.max() and 1.99 < ball.max() <= 2.0
    half = field_heights(Sphere(4.0), prof, scale=0.5)
    assert half.shape == (h // 2, w // 2)


def test_press_object_is_press_of_the_field_heights(prof, fabric):
    fid = get_fidelity("fast")
    ball = frame.press_object(Sphere(4.0), prof, fid, force_n=0.3)
    ref = press(field_heights(Sphere(4.0), prof), prof, fid, force_n=0.3)
    np.testing.assert_array_equal(ball.depth_mm, ref.depth_mm)
    assert ball.normal_force_n == pytest.approx(0.3, rel=0.05)
    # a fabric brings its compliance and texture scale, and its seed picks its irregularities
    obj = FabricObject(fabric)
    cloth = frame.press_object(obj, prof, fid, force_n=1.0, seed=4)
    h, w = prof.shape
    mm = prof.image.mm_per_px
    hf = heightfield(fabric, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                     mm_per_px=mm, seed=4)
    ref = press(hf, prof, fid, force_n=1.0, support=fabric.support(), texture_mm=fabric.texture_mm)
    np.testing.assert_array_equal(cloth.depth_mm, ref.depth_mm)
    rigid = press(hf, prof, fid, force_n=1.0)
    assert not np.array_equal(cloth.depth_mm, rigid.depth_mm)


def test_render_frame_dent_and_record(prof):
    rgb, info = frame.render_frame(Sphere(4.0), prof, "fast", depth_mm=0.4, seed=3)
    flat, _ = frame.render_frame(Sphere(4.0), prof, "fast", depth_mm=0.0, seed=3)
    assert rgb.shape == (*prof.shape, 3) and rgb.dtype == np.uint8
    assert info["object"] == {"indenter": "sphere", "diameter_mm": 4.0}
    assert info["imprint"]["indentation_mm"] == pytest.approx(0.4, rel=1e-3)
    assert set(info["stages_ms"]) == {"setup", "object", "imprint", "markers", "renderer_setup", "render"}
    diff = np.abs(rgb.astype(float) - flat)
    h, w = prof.shape
    assert diff[h // 2 - 10:h // 2 + 10, w // 2 - 10:w // 2 + 10].mean() > 3 * diff[:15, :15].mean() + 1
    again, _ = frame.render_frame(Sphere(4.0), prof, "fast", depth_mm=0.4, seed=3)
    np.testing.assert_array_equal(again, rgb)


def test_render_frame_default_force_and_bad_input(prof):
    _, info = frame.render_frame(Cylinder(3.0), prof, "fast")
    assert info["imprint"]["normal_force_n"] == pytest.approx(frame.DEFAULT_FORCE_N, rel=0.05)
    assert info["object"] == {"indenter": "cylinder", "diameter_mm": 3.0}
    with pytest.raises(GelsimError, match="finite number >= 0"):
        frame.render_frame(Sphere(4.0), prof, "fast", force_n=float("nan"))
    with pytest.raises(GelsimError, match="not something the sensor can touch"):
        frame.render_frame("sphere", prof, "fast")


def test_describe():
    fab = load_catalog()[21]
    assert frame.describe(FabricObject(fab)) == {"fabric": 21, "name": fab.name, "family": fab.family}
    assert frame.describe(Mesh("ball.stl")) == {"indenter": "ball.stl", "diameter_mm": None}


def test_press_report_against_hertz(prof):
    rep = frame.press_report(Sphere(4.0), 0.05, profile=prof, fidelity="fast")
    gel = prof.gel
    a, d = hertz(2.0 / (2.0 / 4.0 + 1.0 / gel.dome_radius_mm), 0.05, gel)   # the dome's curvature added
    assert rep["hertz_contact_radius_mm"] == pytest.approx(a) and rep["hertz_indentation_mm"] == pytest.approx(d)
    assert rep["indenter"] == "sphere" and rep["diameter_mm"] == 4.0 and rep["model"] == "twoscale"
    assert rep["contact_radius_ratio"] == pytest.approx(rep["contact_radius_mm"] / a)
    assert rep["contact_radius_mm"] == pytest.approx(np.sqrt(rep["contact_area_mm2"] / np.pi))
    assert rep["resolution_px"] == [160, 120]
    wide = frame.press_report(Sphere(4.0), 0.05, profile=prof, fidelity="fast", resolution_px=320)
    assert wide["resolution_px"] == [320, 240]
    cyl = frame.press_report(indenter("cylinder", diameter_mm=3.0, length_mm=5.0), 0.05, profile=prof,
                             fidelity="fast")
    assert cyl["indenter"] == "cylinder" and cyl["hertz_contact_radius_mm"] is None and cyl["indentation_mm"] > 0
    assert frame.hertz_for(Cylinder(3.0), 0.05, gel) is None
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(GelsimError, match="not a positive force"):
            frame.press_report(Sphere(4.0), bad, profile=prof)


def test_indenter_factory(tmp_path):
    assert indenter("sphere", diameter_mm=3.0) == Sphere(3.0)
    assert indenter("cylinder", diameter_mm=2.0, length_mm=4.0, angle_deg=30.0) == Cylinder(2.0, 4.0, 30.0)
    assert indenter(str(tmp_path / "m.OBJ")) == Mesh(str(tmp_path / "m.OBJ"))
    with pytest.raises(GelsimError, match="unknown indenter 'cone'"):
        indenter("cone", diameter_mm=1.0)
    with pytest.raises(GelsimError, match="give a value > 0 mm"):
        indenter("sphere")
    with pytest.raises(GelsimError, match="not finite"):
        indenter("cylinder", diameter_mm=1.0, angle_deg=float("inf"))
