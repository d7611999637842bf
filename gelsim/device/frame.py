"""The whole frame on the device: a sequence's fabric patch to camera pixels, batched over frames.

What :func:`gelsim.sequence.render_sequence` does per frame after the physics, for many sequences in step (frame t
of every sequence in one batch, each warm-started from its own frame t - 1):

1. **Protrusion** (and the crown envelope) sampled from the sequence's patch at the frame's pose
   (:func:`sample_patches`: :meth:`gelsim.scene.HeightPatch.sample` on the device);
2. **imprint** (:func:`gelsim.gel.twoscale_torch.press_batch`) and the contact labels (:func:`contact_labels`);
3. **markers** (:func:`gelsim.markers_torch.displace_batch`), with the sequence's shortcut for negligible shear
   and twist;
4. **optics**: the torch backend's :class:`~gelsim.optics.torch_backend.BatchRenderer` fed device tensors
   (:class:`DeviceRenderer`, a thin adapter: its ``stage`` takes host arrays).

The physics (MuJoCo) and the fabric's patch stay on the CPU, once per sequence (:func:`prepare_sequence`).
:func:`render_sequences` strings them together and reports each stage's time; ``benchmarks/bench_device.py``
measures it. Labels match render_sequence's within the device imprint's tolerance
(:data:`gelsim.gel.twoscale_torch.TOLERANCE`); frames within the torch backend's.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .. import batch_ops as ops
from ..labels import contact_location_torch
from ..scene_torch import PatchBank, sample_patches


# ---------------------------------------------------------------- sequences in step

@dataclass
class PreparedSequence:
    """What the CPU does once per sequence before its frames: the contact simulation, the fabric's patch and its
    crown envelope (:func:`prepare_sequence`), with the seconds each took."""
    obj: object
    motion: object
    seed: int
    contact: object
    patch: object
    envelope: object
    props: dict
    seconds: dict = field(default_factory=dict)


def prepare_sequence(obj, motion, profile, fidelity, *, seed: int) -> PreparedSequence:
    """The CPU part of :func:`gelsim.sequence.render_sequence` for one sequence: physics surface, contact
    simulation (MuJoCo), the image-resolution patch and its crown envelope."""
    from ..contact import simulate
    from ..fidelity import get_fidelity
    from ..scene import as_object, physics_surface, press_properties, travel_patch
    from ..sequence import crown_envelope_patch

    fid = get_fidelity(fidelity)
    obj = as_object(obj)
    t0 = time.process_time()
    surface = physics_surface(obj, motion, profile, seed=seed)
    t1 = time.process_time()
    contact = simulate(motion, surface, profile, fid)
    t2 = time.process_time()
    patch = travel_patch(obj, motion, profile, profile.image.mm_per_px, seed=seed,
                         poses=(contact.position_mm, contact.yaw_deg))
    envelope = crown_envelope_patch(patch, obj, profile, fid)
    t3 = time.process_time()
    return PreparedSequence(obj, motion, seed, contact, patch, envelope, press_properties(obj),
                            {"fabric": (t1 - t0) + (t3 - t2), "physics": t2 - t1})


def _negligible(shear, twist, profile):
    from ..sequence import negligible_px

    return negligible_px(shear, twist, profile)


def render_sequences(prepared: list[PreparedSequence], profile, fidelity, renderer, *, sensor_seed: int = 0,
                     outputs=("frames", "imprint", "markers"), sink=None, sync: bool = True,
                     optics_batch: int | None = None) -> dict:
    """Render ``prepared`` sequences in step on the device of ``renderer`` (a :class:`gelsim.optics.torch_backend.BatchRenderer`): frame t of
    every sequence in one batch. Each finished batch of uint8 frames goes to ``sink(frames (B, H, W, 3) host
    array, [(sequence, frame index), ...])`` when given; ``optics_batch``: the optics render at most that many
    frames per call (the same bytes for any: the torch optics' frames do not depend on their batch). Returns each sequence's labels (as render_sequence's)
    under ``"labels"``, and ``"seconds"``: wall seconds per stage (``sync``: the device is synchronised at each
    stage's end, so that the stages' times are its own) and ``"frames"``: the count."""
    torch = ops.torch_module()
    from ..fidelity import get_fidelity
    from ..markers import marker_grid
    from ..gel.twoscale_torch import press_batch
    from ..markers_torch import displace_batch

    fid = get_fidelity(fidelity)
    dev = renderer.device
    outputs = set(outputs)
    want_frames = "frames" in outputs
    h, w = profile.shape
    mm = profile.image.mm_per_px
    seconds: dict = {"upload": 0.0, "sample": 0.0, "imprint": 0.0, "labels": 0.0, "markers": 0.0, "optics": 0.0,
                     "download": 0.0}
    clock = time.perf_counter

    def lap(stage, t):
        if sync and dev.type == "cuda":
            torch.cuda.synchronize(dev)
        now = clock()
        seconds[stage] += now - t
        return now

    t = clock()
    n = len(prepared)
    bank = PatchBank.from_patches([s.patch for s in prepared], dev)
    has_env = [s.envelope is not None for s in prepared]
    ebank = PatchBank.from_patches([s.envelope if s.envelope is not None else s.patch for s in prepared], dev) \
        if any(has_env) else None
    markers_on = profile.markers.enabled and ("markers" in outputs or want_frames)
    rest = marker_grid(profile, seed=sensor_seed) if markers_on else None
    rngs = [np.random.default_rng(s.seed) for s in prepared]
    T = [s.motion.num_frames for s in prepared]
    labels = [{"indentation_mm": np.zeros(T[i], np.float32), "contact_area_mm2": np.zeros(T[i], np.float32),
               "contact_centroid_px": np.full((T[i], 2), np.nan, np.float32),
               "contact_bbox_px": np.full((T[i], 4), np.nan, np.float32),
               "markers_xy_px": np.zeros((T[i], 0 if rest is None else len(rest), 2), np.float32)}
              for i in range(n)]
    state: list = [None] * n
    t = lap("upload", t)
    frames_done = 0
    for step in range(max(T)):
        idx = [i for i in range(n) if step < T[i]]
        cons = [prepared[i].contact for i in idx]
        forces = np.array([float(c.normal_force_n[step]) for c in cons])
        touching = np.array([bool(c.in_contact[step]) and f > 0 for c, f in zip(cons, forces)])
        poses = [(float(c.position_mm[step, 0]), float(c.position_mm[step, 1]), float(c.yaw_deg[step]),
                  tuple(float(v) for v in c.tilt_deg[step])) for c in cons]
        live = [j for j in range(len(idx)) if touching[j]]
        depth = torch.zeros((len(idx), h, w), device=dev)
        mask = torch.zeros((len(idx), h, w), dtype=torch.bool, device=dev)
        if live:
            which = [idx[j] for j in live]
            prot = sample_patches(bank, which, [poses[j] for j in live], (h, w), mm)
            env = None
            if ebank is not None:
                env = sample_patches(ebank, which, [poses[j] for j in live], (h, w), mm)
            t = lap("sample", t)
            warm = [state[i] for i in which]
            ib = press_batch(prot, profile, fid, forces[live], props=[prepared[i].props for i in which],
                             envelope_mm=env, warm=warm)
            lt = torch.as_tensor(live, device=dev)
            depth[lt] = ib.depth_mm
            mask[lt] = ib.contact_mask
            t = lap("imprint", t)
            cen, bb = contact_location_torch(ib.contact_mask)
            for j, i in enumerate(which):
                lab = labels[i]
                lab["indentation_mm"][step] = ib.indentation_mm[j]
                lab["contact_area_mm2"][step] = ib.contact_area_mm2[j]
                lab["contact_centroid_px"][step] = cen[j]
                lab["contact_bbox_px"][step] = bb[j]
                state[i] = ib.states[j]
            t = lap("labels", t)
        for j, i in enumerate(idx):
            if not touching[j]:
                state[i] = None
        corners = None
        if rest is not None:
            shear = np.zeros((len(idx), 2))
            twist = np.zeros(len(idx))
            for j, c in enumerate(cons):
                if touching[j]:
                    sh, tw = tuple(float(v) for v in c.shear_mm[step]), float(c.twist_deg[step])
                    skip_s, skip_t = _negligible(sh, tw, profile)
                    shear[j] = (0.0, 0.0) if skip_s else sh
                    twist[j] = 0.0 if skip_t else tw
            xy, corners = displace_batch(profile, fid, depth, mask, shear_mm=shear, twist_deg=twist, rest=rest)
            xy_h = xy.cpu().numpy()
            for j, i in enumerate(idx):
                labels[i]["markers_xy_px"][step] = xy_h[j]
            t = lap("markers", t)
        if want_frames:
            offsets = [renderer.draw(rngs[i]) for i in idx]
            chunk = optics_batch or len(idx)
            for a in range(0, len(idx), chunk):
                part = slice(a, a + chunk)
                out = renderer.frames(depth[part], None if corners is None else corners[part], offsets[part])
                t = lap("optics", t)
                host = out.cpu().numpy()
                t = lap("download", t)
                if sink is not None:      # the consumer's time (encoding) is not a stage's
                    sink(host, [(i, step) for i in idx[part]])
                    t = clock()
        frames_done += len(idx)
    result = []
    for i, s in enumerate(prepared):
        lab = s.contact.to_dict()
        lab.update(labels[i])
        if "markers" in outputs or want_frames:   # the schema's key, empty without markers (as render_sequence's)
            lab["markers_rest_px"] = np.zeros((0, 2), np.float32) if rest is None else rest.astype(np.float32)
        result.append(lab)
    return {"labels": result, "seconds": seconds, "frames": frames_done}
