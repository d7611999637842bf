"""One tactile sequence end to end: touched object -> contact -> gel -> optics.

:func:`render_sequence` strings the stages together for one (object, motion) pair: the object's
heights and the contact simulation once (:class:`SequenceRun`), then per frame the frame pipeline of
:mod:`gelsim.stream` (imprint, nuisance, markers, labels, optics). It yields one
:class:`gelsim.stream.FrameRecord` per frame (constant memory) to whoever consumes them
(:mod:`gelsim.sinks`); the sequence's labels are assembled from the records'
(:func:`gelsim.stream.sequence_labels`). :func:`render_sequences` runs several sequences in step, frame t
of each in one batch of the pipeline (the torch engine's way; on the numpy engine the same bytes as one by
one). Their options (renderer, sensor seed, shortcuts, outputs, nuisance, reused parts) are one
:class:`SequenceOptions`.

Shortcuts (``SequenceOptions(shortcuts=True)``, the default) skip work a frame does not need; each
gives the full computation's result within the tolerance stated here, checked by
``tests/gelsim/test_shortcuts.py``, and ``gelsim bench`` reports what they save:

* frames out of contact reuse the flat gel: no protrusion sample, no imprint, no
  marker solve, the cached background (exact);
* the imprint, the marker fields and the shading are computed over the touched
  region only (``press(window="touched")``; pyramid model: indentation and contact area
  within 1% of the full frame's on fabric presses (0.12% measured), up to 3% on a sphere at
  work grids of 96x72 and 160x120 (equal at 320x240 and up), frames within 1 DN (3 DN on that
  sphere);
  elastic model: it cuts its 1/r tail 3 gel thicknesses from the contact, < 2% of the
  peak depth);
* shear and twist terms whose largest marker displacement is below
  :data:`NEGLIGIBLE_PX` are dropped (press sequences: the hand's tremor twists the gel
  by about 0.001 degree); markers then move by < NEGLIGIBLE_PX;
* outputs nobody asked for (``outputs``) are not computed: without ``"frames"`` no
  optics; without ``"frames"`` and ``"markers"`` no marker solve; with none of the
  three, no imprint either (exact: the labels that are computed are unchanged).

``shortcuts=False`` runs every stage on every frame over the full frame (for tests
and for measuring the savings).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Collection, Iterator, Mapping, Sequence

import numpy as np

from .contact import ContactFrames, Surface, simulate
from .errors import GelsimError
from .fidelity import Fidelity
from .gel.twoscale import crown_envelope, envelope_kernel_px, texture_scale_mm
from .motion import Motion
from .scene import PHYSICS_MM_PER_PX, HeightPatch, TouchedObject, as_object, physics_surface, press_properties, travel_patch, travel_patch_parts  # noqa: F401
from .sensor import SensorProfile
from .stream import (NUMPY, FrameParts, FrameRecord, FrameRequest, FrameSetup, StageTimer, Touch, make_frames,
                     noise_generator)

# Shear and twist terms that move no marker by more than this are skipped, px. A marker edge
# moving by 0.005 px changes its anti-aliased coverage by 0.5% of a pixel: at most about
# 0.6 DN (darkness 0.85 of a ~140 DN gel), below half a quantisation step.
NEGLIGIBLE_PX = 0.005
# What render_sequence can produce besides the contact labels (always computed).
OUTPUTS = frozenset({"frames", "imprint", "markers"})


@dataclass(frozen=True)
class SequenceOptions:
    """How :func:`render_sequence` (and :func:`render_sequences`) runs: what it computes, and the parts of the
    sequence already computed.

    ``renderer``: the sensor's renderer for the engine (a :class:`gelsim.optics.Renderer` for the numpy engine,
    a :class:`gelsim.optics.torch_backend.BatchRenderer` for the torch engine; default: the engine's for the
    fidelity level, made per call). ``sensor_seed`` fixes what belongs to the physical sensor and stays the same across a
    dataset (background illumination field, printed marker jitter). ``shortcuts``: skip work frames do
    not need (see the module docstring); False computes everything on every frame. ``outputs``: any of
    ``"frames"``, ``"imprint"`` (labels ``indentation_mm``, ``contact_area_mm2``, ``contact_centroid_px``,
    ``contact_bbox_px``) and ``"markers"`` (``markers_xy_px``, ``markers_rest_px``); the contact labels are
    always computed; without ``"frames"`` the records carry no frame (a sink may render them:
    :class:`gelsim.sinks.DeviceFrames`). ``contact``: a finished contact simulation of this motion to reuse
    (no physics run; e.g. to compare fidelity levels on the same contact). ``surface`` and ``patch``: the
    object's physics surface and image-resolution heights when already built (default:
    :func:`gelsim.scene.physics_surface` and :func:`gelsim.scene.travel_patch`). ``nuisance``: stage ->
    severity of a nuisance level (:meth:`gelsim.nuisance.NuisanceModel.level`; empty: none, today's
    frames), ``nuisance_stages`` the stages' parameters (default: gelsim/assets/nuisance.toml's).
    """
    renderer: Any = None
    sensor_seed: int = 0
    shortcuts: bool = True
    outputs: Collection[str] = OUTPUTS
    contact: ContactFrames | None = None
    surface: Surface | None = None
    patch: HeightPatch | None = None
    nuisance: Mapping[str, float] = field(default_factory=dict)
    nuisance_stages: object = None

    def __post_init__(self):
        outputs = frozenset(self.outputs)
        if not outputs <= OUTPUTS:
            raise GelsimError(f"unknown outputs {sorted(outputs - OUTPUTS)}; choose from {sorted(OUTPUTS)}")
        object.__setattr__(self, "outputs", outputs)


def negligible_px(shear_mm, twist_deg: float, profile: SensorProfile) -> tuple[bool, bool]:
    """Whether the shear and the twist each move every marker by less than NEGLIGIBLE_PX.

    The twist's lever arm is bounded by the image's diagonal (the centroid lies inside)."""
    mmpp = profile.image.mm_per_px
    shear_px = math.hypot(float(shear_mm[0]), float(shear_mm[1])) / mmpp
    h, w = profile.shape
    twist_px = abs(math.radians(float(twist_deg))) * math.hypot(w, h)
    return shear_px < NEGLIGIBLE_PX, twist_px < NEGLIGIBLE_PX


def crown_envelope_px(patch, obj: TouchedObject, profile: SensorProfile, fidelity: Fidelity) -> int | None:
    """The side of the crown envelope's closing on ``patch``'s grid (:func:`gelsim.gel.twoscale.envelope_kernel_px`,
    px); None when no frame needs an envelope (no patch, an object without texture, a model without the envelope)."""
    tex = texture_scale_mm(obj.texture_mm, profile.gel)
    if patch is None or tex is None or fidelity.imprint_model not in ("twoscale", "elastic"):
        return None
    return envelope_kernel_px(tex, patch.mm_per_px)


def crown_envelope_patch(patch: HeightPatch | None, obj: TouchedObject, profile: SensorProfile,
                         fidelity: Fidelity) -> HeightPatch | None:
    """The crown envelope (:func:`gelsim.gel.twoscale.crown_envelope`) of ``patch``'s heights, on its grid;
    None when no frame needs one (:func:`crown_envelope_px`)."""
    if crown_envelope_px(patch, obj, profile, fidelity) is None:
        return None
    tex = texture_scale_mm(obj.texture_mm, profile.gel)
    return HeightPatch(crown_envelope(patch.heights_mm, tex, patch.mm_per_px), patch.origin_mm, patch.mm_per_px)


class SequenceRun:
    """One sequence's frames, one at a time, for any engine: what :func:`render_sequences` keeps per sequence.

    Built once (the contact simulation, the object's image-resolution patch and its crown envelope, the nuisance,
    the noise stream: their seconds in :attr:`seconds`; with ``device_patch``, the patch's host part only,
    :func:`gelsim.scene.travel_patch_parts`, and the envelope's side, :attr:`envelope_px`, both for the torch
    engine to finish on its device), it gives each frame's pose and request
    (:meth:`request`: the :class:`gelsim.stream.Touch` with the sequence's shortcuts and warm start) and makes its
    record from what the pipeline made (:meth:`record`: the contact simulation's row of labels, then the
    pipeline's)."""

    def __init__(self, obj, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *, seed: int,
                 options: SequenceOptions = SequenceOptions(), device_patch: bool = False):
        o = self.options = options
        self.device_patch = device_patch
        self.obj = obj = as_object(obj)
        self.motion, self.profile, self.fidelity, self.seed, self.shortcuts = motion, profile, fidelity, seed, o.shortcuts
        contact = o.contact
        if contact is not None and len(contact.normal_force_n) != motion.num_frames:
            raise GelsimError(f"contact has {len(contact.normal_force_n)} frames, the motion {motion.num_frames}; "
                              "simulate this motion")
        self.want_imprint = bool({"frames", "markers", "imprint"} & o.outputs)
        timer = StageTimer()
        if contact is None:
            surface = o.surface if o.surface is not None else physics_surface(obj, motion, profile, seed=seed)
            timer.lap("fabric")
            contact = simulate(motion, surface, profile, fidelity)
            timer.lap("physics")
        self.contact = contact
        self.props = press_properties(obj)
        # The image-resolution patch is the costliest fabric step: built only if some frame presses.
        touches = bool(np.any(contact.in_contact & (contact.normal_force_n > 0)))
        patch = o.patch
        if patch is None and self.want_imprint and (touches or not o.shortcuts):
            make = travel_patch_parts if device_patch else travel_patch
            patch = make(obj, motion, profile, profile.image.mm_per_px, seed=seed,
                         poses=(contact.position_mm, contact.yaw_deg))
        self.patch = patch
        # The crown envelope of the object's texture is a property of the object, not of the pose: taken once
        # on the patch and seen through each frame's pose like the heights (press(envelope_mm=)).
        self.envelope_px = crown_envelope_px(patch, obj, profile, fidelity)
        self.envelope = None if device_patch else crown_envelope_patch(patch, obj, profile, fidelity)
        timer.lap("fabric")
        self.nuisance = None
        if o.nuisance:
            from .nuisance import load_nuisance
            from .nuisance.sequence import SequenceNuisance

            stages = o.nuisance_stages if o.nuisance_stages is not None else load_nuisance().stages
            hairiness = float(getattr(getattr(obj, "fabric", None), "hairiness", 0.0) or 0.0)
            self.nuisance = SequenceNuisance(o.nuisance, stages, seed, hairiness, profile, motion)
            timer.lap("nuisance")
        self.seconds = timer.take()
        self.state = contact.to_dict()
        self.rng = noise_generator(seed)
        self.window = "touched" if o.shortcuts else "full"
        self.prev = None  # the previous frame's imprint warm-starts the next (same result, fewer iterations)

    @property
    def num_frames(self) -> int:
        return self.motion.num_frames

    def again(self) -> "SequenceRun":
        """This sequence from its first frame again, its contact simulation and patch reused (a benchmark's
        repetition: no physics)."""
        return SequenceRun(self.obj, self.motion, self.profile, self.fidelity, seed=self.seed,
                           options=dataclasses.replace(self.options, contact=self.contact, patch=self.patch),
                           device_patch=self.device_patch)

    def touching(self, i: int) -> bool:
        """Frame ``i`` is pressed: in contact with a positive normal force."""
        return bool(self.contact.in_contact[i]) and float(self.contact.normal_force_n[i]) > 0.0

    def pose(self, i: int):
        """Frame ``i``'s pose, (x mm, y mm, yaw deg, (tilt x, tilt y) deg), when it presses the gel (a frame out of
        contact does not, with the shortcuts; nor any when no output needs an imprint); None else."""
        if not (self.want_imprint and (self.touching(i) or not self.shortcuts)):
            return None
        c = self.contact
        return c.position_mm[i, 0], c.position_mm[i, 1], c.yaw_deg[i], tuple(c.tilt_deg[i])

    def request(self, i: int, protrusion_mm=None, envelope_mm=None) -> FrameRequest:
        """Frame ``i``'s request to the pipeline, given its heights (``protrusion_mm``, ``envelope_mm``: the patch
        and the envelope seen through :meth:`pose`; ignored when the frame does not press)."""
        touch = None
        if self.pose(i) is not None:
            c = self.contact
            force = float(c.normal_force_n[i])
            shear, twist = tuple(float(v) for v in c.shear_mm[i]), float(c.twist_deg[i])
            if self.shortcuts:
                skip_shear, skip_twist = negligible_px(shear, twist, self.profile)
                shear = (0.0, 0.0) if skip_shear else shear
                twist = 0.0 if skip_twist else twist
            touch = Touch(protrusion_mm, force_n=force if self.touching(i) else 0.0, shear_mm=shear, twist_deg=twist,
                          warm=self.prev, window=self.window, envelope_mm=envelope_mm, properties=self.props)
        return FrameRequest(touch, self.rng, True, self.nuisance, i, self.contact.tilt_deg[i])

    def record(self, i: int, request: FrameRequest, part: FrameParts, seconds: dict) -> FrameRecord:
        """Frame ``i``'s record from the pipeline's ``part`` of it (its ``frame`` on the host) and its ``seconds``
        (the sequence's set-up seconds go to its first record)."""
        if request.touch is not None:
            self.prev = part.imprint if self.touching(i) else None
        if self.seconds:
            seconds = _sum_seconds(self.seconds, seconds)
            self.seconds = {}
        labels = {k: v[i] for k, v in self.state.items()}
        labels.update(part.labels)
        return FrameRecord(i, request.touch, part.imprint, part.markers, part.frame, labels, seconds, part.nuisance,
                           part.optics)


def _sum_seconds(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = out.get(k, 0.0) + v
    return out


def render_sequences(sequences: Sequence, profile: SensorProfile, fidelity: Fidelity, *,
                     options: SequenceOptions = SequenceOptions(), engine=NUMPY) -> Iterator[tuple[int, FrameRecord]]:
    """The frames of ``sequences`` ((object, motion, seed) each, made with ``options``, or a :class:`SequenceRun`
    made already) in step: frame t of every sequence still running
    in one batch of the pipeline (:func:`gelsim.stream.make_frames` on ``engine``), each warm-started from its own
    frame t - 1. Yields ``(k, record)``, sequence ``k``'s :class:`gelsim.stream.FrameRecord` of each frame, the
    sequences' frames in order (:func:`gelsim.sinks.drain_each` feeds each sequence's to its own sinks).

    A record's seconds are its share of its batch's (the engine's clock: CPU seconds on the numpy engine, wall
    seconds on the torch engine) and, in its sequence's first record, the sequence's set-up (the contact
    simulation, the patch: CPU seconds). The torch engine's frames depend on their batch by float rounding only
    (docs/device.md); the numpy engine's not at all. ``options`` as :func:`render_sequence`'s, for every sequence
    (``contact``, ``surface``, ``patch``: with one sequence only); its renderer: one for ``engine``
    (a :class:`gelsim.optics.torch_backend.BatchRenderer` for the torch engine), default the engine's."""
    o = options
    if len(sequences) > 1 and (o.contact is not None or o.surface is not None or o.patch is not None):
        raise GelsimError("a contact, surface or patch given in the options is one sequence's; run the sequences "
                          "one by one with it, or drop it")
    runs = [s if isinstance(s, SequenceRun) else
            SequenceRun(*s[:2], profile, fidelity, seed=s[2], options=o, device_patch=engine.device_patches)
            for s in sequences]
    want_frames = "frames" in o.outputs
    want_markers = want_frames or "markers" in o.outputs
    renderer = (o.renderer or engine.renderer(profile, fidelity, o.sensor_seed)) if want_frames else None
    setup = FrameSetup.make(profile, fidelity, sensor_seed=o.sensor_seed, markers=want_markers, renderer=renderer,
                            imprint_labels=runs[0].want_imprint, marker_labels=want_markers)
    timer = StageTimer(engine.clock)
    heights = engine.upload([r.patch for r in runs])
    envelopes = engine.crown_envelopes(heights, runs)
    timer.lap("fabric")                     # (the patches to the engine: on the torch engine, made on its device)
    for step in range(max(r.num_frames for r in runs)):
        live = [k for k, r in enumerate(runs) if step < r.num_frames]
        pressing = [k for k in live if runs[k].pose(step) is not None]
        poses = [runs[k].pose(step) for k in pressing]
        prot = dict(zip(pressing, engine.heights(heights, pressing, poses, profile)))
        env = dict(zip(pressing, engine.envelopes(envelopes, pressing, poses, profile)))
        requests = [runs[k].request(step, prot.get(k), env.get(k)) for k in live]
        if pressing:
            timer.lap("fabric")
        made = make_frames(requests, setup, engine)
        timer.restart()                     # (the pipeline's own seconds are in made.seconds)
        frames = None if made.frames is None else engine.to_host(made.frames)
        if frames is not None:
            timer.lap("optics")             # the frames' way to the host
        seconds = _sum_seconds(timer.take(), made.seconds)
        share = {k: v / len(live) for k, v in seconds.items()}
        for j, k in enumerate(live):
            part = made.parts[j] if frames is None else dataclasses.replace(made.parts[j], frame=frames[j])
            yield k, runs[k].record(step, requests[j], part, share)
        timer.restart()  # time spent by the consumer (encoding) is not ours


def render_sequence(obj: TouchedObject, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *,
                    seed: int, options: SequenceOptions = SequenceOptions()) -> Iterator[FrameRecord]:
    """Yield one :class:`gelsim.stream.FrameRecord` per frame of the sequence (constant memory): its pose and
    forces, imprint, markers, labels and, when rendered, its ``uint8 (H, W, 3)`` frame, each made by the frame
    pipeline (:func:`gelsim.stream.make_frames`, the numpy engine; :func:`render_sequences` of this one
    sequence). The sequence's labels are :func:`gelsim.stream.sequence_labels` of the records'
    (:func:`gelsim.sinks.drain` collects them), its stage times the sum of theirs.

    ``obj``: what the sensor touches (a :class:`gelsim.scene.TouchedObject`, or a catalog Fabric).
    ``seed`` drives everything random in this sequence (the object's irregularity phase, the camera
    noise: :func:`gelsim.stream.noise_generator`). ``options``: see :class:`SequenceOptions`.
    """
    for _, record in render_sequences([(obj, motion, seed)], profile, fidelity, options=options):
        yield record
