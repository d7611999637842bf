"""Each nuisance stage's own random generator per sequence.

``stage_rng(seed, stage)`` is seeded by the sequence's seed and a fixed tag of the stage, so a stage's draws
do not depend on which other stages run, on the frame order or on the worker, and a level that runs no
stage draws nothing (its output is the stage-free output, byte for byte).
"""
from __future__ import annotations

import numpy as np

from ..errors import GelsimError
from .params import STAGES

#: Tag mixed into every nuisance generator's seed ("nuis" in ASCII), apart from the other streams a sequence
#: seed feeds (motion, fabric, camera noise).
NUISANCE_TAG = 0x6E756973
#: Fixed per stage: changing a stage's position in STAGES must not change its draws. (2 and 3 were the
#: exposure and white-balance stages before they became one start-up stage: not reused.)
STAGE_TAGS = {"fibres": 1, "startup": 4}
assert set(STAGE_TAGS) == set(STAGES)


def stage_rng(seed: int, stage: str) -> np.random.Generator:
    """The generator of ``stage`` for the sequence with seed ``seed`` (an integer >= 0)."""
    if stage not in STAGE_TAGS:
        raise GelsimError(f"unknown nuisance stage {stage!r}; known stages are {', '.join(STAGES)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise GelsimError(f"seed {seed!r} must be an integer >= 0")
    return np.random.default_rng([int(seed), NUISANCE_TAG, STAGE_TAGS[stage]])
