"""Named fidelity levels: one choice that sets every speed/accuracy knob.

Levels live in ``assets/fidelity.toml``; see that file for what each knob does.
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
    est_ms_per_frame_vga: float = param(50.0, lo=0.0, hi=1e6,
                                        doc="measured end-to-end ms per 640x480 frame on one core (for --dry-run estimates)")


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
