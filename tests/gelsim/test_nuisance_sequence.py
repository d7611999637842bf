"""The nuisance stages in the frame stream (gelsim.nuisance.sequence, composite.CameraGains, render_sequence,
gelsim generate --nuisance): off gives today's bytes, labels never change, every backend, batch and worker
count renders the same inputs, bad values are refused in one line."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from gelsim.dataset import GenerateConfig, generate
from gelsim.errors import GelsimError
from gelsim.fabrics import load_catalog
from gelsim.fidelity import get_fidelity
from gelsim.motion import sample_motion
from gelsim.nuisance import load_nuisance
from gelsim.nuisance.sequence import SequenceNuisance, camera_gains
from gelsim.optics import Renderer
from gelsim.optics.composite import check_gains
from gelsim.optics.ops.readout import to_uint8
from gelsim.sequence import SequenceOptions, render_sequence
from gelsim.sinks import DeviceFrames, KeepFrames, drain
from gelsim.stream import sequence_labels

HAIRY = 73            # mohair plush, catalog hairiness 0.5
MODEL = load_nuisance()


@pytest.fixture(scope="module")
def small(vitac):
    return vitac.with_resolution(96, 72)


def _run(profile, level: str, *, fabric=HAIRY, precontact=(2, 2), seed=3, **opts):
    motion = sample_motion("press", seed, frames=(8, 8), precontact=precontact)
    options = SequenceOptions(nuisance=MODEL.level(level) if level != "none" else {}, **opts)
    records = list(render_sequence(load_catalog()[fabric], motion, profile, get_fidelity("fast"), seed=seed,
                                   options=options))
    return motion, records


def test_camera_gains_are_the_controllers_on_a_flat_scene():
    st = MODEL.stages
    g = camera_gains(5, MODEL.level("camera"), st, 30)
    assert g.shape == (30, 3)
    # frame 0 at the drawn start for delay_frames frames, then settled to within the stable region
    d = st.exposure.delay_frames
    luma = g @ np.array([0.299, 0.587, 0.114])
    assert np.all(luma[:d] < 0.7) and np.allclose(g[:d, 1], g[0, 1])
    assert np.all(np.abs(g[d + 1:, 1] - 1.0) <= st.exposure.stable_region)
    assert camera_gains(5, {}, st, 30) is None and camera_gains(5, {"fibres": 1.0}, st, 30) is None
    np.testing.assert_array_equal(g, camera_gains(5, MODEL.level("camera"), st, 30))
    assert not np.array_equal(g, camera_gains(6, MODEL.level("camera"), st, 30))


def test_the_camera_stage_multiplies_before_the_noise_and_does_nothing_without_gains(small):
    r = Renderer(small, seed=1)
    g = np.array([0.5, 0.8, 1.1])
    want = r.render_float(None) * g.astype(np.float32)
    np.testing.assert_array_equal(r.render(None, seed=4, noise=False, gains=g), to_uint8(want))
    plain = r.render(None, seed=4)
    np.testing.assert_array_equal(r.render(None, seed=4, gains=None), plain)
    np.testing.assert_array_equal(r.render(None, seed=4, gains=np.ones(3)), plain)
    for bad in ([1.0, 2.0], [1.0, np.nan, 1.0], [-1.0, 1.0, 1.0]):
        with pytest.raises(GelsimError, match="three finite numbers"):
            check_gains(bad)


def test_the_camera_stage_torch_kernel_gives_the_numpy_kernels_frames(small):
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, BatchRenderer

    pytest.importorskip("torch")
    fast, br = Renderer(small, seed=1), BatchRenderer(Renderer(small, "torch", seed=1))
    gains = [np.array([0.3, 0.3, 0.35]), None, np.array([1.1, 1.0, 0.9])]
    got = br.render([None] * 3, seeds=[1, 2, 3], gains=gains)
    for f, g, s in zip(got, gains, (1, 2, 3)):
        want = fast.render(None, seed=s, gains=g)
        assert np.abs(f.astype(np.int16) - want.astype(np.int16)).max() <= TOL_MAX_UINT8_DN
    with pytest.raises(GelsimError, match="one \\(or None\\) per frame"):
        br.render([None] * 3, seeds=[1, 2, 3], gains=gains[:2])


def test_fibres_dent_a_hairy_fabrics_frames_before_contact_and_never_the_labels(small):
    motion, plain = _run(small, "none")
    _, hand = _run(small, "handheld")
    P = motion.precontact_frames
    for a, b in zip(plain, hand):
        assert all(np.asarray(a.labels[k]).tobytes() == np.asarray(b.labels[k]).tobytes() for k in a.labels)
        assert b.nuisance is not None and b.nuisance.gains is not None
    dented = [r.index for r in hand if r.nuisance.dents_mm is not None]
    assert dented and dented[0] <= P, dented          # fibres reach the gel before the fabric or with it
    assert plain[0].nuisance is None
    # the frame before contact differs from the plain one by more than the camera's noise
    diff = np.abs(hand[0].frame.astype(np.int16) - plain[0].frame.astype(np.int16))
    assert diff.mean() > 3 * small.noise.read_sigma_dn


def test_no_fibres_on_a_fabric_without_hairs(small):
    silk = 13                                           # hairiness 0
    assert load_catalog()[silk].hairiness == 0
    _, recs = _run(small, "handheld", fabric=silk)
    assert all(r.nuisance.dents_mm is None for r in recs)


def test_sequence_nuisance_refuses_unknown_stages(small):
    motion = sample_motion("press", 1, frames=(8, 8), precontact=(1, 1))
    with pytest.raises(GelsimError, match="unknown nuisance stage 'flicker'"):
        SequenceNuisance({"flicker": 1.0}, MODEL.stages, 1, 0.5, small, motion)


def test_device_frames_render_the_nuisance_as_the_sequence_would(small):
    """The torch backend renders the same dents and gains: frames within its tolerance of the fast
    backend's, the same bytes for any batch."""
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, BatchRenderer

    pytest.importorskip("torch")
    motion, fast = _run(small, "handheld")
    out = {}
    for batch in (1, 5):
        frames = KeepFrames()
        with DeviceFrames(BatchRenderer(Renderer(small, "torch")), batch, [frames]) as dev:
            labels, _ = drain(render_sequence(load_catalog()[HAIRY], motion, small, get_fidelity("fast"), seed=3,
                                              options=SequenceOptions(outputs={"imprint", "markers"},
                                                                      nuisance=MODEL.level("handheld"))), [dev])
        out[batch] = [f.tobytes() for f in frames.frames]
        want = sequence_labels([r.labels for r in fast])
        assert all(labels[k].tobytes() == want[k].tobytes() for k in labels)
        for f, r in zip(frames.frames, fast):
            assert np.abs(f.astype(np.int16) - r.frame.astype(np.int16)).max() <= TOL_MAX_UINT8_DN
    assert out[1] == out[5]


def _digest(root: Path, what: str) -> str:
    h = hashlib.sha256()
    for p in sorted((root / what).rglob("*")):
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def test_generate_nuisance_levels_keep_the_labels_and_any_worker_count_the_bytes(tmp_path):
    base = dict(fabrics=2, sequences_per_fabric=2, frames=(8, 8), precontact=(1, 1), resolution=(64, 48),
                fidelity="fast")
    none = generate(GenerateConfig(**base), tmp_path / "none", workers=1, previews=False)
    hand = generate(GenerateConfig(**base, nuisance="handheld"), tmp_path / "h1", workers=1, previews=False)
    generate(GenerateConfig(**base, nuisance="handheld"), tmp_path / "h2", workers=2, previews=False)
    assert none["options"]["nuisance"] == "none" and hand["options"]["nuisance"] == "handheld"
    assert _digest(tmp_path / "none", "labels") == _digest(tmp_path / "h1", "labels")
    assert _digest(tmp_path / "none", "videos") != _digest(tmp_path / "h1", "videos")
    assert _digest(tmp_path / "h1", "videos") == _digest(tmp_path / "h2", "videos")
    with pytest.raises(GelsimError, match="unknown nuisance level 'loud'"):
        generate(GenerateConfig(**base, nuisance="loud"), tmp_path / "bad", workers=1, previews=False)
    assert not (tmp_path / "bad").exists()
