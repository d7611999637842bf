"""The webcam's auto-exposure and auto white balance: per-frame colour gains, and the kernel that applies them.

A webcam meters each frame and moves its exposure (one gain) and its white balance (R and B gains
against G) towards targets; gelsim's frame at gain 1 is the settled state. The controllers follow
libcamera's Raspberry Pi AGC and AWB rules (docs/nuisance.md, section 2; numbers in
``gelsim/assets/nuisance.toml``):

* **exposure**: frame 0 is exposed at ``start`` (relative to the settled exposure). Frame t is metered;
  the exposure computed from it applies from frame ``t + delay_frames``. Within the first
  ``startup_frames`` metered frames the controller jumps to its target; after them it moves
  ``speed`` of the way (``sqrt(speed)`` once within ``near_band`` of the target) and not at all within
  ``stable_region`` of it. The target is ``1 / luma_ratio``: the exposure that brings the frame's mean
  luminance back to the flat gel's (a linear sensor; clipping is not modelled).
* **white balance**: the first ``delay_frames`` frames are balanced with gains ``start``; in the first
  ``startup_frames`` frames each frame is metered and the gains jump to their targets, afterwards every
  ``period_frames``-th frame moves them ``speed`` of the way; an update applies ``delay_frames`` later. The target is grey-world against
  the flat gel: the gains that bring the frame's channel means, relative to G, back to the flat gel's.

Both are pure: a frozen state and a step ``(state, metered) -> (gain, state)``, so a frame stream can
run them frame by frame, and :func:`exposure_gains` / :func:`white_balance_gains` run them over a whole
sequence with the same result. The gains are applied by :class:`gelsim.optics.composite.CameraGains`
(numpy and torch kernels, the same bits).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import GelsimError
from .params import ExposureParams, WhiteBalanceParams, check_severity

#: Rec. 601 luma weights of R, G, B (what libcamera's AGC meters).
LUMA_RGB = np.array([0.299, 0.587, 0.114], np.float64)


# ---------------------------------------------------------------- metering

def frame_means(frame: np.ndarray) -> np.ndarray:
    """Channel means of a ``(H, W, 3)`` frame (DN), float64 (3,)."""
    f = np.asarray(frame)
    if f.ndim != 3 or f.shape[2] != 3:
        raise GelsimError(f"frame has shape {f.shape}; give (H, W, 3)")
    return f.reshape(-1, 3).mean(axis=0, dtype=np.float64)


def metered_ratios(frame: np.ndarray, background_means: np.ndarray) -> tuple[float, np.ndarray]:
    """What the controllers meter on ``frame`` (at gain 1) against the flat gel's channel means
    ``background_means`` (3,): (luma ratio, channel-mean ratios (3,)). Both 1 for the flat gel."""
    bg = np.asarray(background_means, np.float64)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)) or np.any(bg <= 0):
        raise GelsimError(f"background means {bg} must be three positive numbers (DN)")
    m = frame_means(frame)
    return float(LUMA_RGB @ m / (LUMA_RGB @ bg)), m / bg


# ---------------------------------------------------------------- draws

def draw_exposure_start(rng: np.random.Generator, p: ExposureParams, severity: float) -> float:
    """Frame 0's exposure relative to the settled one: ``max(0, 1 - severity (1 - r))``, r uniform in
    ``p.start_ratio``. One uniform draw whatever the severity (so severities share their draws)."""
    s = check_severity(severity)
    r = float(rng.uniform(p.start_ratio[0], p.start_ratio[1]))
    return max(0.0, 1.0 - s * (1.0 - r))


def draw_white_balance_start(rng: np.random.Generator, p: WhiteBalanceParams, severity: float) -> np.ndarray:
    """Frame 0's white-balance gains, float64 (3,): G is 1, R and B are ``1 + severity u``, u uniform in
    ``[-start_offset_max, start_offset_max]``. Two uniform draws whatever the severity."""
    s = check_severity(severity)
    u = rng.uniform(-p.start_offset_max, p.start_offset_max, 2)
    return np.array([1.0 + s * u[0], 1.0, 1.0 + s * u[1]])


# ---------------------------------------------------------------- exposure

@dataclass(frozen=True)
class ExposureState:
    """Between two frames: the index of the next frame, the exposures already decided for the next
    ``delay_frames`` frames (oldest first) and the controller's filtered exposure (None before the first
    metering)."""
    frame: int
    pending: tuple[float, ...]
    filtered: float | None


def exposure_start(start: float, p: ExposureParams) -> ExposureState:
    """The state before frame 0 of a stream whose first ``delay_frames`` frames are exposed at ``start``."""
    if not (math.isfinite(start) and start >= 0.0):
        raise GelsimError(f"start exposure {start} must be a finite ratio >= 0")
    return ExposureState(frame=0, pending=(float(start),) * p.delay_frames, filtered=None)


def _filter(filtered: float | None, target: float, metered: int, p: ExposureParams) -> float:
    """libcamera's AGC filter: the new filtered exposure after the ``metered``-th metering."""
    if filtered is None or metered <= p.startup_frames:
        return target
    if filtered * (1.0 - p.stable_region) < target < filtered * (1.0 + p.stable_region):
        return filtered
    speed = p.speed
    if target * (1.0 - p.near_band) < filtered < target * (1.0 + p.near_band):
        speed = math.sqrt(speed)
    return speed * target + (1.0 - speed) * filtered


def exposure_step(state: ExposureState, luma_ratio: float, p: ExposureParams) -> tuple[float, ExposureState]:
    """Frame ``state.frame``: the exposure (gain) it is taken at, and the state after metering it.
    ``luma_ratio``: the frame's mean luminance at gain 1 over the flat gel's (> 0)."""
    if not (math.isfinite(luma_ratio) and luma_ratio > 0.0):
        raise GelsimError(f"luma ratio {luma_ratio} must be a positive finite number")
    if len(state.pending) != p.delay_frames:
        raise GelsimError(f"exposure state holds {len(state.pending)} pending frames, the parameters "
                          f"{p.delay_frames}; start it with exposure_start and these parameters")
    filtered = _filter(state.filtered, 1.0 / luma_ratio, state.frame + 1, p)
    gain = state.pending[0]
    return float(gain), ExposureState(frame=state.frame + 1, pending=state.pending[1:] + (filtered,),
                                      filtered=filtered)


def exposure_gains(luma_ratios, start: float, p: ExposureParams) -> np.ndarray:
    """The exposure of every frame of a sequence, float64 (T,), from its frames' luma ratios (T,)."""
    state = exposure_start(start, p)
    out = []
    for r in np.asarray(luma_ratios, np.float64).ravel():
        g, state = exposure_step(state, float(r), p)
        out.append(g)
    return np.array(out)


# ---------------------------------------------------------------- white balance

@dataclass(frozen=True)
class WhiteBalanceState:
    """Between two frames: the next frame's index and the gains (3,) already decided for the next
    ``delay_frames`` frames (oldest first)."""
    frame: int
    pending: tuple[tuple[float, float, float], ...]


def white_balance_start(start, p: WhiteBalanceParams) -> WhiteBalanceState:
    """The state before frame 0 of a stream whose first ``delay_frames`` frames are balanced with gains
    ``start`` (3,)."""
    g = np.asarray(start, np.float64)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
        raise GelsimError(f"white-balance gains {start} must be three positive numbers")
    return WhiteBalanceState(frame=0, pending=(tuple(float(v) for v in g),) * p.delay_frames)


def white_balance_step(state: WhiteBalanceState, channel_ratios, p: WhiteBalanceParams) \
        -> tuple[np.ndarray, WhiteBalanceState]:
    """Frame ``state.frame``: its gains (3,), and the state after metering it. ``channel_ratios`` (3,):
    the frame's channel means at gain 1 over the flat gel's."""
    c = np.asarray(channel_ratios, np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)) or np.any(c <= 0):
        raise GelsimError(f"channel ratios {channel_ratios} must be three positive numbers")
    if len(state.pending) != p.delay_frames:
        raise GelsimError(f"white-balance state holds {len(state.pending)} pending frames, the parameters "
                          f"{p.delay_frames}; start it with white_balance_start and these parameters")
    t = state.frame
    latest = np.array(state.pending[-1])                   # the most recent decision
    startup = t < p.startup_frames
    if startup or (t - p.startup_frames) % p.period_frames == 0:
        target = c[1] / c                                  # grey-world against the flat gel, G fixed at 1
        speed = 1.0 if startup else p.speed
        latest = speed * target + (1.0 - speed) * latest
    decided = tuple(float(v) for v in latest)
    return np.array(state.pending[0]), WhiteBalanceState(frame=t + 1, pending=state.pending[1:] + (decided,))


def white_balance_gains(channel_ratios, start, p: WhiteBalanceParams) -> np.ndarray:
    """The white-balance gains of every frame of a sequence, float64 (T, 3), from its channel ratios (T, 3)."""
    c = np.asarray(channel_ratios, np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise GelsimError(f"channel ratios have shape {c.shape}; give (T, 3)")
    state = white_balance_start(start, p)
    out = []
    for row in c:
        g, state = white_balance_step(state, row, p)
        out.append(g)
    return np.array(out).reshape(-1, 3)


# ---------------------------------------------------------------- both, per frame

@dataclass(frozen=True)
class CameraState:
    """The exposure and white-balance controllers of one stream (None: that stage is off)."""
    exposure: ExposureState | None
    white_balance: WhiteBalanceState | None


def camera_start(seed: int, severities: dict, stages) -> CameraState:
    """The camera stages' state before frame 0 of a sequence: frame 0's exposure and white balance drawn
    from the stages' own generators (:func:`gelsim.nuisance.seeds.stage_rng`). ``severities``: stage name ->
    severity, as :meth:`gelsim.nuisance.params.NuisanceModel.level` gives (absent or 0: off, nothing drawn);
    ``stages``: :class:`gelsim.nuisance.params.StageParams`."""
    from .seeds import stage_rng

    e = severities.get("exposure", 0.0)
    w = severities.get("white_balance", 0.0)
    exp = None if not e else exposure_start(draw_exposure_start(stage_rng(seed, "exposure"), stages.exposure, e),
                                            stages.exposure)
    wb = None if not w else white_balance_start(
        draw_white_balance_start(stage_rng(seed, "white_balance"), stages.white_balance, w), stages.white_balance)
    return CameraState(exposure=exp, white_balance=wb)


def camera_step(state: CameraState, frame: np.ndarray, background_means, stages) -> tuple[np.ndarray, CameraState]:
    """Frame ``state``'s next frame, ``frame`` (float32 ``(H, W, 3)`` DN at gain 1, before noise): its
    per-channel gains (3,) (exposure x white balance; ones when both stages are off) and the state after
    the camera metered it. ``background_means`` (3,): the flat gel's channel means, DN."""
    gains = np.ones(3)
    if state.exposure is None and state.white_balance is None:
        return gains, state
    luma, channels = metered_ratios(frame, background_means)
    exp, wb = state.exposure, state.white_balance
    if exp is not None:
        g, exp = exposure_step(exp, luma, stages.exposure)
        gains = gains * g
    if wb is not None:
        g3, wb = white_balance_step(wb, channels, stages.white_balance)
        gains = gains * g3
    return gains, CameraState(exposure=exp, white_balance=wb)
