"""The nuisance stages' parameters and named levels, from ``gelsim/assets/nuisance.toml`` (docs/nuisance.md).

:func:`load_nuisance` builds a :class:`NuisanceModel`: one frozen dataclass per stage (units in the
names; each value's source is in the data file) and the named levels, each a mapping of stage name to
severity (0: off, 1: the file's values, up to :data:`MAX_SEVERITY` for sweeps). Unknown keys, stages or
levels, values out of range and ranges upside down are :class:`~gelsim.errors.GelsimError` naming the
file and key.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

from ..errors import GelsimError
from ..params import ASSETS_DIR, build, load_toml, param

NUISANCE_FILE = ASSETS_DIR / "nuisance.toml"
#: The stages, in the order a frame goes through them: the fibres dent the gel (before shading), the
#: camera's start-up scales the light (before noise and quantisation).
STAGES = ("fibres", "startup")
#: Largest severity a level or a sweep may ask for (4 x each stage's nominal effect).
MAX_SEVERITY = 4.0
#: The level that changes nothing (no stage runs, no generator is drawn).
NONE_LEVEL = "none"

Range = tuple[float, float]


def _check_range(where: str, r: Range, lo: float, hi: float) -> None:
    if not (lo <= r[0] <= r[1] <= hi):
        raise GelsimError(f"{where}: [{r[0]}, {r[1]}] must satisfy {lo} <= low <= high <= {hi}; give [low, high]")


IntRange = tuple[int, int]


@dataclass(frozen=True)
class StartupParams:
    """The webcam's start-up: auto-exposure and auto white balance settling after its stream starts. Gains
    are relative to the settled frame (gelsim's frame at gain 1); frames are camera frames of the stream."""
    restart_share: float = param(lo=0.0, hi=1.0, doc="share of recordings that catch a fresh stream at severity 1")
    preroll_frames: IntRange = param(doc="frames the stream ran before such a recording's frame 0, uniform [low, high]")
    exposure_start: Range = param(doc="the stream's first frame's exposure over the settled one, uniform [low, high]")
    exposure_delay_frames: int = param(lo=0, hi=8, doc="frames kept at the start exposure")
    exposure_settle_frames: IntRange = param(doc="stream frame by which the exposure is within stable_region")
    white_balance_start_max: float = param(doc="largest relative error of the R and B gains at the stream's start")
    white_balance_delay_frames: int = param(lo=0, hi=8, doc="frames kept at the start balance")
    white_balance_settle_frames: IntRange = param(doc="stream frame by which the balance is within stable_region")
    stable_region: float = param(0.02, lo=0.0, hi=0.5, lo_open=True, doc="a controller this close to its target stops")

    def validate(self, where: str) -> None:
        _check_range(f"{where}.exposure_start", self.exposure_start, 1e-3, 1.0)
        _check_range(f"{where}.preroll_frames", self.preroll_frames, 0, 10_000)
        if not 0.0 <= self.white_balance_start_max < 1.0:
            raise GelsimError(f"{where}.white_balance_start_max: {self.white_balance_start_max} must be in [0, 1) "
                              "so that every gain stays positive")
        for name, delay in (("exposure", self.exposure_delay_frames), ("white_balance", self.white_balance_delay_frames)):
            r = getattr(self, f"{name}_settle_frames")
            _check_range(f"{where}.{name}_settle_frames", r, delay + 1, 10_000)


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
    startup: StartupParams
    fibres: FibreParams


@dataclass(frozen=True)
class NuisanceModel:
    """The stages' parameters and the named levels (level name -> {stage: severity})."""
    stages: StageParams
    levels: Mapping[str, Mapping[str, float]]
    overrides: Mapping[str, Mapping[str, Mapping[str, object]]] = dataclasses.field(default_factory=dict)

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

    def stages_for(self, name: str) -> StageParams:
        """The stages' parameters as level ``name`` runs them: the file's, with the level's own
        ``[levels.NAME.params.STAGE]`` values in place."""
        if name not in self.levels:
            raise GelsimError(f"unknown nuisance level {name!r}; choose one of {', '.join(self.levels)}")
        stages = self.stages
        for stage, values in self.overrides.get(name, {}).items():
            stages = dataclasses.replace(stages, **{stage: dataclasses.replace(getattr(stages, stage), **values)})
        return stages


def check_severity(value: float, where: str = "severity") -> float:
    """``value`` as a float in [0, MAX_SEVERITY], else a GelsimError naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0.0 <= value <= MAX_SEVERITY:
        raise GelsimError(f"{where} {value!r} must be a number from 0 (off) to {MAX_SEVERITY:g}; 1 is the data file's value")
    return float(value)


def _levels(data: object, where: str, stages: StageParams):
    """The levels (name -> {stage: severity}) and their parameter overrides (name -> {stage: {key: value}}),
    each override checked by building the stage's parameters with it."""
    if not isinstance(data, dict) or not data:
        raise GelsimError(f"{where}: expected tables of named levels, e.g. [levels.camera]")
    out, overrides = {}, {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise GelsimError(f"{where}.{name}: expected a table of stage = severity")
        table = dict(table)
        params = table.pop("params", {})
        if not isinstance(params, dict) or any(not isinstance(v, dict) for v in params.values()):
            raise GelsimError(f"{where}.{name}.params: expected tables [levels.{name}.params.STAGE] of parameter = value")
        for stage, values in params.items():
            if stage not in STAGES:
                raise GelsimError(f"{where}.{name}.params.{stage}: unknown stage; known stages are {', '.join(STAGES)}")
            base = {f.name: getattr(getattr(stages, stage), f.name)
                    for f in dataclasses.fields(getattr(stages, stage))}
            unknown = sorted(set(values) - set(base))
            if unknown:
                raise GelsimError(f"{where}.{name}.params.{stage}.{unknown[0]}: unknown parameter; "
                                  f"known: {', '.join(base)}")
            built = build(type(getattr(stages, stage)), {**base, **values}, where=f"{where}.{name}.params.{stage}")
            overrides.setdefault(name, {})[stage] = MappingProxyType(
                {k: getattr(built, k) for k in values})
        for stage, sev in table.items():
            if stage not in STAGES:
                raise GelsimError(f"{where}.{name}.{stage}: unknown stage; known stages are {', '.join(STAGES)}")
            check_severity(sev, f"{where}.{name}.{stage}:")
        out[name] = MappingProxyType({k: float(v) for k, v in table.items()})
    if NONE_LEVEL not in out or any(v > 0 for v in out[NONE_LEVEL].values()):
        raise GelsimError(f"{where}.{NONE_LEVEL}: must exist and switch every stage off (it is today's output)")
    return MappingProxyType(out), MappingProxyType({k: MappingProxyType(v) for k, v in overrides.items()})


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
    levels, overrides = _levels(data["levels"], f"{path.name}:levels", stages)
    return NuisanceModel(stages=stages, levels=levels, overrides=overrides)
