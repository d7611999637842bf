"""The two engines of the frame pipeline (:func:`gelsim.stream.make_frames`), side by side: what each stage of a
batch of frames runs on.

* :class:`NumpyEngine`: the frames one by one on the CPU, in numpy, OpenCV and numba: :func:`gelsim.gel.press`,
  :func:`gelsim.markers.displace`, :func:`gelsim.labels.contact_location`, :meth:`gelsim.optics.Renderer.render_input`.
  The bit-exact reference and the CPU default (a batch of one, as a sequence, a sensor or ``gelsim render`` makes
  them).
* :class:`TorchEngine`: the whole batch at once on a torch device (``cpu`` or ``cuda``):
  :func:`gelsim.gel.twoscale_torch.press_batch`, :func:`gelsim.markers_torch.displace_batch`,
  :func:`gelsim.labels.contact_location_torch`, :meth:`gelsim.optics.torch_backend.BatchRenderer.frames`. Within
  the stated tolerances of the numpy engine (:data:`gelsim.gel.twoscale_torch.TOLERANCE`,
  :data:`gelsim.markers_torch.TOL_PX`, the torch optics' ``TOL_MAX_UINT8_DN``).

An engine has the same methods, each on the whole batch: ``press`` (the touches' imprints), ``displace`` (the
markers), ``locate`` (each imprint's contact centroid and box), ``render`` (the uint8 frames of the frames' optics
inputs), ``clock`` (its stage clock), and for sequences ``upload`` and ``crown_envelopes`` (the objects' height
patches and their crown envelopes, as the engine keeps them), ``heights`` and ``envelopes`` (those seen through each
frame's pose: :meth:`gelsim.scene.HeightPatch.sample` or its torch twin
:func:`gelsim.scene_torch.sample_patches`), ``renderer`` (the default renderer) and ``to_host`` (the frames as
uint8 arrays on the host). The imprints and markers it returns are its own batch objects; ``imprint``
and ``markers`` give frame ``b``'s as :class:`gelsim.gel.Imprint` and :class:`gelsim.markers.Markers` (the torch
engine's imprint holds tensors on its device). What is done with them, in which order, is the pipeline's, written
once.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .gel import Imprint, press
from .labels import contact_location
from .markers import Markers, displace

# Stage clock of the numpy engine: the thread's CPU time. A generation worker is one thread on one core, so this is
# its per-core cost whatever else the machine runs (wall time would count other processes' turns).
stage_clock = time.thread_time


class NumpyEngine:
    """The frames one at a time on the CPU (see the module docstring). Its batch objects are lists, one entry per
    frame (None where a frame has none). A touch given again right after itself (the same object: a frame rendered
    with several noise draws) is pressed once.
    ``clock``: its stage clock (default :data:`stage_clock`, the thread's CPU time; ``gelsim render`` reports
    wall time)."""

    name = "numpy"
    #: Sequences give this engine their finished patches and envelopes (:class:`gelsim.sequence.SequenceRun`).
    device_patches = False

    def __init__(self, clock=stage_clock):
        self.clock = clock

    @staticmethod
    def renderer(profile, fidelity, seed: int):
        """The default renderer of ``profile`` at ``fidelity`` (its backend and supersampling; ``seed``: the
        sensor's background and noise bank)."""
        from .optics import Renderer

        return Renderer(profile, fidelity.render_backend, supersample=fidelity.supersample, seed=seed)

    @staticmethod
    def upload(patches: Sequence) -> list:
        """Height patches (:class:`gelsim.scene.HeightPatch`, :class:`gelsim.scene.PatchParts` finished here, or
        None) as :meth:`heights` reads them."""
        return [p.finish() if hasattr(p, "finish") else p for p in patches]

    def crown_envelopes(self, patches: list, runs: Sequence) -> list:
        """The sequences' crown envelopes (their :class:`gelsim.sequence.SequenceRun`'s, made on the host) as
        :meth:`envelopes` reads them."""
        return self.upload([r.envelope for r in runs])

    @staticmethod
    def heights(patches: list, which: Sequence[int], poses: Sequence, profile) -> list[np.ndarray]:
        """Patch ``which[b]`` seen through pose ``poses[b]`` = (x mm, y mm, yaw deg, (tilt x, tilt y) deg) at the
        profile's image: float32 (H, W) mm each."""
        return [patches[k].sample(profile.shape, profile.image.mm_per_px, *pose) for k, pose in zip(which, poses)]

    @staticmethod
    def envelopes(patches: list, which: Sequence[int], poses: Sequence, profile) -> list:
        """The crown envelopes as :func:`gelsim.gel.press` reads them: a function of the box it reads (the
        touched region only), or None where a sequence has none."""
        return [None if patches[k] is None else
                functools.partial(patches[k].sample, profile.shape, profile.image.mm_per_px, *pose)
                for k, pose in zip(which, poses)]

    @staticmethod
    def to_host(frames):
        return frames

    def press(self, touches: Sequence, setup) -> list[Imprint | None]:
        out: list[Imprint | None] = []
        last = None
        for t in touches:
            if t is None:
                out.append(None)
            elif last is not None and t is last[0]:
                out.append(last[1])
            else:
                imp = press(t.protrusion_mm, setup.profile, setup.fidelity, force_n=t.force_n, depth_mm=t.depth_mm,
                            window=t.window, warm=t.warm, envelope_mm=t.envelope_mm, **t.properties)
                last = (t, imp)
                out.append(imp)
        return out

    def displace(self, imprints: list, touches: Sequence, setup) -> list[Markers]:
        flat = setup.flat_markers
        out = []
        for imp, t in zip(imprints, touches):
            if imp is None:
                out.append(flat)
            else:
                out.append(displace(setup.profile, setup.fidelity, imp, shear_mm=t.shear_mm, twist_deg=t.twist_deg,
                                    rest=flat.rest_px))
        return out

    def locate(self, imprints: list) -> list:
        return [None if imp is None else contact_location(imp.contact_mask) for imp in imprints]

    def render(self, inputs: Sequence, setup) -> list[np.ndarray]:
        return [setup.renderer.render_input(i) for i in inputs]

    @staticmethod
    def imprint(imprints: list, b: int) -> Imprint | None:
        return imprints[b]

    @staticmethod
    def markers(markers: list, b: int) -> Markers | None:
        return markers[b]

    @staticmethod
    def render_markers(markers: list, b: int) -> Markers | None:
        """Frame ``b``'s markers as the optics read them."""
        return markers[b]

    @staticmethod
    def render_depth(imprint: Imprint | None, dents_mm: np.ndarray | None) -> np.ndarray | None:
        """The depth the optics render, float32 ``(H, W)`` mm or None: the imprint's plus the nuisance's dents (the
        fibres of a hairy fabric), never added to the imprint itself (the labels')."""
        depth = None if imprint is None else imprint.depth_mm
        if dents_mm is None:
            return depth
        return dents_mm if depth is None else depth + dents_mm

    @staticmethod
    def render_extent(imprint: Imprint | None, dents_mm: np.ndarray | None) -> tuple[int, int, int, int] | None:
        """The box where :meth:`render_depth` is positive, ``(row0, row1, col0, col1)``, where it is the imprint's
        own depth (its :attr:`~gelsim.gel.Imprint.depth_extent`, the markers' too); None otherwise (with dents
        the optics find it themselves)."""
        return None if imprint is None or dents_mm is not None else imprint.depth_extent


@dataclass
class TorchImprints:
    """A batch's imprints on the device: ``depth_mm`` float32 ``(B, H, W)`` mm and ``contact_mask`` bool ``(B, H, W)``
    (zero where a frame has no touch), ``pressed`` which frames had one, and ``batch`` the
    :class:`gelsim.gel.twoscale_torch.ImprintBatch` of the pressed ones (in order)."""
    depth_mm: object
    contact_mask: object
    pressed: list[int]
    batch: object


@dataclass
class TorchMarkers:
    """A batch's markers: ``xy`` float32 ``(B, N, 2)`` and ``corners`` ``(B, N, 4, 2)`` px on the device, their
    host copies ``xy_host`` and ``corners_host``, and ``rest`` float32 ``(N, 2)`` px."""
    xy: object
    corners: object
    xy_host: np.ndarray
    corners_host: np.ndarray
    rest: np.ndarray


class TorchEngine:
    """The whole batch at once on ``device`` (see the module docstring). ``optics_batch``: the optics render at
    most that many frames per call (the torch optics' frames do not depend on their batch); ``sync``: the clock
    waits for the device (each stage's time its own on a GPU; else what the host waited for). ``i420``: the frames
    come to the host as :class:`gelsim.video.I420` (converted on the device, :func:`gelsim.video_torch.rgb_to_i420`:
    half the bytes, and no conversion left to the host's encoder; an H.264 video of even size takes them)."""

    name = "torch"
    #: Sequences leave this engine their patches' last steps (a rotated fabric's resampling, the crown envelope),
    #: made on its device (:func:`gelsim.scene_torch.finish_rotated`, :meth:`gelsim.scene_torch.PatchBank.closed`).
    device_patches = True

    def __init__(self, device=None, *, optics_batch: int | None = None, sync: bool = False, i420: bool = False):
        from .optics.torch_backend import resolve_device

        self.device = device if hasattr(device, "type") else resolve_device(device)
        self.optics_batch = optics_batch
        self.sync = sync
        self.i420 = i420

    def clock(self) -> float:
        if self.sync and self.device.type == "cuda":
            import torch

            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def renderer(self, profile, fidelity, seed: int):
        """The torch optics of ``profile`` on this engine's device (supersampling of ``fidelity``)."""
        from .optics import Renderer
        from .optics.torch_backend import BatchRenderer

        return BatchRenderer(Renderer(profile, "torch", supersample=fidelity.supersample, seed=seed,
                                      device=self.device))

    def upload(self, patches: Sequence):
        """Height patches on the device (:class:`gelsim.scene_torch.PatchBank`, a rotated fabric's
        :class:`gelsim.scene.PatchParts` finished there; None where a sequence has none, none at all: None)."""
        from .scene_torch import PatchBank

        have = [k for k, p in enumerate(patches) if p is not None]
        if not have:
            return None
        return PatchBank.from_patches([patches[k] for k in have], self.device), {k: j for j, k in enumerate(have)}

    def crown_envelopes(self, bank, runs: Sequence):
        """The sequences' crown envelopes on the device, as :meth:`envelopes` reads them: the closings of ``bank``'s
        patches (:meth:`gelsim.scene_torch.PatchBank.closed`, :attr:`gelsim.sequence.SequenceRun.envelope_px`), or
        the runs' own where they were made on the host (runs prepared for the numpy engine)."""
        made = [r.envelope is not None for r in runs]
        if any(made):
            if not all(made[k] or r.envelope_px is None for k, r in enumerate(runs)):
                raise ValueError("runs prepared for both engines in one batch; prepare them with one device_patch")
            return self.upload([r.envelope for r in runs])
        if bank is None:
            return None
        patches, index = bank
        have = [k for k, r in enumerate(runs) if k in index and r.envelope_px is not None]
        if not have:
            return None
        return patches.closed({index[k]: runs[k].envelope_px for k in have}), {k: j for j, k in enumerate(have)}

    def heights(self, bank, which: Sequence[int], poses: Sequence, profile) -> list:
        """:meth:`NumpyEngine.heights` on the device (:func:`gelsim.scene_torch.sample_patches`): tensor rows."""
        from .scene_torch import sample_patches

        if not which:
            return []
        patches, index = bank
        poses = [(float(x), float(y), float(yaw), tuple(float(v) for v in tilt)) for x, y, yaw, tilt in poses]
        out = sample_patches(patches, [index[k] for k in which], poses, profile.shape, profile.image.mm_per_px)
        return list(out)

    def envelopes(self, bank, which: Sequence[int], poses: Sequence, profile) -> list:
        """The crown envelopes seen through each pose on the device (tensor rows), None where a sequence has none."""
        if bank is None:
            return [None] * len(which)
        have = [j for j, k in enumerate(which) if k in bank[1]]
        rows = self.heights(bank, [which[j] for j in have], [poses[j] for j in have], profile)
        out: list = [None] * len(which)
        for j, r in zip(have, rows):
            out[j] = r
        return out

    def to_host(self, frames):
        """uint8 ``(B, H, W, 3)`` frames on the device, as a host array; with ``i420``, a list of
        :class:`gelsim.video.I420` (converted here, on the device)."""
        if not self.i420:
            return frames.cpu().numpy()
        from .video import I420
        from .video_torch import rgb_to_i420

        return [I420(p) for p in rgb_to_i420(frames).cpu().numpy()]

    def _tensor(self, x):
        import torch

        return x if torch.is_tensor(x) else torch.as_tensor(np.ascontiguousarray(x, np.float32), device=self.device)

    def press(self, touches: Sequence, setup) -> TorchImprints:
        import torch

        from .gel.twoscale_torch import press_batch

        h, w = setup.profile.shape
        n = len(touches)
        depth = torch.zeros((n, h, w), device=self.device)
        mask = torch.zeros((n, h, w), dtype=torch.bool, device=self.device)
        pressed = [b for b, t in enumerate(touches) if t is not None]
        batch = None
        if pressed:
            ts = [touches[b] for b in pressed]
            if any(t.window != "touched" or t.depth_mm is not None for t in ts):
                from .errors import GelsimError

                raise GelsimError("the torch engine presses by force over the touched window; use the numpy engine "
                                  "for press(depth_mm=) or window='full'")
            prot = torch.stack([self._tensor(t.protrusion_mm) for t in ts])
            env = None
            if any(t.envelope_mm is not None for t in ts):        # (a frame without one: its heights, never read)
                env = torch.stack([self._tensor(t.envelope_mm if t.envelope_mm is not None else t.protrusion_mm)
                                   for t in ts])
            batch = press_batch(prot, setup.profile, setup.fidelity, [float(t.force_n) for t in ts],
                                props=[t.properties for t in ts], envelope_mm=env,
                                warm=[None if t.warm is None else t.warm.state for t in ts])
            ix = torch.as_tensor(pressed, device=self.device)
            depth[ix] = batch.depth_mm
            mask[ix] = batch.contact_mask
        return TorchImprints(depth, mask, pressed, batch)

    def displace(self, imprints: TorchImprints, touches: Sequence, setup) -> TorchMarkers:
        from .markers_torch import displace_batch

        n = len(touches)
        shear = np.zeros((n, 2))
        twist = np.zeros(n)
        for b, t in enumerate(touches):
            if t is not None:
                shear[b], twist[b] = t.shear_mm, t.twist_deg
        rest = setup.flat_markers.rest_px
        xy, corners = displace_batch(setup.profile, setup.fidelity, imprints.depth_mm, imprints.contact_mask,
                                     shear_mm=shear, twist_deg=twist, rest=rest)
        return TorchMarkers(xy, corners, xy.cpu().numpy(), corners.cpu().numpy(), rest)

    def locate(self, imprints: TorchImprints) -> list:
        from .labels import contact_location_torch

        out: list = [None] * imprints.depth_mm.shape[0]
        if imprints.pressed:
            cen, box = contact_location_torch(imprints.batch.contact_mask)
            for j, b in enumerate(imprints.pressed):
                out[b] = (cen[j], box[j])
        return out

    def render(self, inputs: Sequence, setup):
        """uint8 ``(B, H, W, 3)`` on the device from the frames' optics inputs (depth and marker corners as
        tensors on the device, or None)."""
        import torch

        br = setup.renderer
        h, w = setup.profile.shape
        depth = torch.stack([torch.zeros((h, w), device=self.device) if i.depth_mm is None else i.depth_mm
                             for i in inputs])
        corners = None
        if br.profile.markers.enabled and any(i.markers is not None for i in inputs):
            corners = torch.stack([i.markers for i in inputs])
        draws = [br.draw(i.seed, i.noise) for i in inputs]
        gains = [i.gains for i in inputs]
        gains = None if all(g is None for g in gains) else gains
        n = len(inputs)
        chunk = self.optics_batch or n
        parts = []
        for a in range(0, n, chunk):
            s = slice(a, a + chunk)
            parts.append(br.frames(depth[s], None if corners is None else corners[s], draws[s],
                                   None if gains is None else gains[s], list(inputs[s])))
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    @staticmethod
    def imprint(imprints: TorchImprints, b: int) -> Imprint | None:
        """Frame ``b``'s imprint (its depth and mask tensors views of the batch's), None without a touch."""
        if b not in imprints.pressed:
            return None
        j = imprints.pressed.index(b)
        ib = imprints.batch
        return Imprint(imprints.depth_mm[b], imprints.contact_mask[b], float(ib.indentation_mm[j]),
                       float(ib.normal_force_n[j]), float(ib.contact_area_mm2[j]), bool(ib.bottomed[j]), ib.states[j])

    @staticmethod
    def markers(markers: TorchMarkers, b: int) -> Markers:
        return Markers(markers.rest, markers.xy_host[b], markers.corners_host[b])

    @staticmethod
    def render_markers(markers: TorchMarkers, b: int):
        """Frame ``b``'s marker corners as the optics read them: a tensor on the device."""
        return markers.corners[b]

    def render_depth(self, imprint: Imprint | None, dents_mm: np.ndarray | None):
        """:meth:`NumpyEngine.render_depth` on the device (the dents, made on the host per sequence, moved here)."""
        depth = None if imprint is None else imprint.depth_mm
        if dents_mm is None:
            return depth
        dents = self._tensor(dents_mm)
        return dents if depth is None else depth + dents

    @staticmethod
    def render_extent(imprint: Imprint | None, dents_mm: np.ndarray | None) -> None:
        """None: the batch renderer finds its frames' boxes on the device (:meth:`NumpyEngine.render_extent`)."""
        return None
