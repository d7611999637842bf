"""The frame pipeline: how a batch of tactile frames is made, and the record that carries each to its consumers.

One function makes frames, for every caller: :func:`make_frames` takes a batch of :class:`FrameRequest` (each a
:class:`Touch`, or None: nothing presses, the flat gel) and runs its stages, in this order, on an engine
(:mod:`gelsim.engines`: the numpy engine, a frame at a time, the bit-exact reference; or the torch engine, the
whole batch at once on a device):

1. **imprint**: the objects pressed into the gel (:class:`~gelsim.gel.Imprint`: depth, contact mask, indentation,
   force, area);
2. **nuisance**: each frame's :class:`~gelsim.nuisance.sequence.FrameNuisance` from its sequence's
   :class:`~gelsim.nuisance.sequence.SequenceNuisance` (``frame(index, imprint, tilt_deg=)``): fibre dents added to
   the depth the optics render (never to the imprint) and the camera's gains;
3. **markers**: the printed markers moved by the imprint and the contact's shear and twist
   (:class:`~gelsim.markers.Markers`);
4. **labels**: the imprint's (indentation, area, contact centroid and box) and the markers' labels of
   :data:`gelsim.schema.LABELS`, when the setup asks for them;
5. **optics**: each frame's inputs to the optics in one :class:`~gelsim.optics.composite.OpticsInput` (the depth
   to render, the markers, the gains, its noise seed), rendered to ``uint8 (H, W, 3)`` RGB.

What stays the same from frame to frame of a sensor (profile, fidelity, printed markers, renderer, which labels) is
a :class:`FrameSetup`; a stage whose input is absent does not run. The result is a :class:`FrameBatch`: per frame
its :class:`FrameParts`, and the CPU (numpy engine) or wall (torch engine) seconds of each stage. Its callers:

* :func:`gelsim.frame.render_frame` (``gelsim render``), :func:`gelsim.texture.texture_budget` (``gelsim texture``)
  and :meth:`gelsim.mujoco.GelSightSensor.render`: :func:`make_frame`, a batch of one, numpy;
* :func:`gelsim.sequence.render_sequence` (each frame of a sequence, numpy) and
  :func:`gelsim.sequence.render_sequences` (sequences in step, frame t of each in one batch, torch), yielding one
  :class:`FrameRecord` per frame to the sinks (:mod:`gelsim.sinks`: ``write(record)``, ``close()``, ``seconds``);
* :class:`gelsim.mujoco.batch.BatchGelSightSensor`: N pads in one batch, torch.

:func:`sequence_labels` assembles a sequence's labels from its records' (``docs/architecture.md``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .engines import NumpyEngine, stage_clock
from .fidelity import Fidelity
from .gel import Imprint
from .markers import Markers, rest_markers
from .optics.composite import OpticsInput
from .schema import LABELS
from .sensor import SensorProfile

__all__ = ["stage_clock", "StageTimer", "noise_generator", "Touch", "FrameRequest", "FrameSetup", "FrameParts",
           "FrameBatch", "NUMPY", "make_frames", "make_frame", "FrameRecord", "sequence_labels", "PER_FRAME_LABELS"]

#: The label keys with one row per frame (the others, ``markers_rest_px``, are the sequence's).
PER_FRAME_LABELS = frozenset(k.name for k in LABELS if k.shape[:1] == ("T",))
#: The numpy engine: every caller's unless it gives another (:mod:`gelsim.engines`).
NUMPY = NumpyEngine()


class StageTimer:
    """Seconds per stage by ``clock`` (default :data:`stage_clock`): :meth:`lap` charges the time since the
    last lap (or :meth:`restart`) to a stage; :meth:`take` hands the sums over and starts new ones."""

    def __init__(self, clock: Callable[[], float] = stage_clock):
        self.clock = clock
        self.seconds: dict[str, float] = {}
        self._t = clock()

    def restart(self) -> None:
        """Start timing afresh (what ran since the last lap was not ours: a consumer's turn)."""
        self._t = self.clock()

    def lap(self, stage: str) -> None:
        now = self.clock()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + (now - self._t)
        self._t = now

    def take(self) -> dict[str, float]:
        out, self.seconds = self.seconds, {}
        return out


def noise_generator(seed: int) -> np.random.Generator:
    """A sequence's camera-noise stream: frame ``i``'s noise is the ``i``-th draw of the renderer (the numpy
    renderer's, :meth:`gelsim.optics.Renderer.render`, or a batched one's, :class:`gelsim.sinks.DeviceFrames`,
    drawing in the same order) from this generator."""
    return np.random.default_rng(seed)


@dataclass(frozen=True)
class Touch:
    """What presses the gel in one frame: :func:`gelsim.gel.press`'s inputs (but the profile and
    fidelity), and how the contact surface is sheared and twisted relative to the sensor.

    protrusion_mm: float32 (H, W) mm, the object's heights towards the gel at the image's resolution or
    on the imprint's grid (a numpy array, or for the torch engine also a tensor on its device); force_n (N; 0: the flat gel's imprint) or depth_mm (mm past first touch);
    shear_mm: (x, y) mm and twist_deg: degrees (+x towards +y) of the contact surface; warm: the
    previous frame's imprint of the same sequence as the engine made it (warm start); window: ``"touched"`` or ``"full"``; envelope_mm: the object's
    crown envelope as the protrusion sees it (an array or ``f(box)``); properties: the object's own
    (:func:`gelsim.scene.press_properties`: support, texture_mm, valley_mm)."""
    protrusion_mm: np.ndarray
    force_n: float | None = None
    depth_mm: float | None = None
    shear_mm: tuple[float, float] = (0.0, 0.0)
    twist_deg: float = 0.0
    warm: Imprint | None = None
    window: str = "touched"
    envelope_mm: np.ndarray | Callable[..., np.ndarray] | None = None
    properties: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FrameRequest:
    """One frame to make: its :class:`Touch` (None: nothing presses it), where its random draws come from
    (``seed``: an int, or its sequence's :func:`noise_generator`, drawn from once per rendered frame, in frame
    order; ``noise`` False: a noiseless frame) and its sequence's nuisance (``nuisance``: a
    :class:`~gelsim.nuisance.sequence.SequenceNuisance` whose ``frame(index, imprint, tilt_deg=tilt_deg)`` the
    pipeline calls, in frame order, or None)."""
    touch: Touch | None = None
    seed: int | np.random.Generator = 0
    noise: bool = True
    nuisance: Any = None
    index: int = 0
    tilt_deg: Any = (0.0, 0.0)


@dataclass(frozen=True)
class FrameSetup:
    """What every frame of one sensor shares: its profile and fidelity, its printed markers at rest
    (``flat_markers``: :func:`gelsim.markers.rest_markers`; None: no markers computed), its renderer (None: no
    image rendered; a :class:`gelsim.optics.Renderer` for the numpy engine, a
    :class:`gelsim.optics.torch_backend.BatchRenderer` for the torch engine) and which labels each frame gets
    (``imprint_labels``: indentation, area, contact centroid and box; ``marker_labels``: the markers' centres)."""
    profile: SensorProfile
    fidelity: Fidelity
    flat_markers: Markers | None = None
    renderer: Any = None
    imprint_labels: bool = False
    marker_labels: bool = False

    @classmethod
    def make(cls, profile: SensorProfile, fidelity: Fidelity, *, sensor_seed: int = 0, markers: bool = True,
             renderer=None, imprint_labels: bool = False, marker_labels: bool = False) -> "FrameSetup":
        """The setup of ``profile``'s sensor whose printed markers are jittered by ``sensor_seed``; markers
        when ``markers`` and the profile has them."""
        flat = rest_markers(profile, seed=sensor_seed) if markers and profile.markers.enabled else None
        return cls(profile, fidelity, flat, renderer, imprint_labels, marker_labels)


@dataclass(frozen=True)
class FrameParts:
    """One frame as :func:`make_frames` made it: the imprint (None when nothing pressed), the markers (None
    without markers), the ``uint8 (H, W, 3)`` RGB frame (None without a renderer; a tensor row on the torch
    engine's device), the frame's :class:`~gelsim.nuisance.sequence.FrameNuisance` (or None), its labels (the
    setup's, :data:`gelsim.schema.LABELS` keys and dtypes; empty without) and its inputs to the optics (one
    :class:`~gelsim.optics.composite.OpticsInput`, whoever renders it)."""
    imprint: Imprint | None
    markers: Markers | None
    frame: Any
    nuisance: Any = None
    labels: Mapping[str, np.ndarray] = field(default_factory=dict)
    optics: OpticsInput | None = None


@dataclass
class FrameBatch:
    """What :func:`make_frames` made: ``parts`` (one :class:`FrameParts` per request, in order), ``seconds`` (per
    stage, by the engine's clock) and the engine's own batch objects (``imprints``, ``markers``, ``frames``: the
    torch engine's tensors on its device, which :class:`gelsim.mujoco.batch.BatchGelSightSensor` hands out)."""
    parts: list[FrameParts]
    seconds: dict[str, float]
    imprints: Any = None
    markers: Any = None
    frames: Any = None


def make_frames(requests: Sequence[FrameRequest], setup: FrameSetup, engine=NUMPY) -> FrameBatch:
    """The frames of ``requests`` (see the module docstring), their stages on ``engine`` (default the numpy
    engine): imprint, nuisance, markers, labels, optics, each only when it has something to do."""
    timer = StageTimer(engine.clock)
    n = len(requests)
    touches = [r.touch for r in requests]
    imprints = engine.press(touches, setup)
    if any(t is not None for t in touches):
        timer.lap("imprint")
    imprint = [engine.imprint(imprints, b) for b in range(n)]
    nuisance = [None] * n
    if any(r.nuisance is not None for r in requests):
        nuisance = [None if r.nuisance is None else r.nuisance.frame(r.index, imprint[b], tilt_deg=r.tilt_deg)
                    for b, r in enumerate(requests)]
        timer.lap("nuisance")
    markers = mk = None
    if setup.flat_markers is not None:
        markers = engine.displace(imprints, touches, setup)
        mk = [engine.markers(markers, b) for b in range(n)]
        timer.lap("markers")
    labels = [frame_labels(setup, imprint[b], None if mk is None else mk[b]) for b in range(n)]
    if setup.imprint_labels:
        for b, where in enumerate(engine.locate(imprints)):
            if where is not None:
                labels[b]["contact_centroid_px"] = where[0].astype(np.float32)
                labels[b]["contact_bbox_px"] = where[1].astype(np.float32)
    if setup.imprint_labels or setup.marker_labels:
        timer.lap("labels")
    dents = [None if nu is None else nu.dents_mm for nu in nuisance]
    optics = [OpticsInput(engine.render_depth(imprint[b], dents[b]),
                          None if markers is None else engine.render_markers(markers, b),
                          None if nuisance[b] is None else nuisance[b].gains, r.seed, r.noise,
                          engine.render_extent(imprint[b], dents[b]))
              for b, r in enumerate(requests)]
    frames = None
    if setup.renderer is not None:
        frames = engine.render(optics, setup)
        timer.lap("optics")
    parts = [FrameParts(imprint[b], None if mk is None else mk[b], None if frames is None else frames[b], nuisance[b],
                        labels[b], optics[b]) for b in range(n)]
    return FrameBatch(parts, timer.take(), imprints, markers, frames)


def frame_labels(setup: FrameSetup, imprint: Imprint | None, markers: Markers | None) -> dict[str, np.ndarray]:
    """One frame's labels of ``setup``'s kinds (:data:`gelsim.schema.LABELS` order and dtypes): the imprint's
    (zero and NaN without one; its contact centroid and box are the engine's to fill in) and the markers' (empty
    without markers)."""
    labels: dict[str, np.ndarray] = {}
    if setup.imprint_labels:
        depth, area = (0.0, 0.0) if imprint is None else (imprint.indentation_mm, imprint.contact_area_mm2)
        labels.update(indentation_mm=np.float32(depth), contact_area_mm2=np.float32(area),
                      contact_centroid_px=np.full(2, np.nan, np.float32), contact_bbox_px=np.full(4, np.nan, np.float32))
    if setup.marker_labels:
        none = np.zeros((0, 2), np.float32)
        labels.update(markers_xy_px=none if markers is None else markers.xy_px.astype(np.float32, copy=False),
                      markers_rest_px=none if markers is None else markers.rest_px.astype(np.float32, copy=False))
    return labels


def make_frame(touch: Touch | None, setup: FrameSetup, *, seed: int | np.random.Generator = 0, noise: bool = True,
               nuisance=None, index: int = 0, tilt_deg=(0.0, 0.0)) -> FrameParts:
    """One frame (a batch of one on the numpy engine): ``touch`` pressed into the gel (None: nothing presses, the
    flat gel), its markers, its labels (the setup's), its image (``seed``, ``noise``: its noise; ``nuisance``: its
    sequence's :class:`~gelsim.nuisance.sequence.SequenceNuisance`, asked for frame ``index`` at ``tilt_deg``)."""
    return make_frames([FrameRequest(touch, seed, noise, nuisance, index, tilt_deg)], setup).parts[0]


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a sequence, as :func:`gelsim.sequence.render_sequence` yields it to its consumers.

    index: the frame's number in its sequence (from 0). touch: what pressed the gel (None: nothing was
    pressed, as before contact). imprint, markers, frame: :class:`FrameParts`'s (each None when not
    computed; ``frame`` None also when a sink renders it, :class:`gelsim.sinks.DeviceFrames`; from a torch engine
    made with ``i420``, a :class:`gelsim.video.I420` that a video sink encodes as it is). labels:
    this frame's labels, keys and dtypes of :data:`gelsim.schema.LABELS` in their order: its pose and
    forces (the contact simulation's row: ``time_s`` ... ``twist_deg``), then the imprint's and the
    markers' labels when computed (``markers_rest_px``, the sequence's, in every frame). seconds: CPU
    seconds per stage spent on this frame since the previous record (the first record's include the
    sequence's set-up: ``fabric``, ``physics``; on the torch engine its share of its batch's wall seconds).
    nuisance: the frame's :class:`~gelsim.nuisance.sequence.FrameNuisance` (or None), as the pipeline asked
    its sequence for it. optics: the frame's inputs to the optics in one object (the depth to render, the
    markers, the gains, its noise seed): what a sink that renders reads (:class:`gelsim.sinks.DeviceFrames`).
    """
    index: int
    touch: Touch | None
    imprint: Imprint | None
    markers: Markers | None
    frame: np.ndarray | None
    labels: Mapping[str, np.ndarray]
    seconds: Mapping[str, float]
    nuisance: Any = None
    optics: OpticsInput | None = None

    @property
    def depth_mm(self) -> np.ndarray | None:
        """The imprint's depth, float32 (H, W) mm, or None (the flat gel)."""
        return None if self.imprint is None else self.imprint.depth_mm


def sequence_labels(rows: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """A sequence's labels (what the dataset's labels .npz holds) from its frames' (:attr:`FrameRecord.labels`,
    in frame order): the per-frame keys stacked (T first), the sequence's own (``markers_rest_px``) as
    every frame holds them. Keys in the frames' order, dtypes kept."""
    return {k: np.stack([r[k] for r in rows]) if k in PER_FRAME_LABELS else np.asarray(v)
            for k, v in rows[0].items()}
