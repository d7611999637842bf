"""Tests of gelsim.stream: the frame pipeline (make_frames, make_frame), the frame record and the labels assembled
from records."""
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
from gelsim.nuisance.sequence import FrameNuisance
from gelsim.stream import FrameRequest, FrameSetup, StageTimer, Touch, make_frame, make_frames, sequence_labels


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
    made = make_frames([FrameRequest(touch, 11)], setup)
    imprint, markers, rgb = made.parts[0].imprint, made.parts[0].markers, made.parts[0].frame
    assert set(made.seconds) == {"imprint", "markers", "optics"}
    ref = press(prot, small, fid, force_n=1.5)
    mk = displace(small, fid, ref, shear_mm=(0.05, -0.02), twist_deg=0.5, seed=4)
    assert imprint.depth_mm.tobytes() == ref.depth_mm.tobytes() and imprint.indentation_mm > 0
    assert markers.xy_px.tobytes() == mk.xy_px.tobytes()
    assert rgb.tobytes() == Renderer(small, "fast", seed=4).render(ref.depth_mm, mk, seed=11).tobytes()


def test_make_frame_without_touch_is_the_flat_gel(small):
    fid = get_fidelity("fast")
    renderer = Renderer(small, "fast", seed=2)
    parts = make_frame(None, FrameSetup.make(small, fid, sensor_seed=2, renderer=renderer), noise=False)
    imprint, markers, rgb = parts.imprint, parts.markers, parts.frame
    flat = rest_markers(small, seed=2)
    assert imprint is None and markers.xy_px.tobytes() == flat.xy_px.tobytes()
    assert rgb.tobytes() == renderer.render(None, flat, noise=False).tobytes()
    # no markers asked for, no renderer: nothing but the imprint
    made = make_frames([FrameRequest(Touch(field_heights(Sphere(6.0), small), depth_mm=0.3))],
                       FrameSetup.make(small, fid, markers=False))
    parts = made.parts[0]
    assert parts.markers is None and parts.frame is None and parts.imprint.indentation_mm == pytest.approx(0.3)
    assert set(made.seconds) == {"imprint"}


def test_render_frame_runs_the_pipeline(small, monkeypatch):
    calls = []
    real = stream.make_frames
    monkeypatch.setattr(stream, "make_frames", lambda *a, **k: calls.append(a[0]) or real(*a, **k))
    rgb, info = frame_mod.render_frame(Sphere(5.0), small, "fast", force_n=1.0, seed=1)
    assert len(calls) == 1 and calls[0][0].touch.force_n == 1.0 and rgb.shape == (120, 160, 3)
    assert info["imprint"]["indentation_mm"] > 0


def test_a_batch_is_its_frames_one_by_one(small):
    """make_frames of several requests (a shared noise stream, a touch given twice) is each frame made alone."""
    fid = get_fidelity("fast")
    setup = FrameSetup.make(small, fid, sensor_seed=3, renderer=Renderer(small, "fast", seed=3), imprint_labels=True,
                            marker_labels=True)
    touch = Touch(field_heights(Sphere(6.0), small), force_n=1.2, twist_deg=0.4)
    other = Touch(field_heights(Sphere(4.0), small), force_n=0.8, shear_mm=(0.03, 0.0))
    rng = np.random.default_rng(5)
    made = make_frames([FrameRequest(touch, rng), FrameRequest(touch, rng), FrameRequest(None, rng),
                        FrameRequest(other, rng)], setup)
    rng = np.random.default_rng(5)
    for got, t in zip(made.parts, (touch, touch, None, other)):
        alone = make_frame(t, setup, seed=rng)
        assert got.frame.tobytes() == alone.frame.tobytes()
        assert list(got.labels) == list(alone.labels) and all(got.labels[k].tobytes() == alone.labels[k].tobytes()
                                                              for k in got.labels)
    assert made.parts[0].imprint is made.parts[1].imprint                  # the same touch again: pressed once
    assert np.isnan(made.parts[2].labels["contact_centroid_px"]).all() and made.parts[2].labels["indentation_mm"] == 0
    assert list(made.parts[0].labels) == ["indentation_mm", "contact_area_mm2", "contact_centroid_px",
                                          "contact_bbox_px", "markers_xy_px", "markers_rest_px"]


class Nuisance:
    """A sequence's nuisance for the test: a dent and gains from frame 1 on; it records how it was asked."""

    def __init__(self, shape):
        self.dent = np.zeros(shape, np.float32)
        self.dent[10:20, 30:40] = 0.05
        self.calls = []

    def frame(self, i, imprint, *, tilt_deg=(0.0, 0.0)):
        self.calls.append((i, None if imprint is None else imprint.indentation_mm, tuple(tilt_deg)))
        return None if i == 0 else FrameNuisance(self.dent, np.array([1.1, 1.0, 0.9]))


def test_the_pipeline_asks_each_frames_nuisance_and_renders_it_without_touching_the_labels(small):
    fid = get_fidelity("fast")
    renderer = Renderer(small, "fast", seed=1)
    setup = FrameSetup.make(small, fid, sensor_seed=1, renderer=renderer, imprint_labels=True)
    nuis = Nuisance(small.shape)
    touch = Touch(field_heights(Sphere(6.0), small), force_n=1.0)
    made = make_frames([FrameRequest(None, 7, nuisance=nuis, index=0, tilt_deg=(0.1, 0.2)),
                        FrameRequest(touch, 8, nuisance=nuis, index=1, tilt_deg=(0.3, 0.4))], setup)
    first, second = made.parts
    assert nuis.calls == [(0, None, (0.1, 0.2)), (1, second.imprint.indentation_mm, (0.3, 0.4))]
    assert first.nuisance is None and second.nuisance.dents_mm is nuis.dent and "nuisance" in made.seconds
    plain = make_frame(touch, setup, seed=8)
    assert second.imprint.depth_mm.tobytes() == plain.imprint.depth_mm.tobytes()        # the labels' imprint: no dent
    assert all(second.labels[k].tobytes() == plain.labels[k].tobytes() for k in plain.labels)
    want = renderer.render(plain.imprint.depth_mm + nuis.dent, plain.markers, seed=8, gains=[1.1, 1.0, 0.9])
    assert second.frame.tobytes() == want.tobytes() != plain.frame.tobytes()
    assert second.optics.depth_mm.tobytes() == (plain.imprint.depth_mm + nuis.dent).tobytes()     # the one object
    assert second.optics.seed == 8 and list(second.optics.gains) == [1.1, 1.0, 0.9]


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
