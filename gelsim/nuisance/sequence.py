"""The nuisance stages of one sequence, frame by frame, for the frame stream (docs/nuisance.md, section 3).

:class:`SequenceNuisance` is built once per sequence from a level's stages and the sequence's seed; for
each frame it gives a :class:`FrameNuisance`: the fibres' dents (mm, added to the depth the optics
render, never to the imprint the labels come from), the camera's per-channel gains (exposure x white
balance of the start-up, applied by :class:`gelsim.optics.composite.CameraGains` before the noise) and what
was applied (the per-frame record, :mod:`gelsim.nuisance.record`). All of it is computed on the CPU from the
sequence's own generators (:func:`gelsim.nuisance.seeds.stage_rng`), so every backend, batch size and worker
count renders the same inputs.

The start-up's gains are a function of the seed and the frame index alone, known before any frame is
rendered: the controllers' answer to the touch itself is not modelled (a touch moves a 320x240 frame's mean
luminance by 0.9% in the median, at most 2.7%, of the flat gel's: about the AGC's 2% stable region, so a
settled camera barely answers it; measured 2026-11-28 on the cpu preset's data, docs/nuisance.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..errors import GelsimError
from .camera import draw_startup, startup_gains
from .fibres import approach_gap_mm, draw_dents_mm, draw_fibres, fibre_depths_mm, gap_map_mm
from .params import STAGES, StageParams
from .seeds import stage_rng


@dataclass(frozen=True)
class FrameNuisance:
    """One frame's nuisance inputs and what they were: ``dents_mm`` float32 ``(H, W)`` mm added to the
    rendered depth (None: no dent), ``gains`` float64 ``(3,)`` per-channel gains before the noise (None: all
    1); for the record, ``stream_age_frames`` (frames since the camera's stream started; -1: settled),
    ``fibres_touching`` (fibres denting the gel) and ``fibre_dent_max_mm`` (the deepest dent, mm)."""
    dents_mm: np.ndarray | None = None
    gains: np.ndarray | None = None
    stream_age_frames: int = -1
    fibres_touching: int = 0
    fibre_dent_max_mm: float = 0.0


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
        self.startup = None
        self.gains = None
        if severities.get("startup", 0.0) > 0:
            self.startup = draw_startup(stage_rng(seed, "startup"), stages.startup, severities["startup"])
            self.gains = startup_gains(self.startup, motion.num_frames, stages.startup)
        self.fibres = None
        if severities.get("fibres", 0.0) > 0 and hairiness > 0:
            f = draw_fibres(stage_rng(seed, "fibres"), profile.field_mm, float(hairiness), stages.fibres,
                            severities["fibres"])
            self.fibres = f if len(f) else None
        self._last_contact = None
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
        """Frame ``i``'s inputs (None: nothing to add), given its :class:`~gelsim.gel.Imprint` (None where
        nothing presses) and the sensor's tilt (roll, pitch) degrees. Call in frame order: the frame pipeline
        (:func:`gelsim.stream.make_frames`) asks once per frame and hands the answer on in the frame's record
        (:attr:`gelsim.stream.FrameRecord.nuisance`), which the per-frame record is written from."""
        return self._frame(i, None if imprint is None else float(imprint.indentation_mm), tilt_deg)

    def _frame(self, i: int, indentation_mm: float | None, tilt_deg) -> FrameNuisance | None:
        if not self.active:
            return None
        p = self.profile
        dents, touching, deepest = None, 0, 0.0
        if self.fibres is not None:
            gap = gap_map_mm(p.shape, p.image.mm_per_px, self._apex_gap_mm(i, indentation_mm), p.gel.dome_radius_mm,
                             tuple(float(v) for v in tilt_deg))
            depth = fibre_depths_mm(self.fibres, gap, p.image.mm_per_px, p.gel.young_modulus_mpa,
                                    p.gel.poisson_ratio, self.stages.fibres)
            touching = int(np.count_nonzero(depth))
            if touching:
                deepest = float(depth.max())
                d = draw_dents_mm(self.fibres, depth, p.shape, p.image.mm_per_px, self.stages.fibres)
                dents = d if d.any() else None
        gains = None if self.gains is None else self.gains[i]
        age = -1 if self.gains is None else int(self.startup.age_frames + i)
        return FrameNuisance(dents, gains, age, touching, deepest)
