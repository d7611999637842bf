"""gelsim.units: one unit of a sensor model, drawn from the profile's [unit_variation]."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gelsim.calibrate import fit_lights
from gelsim.errors import GelsimError
from gelsim.markers import marker_grid
from gelsim.optics import Renderer
from gelsim.optics.lut import adjust_channels, load_table, table_path
from gelsim.realism import ball_depth
from gelsim.sensor import UnitVariationSpec, load_profile
from gelsim.units import draw_unit, unit_record, variation_ranges


def test_same_seed_same_unit_other_seed_other_unit(vitac320):
    a, b, c = draw_unit(vitac320, 5), draw_unit(vitac320, 5), draw_unit(vitac320, 6)
    assert a == b and a.name == "vitac#unit5"
    assert unit_record(a) != unit_record(c)
    # every varied parameter moves for some seed (none is stuck at the model's value)
    recs = [unit_record(draw_unit(vitac320, s)) for s in range(20)]
    base = unit_record(vitac320)
    for key in ("gel_thickness_mm", "gel_young_modulus_mpa", "marker_size_mm", "marker_pitch_mm", "read_sigma_dn",
                "blur_sigma_px", "background_gain", "shading_gain_dn", "marker_missing_fraction",
                "gel_dome_radius_mm"):
        assert any(r[key] != base[key] for r in recs), key
    assert any(r["lights"][0]["azimuth_deg"] != base["lights"][0]["azimuth_deg"] for r in recs)


def test_draws_stay_in_the_documented_ranges(vitac320):
    v = vitac320.unit_variation
    base = unit_record(vitac320)
    for seed in range(200):
        r = unit_record(draw_unit(vitac320, seed))
        for lt, lb in zip(r["lights"], base["lights"]):
            assert abs(lt["intensity"] / lb["intensity"] - 1) <= v.led_intensity_frac + 1e-9
            assert abs(lt["azimuth_deg"] - lb["azimuth_deg"]) <= v.led_azimuth_deg + 1e-9
            assert abs(lt["elevation_deg"] - lb["elevation_deg"]) <= v.led_elevation_deg + 1e-9
            assert all(0.0 <= c <= 1.0 for c in lt["color_rgb"])
        assert abs(r["gel_thickness_mm"] / base["gel_thickness_mm"] - 1) <= v.gel_thickness_frac + 1e-9
        assert abs(r["gel_young_modulus_mpa"] / base["gel_young_modulus_mpa"] - 1) <= v.gel_modulus_frac + 1e-9
        assert abs(r["gel_dome_radius_mm"] / base["gel_dome_radius_mm"] - 1) <= v.dome_radius_frac + 1e-9
        assert abs(r["marker_pitch_mm"] / base["marker_pitch_mm"] - 1) <= v.marker_pitch_frac + 1e-9
        assert 0 <= r["marker_jitter_mm"] - base["marker_jitter_mm"] <= v.marker_jitter_mm + 1e-12
        assert 0 <= r["marker_missing_fraction"] <= v.marker_missing_max + 1e-12
        assert 0 <= r["blur_sigma_px"] - base["blur_sigma_px"] <= v.blur_px + 1e-12
        assert all(abs(a - b) <= v.background_offset_dn + 1e-9
                   for a, b in zip(r["background_rgb_dn"], base["background_rgb_dn"]))
        # the exposure scales background and shading together
        assert r["background_gain"] == pytest.approx(r["shading_gain_dn"] / base["shading_gain_dn"])
        assert abs(r["background_gain"] - 1) <= v.exposure_frac + 1e-9


def test_no_section_or_zero_ranges_change_nothing(vitac320):
    r15 = dataclasses.replace(load_profile("gelsight-r15"), unit_variation=None)
    assert draw_unit(r15, 3) is r15
    zero = dataclasses.replace(vitac320, unit_variation=UnitVariationSpec())
    drawn = draw_unit(zero, 3)
    assert dataclasses.replace(drawn, name=zero.name) == zero
    with pytest.raises(GelsimError, match="integer"):
        draw_unit(vitac320, 1.5)
    assert set(variation_ranges(vitac320)) == {f.name for f in dataclasses.fields(UnitVariationSpec)}
    assert variation_ranges(r15) is None
    # a flat gel stays flat whatever its unit draws
    flat = dataclasses.replace(vitac320, gel=dataclasses.replace(vitac320.gel, dome_radius_mm=0.0))
    assert all(draw_unit(flat, s).gel.dome_radius_mm == 0.0 for s in range(5))


def test_a_unit_renders_differently_and_deterministically(vitac320):
    d = ball_depth(vitac320, (160.0, 120.0), 25.0, 4.0)
    base = Renderer(vitac320).render(d, None, noise=False).astype(float)
    u1 = Renderer(draw_unit(vitac320, 11)).render(d, None, noise=False).astype(float)
    u1b = Renderer(draw_unit(vitac320, 11)).render(d, None, noise=False).astype(float)
    np.testing.assert_array_equal(u1, u1b)
    assert np.abs(u1 - base).mean() > 0.5


def test_channel_gain_and_rotation_of_a_calibrated_table():
    """Turning the red LED by 30 degrees turns the red table's response by 30 degrees (the azimuth
    fit_lights reads off it), leaves the others; a channel gain of 2 doubles that channel."""
    prof = load_profile("gelsight-r15")
    t = load_table(table_path(prof))
    az0 = [lt.azimuth_deg for lt in fit_lights(t, prof.lights[0])]
    turned = adjust_channels(t, (1.0, 1.0, 1.0), (30.0, 0.0, 0.0))
    az1 = [lt.azimuth_deg for lt in fit_lights(turned, prof.lights[0])]
    assert (az1[0] - az0[0] + 180) % 360 - 180 == pytest.approx(30.0, abs=2.0)
    assert az1[1] == pytest.approx(az0[1], abs=0.2) and az1[2] == pytest.approx(az0[2], abs=0.2)
    k = int(np.argmin(t["shadow_rgb"][:, 0]))             # the red LED's shadow turns with it
    assert turned["shadow_dirs_deg"][k] == pytest.approx(t["shadow_dirs_deg"][k] + 30.0)
    doubled = adjust_channels(t, (1.0, 2.0, 1.0), (0.0, 0.0, 0.0))
    np.testing.assert_allclose(doubled["table"][..., 1::3], 2 * t["table"][..., 1::3])
    np.testing.assert_allclose(doubled["table"][..., 0::3], t["table"][..., 0::3])
    assert adjust_channels(t, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)) is t
    # through the renderer: a profile whose green is doubled shows twice the green change
    p = prof.with_resolution(320)
    d = ball_depth(p, (160.0, 120.0), 30.0, 4.0)
    a = Renderer(p).render_float(d) - Renderer(p).background_float()
    g2 = dataclasses.replace(p, shading=dataclasses.replace(p.shading, channel_gain=(1.0, 2.0, 1.0)))
    b = Renderer(g2).render_float(d) - Renderer(g2).background_float()
    np.testing.assert_allclose(b[..., 1], 2 * a[..., 1], atol=1e-3)
    np.testing.assert_allclose(b[..., 0], a[..., 0], atol=1e-3)


def test_missing_markers_and_background_gain(vitac320):
    n = len(marker_grid(vitac320))
    some = dataclasses.replace(vitac320, markers=dataclasses.replace(vitac320.markers, missing_fraction=0.1))
    kept = marker_grid(some, seed=4)
    assert len(kept) == n - round(0.1 * n)
    assert len(marker_grid(some, seed=4)) == len(kept) and np.array_equal(marker_grid(some, seed=4), kept)
    bright = dataclasses.replace(vitac320, background=dataclasses.replace(vitac320.background, gain=1.2))
    np.testing.assert_allclose(Renderer(bright).background_float(), 1.2 * Renderer(vitac320).background_float(),
                               rtol=1e-5)
    assert math.isclose(vitac320.background.gain, 1.0)
