"""The whole frame on the device: a sequence's fabric patch to camera pixels, batched over frames.

What :func:`gelsim.sequence.render_sequence` does per frame after the physics, for many sequences in step (frame t
of every sequence in one batch, each warm-started from its own frame t - 1):

1. **Protrusion** (and the crown envelope) sampled from the sequence's patch at the frame's pose
   (:func:`sample_patches`: :meth:`gelsim.scene.HeightPatch.sample` on the device);
2. **imprint** (:func:`gelsim.device.imprint.press_batch`) and the contact labels (:func:`contact_labels`);
3. **markers** (:func:`gelsim.device.markers.displace_batch`), with the sequence's shortcut for negligible shear
   and twist;
4. **optics**: the torch backend's :class:`~gelsim.optics.torch_backend.BatchRenderer` fed device tensors
   (:class:`DeviceRenderer`, a thin adapter: its ``stage`` takes host arrays).

The physics (MuJoCo) and the fabric's patch stay on the CPU, once per sequence (:func:`prepare_sequence`).
:func:`render_sequences` strings them together and reports each stage's time; ``benchmarks/bench_device.py``
measures it. Labels match render_sequence's within the device imprint's tolerance
(:data:`gelsim.device.imprint.TOLERANCE`); frames within the torch backend's.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..optics.torch_backend import BatchRenderer
from ..scene import NEAR_TRANSLATION_PX
from . import ops


# ---------------------------------------------------------------- patches to protrusion maps

@dataclass
class PatchBank:
    """Height patches on the device: ``heights`` float32 ``(S, Hp, Wp)`` mm, patch s in the corner of the batch's
    largest, continued beyond its own ``sizes[s]`` (rows, cols) by replicating its edge (what the warp's
    replicated border reads there); ``origins`` (x0, y0) mm and ``mm_per_px`` as :class:`gelsim.scene.HeightPatch`."""
    heights: object
    sizes: list
    origins: list
    mm_per_px: float

    @classmethod
    def from_patches(cls, patches: list, device) -> "PatchBank":
        torch = ops.torch_module()
        hp = max(p.heights_mm.shape[0] for p in patches)
        wp = max(p.heights_mm.shape[1] for p in patches)
        out = np.empty((len(patches), hp, wp), np.float32)
        for s, p in enumerate(patches):
            a = p.heights_mm
            out[s] = np.pad(a, ((0, hp - a.shape[0]), (0, wp - a.shape[1])), mode="edge")
        mm = {float(p.mm_per_px) for p in patches}
        if len(mm) != 1:
            raise ValueError("patches of one bank share their cell size")
        return cls(torch.as_tensor(out, device=device), [p.heights_mm.shape for p in patches],
                   [tuple(p.origin_mm) for p in patches], mm.pop())


def sample_patches(bank: PatchBank, which, poses, shape: tuple[int, int], sensor_mm_per_px: float):
    """:meth:`gelsim.scene.HeightPatch.sample` of patch ``which[b]`` at pose ``poses[b]`` = (x_mm, y_mm, yaw_deg,
    (tilt_x, tilt_y) deg) for every frame: float32 ``(B, H, W)`` mm. Near a translation the same 2 x 2 filter
    (:func:`gelsim.scene._shifted`); else bilinear at the affine map's float coordinates, the patch's edge
    replicated (OpenCV's warpAffine; within about 1e-5 of the heights' range of it, its own float rounding)."""
    torch = ops.torch_module()
    dev = bank.heights.device
    H, W = shape
    bsz = len(which)
    s, p = sensor_mm_per_px, bank.mm_per_px
    cu, cv = (W - 1) / 2.0, (H - 1) / 2.0
    coef = np.zeros((bsz, 6))
    shifted = np.zeros(bsz, bool)
    fx = np.zeros(bsz, np.float32)
    fy = np.zeros(bsz, np.float32)
    ix = np.zeros(bsz, np.int64)
    iy = np.zeros(bsz, np.int64)
    tilt = np.zeros((bsz, 2), np.float32)
    for b, (k, pose) in enumerate(zip(which, poses)):
        x_mm, y_mm, yaw, tl = pose
        c, sn = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        x0, y0 = bank.origins[k]
        a11, a12, a21, a22 = c * s / p, -sn * s / p, sn * s / p, c * s / p
        b1 = (x_mm - x0) / p - a11 * cu - a12 * cv
        b2 = (y_mm - y0) / p - a21 * cu - a22 * cv
        coef[b] = (a11, a12, b1, a21, a22, b2)
        off = (abs(a11 - 1.0) + abs(a21)) * W + (abs(a12) + abs(a22 - 1.0)) * H
        if off <= NEAR_TRANSLATION_PX:
            tx = a11 * cu + a12 * cv + b1 - cu
            ty = a21 * cu + a22 * cv + b2 - cv
            xi, yi = math.floor(tx), math.floor(ty)
            rows, cols = bank.sizes[k]
            if not (xi < 0 or yi < 0 or xi + W + 1 > cols or yi + H + 1 > rows):
                shifted[b] = True
                ix[b], iy[b] = xi, yi
                fx[b], fy[b] = np.float32(tx - xi), np.float32(ty - yi)
        if tl[0] or tl[1]:
            tilt[b] = (np.float32(math.tan(math.radians(tl[1]))), np.float32(math.tan(math.radians(tl[0]))))
    src = bank.heights.index_select(0, ops.as_index(which, dev))
    rows_t = ops.as_index([bank.sizes[k][0] for k in which], dev)[:, None, None]
    cols_t = ops.as_index([bank.sizes[k][1] for k in which], dev)[:, None, None]
    wp = src.shape[2]
    flat = src.reshape(bsz, -1)

    hp = src.shape[1]

    def at(yy, xx):
        i = yy.clamp(0, hp - 1) * wp + xx.clamp(0, wp - 1)
        return torch.gather(flat, 1, i.reshape(bsz, -1)).reshape(i.shape)

    # the general map: float64 coordinates, replicated edge
    cf = torch.as_tensor(coef, device=dev)
    xs = torch.arange(W, device=dev, dtype=torch.float64)[None, None, :]
    ys = torch.arange(H, device=dev, dtype=torch.float64)[None, :, None]
    X = cf[:, 0, None, None] * xs + cf[:, 1, None, None] * ys + cf[:, 2, None, None]
    Y = cf[:, 3, None, None] * xs + cf[:, 4, None, None] * ys + cf[:, 5, None, None]
    x0 = torch.floor(X)
    y0 = torch.floor(Y)
    ax = (X - x0).float()
    ay = (Y - y0).float()
    x0 = x0.long()
    y0 = y0.long()
    cx0, cx1 = x0.clamp(0) .minimum(cols_t - 1), (x0 + 1).clamp(0).minimum(cols_t - 1)
    cy0, cy1 = y0.clamp(0).minimum(rows_t - 1), (y0 + 1).clamp(0).minimum(rows_t - 1)
    out = (at(cy0, cx0) * ((1 - ay) * (1 - ax)) + at(cy0, cx1) * ((1 - ay) * ax)
           + at(cy1, cx0) * (ay * (1 - ax)) + at(cy1, cx1) * (ay * ax))
    if shifted.any():
        ixt = ops.as_index(ix, dev)[:, None, None]
        iyt = ops.as_index(iy, dev)[:, None, None]
        xx = torch.arange(W, device=dev)[None, None, :] + ixt
        yy = torch.arange(H, device=dev)[None, :, None] + iyt
        fxt = torch.as_tensor(fx, device=dev)[:, None, None]
        fyt = torch.as_tensor(fy, device=dev)[:, None, None]
        one = 1.0
        k00, k01 = (one - fxt) * (one - fyt), fxt * (one - fyt)
        k10, k11 = (one - fxt) * fyt, fxt * fyt
        xx1 = xx + 1
        yy1 = yy + 1
        sh = at(yy, xx) * k00 + at(yy, xx1) * k01 + at(yy1, xx) * k10 + at(yy1, xx1) * k11
        out = torch.where(torch.as_tensor(shifted, device=dev)[:, None, None], sh, out)
    if tilt.any():
        xs32 = ((torch.arange(W, device=dev, dtype=torch.float32) - cu) * s).float()
        ys32 = ((torch.arange(H, device=dev, dtype=torch.float32) - cv) * s).float()
        tt = torch.as_tensor(tilt, device=dev)
        out = out + tt[:, 0, None, None] * xs32[None, None, :]
        out = out + tt[:, 1, None, None] * ys32[None, :, None]
    return out


# ---------------------------------------------------------------- labels

def contact_labels(mask):
    """:func:`gelsim.sequence.contact_location` per frame of bool ``(B, H, W)``: centroid float ``(B, 2)`` (x, y)
    px and bounding box float ``(B, 4)`` (x0, y0, x1, y1) of the pixels' edges, NaN for an empty mask (numpy)."""
    torch = ops.torch_module()
    cols = mask.sum(dim=1, dtype=torch.float64)            # (B, W)
    rows = mask.sum(dim=2, dtype=torch.float64)            # (B, H)
    n = cols.sum(dim=1)
    cx = (cols * torch.arange(cols.shape[1], device=mask.device, dtype=torch.float64)).sum(dim=1)
    cy = (rows * torch.arange(rows.shape[1], device=mask.device, dtype=torch.float64)).sum(dim=1)
    box = ops.bbox(mask)
    n, cx, cy, box = n.cpu().numpy(), cx.cpu().numpy(), cy.cpu().numpy(), box.cpu().numpy()
    empty = n == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = np.stack([cx / n, cy / n], axis=1)
    bb = np.stack([box[:, 2] - 0.5, box[:, 0] - 0.5, box[:, 3] - 0.5, box[:, 1] - 0.5], axis=1).astype(np.float64)
    cen[empty] = np.nan
    bb[empty] = np.nan
    return cen, bb


# ---------------------------------------------------------------- optics from device tensors

class DeviceRenderer(BatchRenderer):
    """The torch backend's :class:`~gelsim.optics.torch_backend.BatchRenderer` with one call for a batch whose
    depth and marker corners are already device tensors (its :meth:`stage` and :meth:`compose` keep them there)."""

    def frames(self, depth, corners, offsets):
        """uint8 ``(B, H, W, 3)`` on the device from depth float32 ``(B, H, W)`` mm, corners float32 ``(B, N, 4, 2)``
        px (or None) and each frame's draws (:meth:`draw`)."""
        corners = corners if self.profile.markers.enabled else None
        return self.quantise(self.compose(depth, corners, offsets), offsets)


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
    """Render ``prepared`` sequences in step on the device of ``renderer`` (a :class:`DeviceRenderer`): frame t of
    every sequence in one batch. Each finished batch of uint8 frames goes to ``sink(frames (B, H, W, 3) host
    array, [(sequence, frame index), ...])`` when given; ``optics_batch``: the optics render at most that many
    frames per call (the same bytes for any: the torch optics' frames do not depend on their batch). Returns each sequence's labels (as render_sequence's)
    under ``"labels"``, and ``"seconds"``: wall seconds per stage (``sync``: the device is synchronised at each
    stage's end, so that the stages' times are its own) and ``"frames"``: the count."""
    torch = ops.torch_module()
    from ..fidelity import get_fidelity
    from ..markers import marker_grid
    from .imprint import press_batch
    from .markers import displace_batch

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
            cen, bb = contact_labels(ib.contact_mask)
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
