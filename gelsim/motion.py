"""Hand-held GelSight motions of ViTac Cloth: press, slip and twist.

A :class:`Motion` is everything the contact simulation (:mod:`gelsim.contact`)
needs to move the sensor for one sequence: the action, how many camera frames
and how many of them come before contact, where and how the hand approaches,
how hard it presses, and the variability of a sensor held by hand (tilt,
tremor). :func:`sample_motion` draws one from the ranges in
``gelsim/assets/motions.toml`` (:class:`MotionRanges`, each range with its source).

Frames and coordinates: positions are in mm in the surface (fabric) frame, the
frame of :class:`gelsim.contact.Surface`: ``x`` along heightmap columns, ``y``
along rows. Yaw rotates the sensor from ``+x`` towards ``+y``; a sensor-frame
point ``p`` lies at ``position + R(yaw) p`` in the fabric frame. Timing fields
are fractions of the in-contact time (first contact to last frame), so a motion
does not depend on the camera rate.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np

from .errors import GelsimError, check_choice
from .params import ASSETS_DIR, build, load_toml, param
from .schema import ACTIONS  # noqa: F401  (the dataset's action names; gelsim.motion.ACTIONS for callers)

MOTIONS_FILE = ASSETS_DIR / "motions.toml"

Range = tuple[float, float]


def _check_range(where: str, r: tuple[float, float], lo: float | None = None, hi: float | None = None) -> None:
    if not r[0] <= r[1]:
        raise GelsimError(f"{where}: low {r[0]} is above high {r[1]}; give [low, high]")
    if lo is not None and r[0] < lo:
        raise GelsimError(f"{where}: {r[0]} is below {lo}; raise the low end")
    if hi is not None and r[1] > hi:
        raise GelsimError(f"{where}: {r[1]} is above {hi}; lower the high end")


class _Ranges:
    """A table of ``[low, high]`` ranges: ``validate`` checks that each field named in ``BOUNDS``
    has low <= high within its ``(lo, hi)`` bounds (the order of ``BOUNDS`` is the order of the checks)."""
    BOUNDS: ClassVar[dict[str, tuple[float, float]]] = {}

    def validate(self, where: str) -> None:
        for name, (lo, hi) in self.BOUNDS.items():
            _check_range(f"{where}.{name}", getattr(self, name), lo, hi)


# A sequence keeps at least this many frames in contact (the press needs a ramp and a hold).
MIN_CONTACT_FRAMES = 3


@dataclass(frozen=True)
class ActionWeights:
    press: float = param(7.0, lo=0.0, doc="relative frequency of press")
    slip: float = param(1.0, lo=0.0, doc="relative frequency of slip")
    twist: float = param(2.0, lo=0.0, doc="relative frequency of twist")

    def validate(self, where: str) -> None:
        if self.press + self.slip + self.twist <= 0:
            raise GelsimError(f"{where}: all action weights are 0; give at least one a positive weight")


@dataclass(frozen=True)
class TimingRanges(_Ranges):
    BOUNDS = {"contact_phase": (0.01, 0.99), "rise_fraction": (0.0, 1.0), "hold_fraction": (0.0, 1.0),
              "release_tail_fraction": (0.0, 1.0), "settle_fraction": (0.0, 1.0), "end_fraction": (0.0, 1.0)}
    precontact_frames: tuple[int, int] = param(doc="frames before the first contact frame, [low, high] inclusive")
    contact_phase: Range = param(doc="fraction of a frame period between contact and the first in-contact frame")
    rise_fraction: Range = param(doc="force rise time, fraction of the in-contact time")
    hold_fraction: Range = param(doc="press hold time, fraction of the in-contact time")
    release_tail_fraction: Range = param(doc="press: time after the release (lifted), fraction")
    settle_fraction: Range = param(doc="slip/twist: settling time after the rise, fraction")
    end_fraction: Range = param(doc="slip/twist: still time at the end, fraction")
    late_start_fraction: float = param(0.0, lo=0.0, hi=1.0,
                                       doc="share of sequences whose recording started well before the touch")
    late_start_frames: tuple[int, int] = param((0, 0), doc="their pre-contact frames, [low, high] inclusive")

    def validate(self, where: str) -> None:
        for name in ("precontact_frames", "late_start_frames"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise GelsimError(f"{where}.{name}: need 0 <= low <= high, got {(lo, hi)}")
        super().validate(where)
        if self.rise_fraction[1] + self.hold_fraction[1] + self.release_tail_fraction[1] > 0.9 + 1e-9:
            raise GelsimError(f"{where}: rise + hold + release_tail fractions can exceed 0.9, leaving little "
                              "time to release; lower their high ends")
        if self.rise_fraction[1] + self.settle_fraction[1] + self.end_fraction[1] > 0.8:
            raise GelsimError(f"{where}: rise + settle + end fractions can exceed 0.8, leaving little time "
                              "to slip or twist; lower their high ends")


@dataclass(frozen=True)
class ApproachRanges(_Ranges):
    BOUNDS = {"speed_mm_s": (0.5, 200.0)}
    speed_mm_s: Range = param(doc="approach speed, mm/s")
    start_offset_mm: float = param(5.0, lo=0.0, hi=1000.0, doc="start within this distance of the origin, mm")
    fabric_rotation_deg: Range = param((0.0, 360.0), doc="fabric orientation, degrees")


@dataclass(frozen=True)
class ForceRanges(_Ranges):
    BOUNDS = {"peak_force_n": (0.05, 50.0), "slip_force_scale": (0.05, 1.0)}
    peak_force_n: Range = param(doc="target normal force of a press, N")
    slip_force_scale: Range = param((0.5, 0.9), doc="slip/twist force relative to a press")


@dataclass(frozen=True)
class TiltRanges:
    max_tilt_deg: float = param(3.0, lo=0.0, hi=15.0, doc="largest roll or pitch of the sensor, degrees")


@dataclass(frozen=True)
class SlipRanges(_Ranges):
    BOUNDS = {"distance_mm": (0.0, 50.0)}
    distance_mm: Range = param(doc="slide distance, mm")


@dataclass(frozen=True)
class TwistRanges(_Ranges):
    BOUNDS = {"angle_deg": (0.0, 180.0)}
    angle_deg: Range = param(doc="magnitude of the rotation about the normal, degrees")


@dataclass(frozen=True)
class TremorRanges(_Ranges):
    BOUNDS = {"amplitude_mm": (0.0, 1.0), "frequency_hz": (0.0, 100.0), "force_fraction": (0.0, 0.5)}
    amplitude_mm: Range = param(doc="hand tremor amplitude, mm")
    frequency_hz: Range = param(doc="hand tremor frequency, Hz")
    force_fraction: Range = param((0.01, 0.05), doc="force modulation by tremor, fraction of the peak")


@dataclass(frozen=True)
class MotionRanges:
    """Distributions of the hand-held motions (``gelsim/assets/motions.toml``)."""
    actions: ActionWeights
    timing: TimingRanges
    approach: ApproachRanges
    force: ForceRanges
    tilt: TiltRanges
    slip: SlipRanges
    twist: TwistRanges
    tremor: TremorRanges


def load_motion_ranges(path: str | Path | None = None) -> MotionRanges:
    """Load :class:`MotionRanges` from a TOML file (default ``gelsim/assets/motions.toml``)."""
    path = Path(path) if path is not None else MOTIONS_FILE
    return build(MotionRanges, load_toml(path), where=path.name)


MAX_TWIST_DEG = 180.0   # TwistRanges.angle_deg's upper bound
MAX_SLIP_MM = 100.0     # far past any hand-held slide; bounds the fabric patch the pipeline generates


@dataclass(frozen=True)
class Motion:
    """One hand-held sensor motion. Lengths mm, angles degrees, forces N, speeds mm/s."""
    action: Literal["press", "slip", "twist"]
    num_frames: int                    # total frames, pre-contact ones included
    precontact_frames: int             # frames before the first contact; the first in-contact frame has this index
    start_xy_mm: tuple[float, float]   # sensor centre at the start, fabric frame
    fabric_rotation_deg: float         # orientation of the fabric under the sensor
    approach_speed_mm_s: float
    peak_force_n: float                # target normal force while pressing
    tilt_deg: tuple[float, float]      # roll (gel lower at +y), pitch (gel lower at +x)
    slip_direction_deg: float = 0.0    # direction of the slide in the fabric frame (0 = +x); 0 unless slip
    slip_distance_mm: float = 0.0      # 0 unless slip
    twist_deg: float = 0.0             # signed rotation about the normal (+: from +x towards +y); 0 unless twist
    tremor_amplitude_mm: float = 0.0
    tremor_frequency_hz: float = 10.0
    tremor_phase_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x, y and force tremor phases
    tremor_force_fraction: float = 0.0  # force modulation, fraction of peak_force_n
    contact_phase: float = 0.5         # contact happens this fraction of a frame before frame precontact_frames
    rise_fraction: float = 0.25        # force rise, fraction of the in-contact time
    hold_fraction: float = 0.4         # press: hold; slip/twist: unused
    release_fraction: float = 0.25     # press: release ramp; slip/twist: unused
    settle_fraction: float = 0.1       # slip/twist: still after the rise
    end_fraction: float = 0.05         # slip/twist: still at the end

    def __post_init__(self) -> None:
        check_choice("action", self.action, ACTIONS)
        if not 0 <= self.precontact_frames < self.num_frames:
            raise GelsimError(f"precontact_frames {self.precontact_frames} must be in [0, num_frames="
                              f"{self.num_frames}); lower it")
        if self.num_frames - self.precontact_frames < 3:
            raise GelsimError("a motion needs at least 3 in-contact frames; raise num_frames or lower precontact_frames")
        if not 0.0 < self.contact_phase < 1.0:
            raise GelsimError(f"contact_phase {self.contact_phase} must be in (0, 1)")
        if self.approach_speed_mm_s <= 0 or self.peak_force_n <= 0:
            raise GelsimError("approach_speed_mm_s and peak_force_n must be positive")
        # The documented ranges of gelsim/assets/motions.toml bound a twist to half a turn and a slip to
        # a few centimetres; beyond them the fabric patch and the physics are not sized for it.
        if abs(self.twist_deg) > MAX_TWIST_DEG:
            raise GelsimError(f"twist_deg {self.twist_deg} is beyond +-{MAX_TWIST_DEG:g} degrees; give a smaller twist")
        if not 0.0 <= self.slip_distance_mm <= MAX_SLIP_MM:
            raise GelsimError(f"slip_distance_mm {self.slip_distance_mm} must be in 0-{MAX_SLIP_MM:g} mm")

    @property
    def contact_frames(self) -> int:
        """Number of frames from the first in-contact frame to the end."""
        return self.num_frames - self.precontact_frames

    def slip_vector_mm(self) -> tuple[float, float]:
        """Total commanded slide (dx, dy) of the sensor, mm, fabric frame."""
        a = math.radians(self.slip_direction_deg)
        return (self.slip_distance_mm * math.cos(a), self.slip_distance_mm * math.sin(a))

    def travel_bounds_mm(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the sensor centre over the sequence, fabric frame, mm.

        Covers the commanded slide plus tremor and the lag of the hand's position servo
        (0.5 mm margin); callers add the sensor's field (its circumscribed circle for twist).
        """
        x0, y0 = self.start_xy_mm
        dx, dy = self.slip_vector_mm()
        m = 2 * self.tremor_amplitude_mm + 0.5  # 0.5 mm: servo lag and gel shear overshoot
        return (min(x0, x0 + dx) - m, min(y0, y0 + dy) - m, max(x0, x0 + dx) + m, max(y0, y0 + dy) + m)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _uniform(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])


def sample_motion(action: str, seed: int | np.random.Generator, *, frames: tuple[int, int] = (25, 36),
                  precontact: tuple[int, int] | None = None, ranges: MotionRanges | None = None) -> Motion:
    """Draw one hand-held motion.

    ``action``: "press", "slip", "twist", or "random" (drawn at the ratios of ``ranges.actions``,
    7:1:2 in ViTac Cloth). ``frames``: total frame count, [low, high] inclusive (ViTac: 25-36).
    ``precontact``: pre-contact frame count, [low, high] inclusive (default from motions.toml).
    Same seed, same motion.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    ranges = ranges or load_motion_ranges()
    if action == "random":
        w = np.array([ranges.actions.press, ranges.actions.slip, ranges.actions.twist], dtype=float)
        action = ACTIONS[int(rng.choice(3, p=w / w.sum()))]
    if action not in ACTIONS:
        raise GelsimError(f"unknown action {action!r}; choose press, slip, twist or random")
    if not 1 <= frames[0] <= frames[1]:
        raise GelsimError(f"frames {frames}: need 1 <= low <= high")
    timing = ranges.timing
    # Drawn always, so that an explicit precontact does not shift the rest of the random stream.
    late = rng.random() < timing.late_start_fraction
    pre = precontact if precontact is not None else (timing.late_start_frames if late else timing.precontact_frames)
    if not 0 <= pre[0] <= pre[1]:
        raise GelsimError(f"precontact {pre}: need 0 <= low <= high")
    num_frames = int(rng.integers(frames[0], frames[1] + 1))
    precontact_frames = int(rng.integers(pre[0], pre[1] + 1))
    if num_frames - precontact_frames < MIN_CONTACT_FRAMES:
        raise GelsimError(f"{num_frames} frames with {precontact_frames} before contact leaves fewer than {MIN_CONTACT_FRAMES} "
                          "in contact; raise frames or lower precontact")
    t, a = ranges.timing, ranges.approach
    r = a.start_offset_mm * math.sqrt(rng.uniform())  # uniform over the disk
    phi = rng.uniform(0, 2 * math.pi)
    tilt_max = ranges.tilt.max_tilt_deg
    peak = _uniform(rng, ranges.force.peak_force_n)
    kw: dict = {}
    if action != "press":
        peak *= _uniform(rng, ranges.force.slip_force_scale)
    if action == "slip":
        kw = dict(slip_direction_deg=_uniform(rng, (0.0, 360.0)), slip_distance_mm=_uniform(rng, ranges.slip.distance_mm))
    elif action == "twist":
        kw = dict(twist_deg=float(rng.choice([-1.0, 1.0])) * _uniform(rng, ranges.twist.angle_deg))
    rise = _uniform(rng, t.rise_fraction)
    hold = _uniform(rng, t.hold_fraction)
    tail = _uniform(rng, t.release_tail_fraction)
    return Motion(
        action=action, num_frames=num_frames, precontact_frames=precontact_frames,
        start_xy_mm=(r * math.cos(phi), r * math.sin(phi)),
        fabric_rotation_deg=_uniform(rng, a.fabric_rotation_deg) % 360.0,
        approach_speed_mm_s=_uniform(rng, a.speed_mm_s), peak_force_n=peak,
        tilt_deg=(_uniform(rng, (-tilt_max, tilt_max)), _uniform(rng, (-tilt_max, tilt_max))),
        tremor_amplitude_mm=_uniform(rng, ranges.tremor.amplitude_mm),
        tremor_frequency_hz=_uniform(rng, ranges.tremor.frequency_hz),
        tremor_phase_rad=tuple(float(v) for v in rng.uniform(0, 2 * math.pi, 3)),
        tremor_force_fraction=_uniform(rng, ranges.tremor.force_fraction),
        contact_phase=_uniform(rng, t.contact_phase),
        rise_fraction=rise, hold_fraction=hold, release_fraction=max(0.0, 1.0 - rise - hold - tail),
        settle_fraction=_uniform(rng, t.settle_fraction), end_fraction=_uniform(rng, t.end_fraction),
        **kw)
