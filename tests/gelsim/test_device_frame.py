"""gelsim.device.frame: the whole frame on the device (patch sampling, imprint, labels, markers, optics) gives what
gelsim.sequence.render_sequence gives with the torch optics: labels within the device imprint's and markers'
tolerances, uint8 frames within the torch backend's (TOL_MAX_UINT8_DN per pixel)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.device.frame import prepare_sequence, render_sequences  # noqa: E402
from gelsim.gel.twoscale_torch import TOLERANCE  # noqa: E402
from gelsim.markers_torch import TOL_PX  # noqa: E402
from gelsim.fabrics import load_catalog  # noqa: E402
from gelsim.fidelity import get_fidelity  # noqa: E402
from gelsim.motion import sample_motion  # noqa: E402
from gelsim.optics import Renderer  # noqa: E402
from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, BatchRenderer  # noqa: E402
from gelsim.sequence import SequenceOptions, render_sequence  # noqa: E402
from gelsim.sinks import DeviceFrames, KeepFrames, drain  # noqa: E402
from gelsim.stream import noise_generator  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]


@pytest.fixture(scope="module")
def setup():
    from gelsim.sensor import load_profile

    prof = load_profile("vitac").with_resolution(160, 120)
    fid = get_fidelity("balanced")
    cat = load_catalog()
    specs = [(cat[1], sample_motion("twist", 5, frames=(7, 7), precontact=(2, 2)), 5),
             (cat[64], sample_motion("slip", 6, frames=(8, 8), precontact=(1, 1)), 6)]
    prep = [prepare_sequence(o, m, prof, fid, seed=s) for o, m, s in specs]
    return prof, fid, specs, prep


@pytest.mark.parametrize("device", DEVICES)
def test_sequences_in_step_equal_render_sequence(setup, device):
    prof, fid, specs, prep = setup
    got: dict = {}

    def sink(frames, which):
        for k, key in enumerate(which):
            got[key] = frames[k]

    out = render_sequences(prep, prof, fid, BatchRenderer(Renderer(prof, "torch", seed=0, device=device)), sink=sink)
    assert out["frames"] == sum(m.num_frames for _, m, _ in specs)
    br = BatchRenderer(Renderer(prof, "torch", seed=0, device="cpu"))
    for i, (obj, motion, seed) in enumerate(specs):
        keep = KeepFrames()
        options = SequenceOptions(outputs={"imprint", "markers"}, contact=prep[i].contact, patch=prep[i].patch)
        ref, _ = drain(render_sequence(obj, motion, prof, fid, seed=seed, options=options),
                       [DeviceFrames(br, 8, noise_generator(seed), [keep])])
        frames = keep.frames
        lab = out["labels"][i]
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
        diff = np.stack([np.abs(got[(i, t)].astype(int) - frames[t].astype(int)) for t in range(len(frames))])
        assert diff.max() <= TOL_MAX_UINT8_DN, diff.max()


def test_no_tensor_is_made_off_the_batchs_device(setup):
    """Every tensor the device path makes is on its inputs' device: with torch's default device set to "meta", a
    tensor made without naming one would be a meta tensor, and the first operation mixing it with the batch's
    (CPU) tensors would fail. (What would break on a GPU; checked here without one.)"""
    prof, fid, specs, prep = setup
    renderer = BatchRenderer(Renderer(prof, "torch", seed=0, device="cpu"))
    torch.set_default_device("meta")
    try:
        out = render_sequences(prep, prof, fid, renderer)
    finally:
        torch.set_default_device(None)
    assert out["frames"] == sum(m.num_frames for _, m, _ in specs)
