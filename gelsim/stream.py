"""The frame stream: how one tactile frame is made, and the record that carries it to every consumer.

One frame is three stages, in this order, made by :func:`make_frame` (and nowhere else):

1. **imprint**: the object's protrusion pressed into the gel (:func:`gelsim.gel.press`) -> an
   :class:`~gelsim.gel.Imprint` (depth map, contact mask, indentation, force, area);
2. **markers**: the printed markers moved by the imprint and by the contact's shear and twist
   (:func:`gelsim.markers.displace`) -> :class:`~gelsim.markers.Markers`;
3. **optics**: the camera image of the pressed gel and its markers, with the camera's noise
   (:meth:`gelsim.optics.Renderer.render`) -> ``uint8 (H, W, 3)`` RGB.

What presses is a :class:`Touch` (None: nothing does, the flat gel); what stays the same from frame to
frame of one sensor (profile, fidelity, printed markers, renderer) is a :class:`FrameSetup`. Each stage's
CPU time goes to a :class:`StageTimer`. Three callers run it:

* :func:`gelsim.frame.render_frame`: one object pressed straight in (``gelsim render``);
* :meth:`gelsim.mujoco.GelSightSensor.render`: one frame of a MuJoCo scene;
* :func:`gelsim.sequence.render_sequence`: every frame of a sequence, each yielded as a
  :class:`FrameRecord` (the frame's pose and forces and its labels with it).

The records' consumers are sinks (:mod:`gelsim.sinks`, one interface: ``write(record)``, ``close()``,
``seconds``): the dataset's video writer, the torch backend's batched renderer, the bench's captures.
:func:`sequence_labels` assembles a sequence's labels from its records' (``docs/architecture.md``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from .fidelity import Fidelity
from .gel import Imprint, press
from .markers import Markers, displace, rest_markers
from .schema import LABELS
from .sensor import SensorProfile

# Stage clock: the thread's CPU time. A generation worker is one thread on one core, so this is its
# per-core cost whatever else the machine runs (wall time would count other processes' turns).
stage_clock = time.thread_time

#: The label keys with one row per frame (the others, ``markers_rest_px``, are the sequence's).
PER_FRAME_LABELS = frozenset(k.name for k in LABELS if k.shape[:1] == ("T",))


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
    on the imprint's grid; force_n (N; 0: the flat gel's imprint) or depth_mm (mm past first touch);
    shear_mm: (x, y) mm and twist_deg: degrees (+x towards +y) of the contact surface; warm: the
    previous frame's imprint (warm start); window: ``"touched"`` or ``"full"``; envelope_mm: the object's
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
class FrameSetup:
    """What every frame of one sensor shares: its profile and fidelity, its printed markers at rest
    (``flat_markers``: :func:`gelsim.markers.rest_markers`; None: no markers computed) and its renderer
    (None: no image rendered)."""
    profile: SensorProfile
    fidelity: Fidelity
    flat_markers: Markers | None = None
    renderer: Any = None

    @classmethod
    def make(cls, profile: SensorProfile, fidelity: Fidelity, *, sensor_seed: int = 0, markers: bool = True,
             renderer=None) -> "FrameSetup":
        """The setup of ``profile``'s sensor whose printed markers are jittered by ``sensor_seed``; markers
        when ``markers`` and the profile has them."""
        flat = rest_markers(profile, seed=sensor_seed) if markers and profile.markers.enabled else None
        return cls(profile, fidelity, flat, renderer)


class FrameParts(NamedTuple):
    """What :func:`make_frame` made: the imprint (None when nothing pressed), the markers (None without
    markers) and the ``uint8 (H, W, 3)`` RGB frame (None without a renderer)."""
    imprint: Imprint | None
    markers: Markers | None
    frame: np.ndarray | None


def make_frame(touch: Touch | None, setup: FrameSetup, *, seed: int | np.random.Generator = 0, noise: bool = True,
               timer: StageTimer | None = None) -> FrameParts:
    """One tactile frame: ``touch`` pressed into the gel, the markers it moves, the camera's image.

    ``touch`` None: nothing presses (no imprint; the markers at rest; the flat gel). ``seed``: this
    frame's camera noise (an int, or the sequence's :func:`noise_generator`, drawn from once per
    rendered frame); ``noise``: False for a noiseless frame. ``timer``: gets the stages' times
    (``imprint``, ``markers``, ``optics``), each only when the stage ran.
    """
    timer = timer if timer is not None else StageTimer()
    prof, fid = setup.profile, setup.fidelity
    imprint = None
    if touch is not None:
        imprint = press(touch.protrusion_mm, prof, fid, force_n=touch.force_n, depth_mm=touch.depth_mm,
                        window=touch.window, warm=touch.warm, envelope_mm=touch.envelope_mm, **touch.properties)
        timer.lap("imprint")
    markers = setup.flat_markers
    if markers is not None:
        if imprint is not None:
            markers = displace(prof, fid, imprint, shear_mm=touch.shear_mm, twist_deg=touch.twist_deg,
                               rest=markers.rest_px)
        timer.lap("markers")
    frame = None
    if setup.renderer is not None:
        frame = setup.renderer.render(None if imprint is None else imprint.depth_mm, markers, seed=seed, noise=noise)
        timer.lap("optics")
    return FrameParts(imprint, markers, frame)


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a sequence, as :func:`gelsim.sequence.render_sequence` yields it to its consumers.

    index: the frame's number in its sequence (from 0). touch: what pressed the gel (None: nothing was
    pressed, as before contact). imprint, markers, frame: :class:`FrameParts`'s (each None when not
    computed; ``frame`` None also when a sink renders it, :class:`gelsim.sinks.DeviceFrames`). labels:
    this frame's labels, keys and dtypes of :data:`gelsim.schema.LABELS` in their order: its pose and
    forces (the contact simulation's row: ``time_s`` ... ``twist_deg``), then the imprint's and the
    markers' labels when computed (``markers_rest_px``, the sequence's, in every frame). seconds: CPU
    seconds per stage spent on this frame since the previous record (the first record's include the
    sequence's set-up: ``fabric``, ``physics``).
    """
    index: int
    touch: Touch | None
    imprint: Imprint | None
    markers: Markers | None
    frame: np.ndarray | None
    labels: Mapping[str, np.ndarray]
    seconds: Mapping[str, float]

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
