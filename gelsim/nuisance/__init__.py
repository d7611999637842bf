"""Nuisances of a real, hand-held GelSight before and around the touch (issue 43; docs/nuisance.md).

Stages, each a pure function with its parameters in ``gelsim/assets/nuisance.toml``:

* ``fibres`` (:mod:`.fibres`): loose fibres of hairy fabrics dent the gel before the main contact; a
  depth map (mm) added to the imprint before shading;
* ``exposure`` and ``white_balance`` (:mod:`.camera`): the webcam's auto-exposure and auto white balance
  settling after the stream starts and answering the scene; per-frame colour gains applied to the float
  frame before noise (by :class:`gelsim.optics.composite.CameraGains`, numpy and torch).

Named levels (``none``, ``camera``, ``handheld``) say which stages run at which severity
(:meth:`NuisanceModel.level`); ``none`` runs nothing and draws nothing. Each stage draws from its own
generator per sequence (:func:`stage_rng`). The frame stream runs them through
:class:`.sequence.SequenceNuisance` (:func:`gelsim.sequence.render_sequence`, ``gelsim generate --nuisance``):
the fibres' dents go into the depth the optics render, the camera's gains into
:class:`gelsim.optics.composite.CameraGains`.
"""
from __future__ import annotations

from .camera import (CameraState, ExposureState, WhiteBalanceState, camera_start, camera_step,
                     draw_exposure_start, draw_white_balance_start, exposure_gains, exposure_start, exposure_step,
                     frame_means, metered_ratios, white_balance_gains, white_balance_start, white_balance_step)
from .fibres import (Fibres, approach_gap_mm, buckling_dent_mm, dent_depths_mm, draw_fibres, fibre_dents_mm,
                     gap_map_mm)
from .params import (MAX_SEVERITY, NONE_LEVEL, NUISANCE_FILE, STAGES, ExposureParams, FibreParams, NuisanceModel,
                     StageParams, WhiteBalanceParams, check_severity, load_nuisance)
from .seeds import stage_rng

__all__ = [
    "STAGES", "MAX_SEVERITY", "NONE_LEVEL", "NUISANCE_FILE", "NuisanceModel", "StageParams", "ExposureParams",
    "WhiteBalanceParams", "FibreParams", "load_nuisance", "check_severity", "stage_rng",
    "CameraState", "camera_start", "camera_step", "ExposureState", "exposure_start", "exposure_step",
    "exposure_gains", "draw_exposure_start", "WhiteBalanceState", "white_balance_start", "white_balance_step",
    "white_balance_gains", "draw_white_balance_start", "frame_means", "metered_ratios",
    "Fibres", "draw_fibres", "buckling_dent_mm", "dent_depths_mm", "fibre_dents_mm", "gap_map_mm",
    "approach_gap_mm",
]
