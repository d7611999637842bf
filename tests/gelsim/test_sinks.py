"""Tests of gelsim.sinks: the consumers of a sequence's frame records, and drain, which feeds them."""
from __future__ import annotations

import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.fabrics import load_catalog
from gelsim.fidelity import get_fidelity
from gelsim.gel import Imprint
from gelsim.motion import sample_motion
from gelsim.optics import OpticsInput, Renderer
from gelsim.sequence import SequenceOptions, render_sequence
from gelsim.sinks import DeviceFrames, ImprintCapture, KeepFrames, VideoSink, drain
from gelsim.stream import FrameRecord, noise_generator, sequence_labels


def _dent(profile, depth_mm: float) -> np.ndarray:
    """A round dent ``depth_mm`` deep in the middle of the frame, float32 (H, W) mm."""
    h, w = profile.shape
    yy, xx = np.mgrid[:h, :w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (0.2 * min(h, w)) ** 2
    return np.clip(depth_mm * (1 - r2), 0, None).astype(np.float32)


def _record(i: int, depth: np.ndarray | None, seed=0) -> FrameRecord:
    imprint = None if depth is None else Imprint(depth, depth > 0, float(depth.max()), 1.0, 1.0, False)
    return FrameRecord(i, None, imprint, None, None, {}, {}, optics=OpticsInput(depth, seed=seed))


@pytest.fixture(scope="module")
def small_run(vitac):
    """A short press of a coarse knit at 96x72 (fast level): the records and the drained labels."""
    profile = vitac.with_resolution(96, 72)
    motion = sample_motion("press", 3, frames=(6, 6), precontact=(2, 2))
    fid = get_fidelity("fast")
    records = list(render_sequence(load_catalog()[57], motion, profile, fid, seed=3))
    return profile, motion, fid, records


def test_drain_assembles_the_labels_and_times_of_the_records(small_run, tmp_path):
    profile, motion, fid, records = small_run
    video, frames, capture = VideoSink(tmp_path / "v.mkv", fmt="ffv1", fps=30.0), KeepFrames(), ImprintCapture()
    labels, seconds = drain(iter(records), [video, frames, capture])
    assert (tmp_path / "v.mkv").is_file() and seconds["encode"] > 0
    assert set(seconds) >= {"fabric", "physics", "imprint", "markers", "optics", "encode"}
    assert seconds["optics"] == pytest.approx(sum(r.seconds.get("optics", 0.0) for r in records))
    whole = sequence_labels([r.labels for r in records])
    assert list(labels) == list(whole) and all(np.array_equal(labels[k], whole[k], equal_nan=True) for k in labels)
    assert labels["indentation_mm"].shape == (6,) and labels["markers_rest_px"].ndim == 2
    assert labels["markers_xy_px"].shape == (6, *labels["markers_rest_px"].shape)
    assert all(a is r.frame for a, r in zip(frames.frames, records))
    pressed = [r.index for r in records if r.imprint is not None]
    assert sorted(capture.imprints) == pressed and len(pressed) >= 3
    assert not any(labels["in_contact"][: motion.precontact_frames])


def test_video_sink_needs_frames_and_leaves_nothing_on_error(small_run, tmp_path):
    _, _, _, records = small_run
    path = tmp_path / "v.mp4"
    with pytest.raises(GelsimError, match="was not rendered"):
        with VideoSink(path, fmt="h264", fps=30.0) as v:
            v.write(records[0])
            v.write(_record(1, None))
    assert list(tmp_path.iterdir()) == []


def test_device_frames_same_frames_in_order_for_any_batch(vitac320):
    from gelsim.optics.torch_backend import BatchRenderer

    pytest.importorskip("torch")
    lut = vitac320
    r = BatchRenderer(Renderer(lut, "torch", seed=0))
    depths = [None, _dent(lut, 0.2), _dent(lut, 0.4), None, _dent(lut, 0.05)]
    fast = Renderer(lut, "fast", seed=0)
    out = {}
    for batch in (1, 3, 8):
        frames, rng = KeepFrames(), noise_generator(9)
        with DeviceFrames(r, batch, [frames]) as dev:
            for i, d in enumerate(depths):
                dev.write(_record(i, d, rng))
        out[batch] = [f.tobytes() for f in frames.frames]
        assert dev.seconds["optics"] > 0
        # the noise was drawn from the sequence's generator as the numpy renderer draws it
        ref_rng = noise_generator(9)
        for d in depths:
            fast.render(d, None, seed=ref_rng)
        assert rng.integers(1 << 30) == ref_rng.integers(1 << 30)
    assert len(out[1]) == len(depths) and out[1] == out[3] == out[8]


def test_device_frames_reraises_the_writers_error(vitac320):
    from gelsim.optics.torch_backend import BatchRenderer

    pytest.importorskip("torch")
    r = BatchRenderer(Renderer(vitac320, "torch", seed=0))

    class Full:
        seconds: dict = {}

        def write(self, record):
            raise OSError("disk full")

        def close(self):
            pass

    with pytest.raises(OSError, match="disk full"):
        with DeviceFrames(r, 2, [Full()]) as dev:
            for i in range(5):
                dev.write(_record(i, None))
    with pytest.raises(GelsimError, match="--batch"):
        DeviceFrames(r, 0, [Full()])


def test_device_frames_render_what_the_sequence_would(small_run):
    """A sequence run without frames into DeviceFrames gives the labels byte for byte and the frames of the
    sequence rendered by the fast backend within the torch backend's tolerance."""
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, BatchRenderer

    pytest.importorskip("torch")
    profile, motion, fid, records = small_run
    frames = KeepFrames()
    with DeviceFrames(BatchRenderer(Renderer(profile, "torch")), 4, [frames]) as dev:
        labels, _ = drain(render_sequence(load_catalog()[57], motion, profile, fid, seed=3,
                                          options=SequenceOptions(outputs={"imprint", "markers"})), [dev])
    fast = sequence_labels([r.labels for r in records])
    assert list(labels) == list(fast) and all(labels[k].tobytes() == fast[k].tobytes() for k in labels)
    assert len(frames.frames) == len(records)
    for f, r in zip(frames.frames, records):
        assert np.abs(f.astype(np.int16) - r.frame.astype(np.int16)).max() <= TOL_MAX_UINT8_DN
