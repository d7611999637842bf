"""Named fidelity levels: one choice that sets every speed/accuracy knob.

Levels live in ``gelsim/assets/fidelity.toml``; see that file for what each knob does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from .errors import check_choice
from .params import ASSETS_DIR, build, load_toml, param

FIDELITY_FILE = ASSETS_DIR / "fidelity.toml"
DEFAULT_LEVEL = "balanced"


@dataclass(frozen=True)
class Fidelity:
    name: str
    physics_dt_s: float = param(lo=1e-6, hi=0.02, doc="MuJoCo timestep, s")
    imprint_model: Literal["twoscale", "pyramid", "elastic"] = param(doc="gel imprint model")
    imprint_scale: float = param(lo=0.05, hi=1.0, doc="imprint resolution relative to the image")
    marker_model: Literal["gaussian", "elastic"] = param(doc="marker displacement model")
    render_backend: Literal["fast", "pyrender"] = param(doc="renderer")
    supersample: int = param(lo=1, hi=4, doc="render at this many times the resolution, then average down")
    macro_cells: int = param(lo=8, hi=1024, doc="two-scale model: cells across the touched region in its "
                                                   "macro (contact-scale) elastic solve")
    macro_cells_per_valley: float = param(0.0, lo=0.0, hi=16.0,
                                          doc="two-scale model: at least this many macro cells across the object's "
                                              "narrowest envelope valley (a corduroy's gap between wales; finer "
                                              "cells than macro_cells gives only there); 0 = off")
    est_ms_per_frame_vga: float = param(50.0, lo=0.0, hi=1e6,
                                        doc="measured end-to-end ms per 640x480 frame on one core (for --dry-run estimates)")
    est_ms_per_frame_960: float = param(100.0, lo=0.0, hi=1e6,
                                        doc="measured end-to-end ms per 960x720 frame on one core (for --dry-run estimates)")
    est_worker_efficiency: float = param(1.0, lo=0.1, hi=1.0,
                                         doc="speed of each of several workers relative to one alone (shared memory "
                                             "bandwidth and caches; for --dry-run estimates)")

    def estimate_seconds(self, frames: int, width_px: int, height_px: int, workers: int = 1) -> float:
        """Estimated wall seconds to generate ``frames`` frames of ``width_px`` x ``height_px`` on ``workers``
        workers: the time per frame is linear in the pixel count through the two measured sizes (the
        costs that do not scale with pixels, physics and per-sequence set-up, are its intercept), and
        several workers each run ``est_worker_efficiency`` times as fast as one alone."""
        px_vga, px_960 = 640 * 480, 960 * 720
        slope = (self.est_ms_per_frame_960 - self.est_ms_per_frame_vga) / (px_960 - px_vga)
        ms = max(0.0, self.est_ms_per_frame_vga + slope * (width_px * height_px - px_vga))
        rate = workers * (self.est_worker_efficiency if workers > 1 else 1.0)
        return frames * ms / 1000.0 / rate


def fidelity_levels() -> dict[str, Fidelity]:
    """All levels in file order, fastest first."""
    data = load_toml(FIDELITY_FILE)
    return {name: build(Fidelity, {"name": name, **table}, where=f"fidelity.{name}")
            for name, table in data.items()}


def get_fidelity(name: str | Fidelity = DEFAULT_LEVEL) -> Fidelity:
    if isinstance(name, Fidelity):
        return name
    levels = fidelity_levels()
    check_choice("fidelity", name, levels)
    return levels[name]
