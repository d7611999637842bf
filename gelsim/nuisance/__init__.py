"""Nuisances of a real, hand-held GelSight before and around the touch (issue 43; docs/nuisance.md).

Stages, each a pure function with its parameters in ``gelsim/assets/nuisance.toml``:

* ``fibres`` (:mod:`.fibres`): loose fibres of hairy fabrics dent the gel before the main contact; a
  depth map (mm) added to the imprint before shading;
* ``startup`` (:mod:`.camera`): the webcam's auto-exposure and auto white balance settling after its stream
  starts, in the share of recordings that catch it; per-frame colour gains applied to the float frame before
  noise (by :class:`gelsim.optics.composite.CameraGains`, numpy and torch).

Named levels (``none``, ``camera``, ``handheld``, ``webcam-restart``) say which stages run at which severity
(:meth:`NuisanceModel.level`) and with which parameters (:meth:`NuisanceModel.stages_for`); ``none`` runs
nothing and draws nothing. Each stage draws from its own generator per sequence (:func:`stage_rng`). The frame
stream runs them through :class:`.sequence.SequenceNuisance` (``gelsim generate --nuisance``); what each frame
got is written to the dataset's per-frame record (:mod:`.record`).
"""
from __future__ import annotations

from .camera import Startup, draw_startup, settling, startup_gains
from .fibres import (Fibres, approach_gap_mm, buckling_dent_mm, dent_depths_mm, draw_dents_mm, draw_fibres,
                     fibre_dents_mm, fibre_depths_mm, gap_map_mm)
from .params import (MAX_SEVERITY, NONE_LEVEL, NUISANCE_FILE, STAGES, FibreParams, NuisanceModel, StageParams,
                     StartupParams, check_severity, load_nuisance)
from .record import RECORD, RECORD_KEYS, NuisanceLog, frame_row, record_problems, stack_rows
from .seeds import stage_rng

__all__ = [
    "STAGES", "MAX_SEVERITY", "NONE_LEVEL", "NUISANCE_FILE", "NuisanceModel", "StageParams", "StartupParams",
    "FibreParams", "load_nuisance", "check_severity", "stage_rng",
    "Startup", "draw_startup", "settling", "startup_gains",
    "Fibres", "draw_fibres", "buckling_dent_mm", "dent_depths_mm", "fibre_depths_mm", "draw_dents_mm",
    "fibre_dents_mm", "gap_map_mm", "approach_gap_mm",
    "RECORD", "RECORD_KEYS", "NuisanceLog", "frame_row", "record_problems", "stack_rows",
]
