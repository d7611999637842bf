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


def _rotated_parts(prof, fabric_ids=(1, 26, 51, 64, 76, 90)):
    """A rotated patch of each of these catalog fabrics (woven, twill, knit, corduroy, terry, leather...): the
    host's travel_patch and its parts (gelsim.scene.travel_patch_parts)."""
    from gelsim.fabrics import load_catalog
    from gelsim.motion import sample_motion
    from gelsim.scene import FabricObject, travel_patch, travel_patch_parts

    cat = load_catalog()
    out = []
    for i, fid in enumerate(fabric_ids):
        obj = FabricObject(cat[fid])
        motion = sample_motion("twist" if i % 2 else "slip", 40 + i, frames=(6, 6), precontact=(1, 1))
        mm = prof.image.mm_per_px
        parts = travel_patch_parts(obj, motion, prof, mm, seed=40 + i)
        out.append((obj, travel_patch(obj, motion, prof, mm, seed=40 + i), parts))
    return out


@pytest.mark.parametrize("device", DEVICES)
def test_rotated_patch_finished_on_the_device(vitac, device):
    """A rotated fabric's patch finished on the device (its resampling, relief and cut) is the host's within
    FINISH_TOL of the relief; finished on the host its parts are travel_patch's bytes (the numpy route unchanged).
    A grid read a hundredth of a pixel away falls outside the tolerance."""
    import dataclasses

    from gelsim.fabrics.render import RotatedHeights
    from gelsim.scene_torch import FINISH_TOL, finish_rotated

    for obj, patch, parts in _rotated_parts(vitac):
        assert isinstance(parts.heights, RotatedHeights)
        host = parts.finish()
        assert host.heights_mm.tobytes() == patch.heights_mm.tobytes() and host.origin_mm == patch.origin_mm
        got = finish_rotated(parts.heights, device).cpu().numpy()
        relief = obj.fabric.relief_mm
        assert got.shape == patch.heights_mm.shape
        assert np.abs(got - patch.heights_mm).max() <= FINISH_TOL * relief
        moved = finish_rotated(dataclasses.replace(parts.heights, j0=parts.heights.j0 + 0.01), device).cpu().numpy()
        assert np.abs(moved - patch.heights_mm).max() > FINISH_TOL * relief


@pytest.mark.parametrize("device", DEVICES)
def test_crown_envelopes_closed_on_the_device_exactly(vitac, device):
    """The crown envelope of each patch of a bank (patches of several sizes, each closed over its own) is the host's
    closing (gelsim.gel.twoscale.crown_envelope) to the bit."""
    from gelsim.fidelity import get_fidelity
    from gelsim.sequence import crown_envelope_patch, crown_envelope_px

    fid = get_fidelity("balanced")
    cases = _rotated_parts(vitac, (1, 64, 90))
    bank = PatchBank.from_patches([patch for _, patch, _ in cases], device)
    kernels = {s: crown_envelope_px(patch, obj, vitac, fid) for s, (obj, patch, _) in enumerate(cases)}
    assert len({a.heights_mm.shape for _, a, _ in cases}) > 1 and all(k > 1 for k in kernels.values())
    closed = bank.closed(kernels)
    for s, (obj, patch, _) in enumerate(cases):
        ref = crown_envelope_patch(patch, obj, vitac, fid).heights_mm
        rows, cols = closed.sizes[s]
        assert (rows, cols) == ref.shape
        assert np.array_equal(closed.heights[s, :rows, :cols].cpu().numpy(), ref)
