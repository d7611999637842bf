"""gelsim.sequence.render_sequences on the torch engine: sequences in step, the whole frame on the device (patch
sampling, imprint, labels, markers, optics), give what gelsim.sequence.render_sequence gives (the numpy engine) with
the torch optics: labels within the device imprint's and markers' tolerances, uint8 frames within the torch
backend's (TOL_MAX_UINT8_DN per pixel); on the numpy engine, sequences in step are the same bytes as one by one."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.engines import TorchEngine  # noqa: E402
from gelsim.gel.twoscale_torch import TOLERANCE  # noqa: E402
from gelsim.markers_torch import TOL_PX  # noqa: E402
from gelsim.optics import Renderer  # noqa: E402
from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, BatchRenderer  # noqa: E402
from gelsim.sequence import SequenceOptions, render_sequence, render_sequences  # noqa: E402
from gelsim.sinks import DeviceFrames, KeepFrames, drain, drain_each  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]


def _in_step(prep, prof, fid, device, **kw):
    """The sequences in step on the torch engine on ``device``: each sequence's labels, and its frames."""
    keep = [KeepFrames() for _ in prep]
    renderer = BatchRenderer(Renderer(prof, "torch", seed=0, device=device))
    out = drain_each(render_sequences([p.again() for p in prep], prof, fid, engine=TorchEngine(device, **kw),
                                      options=SequenceOptions(renderer=renderer)), [[k] for k in keep])
    return [labels for labels, _ in out], [k.frames for k in keep]


@pytest.mark.parametrize("device", DEVICES)
def test_sequences_in_step_equal_render_sequence(two_sequences, device):
    prof, fid, specs, prep = two_sequences
    labels, got = _in_step(prep, prof, fid, device)
    assert [len(f) for f in got] == [m.num_frames for _, m, _ in specs]
    br = BatchRenderer(Renderer(prof, "torch", seed=0, device="cpu"))
    for i, (obj, motion, seed) in enumerate(specs):
        keep = KeepFrames()
        options = SequenceOptions(outputs={"imprint", "markers"}, contact=prep[i].contact, patch=prep[i].patch)
        ref, _ = drain(render_sequence(obj, motion, prof, fid, seed=seed, options=options),
                       [DeviceFrames(br, 8, [keep])])
        frames = keep.frames
        lab = labels[i]
        assert list(lab) == list(ref)                          # the schema's keys, in its order
        assert np.abs(lab["indentation_mm"] - ref["indentation_mm"]).max() <= TOLERANCE["indentation_mm"]
        area = ref["contact_area_mm2"]
        assert np.all(np.abs(lab["contact_area_mm2"] - area) <= TOLERANCE["area_rel"] * area + 1e-9)
        touched = np.isfinite(ref["contact_centroid_px"][:, 0])
        assert np.array_equal(np.isfinite(lab["contact_centroid_px"][:, 0]), touched) and touched.sum() >= 4
        assert np.abs(lab["contact_centroid_px"][touched] - ref["contact_centroid_px"][touched]).max() \
            <= TOLERANCE["centroid_px"]
        assert np.abs(lab["markers_xy_px"] - ref["markers_xy_px"]).max() <= TOL_PX + 1e-4
        for k in ("normal_force_n", "in_contact"):
            assert np.array_equal(lab[k], ref[k])
        diff = np.stack([np.abs(got[i][t].astype(int) - frames[t].astype(int)) for t in range(len(frames))])
        assert diff.max() <= TOL_MAX_UINT8_DN, diff.max()


def test_the_optics_batch_changes_no_byte(two_sequences):
    prof, fid, _, prep = two_sequences
    (la, fa), (lb, fb) = _in_step(prep, prof, fid, "cpu"), _in_step(prep, prof, fid, "cpu", optics_batch=1)
    assert all(a.tobytes() == b.tobytes() for x, y in zip(fa, fb) for a, b in zip(x, y))
    assert all(a[k].tobytes() == b[k].tobytes() for a, b in zip(la, lb) for k in a)


def test_sequences_in_step_on_the_numpy_engine_are_each_sequences_own_bytes(two_sequences):
    """The driver is one for both engines: on the numpy engine, a sequence made in step with others is the same
    bytes as made alone (render_sequence)."""
    prof, fid, specs, prep = two_sequences
    keep = [KeepFrames() for _ in prep]
    out = drain_each(render_sequences([p.again() for p in prep], prof, fid), [[k] for k in keep])
    for i, (obj, motion, seed) in enumerate(specs):
        alone = KeepFrames()
        ref, _ = drain(render_sequence(obj, motion, prof, fid, seed=seed,
                                       options=SequenceOptions(contact=prep[i].contact, patch=prep[i].patch)), [alone])
        assert all(out[i][0][k].tobytes() == ref[k].tobytes() for k in ref)
        assert all(a.tobytes() == b.tobytes() for a, b in zip(keep[i].frames, alone.frames))


def test_no_tensor_is_made_off_the_batchs_device(two_sequences):
    """Every tensor the device path makes is on its inputs' device: with torch's default device set to "meta", a
    tensor made without naming one would be a meta tensor, and the first operation mixing it with the batch's
    (CPU) tensors would fail. (What would break on a GPU; checked here without one.)"""
    prof, fid, specs, prep = two_sequences
    renderer = BatchRenderer(Renderer(prof, "torch", seed=0, device="cpu"))
    runs = [p.again() for p in prep]
    engine = TorchEngine("cpu")
    torch.set_default_device("meta")
    try:
        n = sum(1 for _ in render_sequences(runs, prof, fid, options=SequenceOptions(renderer=renderer), engine=engine))
    finally:
        torch.set_default_device(None)
    assert n == sum(m.num_frames for _, m, _ in specs)


def test_patches_made_on_the_device_move_the_labels_within_tolerance(two_sequences):
    """Sequences whose patches the torch engine finishes itself (SequenceRun(device_patch=True): a rotated fabric's
    resampling and the crown envelope on the device, as --stages all makes them) give the labels and frames of
    those given host-made patches, within the device imprint's, markers' and optics' tolerances."""
    from gelsim.sequence import SequenceRun

    prof, fid, specs, prep = two_sequences
    runs = [SequenceRun(obj, motion, prof, fid, seed=seed, options=SequenceOptions(contact=p.contact),
                        device_patch=True) for (obj, motion, seed), p in zip(specs, prep)]
    assert all(r.envelope is None and r.envelope_px for r in runs)
    keep = [KeepFrames() for _ in runs]
    renderer = BatchRenderer(Renderer(prof, "torch", seed=0, device="cpu"))
    out = drain_each(render_sequences(runs, prof, fid, engine=TorchEngine("cpu"),
                                      options=SequenceOptions(renderer=renderer)), [[k] for k in keep])
    ref_labels, ref_frames = _in_step(prep, prof, fid, "cpu")
    for (lab, _), ref, got, frames in zip(out, ref_labels, keep, ref_frames):
        assert np.abs(lab["indentation_mm"] - ref["indentation_mm"]).max() <= TOLERANCE["indentation_mm"]
        area = ref["contact_area_mm2"]
        assert np.all(np.abs(lab["contact_area_mm2"] - area) <= TOLERANCE["area_rel"] * area + 1e-9)
        assert np.abs(lab["markers_xy_px"] - ref["markers_xy_px"]).max() <= TOL_PX + 1e-4
        diff = max(np.abs(a.astype(int) - b.astype(int)).max() for a, b in zip(got.frames, frames))
        assert diff <= TOL_MAX_UINT8_DN, diff
