"""One tactile sequence end to end: touched object -> contact -> gel -> optics.

:func:`render_sequence` strings the stages together for one (object, motion) pair: the object's
heights and the contact simulation once, then per frame the one-frame function of
:mod:`gelsim.stream` (press -> markers -> render). It yields one :class:`gelsim.stream.FrameRecord` per
frame (constant memory) to whoever consumes them (:mod:`gelsim.sinks`); the sequence's labels are
assembled from the records' (:func:`gelsim.stream.sequence_labels`). Its options (renderer, sensor
seed, shortcuts, outputs, reused parts) are one :class:`SequenceOptions`.

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

import functools
import math
from dataclasses import dataclass, field
from typing import Collection, Iterator, Mapping

import numpy as np

from .contact import ContactFrames, Surface, simulate
from .errors import GelsimError
from .fidelity import Fidelity
from .gel import Imprint
from .gel.twoscale import crown_envelope, texture_scale_mm
from .labels import contact_location
from .markers import Markers
from .motion import Motion
from .optics import Renderer
from .scene import PHYSICS_MM_PER_PX, HeightPatch, TouchedObject, as_object, physics_surface, press_properties, travel_patch  # noqa: F401
from .sensor import SensorProfile
from .stream import FrameRecord, FrameSetup, StageTimer, Touch, make_frame, noise_generator

# Shear and twist terms that move no marker by more than this are skipped, px. A marker edge
# moving by 0.005 px changes its anti-aliased coverage by 0.5% of a pixel: at most about
# 0.6 DN (darkness 0.85 of a ~140 DN gel), below half a quantisation step.
NEGLIGIBLE_PX = 0.005
# What render_sequence can produce besides the contact labels (always computed).
OUTPUTS = frozenset({"frames", "imprint", "markers"})


@dataclass(frozen=True)
class SequenceOptions:
    """How :func:`render_sequence` runs: what it computes, and the parts of the sequence already computed.

    ``renderer``: the sensor's :class:`gelsim.optics.Renderer` (default: one for the fidelity level, made
    per call). ``sensor_seed`` fixes what belongs to the physical sensor and stays the same across a
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
    renderer: Renderer | None = None
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


def crown_envelope_patch(patch: HeightPatch | None, obj: TouchedObject, profile: SensorProfile,
                         fidelity: Fidelity) -> HeightPatch | None:
    """The crown envelope (:func:`gelsim.gel.twoscale.crown_envelope`) of ``patch``'s heights, on its grid;
    None when no frame needs one (no patch, an object without texture, a model without the envelope)."""
    tex = texture_scale_mm(obj.texture_mm, profile.gel)
    if patch is None or tex is None or fidelity.imprint_model not in ("twoscale", "elastic"):
        return None
    return HeightPatch(crown_envelope(patch.heights_mm, tex, patch.mm_per_px), patch.origin_mm, patch.mm_per_px)


def render_sequence(obj: TouchedObject, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *,
                    seed: int, options: SequenceOptions = SequenceOptions()) -> Iterator[FrameRecord]:
    """Yield one :class:`gelsim.stream.FrameRecord` per frame of the sequence (constant memory): its pose and
    forces, imprint, markers, labels and, when rendered, its ``uint8 (H, W, 3)`` frame, each made by
    :func:`gelsim.stream.make_frame`. The sequence's labels are :func:`gelsim.stream.sequence_labels` of the
    records' (:func:`gelsim.sinks.drain` collects them), its stage times the sum of theirs.

    ``obj``: what the sensor touches (a :class:`gelsim.scene.TouchedObject`, or a catalog Fabric).
    ``seed`` drives everything random in this sequence (the object's irregularity phase, the camera
    noise: :func:`gelsim.stream.noise_generator`). ``options``: see :class:`SequenceOptions`.
    """
    o = options
    obj = as_object(obj)
    contact = o.contact
    if contact is not None and len(contact.normal_force_n) != motion.num_frames:
        raise GelsimError(f"contact has {len(contact.normal_force_n)} frames, the motion {motion.num_frames}; "
                          "simulate this motion")
    want_frames = "frames" in o.outputs
    want_markers = want_frames or "markers" in o.outputs
    want_imprint = want_markers or "imprint" in o.outputs
    timer = StageTimer()
    renderer = None
    if want_frames:
        renderer = o.renderer or Renderer(profile, fidelity.render_backend, supersample=fidelity.supersample,
                                          seed=o.sensor_seed)
    if contact is None:
        surface = o.surface if o.surface is not None else physics_surface(obj, motion, profile, seed=seed)
        timer.lap("fabric")
        contact = simulate(motion, surface, profile, fidelity)
        timer.lap("physics")
    props = press_properties(obj)
    # The image-resolution patch is the costliest fabric step: built only if some frame presses.
    touches = bool(np.any(contact.in_contact & (contact.normal_force_n > 0)))
    patch = o.patch
    if patch is None and want_imprint and (touches or not o.shortcuts):
        patch = travel_patch(obj, motion, profile, profile.image.mm_per_px, seed=seed,
                             poses=(contact.position_mm, contact.yaw_deg))
    # The crown envelope of the object's texture is a property of the object, not of the pose: taken once
    # on the patch and seen through each frame's pose like the heights (press(envelope_mm=)).
    envelope = crown_envelope_patch(patch, obj, profile, fidelity)
    setup = FrameSetup.make(profile, fidelity, sensor_seed=o.sensor_seed, markers=want_markers, renderer=renderer)
    timer.lap("fabric")

    nuis = None
    if o.nuisance:
        from .nuisance import load_nuisance
        from .nuisance.sequence import SequenceNuisance

        stages = o.nuisance_stages if o.nuisance_stages is not None else load_nuisance().stages
        hairiness = float(getattr(getattr(obj, "fabric", None), "hairiness", 0.0) or 0.0)
        nuis = SequenceNuisance(o.nuisance, stages, seed, hairiness, profile, motion)
        timer.lap("nuisance")
    state = contact.to_dict()
    rng = noise_generator(seed)
    window = "touched" if o.shortcuts else "full"
    prev = None  # the previous frame's imprint warm-starts the next (same result, fewer iterations)
    for i in range(motion.num_frames):
        force = float(contact.normal_force_n[i])
        touching = bool(contact.in_contact[i]) and force > 0.0
        touch = None
        if want_imprint and (touching or not o.shortcuts):
            pose = (profile.shape, profile.image.mm_per_px, contact.position_mm[i, 0], contact.position_mm[i, 1],
                    contact.yaw_deg[i], tuple(contact.tilt_deg[i]))
            shear, twist = tuple(float(v) for v in contact.shear_mm[i]), float(contact.twist_deg[i])
            if o.shortcuts:
                skip_shear, skip_twist = negligible_px(shear, twist, profile)
                shear = (0.0, 0.0) if skip_shear else shear
                twist = 0.0 if skip_twist else twist
            touch = Touch(patch.sample(*pose), force_n=force if touching else 0.0, shear_mm=shear, twist_deg=twist,
                          warm=prev, window=window,
                          envelope_mm=None if envelope is None else functools.partial(envelope.sample, *pose),
                          properties=props)
            timer.lap("fabric")
        extra = None if nuis is None else functools.partial(nuis.frame, i, tilt_deg=contact.tilt_deg[i])
        imprint, markers, frame = make_frame(touch, setup, seed=rng, timer=timer, nuisance=extra)
        extra = None if nuis is None else nuis.last
        if touch is not None:
            prev = imprint if touching else None
        labels = _frame_labels({k: v[i] for k, v in state.items()}, imprint, markers, want_imprint, want_markers)
        yield FrameRecord(i, touch, imprint, markers, frame, labels, timer.take(), extra)
        timer.restart()  # time spent by the consumer (encoding) is not ours


def _frame_labels(state: dict, imprint: Imprint | None, markers: Markers | None, imprint_labels: bool,
                  marker_labels: bool) -> dict[str, np.ndarray]:
    """One frame's labels (:data:`gelsim.schema.LABELS` order and dtypes): its pose and forces (``state``, the
    contact simulation's row), then the imprint's (zero and NaN without one) and the markers' if asked."""
    labels = dict(state)
    if imprint_labels:
        if imprint is None:
            depth, area, centroid, bbox = 0.0, 0.0, np.full(2, np.nan), np.full(4, np.nan)
        else:
            depth, area = imprint.indentation_mm, imprint.contact_area_mm2
            centroid, bbox = contact_location(imprint.contact_mask)
        labels.update(indentation_mm=np.float32(depth), contact_area_mm2=np.float32(area),
                      contact_centroid_px=centroid.astype(np.float32), contact_bbox_px=bbox.astype(np.float32))
    if marker_labels:
        none = np.zeros((0, 2), np.float32)
        labels.update(markers_xy_px=none if markers is None else markers.xy_px.astype(np.float32, copy=False),
                      markers_rest_px=none if markers is None else markers.rest_px.astype(np.float32, copy=False))
    return labels
