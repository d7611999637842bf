"""The nuisance stages of one sequence, frame by frame, for the frame stream (docs/nuisance.md, section 3).

:class:`SequenceNuisance` is built once per sequence from a level's stages and the sequence's seed; for
each frame it gives a :class:`FrameNuisance`: the fibres' dents (mm, added to the depth the optics
render, never to the imprint the labels come from) and the camera's per-channel gains (exposure x white
balance, applied by :class:`gelsim.optics.composite.CameraGains` before the noise). Both are computed on
the CPU from the sequence's own generators (:func:`gelsim.nuisance.seeds.stage_rng`), so every backend,
batch size and worker count renders the same inputs.

The camera's controllers meter a scene whose mean stays at the flat gel's (luma and channel ratios 1):
its gains are then a function of the seed and the frame index alone, known before the frame is
rendered (a batch renders them without waiting for the frames before). A touch moves a 320x240 frame's
mean luminance by 0.9% (median over 40 sequences) to 2.7% (largest) of frame 0's, about the AGC's 2%
stable region: metering the rendered frames would move the start-up gains by up to that much and start
no correction after them (measured 2026-11-28 on the cpu preset's data; docs/nuisance.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..errors import GelsimError
from .camera import camera_start, camera_step
from .fibres import approach_gap_mm, draw_fibres, fibre_dents_mm, gap_map_mm
from .params import STAGES, StageParams
from .seeds import stage_rng

#: What the camera's controllers meter: the flat gel's channel means, relative (the scene is taken as flat).
_FLAT = np.ones((1, 1, 3), np.float32)
_FLAT_MEANS = np.ones(3)


@dataclass(frozen=True)
class FrameNuisance:
    """One frame's nuisance inputs: ``dents_mm`` float32 ``(H, W)`` mm added to the rendered depth (None: no
    dent), ``gains`` float64 ``(3,)`` per-channel gains before the noise (None: all 1)."""
    dents_mm: np.ndarray | None = None
    gains: np.ndarray | None = None


def camera_gains(seed: int, severities: Mapping[str, float], stages: StageParams, num_frames: int) -> np.ndarray | None:
    """The camera's per-channel gains of each frame of a sequence, float64 ``(T, 3)``, or None when neither
    camera stage runs (``severities``: stage -> severity, as :meth:`~gelsim.nuisance.params.NuisanceModel.level`
    gives)."""
    state = camera_start(seed, dict(severities), stages)
    if state.exposure is None and state.white_balance is None:
        return None
    out = np.empty((num_frames, 3))
    for t in range(num_frames):
        out[t], state = camera_step(state, _FLAT, _FLAT_MEANS, stages)
    return out


class SequenceNuisance:
    """The nuisance inputs of every frame of one sequence.

    ``severities``: stage -> severity (empty: nothing, and nothing drawn); ``stages``: the stages'
    parameters; ``seed``: the sequence's; ``hairiness``: the touched fabric's catalog hairiness (0 for an
    object without); ``profile``: the sensor (image size, mm per px, gel dome and modulus); ``motion``:
    the sequence's :class:`gelsim.motion.Motion` (when the approach ends, how fast)."""

    def __init__(self, severities: Mapping[str, float], stages: StageParams, seed: int, hairiness: float,
                 profile, motion):
        unknown = set(severities) - set(STAGES)
        if unknown:
            raise GelsimError(f"unknown nuisance stage {sorted(unknown)[0]!r}; known stages are {', '.join(STAGES)}")
        self.profile, self.motion, self.stages = profile, motion, stages
        self.gains = camera_gains(seed, severities, stages, motion.num_frames)
        self.fibres = None
        if severities.get("fibres", 0.0) > 0 and hairiness > 0:
            f = draw_fibres(stage_rng(seed, "fibres"), profile.field_mm, float(hairiness), stages.fibres,
                            severities["fibres"])
            self.fibres = f if len(f) else None
        self._last_contact = None
        self.last: FrameNuisance | None = None      # what frame() gave last
        self.active = self.gains is not None or self.fibres is not None

    def _apex_gap_mm(self, i: int, indentation_mm: float | None) -> float:
        """The gap between the gel's nearest point and the fabric at frame ``i``, mm (negative: pressed in)."""
        m = self.motion
        fps = self.profile.image.fps_hz
        if indentation_mm is not None and indentation_mm > 0:
            self._last_contact = i
            return -float(indentation_mm)
        if self._last_contact is None and i < m.precontact_frames:
            return approach_gap_mm(i, m.precontact_frames, m.contact_phase, m.approach_speed_mm_s, fps)
        last = self._last_contact if self._last_contact is not None else m.precontact_frames
        return m.approach_speed_mm_s * max(i - last, 1) / fps       # lifting off at the approach speed

    def frame(self, i: int, imprint=None, *, tilt_deg=(0.0, 0.0)) -> FrameNuisance | None:
        """Frame ``i``'s inputs (None: nothing to add; also kept as :attr:`last`), given its
        :class:`~gelsim.gel.Imprint` (None where nothing presses) and the sensor's tilt (roll, pitch)
        degrees. Call in frame order."""
        self.last = self._frame(i, None if imprint is None else float(imprint.indentation_mm), tilt_deg)
        return self.last

    def _frame(self, i: int, indentation_mm: float | None, tilt_deg) -> FrameNuisance | None:
        if not self.active:
            return None
        p = self.profile
        dents = None
        if self.fibres is not None:
            gap = gap_map_mm(p.shape, p.image.mm_per_px, self._apex_gap_mm(i, indentation_mm), p.gel.dome_radius_mm,
                             tuple(float(v) for v in tilt_deg))
            d = fibre_dents_mm(self.fibres, gap, p.image.mm_per_px, p.gel.young_modulus_mpa, p.gel.poisson_ratio,
                               self.stages.fibres)
            dents = d if d.any() else None
        gains = None if self.gains is None else self.gains[i]
        return None if dents is None and gains is None else FrameNuisance(dents, gains)
