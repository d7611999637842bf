"""The centred crop that ``stam``'s models see of each frame, as gelsim's statistics measure it and its
previews draw it (:mod:`gelsim.stats`, :mod:`gelsim.previews`)."""
from __future__ import annotations

import math

from .errors import GelsimError

# Side of the centred square that `stam experiment --preset cpu` keeps from each frame, as a fraction
# of the frame's shorter side: stam/configs/cpu.toml [train] crop (tests/gelsim/test_stats.py checks
# that the two agree; gelsim does not import stam, which sits downstream of it).
STAM_CPU_CROP = 0.5


def check_crop(fraction: float) -> float:
    """``fraction`` if it is a valid crop (0 < fraction <= 1), else a GelsimError."""
    if not (math.isfinite(fraction) and 0 < fraction <= 1):
        raise GelsimError(f"crop fraction {fraction} is out of range; give the kept fraction of the shorter side, "
                          "0-1 (stam's cpu preset: 0.5)")
    return fraction


def crop_box_px(width_px: int, height_px: int, fraction: float = STAM_CPU_CROP) -> tuple[float, float, float, float]:
    """Edges (x0, y0, x1, y1), px, of the centred square stam keeps (``stam.data.centre_square``):
    side ``round(fraction * min(W, H))``, pixel centres at integers."""
    check_crop(fraction)
    side = max(1, round(fraction * min(height_px, width_px)))
    y0, x0 = (height_px - side) // 2, (width_px - side) // 2
    return x0 - 0.5, y0 - 0.5, x0 + side - 0.5, y0 + side - 0.5
