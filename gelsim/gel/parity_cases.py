"""Agreement cases of the device imprint and markers: catalog fabrics pressed, slipped and twisted as the
dataset does it (:func:`gelsim.sequence.render_sequence`), captured frame by frame as the numpy path sees them.

:func:`capture` runs a sequence's motion, contact simulation and fabric patch once and keeps, for every frame in
contact, what :func:`gelsim.gel.press` and :func:`gelsim.markers.displace` take (the protrusion map, the crown
envelope over the whole frame, the force, the shear and twist); :func:`numpy_reference` presses them with the numpy
path, warm-started frame to frame as a sequence is. The tests (``tests/gelsim/test_device_imprint.py``) and the
benchmarks (``benchmarks/bench_device.py``) compare the device path with it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..fidelity import Fidelity, get_fidelity
from ..sensor import SensorProfile

ACTIONS = ("press", "slip", "twist")


@dataclass
class SequenceCase:
    """One sequence's frames in contact, as the imprint and the markers take them.

    prot: float32 (T, H, W) protrusion maps, mm (the profile's image); env: float32 (T, H, W) crown envelopes seen
    through each frame's pose, mm, or None (an object without texture); force_n: float (T,) N; shear_mm: float (T, 2)
    mm; twist_deg: float (T,) degrees; warm: bool (T,), whether frame t warm-starts from frame t - 1 (the previous
    frame was in contact); props: press()'s object keywords (support, texture_mm, valley_mm)."""
    name: str
    fabric_id: int
    action: str
    profile: SensorProfile
    fidelity: Fidelity
    prot: np.ndarray
    env: np.ndarray | None
    force_n: np.ndarray
    shear_mm: np.ndarray
    twist_deg: np.ndarray
    warm: np.ndarray
    props: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.force_n.shape[0])


def family_sample(catalog=None) -> list[int]:
    """The first fabric of every family in the catalog, by id: a sample that covers every texture renderer."""
    from ..fabrics import load_catalog

    seen: dict[str, int] = {}
    for f in (catalog or load_catalog()):
        seen.setdefault(f.family, f.id)
    return sorted(seen.values())


def capture(fabric_id: int, action: str, profile: SensorProfile, fidelity: str | Fidelity = "balanced", *,
            seed: int = 0, frames: int = 12, precontact: int = 2) -> SequenceCase:
    """Simulate one sequence of catalog fabric ``fabric_id`` (``action``: press, slip or twist; ``frames``
    frames of which ``precontact`` before contact) and keep its frames in contact (see :class:`SequenceCase`)."""
    import functools

    from ..contact import simulate
    from ..fabrics import load_catalog
    from ..motion import sample_motion
    from ..scene import FabricObject, physics_surface, press_properties, travel_patch
    from ..sequence import crown_envelope_patch

    fid = get_fidelity(fidelity)
    obj = FabricObject(load_catalog()[fabric_id])
    motion = sample_motion(action, seed, frames=(frames, frames), precontact=(precontact, precontact))
    contact = simulate(motion, physics_surface(obj, motion, profile, seed=seed), profile, fid)
    patch = travel_patch(obj, motion, profile, profile.image.mm_per_px, seed=seed,
                         poses=(contact.position_mm, contact.yaw_deg))
    envelope = crown_envelope_patch(patch, obj, profile, fid)
    prot, env, force, shear, twist, warm = [], [], [], [], [], []
    prev = False
    for i in range(motion.num_frames):
        f = float(contact.normal_force_n[i])
        touching = bool(contact.in_contact[i]) and f > 0.0
        if touching:
            pose = (profile.shape, profile.image.mm_per_px, contact.position_mm[i, 0], contact.position_mm[i, 1],
                    contact.yaw_deg[i], tuple(contact.tilt_deg[i]))
            prot.append(patch.sample(*pose))
            if envelope is not None:
                env.append(functools.partial(envelope.sample, *pose)())
            force.append(f)
            shear.append(np.asarray(contact.shear_mm[i], np.float64))
            twist.append(float(contact.twist_deg[i]))
            warm.append(prev)
        prev = touching
    h, w = profile.shape
    return SequenceCase(f"{fabric_id}-{action}", fabric_id, action, profile, fid,
                        np.asarray(prot, np.float32).reshape(-1, h, w),
                        np.asarray(env, np.float32).reshape(-1, h, w) if envelope is not None else None,
                        np.asarray(force, np.float64), np.asarray(shear, np.float64).reshape(-1, 2),
                        np.asarray(twist, np.float64), np.asarray(warm, bool), press_properties(obj))


def numpy_reference(case: SequenceCase) -> list:
    """The numpy path's :class:`gelsim.gel.Imprint` of every frame of ``case``, warm-started as a sequence is."""
    from . import press

    out, prev = [], None
    for t in range(len(case)):
        im = press(case.prot[t], case.profile, case.fidelity, force_n=float(case.force_n[t]),
                   warm=prev if case.warm[t] else None,
                   envelope_mm=None if case.env is None else case.env[t], **case.props)
        out.append(im)
        prev = im
    return out


def device_imprints(cases: list[SequenceCase], device="cpu") -> list[list]:
    """Every case's frames pressed by :func:`gelsim.gel.twoscale_torch.press_batch`, frame t of every case in one
    batch (the cases' sequences in step, each warm-started from its own previous frame): per case the list of
    its :class:`~gelsim.gel.twoscale_torch.ImprintBatch` rows as (batch, row) pairs."""
    import torch

    from .twoscale_torch import press_batch

    if not cases:
        return []
    profile, fid = cases[0].profile, cases[0].fidelity
    out: list[list] = [[] for _ in cases]
    state: list = [None] * len(cases)
    for t in range(max(len(c) for c in cases)):
        idx = [i for i, c in enumerate(cases) if t < len(c)]
        prot = torch.as_tensor(np.stack([cases[i].prot[t] for i in idx]), device=device)
        envs = [cases[i].env for i in idx]
        env = None
        if all(e is not None for e in envs):
            env = torch.as_tensor(np.stack([e[t] for e in envs]), device=device)
        elif any(e is not None for e in envs):
            env = torch.as_tensor(np.stack([cases[i].env[t] if cases[i].env is not None else cases[i].prot[t]
                                            for i in idx]), device=device)
        warm = [state[i] if cases[i].warm[t] else None for i in idx]
        ib = press_batch(prot, profile, fid, [cases[i].force_n[t] for i in idx], props=[cases[i].props for i in idx],
                         envelope_mm=env, warm=warm)
        for j, i in enumerate(idx):
            state[i] = ib.states[j]
            out[i].append((ib, j))
    return out


def agreement(reference, device) -> dict[str, np.ndarray]:
    """Per-frame agreement of device imprints with the numpy path's (two lists of :class:`gelsim.gel.Imprint`):
    ``mask`` the share of pixels whose contact is the same, ``area_rel`` the contact area's relative difference
    (against the numpy path's; 0 where both are 0), ``centroid_px`` the contact centroids' largest coordinate
    difference (0 where neither has contact, inf where one has), ``indentation_mm`` and ``depth_mm`` (the depth
    maps' largest difference). float64 arrays, one value per frame."""
    from ..labels import contact_location

    out: dict[str, list] = {"mask": [], "area_rel": [], "centroid_px": [], "indentation_mm": [], "depth_mm": []}
    for r, d in zip(reference, device, strict=True):
        out["mask"].append(float(np.mean(r.contact_mask == d.contact_mask)))
        a, b = r.contact_area_mm2, d.contact_area_mm2
        out["area_rel"].append(abs(a - b) / a if a > 0 else (0.0 if b == 0 else np.inf))
        c1, _ = contact_location(r.contact_mask)
        c2, _ = contact_location(d.contact_mask)
        f1, f2 = bool(np.isfinite(c1).all()), bool(np.isfinite(c2).all())
        out["centroid_px"].append(float(np.abs(c1 - c2).max()) if f1 and f2 else (0.0 if f1 == f2 else np.inf))
        out["indentation_mm"].append(abs(r.indentation_mm - d.indentation_mm))
        out["depth_mm"].append(float(np.abs(r.depth_mm - d.depth_mm).max()))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def within(metrics: dict[str, np.ndarray], tolerance: dict[str, float]) -> np.ndarray:
    """bool per frame: every metric of :func:`agreement` within ``tolerance`` (keys as
    :data:`gelsim.gel.twoscale_torch.TOLERANCE`: ``mask_agreement`` a lower bound, the rest upper bounds)."""
    ok = metrics["mask"] >= tolerance["mask_agreement"]
    for k in ("area_rel", "centroid_px", "indentation_mm", "depth_mm"):
        if k in tolerance:
            ok &= metrics[k] <= tolerance[k]
    return ok
