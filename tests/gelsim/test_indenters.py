"""Indenters: sphere, cylinder (on its side) and meshes as protrusion maps."""
import numpy as np
import pytest
import trimesh

from gelsim import indenters
from gelsim.errors import GelsimError


def test_sphere_shape_peak_and_outline(vitac320):
    p = indenters.sphere(4.0, vitac320, center_mm=(1.0, -2.0))
    assert p.shape == vitac320.shape and p.dtype == np.float32
    assert p.min() >= 0 and p.max() == pytest.approx(2.0, abs=1e-3)
    iy, ix = np.unravel_index(np.argmax(p), p.shape)
    mmpp = vitac320.image.mm_per_px
    h, w = vitac320.shape
    assert (ix - (w - 1) / 2) * mmpp == pytest.approx(1.0, abs=mmpp)
    assert (iy - (h - 1) / 2) * mmpp == pytest.approx(-2.0, abs=mmpp)
    assert np.count_nonzero(p) * mmpp ** 2 == pytest.approx(np.pi * 4.0, rel=0.02)


def test_scale_changes_grid_not_field(vitac320):
    p = indenters.sphere(4.0, vitac320, scale=0.5)
    assert p.shape == (vitac320.shape[0] // 2, vitac320.shape[1] // 2)
    assert np.count_nonzero(p) * (2 * vitac320.image.mm_per_px) ** 2 == pytest.approx(np.pi * 4.0, rel=0.05)


def test_cylinder_on_its_side_orientation_and_length(vitac320):
    mmpp = vitac320.image.mm_per_px
    c0 = indenters.cylinder(2.0, vitac320)  # along x, longer than the field
    assert c0.max() == pytest.approx(1.0, abs=1e-3)
    assert np.count_nonzero(c0[:, 0]) > 0 and np.count_nonzero(c0[0, :]) == 0
    width_px = np.count_nonzero(c0[:, vitac320.shape[1] // 2])
    assert width_px * mmpp == pytest.approx(2.0, abs=2 * mmpp)
    c90 = indenters.cylinder(2.0, vitac320, angle_deg=90.0, length_mm=5.0)
    col = c90[:, vitac320.shape[1] // 2]
    assert np.count_nonzero(col) * mmpp == pytest.approx(5.0, abs=2 * mmpp)
    assert np.count_nonzero(c90[vitac320.shape[0] // 2]) * mmpp == pytest.approx(2.0, abs=2 * mmpp)


def test_mesh_sphere_matches_analytic_sphere(vitac320, tmp_path):
    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=4, radius=2.0).export(path)
    m = indenters.mesh(path, vitac320, center_mm=(0.5, 0.5))
    s = indenters.sphere(4.0, vitac320, center_mm=(0.5, 0.5))
    near_top = s > 1.0
    # Relief relative to the first touch agrees within the icosphere's faceting (about 5 um).
    assert np.abs((m.max() - m) - (s.max() - s))[near_top].max() < 0.01
    assert abs(np.count_nonzero(m) - np.count_nonzero(s)) <= 0.02 * np.count_nonzero(s)


def test_mesh_box_footprint(vitac320, tmp_path):
    path = tmp_path / "box.obj"
    trimesh.creation.box((3.0, 2.0, 1.0)).export(path)
    m = indenters.mesh(path, vitac320)
    assert np.count_nonzero(m) * vitac320.image.mm_per_px ** 2 == pytest.approx(6.0, rel=0.05)
    assert m.max() == pytest.approx(1.0, abs=1e-6)


def test_load_indenter_and_errors(vitac320, tmp_path):
    assert np.array_equal(indenters.load_indenter("sphere", vitac320, diameter_mm=3.0), indenters.sphere(3.0, vitac320))
    assert np.array_equal(indenters.load_indenter("cylinder", vitac320, diameter_mm=3.0, angle_deg=10.0),
                          indenters.cylinder(3.0, vitac320, angle_deg=10.0))
    for bad in (dict(name="sphere", diameter_mm=None), dict(name="sphere", diameter_mm=-1.0),
                dict(name="cylinder", diameter_mm=0.0), dict(name="cone", diameter_mm=1.0),
                dict(name=str(tmp_path / "missing.stl"), diameter_mm=None)):
        with pytest.raises(GelsimError):
            indenters.load_indenter(bad["name"], vitac320, diameter_mm=bad["diameter_mm"])
    junk = tmp_path / "junk.stl"
    junk.write_text("not a mesh")
    with pytest.raises(GelsimError):
        indenters.mesh(junk, vitac320)
