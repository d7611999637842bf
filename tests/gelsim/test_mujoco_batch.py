"""gelsim.mujoco.batch: N MuJoCo GelSight sensors rendered in one call equal N single sensors (GelSightSensor, the
numpy path) within the device path's tolerances: uint8 images within the torch optics' TOL_MAX_UINT8_DN, depth
maps within the indentation tolerance (a smooth ball: no texture crowns to flip), contact masks on 99.9% of the pixels, markers within TOL_PX, forces,
shear and twist the same (the host does those). N = 1 and 16 here, 256 in the slow tests."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.gel.twoscale_torch import TOLERANCE  # noqa: E402
from gelsim.markers_torch import TOL_PX  # noqa: E402
from gelsim.errors import GelsimError  # noqa: E402
from gelsim.mujoco import GelSightSensor  # noqa: E402
from gelsim.mujoco.batch import BatchGelSightSensor, ball_scenes  # noqa: E402
from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
RES = (160, 120)


def _twins(scenes):
    out = []
    for s in scenes:
        d = mujoco.MjData(s.model)
        mujoco.mj_copyData(d, s.model, s.data)
        out.append(d)
    return out


def _compare(n: int, device: str, steps: int = 2):
    scenes = ball_scenes(n, seed=n)
    twins = _twins(scenes)
    batch = BatchGelSightSensor([(s.model, s.data, s.pad) for s in scenes], resolution=RES, seed=7, device=device)
    singles = [GelSightSensor(s.model, d, s.pad, profile="vitac", resolution=RES, seed=7) for s, d in zip(scenes, twins)]
    touched = 0
    for _ in range(steps):
        bf = batch.render()
        assert len(bf) == n
        for i, single in enumerate(singles):
            f, g = single.render(), bf.frame(i)
            assert g.in_contact == f.in_contact and g.normal_force_n == f.normal_force_n
            np.testing.assert_array_equal(g.shear_mm, f.shear_mm)
            assert g.twist_deg == f.twist_deg and g.slipping == f.slipping
            assert np.abs(g.rgb.astype(int) - f.rgb.astype(int)).max() <= TOL_MAX_UINT8_DN
            assert np.abs(g.depth_mm - f.depth_mm).max() <= TOLERANCE["indentation_mm"]   # a smooth ball: no crowns
            assert np.mean(g.contact_mask == f.contact_mask) >= TOLERANCE["mask_agreement"]
            assert np.abs(g.markers_xy_px - f.markers_xy_px).max() <= TOL_PX
            touched += f.in_contact
        for s, d in zip(scenes, twins):       # both copies of each scene step the same way
            s.step()
            d.ctrl[:] = s.data.ctrl
            for _ in range(5):
                mujoco.mj_step(s.model, d)
    assert touched >= n                        # the balls press their pads
    return batch


@pytest.mark.parametrize("n", [1, 16])
def test_batch_equals_single_sensors(n):
    _compare(n, "cpu")


@pytest.mark.slow
def test_batch_of_256_equals_single_sensors():
    _compare(256, "cpu", steps=1)


@CUDA
@pytest.mark.parametrize("n", [1, 16])
def test_batch_equals_single_sensors_cuda(n):
    _compare(n, "cuda")


def test_pads_without_contact_are_the_flat_gel():
    scenes = ball_scenes(2)
    scenes[1].data.ctrl[0] = 5.0            # pulled away from its pad
    for _ in range(400):
        mujoco.mj_step(scenes[1].model, scenes[1].data)
    b = BatchGelSightSensor([(s.model, s.data, s.pad) for s in scenes], resolution=RES, noise=False)
    bf = b.render()
    assert bf.in_contact.tolist() == [True, False]
    single = GelSightSensor(scenes[1].model, scenes[1].data, "pad", profile="vitac", resolution=RES, noise=False)
    assert np.abs(bf.frame(1).rgb.astype(int) - single.background().astype(int)).max() <= TOL_MAX_UINT8_DN
    b.reset()
    assert all(st.frame == 0 for _, _, st in b._pads)


def test_bad_input_is_one_line():
    scenes = ball_scenes(1)
    with pytest.raises(GelsimError, match="at least one"):
        BatchGelSightSensor([])
    with pytest.raises(GelsimError, match="model, data, pad"):
        BatchGelSightSensor([(scenes[0].model, scenes[0].data)])
    with pytest.raises(GelsimError, match="fast or balanced"):
        BatchGelSightSensor([(scenes[0].model, scenes[0].data, "pad")], fidelity="reference")
