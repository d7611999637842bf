"""gelsim.scene_torch: the object's heights seen through each frame's pose on a torch device, against
gelsim.scene.HeightPatch.sample (the numpy kernel), within SAMPLE_TOL_MM; a pose moved by a hundredth of a pixel
falls outside it (the tolerance sees a change of either kernel)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.scene_torch import SAMPLE_TOL_MM, PatchBank, sample_patches  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]


@pytest.mark.parametrize("device", DEVICES)
def test_patch_sampling_matches_heightpatch(two_sequences, device):
    prof, _, _, prep = two_sequences
    bank = PatchBank.from_patches([p.patch for p in prep], device)
    which, poses, refs = [], [], []
    for k, p in enumerate(prep):
        c = p.contact
        for i in range(c.position_mm.shape[0]):
            pose = (float(c.position_mm[i, 0]), float(c.position_mm[i, 1]), float(c.yaw_deg[i]),
                    tuple(float(v) for v in c.tilt_deg[i]))
            which.append(k)
            poses.append(pose)
            refs.append(p.patch.sample(prof.shape, prof.image.mm_per_px, *pose))
    got = sample_patches(bank, which, poses, prof.shape, prof.image.mm_per_px).cpu().numpy()
    assert np.abs(got - np.stack(refs)).max() < SAMPLE_TOL_MM
    # the tolerance sees a pose off by a twentieth of a pixel (a change of either kernel of that size)
    mm = prof.image.mm_per_px
    off = [(x + 0.05 * mm, y, yaw, tilt) for x, y, yaw, tilt in poses]
    moved = sample_patches(bank, which, off, prof.shape, mm).cpu().numpy()
    assert np.abs(moved - np.stack(refs)).max() > SAMPLE_TOL_MM
