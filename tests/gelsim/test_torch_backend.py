"""Tests of gelsim.optics.torch_backend: the fast backend's optics in PyTorch, batched over frames.

The stated tolerance (torch_backend.TOL_*) is checked against the fast backend on the CPU; the same
bytes for any batch size and order; the numpy noise draws; the device errors. CUDA is checked only
where a GPU is present (skipped otherwise, as in CI).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.errors import GelsimError  # noqa: E402
from gelsim.optics import Renderer  # noqa: E402
from gelsim.optics.shader import check_shader, shader_class  # noqa: E402
from gelsim.optics.torch_backend import (TOL_MAX_DN, TOL_MAX_UINT8_DN, TOL_MEAN_DN, BatchRenderer,  # noqa: E402
                                         TorchShader, resolve_device)

from test_optics import _weave, marker_grid, replace, sphere_dent  # noqa: E402

W = 320  # 320x240: the shipped sensor at a third of its resolution (the tolerance was measured here and at 960)


@pytest.fixture(scope="module")
def lut(vitac):
    return vitac.with_resolution(W)


@pytest.fixture(scope="module")
def phong(lut):
    # Phong from the lights with a highlight, so that the specular term is compared too
    return replace(lut, shading={"model": "phong", "specular": 0.3})


@pytest.fixture(scope="module")
def fabric_depth(lut):
    from gelsim.fabrics import load_catalog
    from gelsim.frame import press_object
    from gelsim.scene import FabricObject

    return press_object(FabricObject(load_catalog()[21]), lut, "fast", force_n=3.0, seed=1).depth_mm


def _scenes(profile, fabric=None):
    out = {"sphere": sphere_dent(profile, 2.0, 0.5, smooth_px=1.0),
           "steep sphere": sphere_dent(profile, 1.0, 0.6, center_mm=(1.3, -0.7)),
           "weave": _weave(profile, 0.12, 0.1),
           "flat": None}
    if fabric is not None:
        out["fabric"] = fabric
    return out


@pytest.mark.parametrize("shading", ["lut", "phong"])
def test_matches_fast_within_the_stated_tolerance(shading, lut, phong, fabric_depth):
    profile = lut if shading == "lut" else phong
    fast = Renderer(profile, "fast", seed=3)
    batch = BatchRenderer(Renderer(profile, "torch", seed=3))
    scenes = _scenes(profile, fabric_depth if shading == "lut" else None)
    corners, _ = marker_grid(profile, (0.3, 0.2))
    depths = list(scenes.values())
    got = batch.render_float(depths, [corners] * len(depths))
    noisy = batch.render(depths, [corners] * len(depths), [11] * len(depths))
    for i, (name, d) in enumerate(scenes.items()):
        ref = fast.render_float(d, corners)
        if d is not None:
            assert np.abs(ref - fast.background_float()).max() > 10.0, name    # the scene is seen
        err = np.abs(got[i] - ref)
        assert err.mean() < TOL_MEAN_DN and err.max() < TOL_MAX_DN, (name, err.mean(), err.max())
        err8 = np.abs(noisy[i].astype(int) - fast.render(d, corners, seed=11).astype(int))
        assert err8.max() <= TOL_MAX_UINT8_DN and err8.mean() < TOL_MEAN_DN, (name, err8.max(), err8.mean())
    if shading == "lut":
        # the shadows and the halo are part of these scenes (so they are compared too)
        d = torch.from_numpy(scenes["steep sphere"])[None]
        shadows, coarse = batch.shader.terms
        assert shadows.part_torch(d, 0.0).abs().max() > 1.0
        assert coarse.part_torch(d, 0.0).abs().max() > 1.0


def test_shadows_on_a_coarse_grid_match_fast(vitac):
    """At 960x720 the shadows' grid is 4 x 4 pixels (ShadowSpec.grid_factor): ``fast`` aligns it with the
    imprint's box, ``torch`` with the frame, and the two still agree within the stated tolerance where steep
    spheres' shadows fall (measured: at most 0.23 DN, 0.0003 DN on average)."""
    prof = vitac.with_resolution(960)
    assert batch_factor(prof) == 4
    fast = Renderer(prof, "fast", seed=3)
    batch = BatchRenderer(Renderer(prof, "torch", seed=3))
    depths = [sphere_dent(prof, 1.0, 0.6, center_mm=c) for c in ((1.3, -0.7), (-2.11, 0.93))]
    got = batch.render_float(depths)
    for d, g in zip(depths, got):
        ref = fast.render_float(d)
        assert np.abs(ref - fast.background_float()).max() > 10.0
        err = np.abs(g - ref)
        assert err.mean() < TOL_MEAN_DN and err.max() < TOL_MAX_DN, (err.mean(), err.max())


def batch_factor(profile):
    """The shadows' grid factor of ``profile``'s table."""
    from gelsim.optics.lut import table_model

    return table_model(profile).shadows.grid_factor(profile.image.mm_per_px)


def test_a_wrong_shading_is_caught(lut):
    """The comparison above can fail: a table 10% too strong moves the sphere by several DN."""
    fast = Renderer(lut, "fast", seed=3)
    other = BatchRenderer(Renderer(replace(lut, shading={"gain_dn": lut.shading.gain_dn * 1.1}), "torch", seed=3))
    d = sphere_dent(lut, 2.0, 0.5, smooth_px=1.0)
    assert np.abs(other.render_float([d])[0] - fast.render_float(d)).max() > TOL_MAX_DN


def test_same_bytes_for_any_batch_size_and_order(lut):
    r = BatchRenderer(Renderer(lut, "torch", seed=5))
    scenes = list(_scenes(lut).values()) + [sphere_dent(lut, 1.5, 0.3, center_mm=(-2.0, 1.0))]
    corners, _ = marker_grid(lut)
    shifted, _ = marker_grid(lut, (1.7, -0.4))
    marks = [corners, shifted, corners, None, shifted]
    seeds = [1, 2, 3, 4, 5]
    one_by_one = [r.render([d], [m], [s])[0] for d, m, s in zip(scenes, marks, seeds)]
    together = r.render(scenes, marks, seeds)
    backwards = r.render(scenes[::-1], marks[::-1], seeds[::-1])[::-1]
    for a, b, c in zip(one_by_one, together, backwards):
        assert a.tobytes() == b.tobytes() == c.tobytes()
    assert len({f.tobytes() for f in together}) == len(together)     # the frames do differ


def test_stage_takes_device_tensors(lut):
    """The imprint and the markers as tensors (as a device imprint hands them over) give the frames of the
    same arrays, validated on the device with one line per problem."""
    r = BatchRenderer(Renderer(lut, "torch", seed=4))
    depths = [sphere_dent(lut, 2.0, 0.4), None, _weave(lut, 0.05, 0.03)]
    corners, _ = marker_grid(lut)
    marks = [corners, corners + np.float32(0.5), corners]
    want = r.quantise(r.compose(*r.stage(depths, marks)), [r.draw(s) for s in (1, 2, 3)])
    dt = torch.stack([torch.zeros(lut.shape) if d is None else torch.from_numpy(d) for d in depths])
    ct = torch.from_numpy(np.stack(marks))
    got = r.quantise(r.compose(*r.stage(dt, ct)), [r.draw(s) for s in (1, 2, 3)])
    assert torch.equal(want, got)
    for bad, match in ((dt[:, :-1], "depth map tensor has shape"), (dt * float("nan"), "NaN"),
                       (dt - 0.1, "negative"), (dt.double().long(), "dtype")):
        with pytest.raises(GelsimError, match=match):
            r.stage(bad, None)
    with pytest.raises(GelsimError, match="marker corners tensor"):
        r.stage(dt, ct[..., :1])


def test_renderer_one_frame_and_supersampling_agree(lut):
    """Renderer(..., "torch") one frame at a time (the Shader contract, numpy markers and noise) and
    with supersampling agree with the fast backend within the tolerance."""
    d = sphere_dent(lut, 1.2, 0.5, center_mm=(0.7, 0.4))
    corners, _ = marker_grid(lut, (0.5, 0.5))
    ref = Renderer(lut, "fast", seed=1).render_float(d, corners)
    one = Renderer(lut, "torch", seed=1, device="cpu").render_float(d, corners)
    assert np.abs(one - ref).max() < TOL_MAX_DN
    ref2 = Renderer(lut, "fast", supersample=2, seed=1).render_float(d, corners)
    two = BatchRenderer(Renderer(lut, "torch", supersample=2, seed=1)).render_float([d], [corners])[0]
    err = np.abs(two - ref2)
    assert err.mean() < TOL_MEAN_DN and err.max() < TOL_MAX_DN, (err.mean(), err.max())
    assert np.abs(ref2 - ref).max() > TOL_MAX_DN                  # supersampling does change the frame


def test_shader_contract_and_delta(lut):
    cls = check_shader(shader_class("torch", lut), "torch")
    assert cls is TorchShader and cls.name == "torch"
    sh = Renderer(lut, "torch").shader
    assert sh.delta(np.zeros(lut.shape, np.float32)) is None
    d = sphere_dent(lut, 2.0, 0.4)
    roi, change = sh.delta(d)
    assert change.shape == lut.shape + (3,) and np.abs(change).max() > 10.0
    (part_roi, blurred, done), = sh.parts(d, 2, lut.camera.blur_sigma_px)
    assert done and part_roi == roi and 0 < np.abs(blurred - change).max()


def test_device_errors(lut):
    assert resolve_device(None).type == "cpu" and resolve_device("cpu").type == "cpu"
    for bad in ("tpu", "gpu0"):
        with pytest.raises(GelsimError, match="--device"):
            resolve_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(GelsimError, match="no CUDA device on this machine.*use --device cpu"):
            resolve_device("cuda")
    with pytest.raises(GelsimError, match="--device cpu is for the torch backend"):
        Renderer(lut, "fast", device="cpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here (CI has none)")
def test_cuda_agrees_with_cpu(lut):  # pragma: no cover - runs only on a GPU machine
    depths = list(_scenes(lut).values())
    corners, _ = marker_grid(lut)
    cpu = BatchRenderer(Renderer(lut, "torch", seed=2, device="cpu"))
    gpu = BatchRenderer(Renderer(lut, "torch", seed=2, device="cuda"))
    a = cpu.render(depths, [corners] * len(depths), [3] * len(depths))
    b = gpu.render(depths, [corners] * len(depths), [3] * len(depths))
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1
    one = [gpu.render([d], [corners], [3])[0] for d in depths]
    assert all(x.tobytes() == y.tobytes() for x, y in zip(one, b))


def test_profile_without_markers_or_noise(lut):
    quiet = dataclasses.replace(lut, markers=dataclasses.replace(lut.markers, enabled=False),
                                noise=dataclasses.replace(lut.noise, read_sigma_dn=0.0))
    r = BatchRenderer(Renderer(quiet, "torch", seed=0))
    d = sphere_dent(quiet, 2.0, 0.3)
    corners, _ = marker_grid(quiet)
    a = r.render([d], [corners], [1])[0]        # markers disabled in the profile: none drawn
    b = r.render([d], [None], [2])[0]           # no noise: the seed does not matter
    assert a.tobytes() == b.tobytes()
    assert np.abs(a.astype(int) - Renderer(quiet, "fast").render(d).astype(int)).max() <= TOL_MAX_UINT8_DN
