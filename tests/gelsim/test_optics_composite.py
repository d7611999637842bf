"""gelsim.optics.composite: the optics' order written once, run by the numpy Renderer and the torch
BatchRenderer; a stage added to the list (its numpy and its torch kernel) runs in its place on both. The list
is a renderer's argument (``Renderer(..., stages=)``), not a module global to patch."""
from __future__ import annotations

import numpy as np
import pytest

from gelsim.optics import Renderer
from gelsim.optics import composite as C
from gelsim.optics.ops.readout import to_uint8

from test_optics import marker_grid, sphere_dent  # noqa: E402


@pytest.fixture(scope="module")
def small(vitac):
    return vitac.with_resolution(160)


def test_the_order_of_the_stages():
    assert [s.name for s in C.OPTICS_STAGES] == ["markers", "camera gains", "area average", "readout"]
    assert [s.final for s in C.OPTICS_STAGES] == [False, False, False, True]          # the readout last
    assert [s.banded for s in C.OPTICS_STAGES] == [True, True, False, True]           # the average needs the whole frame
    assert isinstance(C.OPTICS_STAGES, tuple)
    for stage in C.OPTICS_STAGES:
        assert not getattr(stage, "__abstractmethods__", None), stage    # numpy and torch kernels both


class Gain(C.Stage):
    """A nuisance for the test: the frame times a gain drawn per frame (an LED's flicker, say)."""

    name = "gain"

    def draw(self, rng, noise):
        return float(rng().uniform(0.6, 0.9))

    def prepare(self, frame):
        draw = frame.draws.get(self.name)
        return None if draw is None else np.float32(draw)

    def apply(self, rows, y0, state):
        rows *= state
        return rows

    def apply_torch(self, frames, batch):
        import torch

        draws = batch.draws_of(self, frames.shape[0])
        g = torch.tensor([1.0 if d is None else d for d in draws], dtype=frames.dtype, device=frames.device)
        return frames * g[:, None, None, None]


class Exposure(C.Stage):
    """Another: the frame scaled so that its mean is 100 DN (an auto-exposure: it needs the whole frame)."""

    name = "exposure"
    banded = False

    def prepare(self, frame):
        return self

    def apply(self, rows, y0, state):
        return (rows * np.float32(100.0 / rows.mean(dtype=np.float64))).astype(np.float32)

    def apply_torch(self, frames, batch):
        return frames * (100.0 / frames.double().mean(dim=(1, 2, 3), keepdim=True)).float()


def test_a_stage_added_to_the_list_runs_in_its_place(small):
    d = sphere_dent(small, 1.5, 0.3)
    corners, _ = marker_grid(small)
    plain = Renderer(small, seed=1)
    r = Renderer(small, seed=1, stages=(C.MarkerShading, Gain, C.AreaAverage, C.Readout))
    assert [s.name for s in r.stages] == ["markers", "gain", "area average", "readout"]
    for seed, depth in ((5, d), (6, None)):
        g = np.float32(np.random.default_rng(seed).uniform(0.6, 0.9))       # drawn first, before the noise
        want = plain.render_float(depth, corners) * g
        np.testing.assert_array_equal(r.render(depth, corners, seed=seed, noise=False), to_uint8(want))
        rng = np.random.default_rng(seed)
        rng.uniform(0.6, 0.9)
        np.testing.assert_array_equal(r.render(depth, corners, seed=seed), plain.optics.noise.apply(want, rng))
    # render_float draws nothing: the gain is not applied there
    np.testing.assert_array_equal(r.render_float(d, corners), plain.render_float(d, corners))


def test_a_stage_that_needs_the_whole_frame(small):
    d = sphere_dent(small, 1.5, 0.3)
    corners, _ = marker_grid(small)
    plain = Renderer(small, seed=1)
    r = Renderer(small, seed=1, stages=(C.MarkerShading, C.AreaAverage, Exposure, C.Readout))
    for depth in (d, None, None):
        f = plain.render_float(depth, corners)
        want = (f * np.float32(100.0 / f.mean(dtype=np.float64))).astype(np.float32)
        np.testing.assert_array_equal(r.render_float(depth, corners), want)
        np.testing.assert_array_equal(r.render(depth, corners, seed=3), plain.optics.noise.apply(want, 3))


def test_both_backends_run_an_added_stage(small):
    pytest.importorskip("torch")
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, TOL_MEAN_DN, BatchRenderer

    stages = (C.MarkerShading, Gain, C.AreaAverage, Exposure, C.Readout)
    fast = Renderer(small, seed=2, stages=stages)
    batch = BatchRenderer(Renderer(small, "torch", seed=2, stages=stages))
    depths = [sphere_dent(small, 1.5, 0.3), None, sphere_dent(small, 1.0, 0.5, center_mm=(1.0, 0.5))]
    corners, _ = marker_grid(small)
    rng_fast, rng_torch = np.random.default_rng(4), np.random.default_rng(4)
    want = [fast.render(d, corners, seed=rng_fast) for d in depths]
    got = batch.render(depths, [corners] * 3, [rng_torch] * 3)
    for a, b in zip(want, got):
        diff = np.abs(a.astype(int) - b.astype(int))
        assert diff.max() <= TOL_MAX_UINT8_DN and diff.mean() < TOL_MEAN_DN        # the backends' tolerance
    assert rng_fast.integers(1 << 30) == rng_torch.integers(1 << 30)    # the same draws, in the same order
    rng = np.random.default_rng(4)
    plain = Renderer(small, seed=2, stages=(C.MarkerShading, C.AreaAverage, C.Readout)).render(depths[0], corners,
                                                                                              seed=rng)
    assert np.abs(want[0].astype(int) - plain).mean() > 5.0                # the added stages do change the frame


def test_check_depth_names_the_problem():
    from gelsim.errors import GelsimError

    with pytest.raises(GelsimError, match="shape"):
        C.check_depth(np.zeros((3, 4), np.float32), (4, 3))
    with pytest.raises(GelsimError, match="NaN"):
        C.check_depth(np.full((2, 2), np.nan, np.float32), (2, 2))
    with pytest.raises(GelsimError, match="negative"):
        C.check_depth(np.full((2, 2), -0.1, np.float32), (2, 2))
    assert C.check_depth(np.full((2, 2), -1e-5, np.float32), (2, 2)).min() == 0.0     # float error clipped


@pytest.mark.parametrize("stages", [(C.MarkerShading, C.AreaAverage), (C.Readout, C.MarkerShading),
                                    (C.MarkerShading, C.MarkerShading, C.Readout)])
def test_a_stage_list_without_the_readout_last_or_with_a_name_twice_is_refused(small, stages):
    from gelsim.errors import GelsimError

    with pytest.raises(GelsimError, match="readout"):
        Renderer(small, stages=stages)


def test_one_object_carries_a_frames_inputs(small):
    """:class:`OpticsInput` (depth, markers, gains, seed, noise) renders what render() gives for them by name."""
    d = sphere_dent(small, 1.5, 0.3)
    corners, _ = marker_grid(small)
    r = Renderer(small, seed=1)
    g = np.array([1.1, 0.9, 1.0])
    np.testing.assert_array_equal(r.render_input(C.OpticsInput(d, corners, g, seed=7)),
                                  r.render(d, corners, seed=7, gains=g))
    np.testing.assert_array_equal(r.render_input(C.OpticsInput(d, None, noise=False)), r.render(d, noise=False))


def test_light_maps_are_made_only_for_a_shader_that_reads_them():
    """A calibrated table's renderer never builds the LEDs' light maps (41 MB of a dataset worker's peak at
    960x720); a Phong renderer gets them."""
    from gelsim.sensor import load_profile

    lut = Renderer(load_profile("vitac").with_resolution(64, 48))
    assert lut.shader.name == "lut" and "maps" not in vars(lut.optics)
    assert len(lut.optics.maps) == len(lut.profile.lights)          # still there when asked for
    phong = Renderer(load_profile("digit").with_resolution(64, 48))
    assert "maps" in vars(phong.optics) and phong.shader.maps is phong.optics.maps
