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
from gelsim.nuisance.record import RECORD_KEYS, record_problems
from gelsim.nuisance.sequence import SequenceNuisance
from gelsim.optics import Renderer
from gelsim.optics.composite import check_gains
from gelsim.optics.ops.readout import to_uint8
from gelsim.sequence import SequenceOptions, render_sequence
from gelsim.sinks import DeviceFrames, KeepFrames, drain
from gelsim.stream import sequence_labels

HAIRY = 73            # mohair plush, catalog hairiness 0.5
MODEL = load_nuisance()
MODEL_PROFILE = __import__("gelsim.sensor", fromlist=["load_profile"]).load_profile("vitac").with_resolution(96, 72)


@pytest.fixture(scope="module")
def small(vitac):
    return vitac.with_resolution(96, 72)


def _run(profile, level: str, *, fabric=HAIRY, precontact=(2, 2), seed=3, params: str | None = None, **opts):
    """A sequence's records at ``level``'s severities with ``params``' (a level's) stage parameters."""
    motion = sample_motion("press", seed, frames=(8, 8), precontact=precontact)
    options = SequenceOptions(nuisance=MODEL.level(level) if level != "none" else {},
                              nuisance_stages=MODEL.stages_for(params or level), **opts)
    records = list(render_sequence(load_catalog()[fabric], motion, profile, get_fidelity("fast"), seed=seed,
                                   options=options))
    return motion, records


def _gains_of(level: str, seed: int, frames: int = 30):
    motion = sample_motion("press", seed, frames=(frames, frames), precontact=(1, 1))
    return SequenceNuisance(MODEL.level(level), MODEL.stages_for(level), seed, 0.0, MODEL_PROFILE, motion).gains


def test_the_camera_level_darkens_a_few_recordings_and_webcam_restart_every_one():
    camera = [_gains_of("camera", k) for k in range(300)]
    restart = [_gains_of("webcam-restart", k) for k in range(300)]
    assert all(g is not None for g in restart)
    hit = [k for k, g in enumerate(camera) if g is not None]
    assert 0 < len(hit) < 30                                 # about 1 in 30 (restart_share)
    for k in hit:                                            # the same start-up where both catch it
        np.testing.assert_array_equal(camera[k], restart[k])
    assert _gains_of("none", 0) is None


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
    _, hand = _run(small, "handheld", params="webcam-restart")
    P = motion.precontact_frames
    for a, b in zip(plain, hand):
        assert all(np.asarray(a.labels[k]).tobytes() == np.asarray(b.labels[k]).tobytes() for k in a.labels)
        assert b.nuisance is not None
    dented = [r.index for r in hand if r.nuisance.dents_mm is not None]
    assert dented and dented[0] <= P, dented          # fibres reach the gel before the fabric or with it
    assert all((r.nuisance.fibres_touching > 0) == (r.nuisance.dents_mm is not None) for r in hand)
    assert all(r.nuisance.fibre_dent_max_mm == (r.nuisance.dents_mm.max() if r.nuisance.dents_mm is not None else 0)
               or r.nuisance.fibre_dent_max_mm >= r.nuisance.dents_mm.max() for r in hand)
    assert plain[0].nuisance is None
    # the frame before contact differs from the plain one by more than the camera's noise
    diff = np.abs(hand[0].frame.astype(np.int16) - plain[0].frame.astype(np.int16))
    assert diff.mean() > 3 * small.noise.read_sigma_dn


def test_no_fibres_on_a_fabric_without_hairs(small):
    silk = 13                                           # hairiness 0
    assert load_catalog()[silk].hairiness == 0
    _, recs = _run(small, "handheld", fabric=silk)
    assert all(r.nuisance is None or r.nuisance.dents_mm is None for r in recs)


def test_sequence_nuisance_refuses_unknown_stages(small):
    motion = sample_motion("press", 1, frames=(8, 8), precontact=(1, 1))
    with pytest.raises(GelsimError, match="unknown nuisance stage 'flicker'"):
        SequenceNuisance({"flicker": 1.0}, MODEL.stages, 1, 0.5, small, motion)


def test_device_frames_render_the_nuisance_as_the_sequence_would(small):
    """The torch backend renders the same dents and gains: frames within its tolerance of the fast
    backend's, the same bytes for any batch."""
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, BatchRenderer

    pytest.importorskip("torch")
    # the handheld stages with every recording catching the start-up: both dents and gains to render
    motion, fast = _run(small, "handheld", seed=2, params="webcam-restart")
    assert any(r.nuisance.gains is not None for r in fast) and any(r.nuisance.dents_mm is not None for r in fast)
    out = {}
    for batch in (1, 5):
        frames = KeepFrames()
        with DeviceFrames(BatchRenderer(Renderer(small, "torch")), batch, [frames]) as dev:
            labels, _ = drain(render_sequence(load_catalog()[HAIRY], motion, small, get_fidelity("fast"), seed=2,
                                              options=SequenceOptions(outputs={"imprint", "markers"},
                                                                      nuisance=MODEL.level("handheld"),
                                                                      nuisance_stages=MODEL.stages_for("webcam-restart"))),
                              [dev])
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


def test_stages_all_with_a_nuisance_level_verifies_and_records_what_the_numpy_route_records(tmp_path, capsys):
    """``--stages all --nuisance handheld`` (the torch engine, on the CPU): the dataset verifies, and its per-frame
    nuisance record holds the values the numpy route records for the same seed (drawn on the host from the
    sequence's generators in both), not rows of 'nothing applied'. Severity 4: more recordings catch the camera's
    start-up and more fibres stand, so that both stages' values are compared."""
    pytest.importorskip("torch")
    from gelsim.cli import main
    from gelsim.dataset import load_manifest
    from gelsim.gel.twoscale_torch import TOLERANCE

    tiny = ["--fabrics", "3", "--sequences-per-fabric", "2", "--frames", "8", "--precontact", "2",
            "--resolution", "64x48", "--fidelity", "fast", "--nuisance", "handheld", "--nuisance-severity", "4",
            "--workers", "1", "--no-previews", "--json"]
    assert main(["generate", "--out", str(tmp_path / "numpy"), *tiny]) == 0
    assert main(["generate", "--out", str(tmp_path / "all"), *tiny, "--backend", "torch", "--stages", "all",
                 "--device", "cpu"]) == 0
    capsys.readouterr()
    assert main(["verify", str(tmp_path / "all")]) == 0 and "OK" in capsys.readouterr().out
    ref, dev = load_manifest(tmp_path / "numpy"), load_manifest(tmp_path / "all")
    assert dev["render"]["stages"] == "all" and [s["id"] for s in ref["sequences"]] == [s["id"] for s in dev["sequences"]]
    caught = touching = 0
    for r, d in zip(ref["sequences"], dev["sequences"]):
        with np.load(tmp_path / "numpy" / r["nuisance"]) as za, np.load(tmp_path / "all" / d["nuisance"]) as zb:
            a, b = dict(za), dict(zb)
        assert list(b) == list(RECORD_KEYS) and not record_problems(b, d["num_frames"])
        for k in ("gains", "stream_age_frames", "fibres_touching"):
            assert np.array_equal(a[k], b[k]), (r["id"], k)
        # in contact the fibres' gap is the engine's indentation (the torch imprint's, within its tolerance)
        assert np.abs(a["fibre_dent_max_mm"] - b["fibre_dent_max_mm"]).max() <= TOLERANCE["indentation_mm"]
        pre = r["precontact_frames"]
        assert np.array_equal(a["fibre_dent_max_mm"][:pre], b["fibre_dent_max_mm"][:pre])
        caught += int(np.any(b["stream_age_frames"] >= 0))
        touching += int(b["fibres_touching"].sum())
    assert caught and touching            # real values, not the rows of a frame with nothing applied


def test_vitac_levels_keep_the_first_contact_frames_and_no_frame_is_black(small):
    """Table II's STAM row: contact frames within a recording's first two frames keep their content at each
    ViTac level's default severity (median change from none at most 3 DN), while frames before contact can
    change; and no frame is black (mean under 1 DN) at any severity, webcam-restart's included."""
    changes = {"camera": [], "handheld": []}
    for seed in range(12):
        motion = sample_motion("press", seed, frames=(8, 8), precontact=(0, 1))
        fabric = load_catalog()[HAIRY if seed % 2 else 21]
        runs = {}
        for level in ("none", "camera", "handheld"):
            opts = SequenceOptions(nuisance=MODEL.level(level), nuisance_stages=MODEL.stages_for(level))
            runs[level] = [r.frame.astype(np.float32) for r in
                           render_sequence(fabric, motion, small, get_fidelity("fast"), seed=seed, options=opts)]
        for level in changes:
            for i in range(motion.precontact_frames, 2):
                changes[level].append(float(np.abs(runs[level][i] - runs["none"][i]).mean()))
    for level, c in changes.items():
        assert len(c) >= 12 and np.median(c) <= 3.0, (level, c)
    for sev in (1.0, 2.0, 3.9):
        for seed in range(4):
            motion = sample_motion("press", seed, frames=(6, 6), precontact=(0, 0))
            opts = SequenceOptions(nuisance=MODEL.level("webcam-restart", sev),
                                   nuisance_stages=MODEL.stages_for("webcam-restart"))
            means = [r.frame.mean() for r in render_sequence(load_catalog()[21], motion, small, get_fidelity("fast"),
                                                             seed=seed, options=opts)]
            assert min(means) >= 1.0, (sev, seed, means)


def test_every_dataset_holds_a_per_frame_nuisance_record_and_verify_reads_it(tmp_path):
    from gelsim.dataset import verify

    base = dict(fabrics=2, sequences_per_fabric=2, frames=(8, 8), precontact=(2, 2), resolution=(64, 48),
                fidelity="fast")
    generate(GenerateConfig(**base), tmp_path / "none", workers=1, previews=False)
    m = generate(GenerateConfig(**base, nuisance="handheld"), tmp_path / "hand", workers=1, previews=False)
    for s in m["sequences"]:
        for root in ("none", "hand"):
            with np.load(tmp_path / root / s["nuisance"]) as z:
                assert list(z) == list(RECORD_KEYS) and not record_problems(z, s["num_frames"])
                if root == "none":
                    assert np.all(z["gains"] == 1) and np.all(z["stream_age_frames"] == -1)
                    assert not z["fibres_touching"].any()
    touched = [np.load(tmp_path / "hand" / s["nuisance"])["fibres_touching"].sum() for s in m["sequences"]]
    assert sum(touched) > 0            # the hairy fabrics among the first two (ids 1 and 2) have standing fibres
    assert verify(tmp_path / "hand") == []
    bad = tmp_path / "hand" / m["sequences"][0]["nuisance"]
    bad.write_bytes(bad.read_bytes()[:-10])
    assert any("nuisance" in f and "checksum" in f for f in verify(tmp_path / "hand"))
