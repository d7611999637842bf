"""Tests of gelsim.stream: the one-frame function, the frame record and the labels assembled from records."""
from __future__ import annotations

import numpy as np
import pytest

from gelsim import frame as frame_mod
from gelsim import stream
from gelsim.fidelity import get_fidelity
from gelsim.gel import press
from gelsim.markers import displace, rest_markers
from gelsim.optics import Renderer
from gelsim.scene import Sphere, field_heights
from gelsim.schema import LABELS
from gelsim.stream import FrameSetup, StageTimer, Touch, make_frame, sequence_labels


@pytest.fixture(scope="module")
def small(vitac):
    return vitac.with_resolution(160, 120)


def test_make_frame_is_press_markers_render(small):
    """The one-frame function is exactly the chain its callers ran by hand: press, displace, render."""
    fid = get_fidelity("fast")
    prot = field_heights(Sphere(6.0), small)
    renderer = Renderer(small, "fast", seed=4)
    setup = FrameSetup.make(small, fid, sensor_seed=4, renderer=renderer)
    touch = Touch(prot, force_n=1.5, shear_mm=(0.05, -0.02), twist_deg=0.5)
    timer = StageTimer()
    imprint, markers, rgb = make_frame(touch, setup, seed=11, timer=timer)
    assert set(timer.take()) == {"imprint", "markers", "optics"} and timer.seconds == {}
    ref = press(prot, small, fid, force_n=1.5)
    mk = displace(small, fid, ref, shear_mm=(0.05, -0.02), twist_deg=0.5, seed=4)
    assert imprint.depth_mm.tobytes() == ref.depth_mm.tobytes() and imprint.indentation_mm > 0
    assert markers.xy_px.tobytes() == mk.xy_px.tobytes()
    assert rgb.tobytes() == Renderer(small, "fast", seed=4).render(ref.depth_mm, mk, seed=11).tobytes()


def test_make_frame_without_touch_is_the_flat_gel(small):
    fid = get_fidelity("fast")
    renderer = Renderer(small, "fast", seed=2)
    imprint, markers, rgb = make_frame(None, FrameSetup.make(small, fid, sensor_seed=2, renderer=renderer),
                                       noise=False)
    flat = rest_markers(small, seed=2)
    assert imprint is None and markers.xy_px.tobytes() == flat.xy_px.tobytes()
    assert rgb.tobytes() == renderer.render(None, flat, noise=False).tobytes()
    # no markers asked for, no renderer: nothing but the imprint
    t = StageTimer()
    parts = make_frame(Touch(field_heights(Sphere(6.0), small), depth_mm=0.3), FrameSetup.make(small, fid, markers=False),
                       timer=t)
    assert parts.markers is None and parts.frame is None and parts.imprint.indentation_mm == pytest.approx(0.3)
    assert set(t.seconds) == {"imprint"}


def test_render_frame_runs_make_frame(small, monkeypatch):
    calls = []
    real = stream.make_frame
    monkeypatch.setattr(stream, "make_frame", lambda *a, **k: calls.append(a[0]) or real(*a, **k))
    rgb, info = frame_mod.render_frame(Sphere(5.0), small, "fast", force_n=1.0, seed=1)
    assert len(calls) == 1 and calls[0].force_n == 1.0 and rgb.shape == (120, 160, 3)
    assert info["imprint"]["indentation_mm"] > 0


def test_sequence_labels_stack_frames_and_keep_the_sequences_own():
    rest = np.arange(6, dtype=np.float32).reshape(3, 2)
    rows = [{"time_s": np.float64(i / 30), "in_contact": np.bool_(i > 0), "indentation_mm": np.float32(0.1 * i),
             "markers_xy_px": rest + i, "markers_rest_px": rest} for i in range(4)]
    lab = sequence_labels(rows)
    assert list(lab) == list(rows[0])
    assert lab["time_s"].dtype == np.float64 and lab["in_contact"].dtype == bool
    assert lab["indentation_mm"].dtype == np.float32 and lab["indentation_mm"].shape == (4,)
    assert lab["markers_xy_px"].shape == (4, 3, 2) and lab["markers_rest_px"].shape == (3, 2)
    assert stream.PER_FRAME_LABELS == {k.name for k in LABELS} - {"markers_rest_px"}


def test_stage_timer_laps_and_takes():
    ticks = iter([0.0, 1.0, 3.0, 3.5, 10.0, 10.25])
    t = StageTimer(lambda: next(ticks))
    t.lap("a")
    t.lap("b")
    t.lap("a")
    assert t.take() == {"a": 1.5, "b": 2.0} and t.seconds == {}
    t.restart()
    t.lap("c")
    assert t.seconds == {"c": 0.25}
