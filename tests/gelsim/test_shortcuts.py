"""Shortcuts of gelsim.sequence.render_sequence: each skips work and keeps the result.

Tolerances (stated in gelsim/sequence.py): frames within 1 DN of the full computation
(a quantisation step: sub-DN float differences may round either way), markers within
2 * NEGLIGIBLE_PX, pyramid indentation and contact area within 1% on these fabric presses
(up to 3% on a sphere at coarse grids: gel.py's touched window, see the xfail below), elastic
depth within 2% of the peak.
"""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from gelsim import engines, sequence
from gelsim.contact import simulate
from gelsim.errors import GelsimError
from gelsim.fabrics import load_catalog
from gelsim.fidelity import get_fidelity
from gelsim.motion import sample_motion
from gelsim.scene import FabricObject, physics_surface
from gelsim.sensor import load_profile
from gelsim.sequence import NEGLIGIBLE_PX, SequenceOptions, render_sequence
from gelsim.sinks import KeepFrames, drain

T, PRE = 8, 3


@pytest.fixture(scope="module")
def setup():
    profile = load_profile("vitac").with_resolution(160, 120)
    fid = get_fidelity("balanced")
    fabric = load_catalog()[1]
    motions, contacts = {}, {}
    for action in ("press", "twist"):
        m = sample_motion(action, 7, frames=(T, T), precontact=(PRE, PRE))
        surf = physics_surface(FabricObject(fabric), m, profile, seed=7)
        motions[action] = m
        contacts[action] = simulate(m, surf, profile, fid)
    return profile, fid, fabric, motions, contacts


def run(setup, action="press", fid=None, **kw):
    profile, base_fid, fabric, motions, contacts = setup
    frames = KeepFrames()
    labels, _ = drain(render_sequence(fabric, motions[action], profile, fid or base_fid, seed=7,
                                      options=SequenceOptions(contact=contacts[action], **kw)), [frames])
    return frames.frames, SimpleNamespace(labels=labels)


@pytest.mark.parametrize("action", ["press", "twist"])
def test_shortcuts_match_full_computation(setup, action):
    fast_frames, fast = run(setup, action)
    full_frames, full = run(setup, action, shortcuts=False)
    assert len(fast_frames) == len(full_frames) == T
    diff = max(int(np.abs(a.astype(np.int16) - b.astype(np.int16)).max()) for a, b in zip(fast_frames, full_frames))
    assert diff <= 1
    assert np.abs(fast.labels["markers_xy_px"] - full.labels["markers_xy_px"]).max() <= 2 * NEGLIGIBLE_PX
    np.testing.assert_allclose(fast.labels["indentation_mm"], full.labels["indentation_mm"], rtol=0.01, atol=1e-6)
    np.testing.assert_allclose(fast.labels["contact_area_mm2"], full.labels["contact_area_mm2"], rtol=0.01,
                               atol=1e-6)
    # the sequence did press: the comparison is not between two flat gels
    assert fast.labels["indentation_mm"].max() > 0.01


def test_precontact_frames_skip_imprint_and_markers(setup, monkeypatch):
    calls = {"press": 0, "displace": 0}
    real_press, real_displace = engines.press, engines.displace

    def counting_press(*a, **k):
        calls["press"] += 1
        return real_press(*a, **k)

    def counting_displace(*a, **k):
        calls["displace"] += 1
        return real_displace(*a, **k)

    monkeypatch.setattr(engines, "press", counting_press)
    monkeypatch.setattr(engines, "displace", counting_displace)
    _, out = run(setup)
    touching = int(np.count_nonzero(out.labels["in_contact"] & (out.labels["normal_force_n"] > 0)))
    assert 0 < touching < T
    assert calls == {"press": touching, "displace": touching}
    calls.update(press=0, displace=0)
    run(setup, shortcuts=False)
    assert calls == {"press": T, "displace": T}


def test_press_drops_negligible_twist_only(setup, monkeypatch):
    seen = []
    real = engines.displace

    def spy(*a, **k):
        seen.append((k["shear_mm"], k["twist_deg"]))
        return real(*a, **k)

    monkeypatch.setattr(engines, "displace", spy)
    profile, *_, contacts = setup
    run(setup, "press")
    c = contacts["press"]
    touching = np.flatnonzero(c.in_contact & (c.normal_force_n > 0))
    assert len(seen) == len(touching)
    skipped = 0
    for (shear, twist), i in zip(seen, touching):
        lever_px = abs(np.radians(c.twist_deg[i])) * np.hypot(*profile.shape)
        if lever_px < NEGLIGIBLE_PX:
            assert twist == 0.0
            skipped += 1
        else:
            assert twist == pytest.approx(float(c.twist_deg[i]))
        # the hand's tremor shears a press by tens of um: a visible fraction of a pixel, kept
        assert shear == pytest.approx(tuple(float(v) for v in c.shear_mm[i]))
    assert skipped > 0


def test_negligible_thresholds():
    profile = load_profile("vitac").with_resolution(160, 120)
    mm = profile.image.mm_per_px
    assert sequence.negligible_px((0.001 * mm, 0.0), 0.0, profile) == (True, True)
    assert sequence.negligible_px((0.1 * mm, 0.0), 0.0, profile) == (False, True)
    assert sequence.negligible_px((0.0, 0.0), 0.01, profile) == (True, False)


def test_twist_sequence_keeps_its_twist(setup, monkeypatch):
    seen = []
    real = engines.displace
    monkeypatch.setattr(engines, "displace", lambda *a, **k: seen.append(k["twist_deg"]) or real(*a, **k))
    run(setup, "twist")
    assert max(abs(t) for t in seen) > 0.1


def test_outputs_nobody_asked_for_are_not_computed(setup, monkeypatch):
    _, full = run(setup)
    called = []
    monkeypatch.setattr(engines, "press", lambda *a, **k: called.append("press"))
    monkeypatch.setattr(engines.NumpyEngine, "renderer", lambda *a, **k: called.append("renderer"))
    monkeypatch.setattr(engines.NumpyEngine, "render", lambda *a, **k: called.append("render"))
    frames, out = run(setup, outputs=())
    assert frames == [None] * T and called == []
    assert "indentation_mm" not in out.labels and "markers_xy_px" not in out.labels
    for k in ("normal_force_n", "shear_mm", "in_contact", "position_mm"):
        np.testing.assert_array_equal(out.labels[k], full.labels[k])


def test_imprint_only_output(setup, monkeypatch):
    _, full = run(setup)
    monkeypatch.setattr(engines, "displace", lambda *a, **k: pytest.fail("markers computed"))
    frames, out = run(setup, outputs=("imprint",))
    assert all(f is None for f in frames)
    np.testing.assert_array_equal(out.labels["indentation_mm"], full.labels["indentation_mm"])
    assert "markers_xy_px" not in out.labels


def test_elastic_touched_window_within_tolerance(setup):
    profile, fid, *_ = setup
    el = dataclasses.replace(fid, imprint_model="elastic")
    a_frames, a = run(setup, fid=el)
    b_frames, b = run(setup, fid=el, shortcuts=False)
    peak = float(a.labels["indentation_mm"].max())
    assert peak > 0.01
    np.testing.assert_allclose(a.labels["indentation_mm"], b.labels["indentation_mm"], atol=0.02 * peak)
    assert np.abs(a.labels["markers_xy_px"] - b.labels["markers_xy_px"]).max() < 0.1


def test_bad_outputs_and_missing_object(setup):
    profile, fid, fabric, motions, contacts = setup
    with pytest.raises(GelsimError, match="unknown outputs"):
        list(render_sequence(fabric, motions["press"], profile, fid, seed=0, options=SequenceOptions(outputs=("video",))))
    with pytest.raises(GelsimError, match="not something the sensor can touch"):
        list(render_sequence(None, motions["press"], profile, fid, seed=0))
    short = dataclasses.replace(motions["press"], num_frames=T + 1)
    with pytest.raises(GelsimError, match="contact has"):
        list(render_sequence(fabric, short, profile, fid, seed=0, options=SequenceOptions(contact=contacts["press"])))


def test_twoscale_touched_window_equals_full():
    # The two-scale model solves on the same grid either way; only its output window differs.
    from gelsim import indenters
    from gelsim.gel import press

    for w in (96, 160, 320):
        p = load_profile("vitac").with_resolution(w)
        prot = indenters.sphere(10.0, p)
        a = press(prot, p, get_fidelity("balanced"), force_n=0.5)
        b = press(prot, p, get_fidelity("balanced"), force_n=0.5, window="full")
        assert a.indentation_mm == pytest.approx(b.indentation_mm, rel=1e-6)
        assert a.contact_area_mm2 == pytest.approx(b.contact_area_mm2, rel=1e-6)
        assert np.abs(a.depth_mm - b.depth_mm).max() <= 0.01 * b.indentation_mm


@pytest.mark.xfail(strict=True, reason="the pyramid model's press(window='touched') differs from window='full' on "
                                       "96x72 and 160x120 work grids: 10 mm sphere, 0.5 N, vitac at 160x120: "
                                       "indentation 0.9% off, 3% at 96x72; equal at 320x240 and 640x480")
def test_pyramid_touched_window_equals_full():
    from gelsim import indenters
    from gelsim.gel import press

    pyramid = dataclasses.replace(get_fidelity("balanced"), imprint_model="pyramid")
    for w in (96, 160):
        p = load_profile("vitac").with_resolution(w)
        p = dataclasses.replace(p, gel=dataclasses.replace(p.gel, dome_radius_mm=0.0))
        prot = indenters.sphere(10.0, p)
        a = press(prot, p, pyramid, force_n=0.5)
        b = press(prot, p, pyramid, force_n=0.5, window="full")
        assert a.indentation_mm == pytest.approx(b.indentation_mm, rel=1e-3)
