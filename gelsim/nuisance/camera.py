"""The webcam's start-up: auto-exposure and auto white balance settling after its stream starts.

A webcam meters each frame and moves its exposure (one gain) and its white balance (R and B gains
against G) towards targets; gelsim's frame at gain 1 is the settled state. When the stream starts, both
begin away from it and settle over its first frames (docs/nuisance.md, section 2; numbers in
``gelsim/assets/nuisance.toml``, ``[stages.startup]``):

* the exposure starts at ``exposure_start`` of the settled one and stays there for ``exposure_delay_frames``
  frames (the sensor's exposure delay: the first correction lands that late); its log error then shrinks by
  the same factor every frame, so that it is within ``stable_region`` of the settled exposure at stream
  frame ``exposure_settle_frames`` (the frames the sources drop before the image is usable); once within
  ``stable_region`` the controller stops, so the exposure keeps that last small error;
* the white balance does the same per channel, from R and B gains up to ``white_balance_start_max`` off.

Which recordings see it: a share of them (``restart_share`` x severity) catches a stream that started
``preroll_frames`` frames before the recording's frame 0; the others were recorded from a settled stream
and get no gains at all. Every draw is made whatever the severity, and a recording that catches the
start-up at severity s also does at any larger one: a severity sweep changes how many recordings see a
start-up, never how dark a frame gets. The gains are applied by
:class:`gelsim.optics.composite.CameraGains` (numpy and torch kernels, the same bits).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import GelsimError
from .params import StartupParams, check_severity


@dataclass(frozen=True)
class Startup:
    """One recording's start-up, as drawn: ``age_frames`` is how many frames the stream had run at the
    recording's frame 0 (None: a settled stream, no start-up in the recording); the stream's first-frame
    exposure (relative to the settled one) and its settle frame; its first-frame white-balance gains
    float64 (3,) (G = 1) and their settle frame."""
    age_frames: int | None
    exposure_start: float
    exposure_settle_frames: int
    white_balance_start: np.ndarray
    white_balance_settle_frames: int


def draw_startup(rng: np.random.Generator, p: StartupParams, severity: float) -> Startup:
    """One recording's start-up at ``severity`` (0-4): whether it catches a fresh stream (with probability
    ``min(1, severity x p.restart_share)``), how long before its frame 0 the stream started, and the
    stream's start values. Seven draws whatever the severity, in a fixed order."""
    s = check_severity(severity)
    catch = float(rng.uniform())
    age = int(rng.integers(p.preroll_frames[0], p.preroll_frames[1], endpoint=True))
    exp0 = float(rng.uniform(p.exposure_start[0], p.exposure_start[1]))
    exp_settle = int(rng.integers(p.exposure_settle_frames[0], p.exposure_settle_frames[1], endpoint=True))
    wb = rng.uniform(-p.white_balance_start_max, p.white_balance_start_max, 2)
    wb_settle = int(rng.integers(p.white_balance_settle_frames[0], p.white_balance_settle_frames[1], endpoint=True))
    caught = catch < min(1.0, s * p.restart_share)
    return Startup(age if caught else None, exp0, exp_settle, np.array([1.0 + wb[0], 1.0, 1.0 + wb[1]]), wb_settle)


def settling(start, delay_frames: int, settle_frames: int, stable_region: float, frames) -> np.ndarray:
    """The gain of a controller that starts at ``start`` (> 0, relative to its settled value; an array
    broadcasts, e.g. three channels) at the stream's frames ``frames`` (int array >= 0), float64
    ``frames.shape + start.shape``.

    Frames ``< delay_frames`` keep ``start``. After them the log error shrinks geometrically, by the factor
    that leaves ``log(1 + stable_region)`` at frame ``settle_frames``; once within ``stable_region`` (in
    log terms) the controller stops and holds that gain. A start already within ``stable_region`` never moves."""
    s0 = np.asarray(start, np.float64)
    if not np.all(np.isfinite(s0) & (s0 > 0)):
        raise GelsimError(f"start gain {start} must be positive and finite")
    log0 = np.log(s0)
    if not (0 <= delay_frames < settle_frames and stable_region > 0):
        raise GelsimError(f"need 0 <= delay_frames ({delay_frames}) < settle_frames ({settle_frames}) "
                          f"and stable_region ({stable_region}) > 0")
    t = np.asarray(frames)
    if t.size and (not np.issubdtype(t.dtype, np.integer) or t.min() < 0):
        raise GelsimError("frames must be integers >= 0 (frames since the stream started)")
    band = math.log1p(stable_region)
    err = np.abs(log0)
    # corrections up to the settle frame; the last one leaves exactly `band`, and the controller holds it
    steps = settle_frames - delay_frames + 1
    rate = np.where(err > band, (band / np.maximum(err, band)) ** (1.0 / steps), 1.0)
    k = np.clip(t - delay_frames + 1, 0, steps)
    if log0.ndim:
        k = k[..., None]
    return np.power(s0, rate ** k)    # start ** 1 is start, exactly


def startup_gains(startup: Startup, num_frames: int, p: StartupParams) -> np.ndarray | None:
    """The per-channel gains (exposure x white balance) of a recording's frames, float64 ``(T, 3)``, or None
    when it did not catch the start-up (a settled stream: gains 1)."""
    if startup.age_frames is None:
        return None
    if num_frames < 0:
        raise GelsimError(f"num_frames {num_frames} must be >= 0")
    t = startup.age_frames + np.arange(num_frames)
    exposure = settling(startup.exposure_start, p.exposure_delay_frames, startup.exposure_settle_frames,
                        p.stable_region, t)
    balance = settling(startup.white_balance_start, p.white_balance_delay_frames,
                       startup.white_balance_settle_frames, p.stable_region, t)
    return exposure[:, None] * balance
