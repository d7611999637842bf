"""The nuisance stages' parameters and named levels, from ``gelsim/assets/nuisance.toml`` (docs/nuisance.md).

:func:`load_nuisance` builds a :class:`NuisanceModel`: one frozen dataclass per stage (units in the
names; each value's source is in the data file) and the named levels, each a mapping of stage name to
severity (0: off, 1: the file's values, up to :data:`MAX_SEVERITY` for sweeps). Unknown keys, stages or
levels, values out of range and ranges upside down are :class:`~gelsim.errors.GelsimError` naming the
file and key.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

from ..errors import GelsimError
from ..params import ASSETS_DIR, build, load_toml, param

NUISANCE_FILE = ASSETS_DIR / "nuisance.toml"
#: The stages, in the order a frame goes through them: the fibres dent the gel (before shading), the
#: camera's exposure and white balance scale the light (before noise and quantisation).
STAGES = ("fibres", "exposure", "white_balance")
#: Largest severity a level or a sweep may ask for (4 x each stage's nominal effect).
MAX_SEVERITY = 4.0
#: The level that changes nothing (no stage runs, no generator is drawn).
NONE_LEVEL = "none"

Range = tuple[float, float]


def _check_range(where: str, r: Range, lo: float, hi: float) -> None:
    if not (lo <= r[0] <= r[1] <= hi):
        raise GelsimError(f"{where}: [{r[0]}, {r[1]}] must satisfy {lo} <= low <= high <= {hi}; give [low, high]")


@dataclass(frozen=True)
class ExposureParams:
    """The webcam's auto-exposure (libcamera's Raspberry Pi AGC rules). Ratios are exposures relative to the
    settled one (the gelsim frame at gain 1); frames are camera frames."""
    start_ratio: Range = param(doc="frame 0's exposure over the settled one, uniform [low, high]")
    delay_frames: int = param(2, lo=1, hi=8, doc="frames between the frame an exposure is computed from and the first it applies to")
    startup_frames: int = param(10, lo=0, hi=1000, doc="frames in which the controller jumps straight to its target")
    speed: float = param(0.2, lo=0.0, hi=1.0, lo_open=True, doc="fraction of the way to the target per frame after start-up")
    near_band: float = param(0.2, lo=0.0, hi=1.0, doc="within this relative distance of the target the speed is sqrt(speed)")
    stable_region: float = param(0.02, lo=0.0, hi=0.5, doc="within this relative distance nothing changes")

    def validate(self, where: str) -> None:
        _check_range(f"{where}.start_ratio", self.start_ratio, 0.0, 1.0)


@dataclass(frozen=True)
class WhiteBalanceParams:
    """The webcam's auto white balance (libcamera's Raspberry Pi AWB rules): R and B gains against G."""
    start_offset_max: float = param(doc="largest relative error of the R and B gains at frame 0")
    startup_frames: int = param(10, lo=0, hi=1000, doc="frames updated every frame at speed 1")
    period_frames: int = param(10, lo=1, hi=1000, doc="after start-up, one update every this many frames")
    speed: float = param(0.05, lo=0.0, hi=1.0, lo_open=True, doc="fraction of the way per update after start-up")
    delay_frames: int = param(1, lo=1, hi=8, doc="frames before an update's gains apply")

    def validate(self, where: str) -> None:
        if not 0.0 <= self.start_offset_max < 1.0 / MAX_SEVERITY:
            raise GelsimError(f"{where}.start_offset_max: {self.start_offset_max} must be in [0, {1 / MAX_SEVERITY:g}) "
                              f"so that a severity up to {MAX_SEVERITY:g} keeps every gain positive")


@dataclass(frozen=True)
class FibreParams:
    """Loose fibres of hairy fabrics denting the gel before the touch. Lengths mm, moduli GPa."""
    density_per_mm2: float = param(doc="standing fibres per mm2 at catalog hairiness 0.6 and severity 1")
    length_mean_mm: float = param(doc="mean free length (exponential)", lo=0.01, hi=20.0)
    diameter_mm: Range = param(doc="fibre diameter, uniform [low, high]")
    modulus_gpa: Range = param(doc="fibre Young's modulus, uniform [low, high]")
    max_depth_over_diameter: float = param(2.0, lo=0.0, hi=20.0, lo_open=True, doc="deepest dent, fibre diameters")
    tail_radii: float = param(10.0, lo=1.0, hi=100.0, doc="a dent is drawn out to this many fibre radii")

    def validate(self, where: str) -> None:
        if not (math.isfinite(self.density_per_mm2) and 0.0 <= self.density_per_mm2 <= 100.0):
            raise GelsimError(f"{where}.density_per_mm2: {self.density_per_mm2} must be in [0, 100] fibres per mm2")
        _check_range(f"{where}.diameter_mm", self.diameter_mm, 1e-4, 1.0)
        _check_range(f"{where}.modulus_gpa", self.modulus_gpa, 1e-3, 1000.0)


@dataclass(frozen=True)
class StageParams:
    exposure: ExposureParams
    white_balance: WhiteBalanceParams
    fibres: FibreParams


@dataclass(frozen=True)
class NuisanceModel:
    """The stages' parameters and the named levels (level name -> {stage: severity})."""
    stages: StageParams
    levels: Mapping[str, Mapping[str, float]]

    def level(self, name: str, severity: float | None = None) -> dict[str, float]:
        """The stages of level ``name`` with their severities, in :data:`STAGES` order (stages at 0
        dropped). ``severity``: replaces every stage's severity of the level (a sweep's knob)."""
        if name not in self.levels:
            raise GelsimError(f"unknown nuisance level {name!r}; choose one of {', '.join(self.levels)}")
        if severity is not None:
            check_severity(severity, "--nuisance-severity")
        out = {}
        for stage in STAGES:
            if stage in self.levels[name]:
                s = self.levels[name][stage] if severity is None else float(severity)
                if s > 0:
                    out[stage] = s
        return out


def check_severity(value: float, where: str = "severity") -> float:
    """``value`` as a float in [0, MAX_SEVERITY], else a GelsimError naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0.0 <= value <= MAX_SEVERITY:
        raise GelsimError(f"{where} {value!r} must be a number from 0 (off) to {MAX_SEVERITY:g}; 1 is the data file's value")
    return float(value)


def _levels(data: object, where: str) -> Mapping[str, Mapping[str, float]]:
    if not isinstance(data, dict) or not data:
        raise GelsimError(f"{where}: expected tables of named levels, e.g. [levels.camera]")
    out = {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise GelsimError(f"{where}.{name}: expected a table of stage = severity")
        for stage, sev in table.items():
            if stage not in STAGES:
                raise GelsimError(f"{where}.{name}.{stage}: unknown stage; known stages are {', '.join(STAGES)}")
            check_severity(sev, f"{where}.{name}.{stage}:")
        out[name] = MappingProxyType({k: float(v) for k, v in table.items()})
    if NONE_LEVEL not in out or any(v > 0 for v in out[NONE_LEVEL].values()):
        raise GelsimError(f"{where}.{NONE_LEVEL}: must exist and switch every stage off (it is today's output)")
    return MappingProxyType(out)


def load_nuisance(path: str | Path | None = None) -> NuisanceModel:
    """Load :class:`NuisanceModel` from a TOML file (default ``gelsim/assets/nuisance.toml``)."""
    path = Path(path) if path is not None else NUISANCE_FILE
    data = load_toml(path)
    unknown = sorted(set(data) - {"stages", "levels"})
    if unknown:
        raise GelsimError(f"{path.name}: unknown table {unknown[0]!r}; the file has [stages.*] and [levels.*]")
    if "stages" not in data or "levels" not in data:
        raise GelsimError(f"{path.name}: needs [stages.*] and [levels.*] tables")
    stages = build(StageParams, data["stages"], where=f"{path.name}:stages")
    return NuisanceModel(stages=stages, levels=_levels(data["levels"], f"{path.name}:levels"))
