"""The dataset: plan, generate (parallel, resumable, deterministic), manifest and verify.

The format itself (layout, manifest fields, label keys, version) is :mod:`gelsim.schema`'s. Besides it
this module writes ``DIR/previews/*.png`` (a frame strip per action and a contact sheet of all fabrics)
and ``DIR/previews/dataset_stats.*`` (statistics per action from the labels, gelsim.stats, and
dataset_actions.png: press/slip/twist frames across families).

Every sequence has its own seed derived from (dataset seed, fabric id, sequence index),
so the output is identical whatever the number of workers and however often the run is
interrupted and resumed. A sequence counts as finished only once its record exists, and
the record is written only after its video and labels were renamed into place.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from . import __version__
from . import schema
from .atomic import atomic_write_json, atomic_write_npz
from .errors import GelsimError
from .provenance import source_digest
from .schema import ACTIONS, SPLITS, load_manifest, sha256_of  # noqa: F401 (load_manifest: for callers)

SPLIT_WEIGHTS = (7.0, 2.0, 1.0)  # the paper's 7:2:1 split, by sequence (the default of --split)
# Bytes per pixel per frame of each format at 960x720, measured on generated sequences
# (benchmarks/bench_generate.py); used only for the disk check and --dry-run.
BYTES_PER_PIXEL = {"h264": 0.02, "ffv1": 0.9, "png": 1.6}
LABELS_BYTES_PER_FRAME = 2_000


@dataclass(frozen=True)
class GenerateConfig:
    """Everything that determines a dataset's content (workers do not)."""
    fabrics: int = 100
    sequences_per_fabric: int = 50
    actions: tuple[float, float, float] = (7.0, 1.0, 2.0)
    frames: tuple[int, int] = (25, 36)
    precontact: tuple[int, int] | None = None   # None: the default range of gelsim/assets/motions.toml
    profile: str = "vitac"
    resolution: tuple[int, int] | None = None   # (width, height); None: the profile's own
    fidelity: str = "balanced"
    seed: int = 0
    format: str = "h264"
    units: int = 0          # sensor units drawn from the profile's [unit_variation]; 0 = the profile itself
    split: tuple[float, float, float] = SPLIT_WEIGHTS   # train:val:test weights, apportioned per fabric
    backend: str | None = None   # render backend (gelsim.optics.BACKENDS); None = the fidelity level's
    nuisance: str = "none"       # a level of gelsim/assets/nuisance.toml (docs/nuisance.md); "none": no stage runs
    nuisance_severity: float | None = None   # every stage of the level at this severity (0-4); None: the file's
    # What runs on the torch backend's device: "optics" (the imprint, markers and labels from the numpy path,
    # byte for byte) or "all" (the whole frame on the torch engine: labels within its stated tolerance). What, not
    # how: a dataset's labels differ between the two, so it is one of options().
    stages: str = "optics"
    # Where and how many frames at a time the torch backend renders: how, not what (the same bytes for
    # any batch, the same dataset within the backend's tolerance on any device), so not in options().
    device: str | None = None    # None = the CPU
    batch: int | None = None     # None = gelsim.optics.torch_backend.DEFAULT_BATCH

    def options(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        for k in PLACEMENT:
            del d[k]
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    def render_backend(self, fidelity) -> str:
        """The backend that renders this dataset: ``backend``, or the fidelity level's."""
        return self.backend or fidelity.render_backend


#: GenerateConfig fields that say where the frames are rendered, not what they hold.
PLACEMENT = ("device", "batch")
#: ``--stages``: what the torch backend runs on its device (GenerateConfig.stages).
DEVICE_STAGES = ("optics", "all")
#: With ``--stages all``, sequences run in step on the device (frame t of each in one batch): a fabric's sequences
#: (of one sensor unit), in groups of at most this many, as even as can be. A frame's device imprint depends on its
#: batch's other frames by float rounding (docs/device.md), so the groups are fixed by the plan alone, never by
#: ``--batch`` or ``--workers``: the same bytes however the dataset is run. 16 bounds a worker's memory at 960x720
#: (16 patches, envelopes and imprint batches: a few GB on the CPU) while filling a GPU with a worker per core.
MAX_LANES = 16


@dataclass(frozen=True)
class Route:
    """How a dataset's frames are made, decided once from its options and fidelity level (:meth:`of`, which
    refuses what cannot run, before anything is written): the render ``backend`` (gelsim.optics.BACKENDS), and
    where the frame pipeline (:func:`gelsim.stream.make_frames`) runs. ``engine`` ``"numpy"``: each sequence on
    the numpy engine in a worker (the bit-exact reference), its frames rendered by the backend's
    :class:`gelsim.optics.Renderer`, or with the torch backend by a :class:`gelsim.sinks.DeviceFrames` sink on
    ``device``, ``batch`` frames at a time (``--stages optics``); ``"torch"``: the whole frame on the torch engine
    on ``device``, a group of a fabric's sequences in step (``--stages all``; :func:`device_groups`), its
    optics ``batch`` frames per call."""
    backend: str
    engine: str
    device: str | None = None
    batch: int = 0

    @classmethod
    def of(cls, config: "GenerateConfig", fidelity) -> "Route":
        """``config``'s route: one line for a backend that does not exist, a device this machine does not have, a
        device, batch or stages without the torch backend, or the whole frame on the device at a fidelity whose
        imprint model it does not run."""
        from .errors import check_choice
        from .optics import BACKENDS

        backend = config.render_backend(fidelity)
        check_choice("--backend", backend, BACKENDS)
        check_choice("--stages", config.stages, DEVICE_STAGES)
        if backend != "torch":
            if config.device is not None or config.batch is not None or config.stages != "optics":
                raise GelsimError(f"--device, --batch and --stages are for --backend torch, not {backend}; add "
                                  "--backend torch or drop them")
            return cls(backend, "numpy")
        if config.stages == "all" and fidelity.imprint_model != "twoscale":
            raise GelsimError(f"--stages all runs the twoscale imprint on the device (fidelity fast or balanced), not "
                              f"{fidelity.name}'s {fidelity.imprint_model!r}; choose --fidelity fast or balanced, or "
                              "--stages optics")
        if config.batch is not None and (isinstance(config.batch, bool) or not isinstance(config.batch, int)
                                         or config.batch < 1):
            raise GelsimError(f"--batch {config.batch!r} is invalid; give a whole number of frames >= 1")
        from .optics.torch_backend import DEFAULT_BATCH, resolve_device

        resolve_device(config.device)
        return cls(backend, "torch" if config.stages == "all" else "numpy", config.device,
                   config.batch or DEFAULT_BATCH)

    @property
    def stages(self) -> str:
        """What runs on the torch backend's device, as the manifest records it: ``optics``, ``all`` or ``none``."""
        return "none" if self.backend != "torch" else ("all" if self.engine == "torch" else "optics")

    @property
    def in_step(self) -> bool:
        """A worker's job is a group of sequences in step (the torch engine), not one sequence."""
        return self.engine == "torch"

    @property
    def labels_origin(self) -> str:
        """Where the labels come from, as the manifest records it."""
        return ("device: the torch engine, within gelsim.gel.twoscale_torch.TOLERANCE of the numpy path"
                if self.engine == "torch" else "numpy: the bit-exact reference")

    def renderer(self, profile, fidelity, seed: int):
        """The renderer of ``profile``'s frames: a :class:`gelsim.optics.Renderer` of the backend, or for the torch
        backend a :class:`gelsim.optics.torch_backend.BatchRenderer` over one on ``device``."""
        from .optics import Renderer

        r = Renderer(profile, self.backend, supersample=fidelity.supersample, seed=seed,
                     device=self.device if self.backend == "torch" else None)
        if self.backend != "torch":
            return r
        from .optics.torch_backend import BatchRenderer

        return BatchRenderer(r)


# Sensor units a dataset may draw: each needs its own renderer in every worker (0.2-0.3 s and ~60 MB
# at 960x720), so a few dozen is plenty for variety and a thousand the most that makes sense.
MAX_UNITS = 1000

PRESETS: dict[str, dict[str, Any]] = {
    # A first look, and a first trained and evaluated model (`stam train --config quick`): 10 fabrics x 4
    # sequences at 320x240, split 2:1:1 per fabric (20 training, 10 validation, 10 test sequences; the
    # paper's 7:2:1 of 3 left no test sequence). Times: docs/quickstart.md.
    "quick": dict(fabrics=10, sequences_per_fabric=4, resolution=(320, 240), fidelity="fast", split=(2.0, 1.0, 1.0)),
    # What `stam experiment --preset cpu` is sized for: all fabrics at 320x240 with the full-resolution
    # imprint (balanced): at 160x120 (0.12 mm/px) the finer weaves fall below two pixels per yarn and
    # STAM learns nothing.
    # Test sequences: 11 per fabric (1,100 in all), so that a paired difference between two models
    # of a few points is resolved (a 100-sequence test split spreads by about 5 points); training
    # and validation keep the 7 and 2 per fabric of a 7:2:1 split of 10.
    "cpu": dict(fabrics=100, sequences_per_fabric=20, resolution=(320, 240), fidelity="balanced",
                split=(7.0, 2.0, 11.0)),
}


@dataclass(frozen=True)
class SequenceSpec:
    id: str
    fabric_id: int
    index: int
    action: str
    seed: int
    num_frames: int
    precontact_frames: int | None
    split: str
    unit: int = -1          # the sensor unit (``GenerateConfig.units``), -1 = the profile itself

    def video_stem(self) -> str:
        return schema.video_stem(self.fabric_id, self.id)

    def labels_rel(self) -> str:
        return schema.labels_path(self.fabric_id, self.id)

    def nuisance_rel(self) -> str:
        return schema.nuisance_path(self.fabric_id, self.id)


# ---------------------------------------------------------------- planning

def parse_ratio(text: str, option: str = "--actions", names: str = "press:slip:twist",
                example: str = "7:1:2") -> tuple[float, float, float]:
    """``"7:1:2"`` -> (7.0, 1.0, 2.0): three non-negative weights (press:slip:twist, or train:val:test)."""
    parts = text.split(":")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != 3 or any(not math.isfinite(v) or v < 0 for v in vals) or sum(vals) <= 0:
        raise GelsimError(f"{option} {text!r} is malformed; give three non-negative {names} weights, e.g. {example}")
    return vals  # type: ignore[return-value]


def parse_range(text: str, option: str, lo: int = 0) -> tuple[int, int]:
    """``"25-36"`` -> (25, 36); a single number N means N-N."""
    parts = text.split("-")
    try:
        vals = [int(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2:
        raise GelsimError(f"{option} {text!r} is malformed; give MIN-MAX, e.g. 25-36")
    a, b = vals
    if a > b:
        raise GelsimError(f"{option} {text!r} is inverted; give MIN-MAX with MIN <= MAX")
    if a < lo:
        raise GelsimError(f"{option} {text!r} is out of range; values must be >= {lo}")
    return a, b


def parse_resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise GelsimError(f"--resolution {text!r} is malformed; give WIDTHxHEIGHT, e.g. 320x240") from None
    if w < 1 or h < 1:
        raise GelsimError(f"--resolution {text!r} is malformed; give WIDTHxHEIGHT in whole pixels, e.g. 320x240")
    return w, h   # the sensor's own range is checked with its profile (SensorProfile.with_resolution)


def apportion(total: int, weights: Iterable[float]) -> list[int]:
    """Split ``total`` into integer parts proportional to ``weights`` (largest remainder)."""
    w = np.asarray(list(weights), dtype=np.float64)
    exact = total * w / w.sum()
    counts = np.floor(exact).astype(int)
    order = np.argsort(-(exact - counts), kind="stable")
    for k in order[: total - counts.sum()]:
        counts[k] += 1
    return counts.tolist()


def interleave(total: int, weights: Iterable[float]) -> list[int]:
    """``total`` choices among ``len(weights)`` options, every prefix as close to the weights as
    possible (smooth weighted round-robin). With weights 7:1:2 each block of 10 holds exactly 7, 1
    and 2, so a fabric with 10 or 50 sequences gets the exact ratio, and a small dataset spread over
    many fabrics still contains every action."""
    w = np.asarray(list(weights), dtype=np.float64)
    current = np.zeros_like(w)
    out = []
    for _ in range(total):
        current += w
        k = int(np.argmax(current))
        current[k] -= w.sum()
        out.append(k)
    return out


def sequence_seed(seed: int, fabric_id: int, index: int) -> int:
    return int(np.random.SeedSequence([seed, fabric_id, index]).generate_state(1)[0])


def plan(config: GenerateConfig, catalog_size: int) -> list[SequenceSpec]:
    """Every sequence of the dataset, with its action, frame count, seed and split."""
    if not 1 <= config.fabrics <= catalog_size:
        raise GelsimError(f"--fabrics {config.fabrics} is out of range; the catalog has fabrics 1-{catalog_size}")
    if config.sequences_per_fabric < 1:
        raise GelsimError("--sequences-per-fabric must be at least 1")
    check_frames(config)
    specs = []
    n = config.sequences_per_fabric
    schedule = interleave(config.fabrics * n, config.actions)
    for fid in range(1, config.fabrics + 1):
        # sorted, then shuffled by the fabric's own permutation below: the plan depends only on
        # how many of each action a fabric gets (datasets made before interleaving keep their plan)
        actions = [ACTIONS[k] for k in sorted(schedule[(fid - 1) * n: fid * n])]
        # Interleave actions deterministically so that any prefix of a fabric's sequences
        # (and so any split) mixes them.
        order_rng = np.random.default_rng([config.seed, fid, 1])
        actions = [actions[k] for k in order_rng.permutation(n)]
        split_of = np.empty(n, dtype=object)
        split_counts = apportion(n, config.split)
        perm = np.random.default_rng([config.seed, fid, 2]).permutation(n)
        start = 0
        for name, c in zip(SPLITS, split_counts):
            split_of[perm[start:start + c]] = name
            start += c
        for i in range(n):
            s = sequence_seed(config.seed, fid, i)
            rng = np.random.default_rng(s)
            frames = int(rng.integers(config.frames[0], config.frames[1] + 1))
            pre = None
            if config.precontact is not None:
                pre = int(rng.integers(config.precontact[0], config.precontact[1] + 1))
            unit = len(specs) % config.units if config.units else -1  # units in turn over the whole plan
            specs.append(SequenceSpec(id=schema.sequence_id(fid, i), fabric_id=fid, index=i, action=actions[i],
                                      seed=s, num_frames=frames, precontact_frames=pre, split=str(split_of[i]),
                                      unit=unit))
    return specs


def device_groups(specs: list[SequenceSpec]) -> list[list[SequenceSpec]]:
    """The groups of sequences that ``--stages all`` runs in step, in plan order: each fabric's sequences of one
    sensor unit, split into ceil(n / :data:`MAX_LANES`) groups as even as can be. A function of the plan only."""
    by: dict[tuple[int, int], list[SequenceSpec]] = {}
    for s in specs:
        by.setdefault((s.fabric_id, s.unit), []).append(s)
    groups = []
    for members in by.values():
        start = 0
        for size in apportion(len(members), [1.0] * math.ceil(len(members) / MAX_LANES)):
            groups.append(members[start:start + size])
            start += size
    return groups


def check_frames(config: GenerateConfig) -> None:
    """One line, before anything is written, when a sequence of ``config.frames`` could keep fewer than
    MIN_CONTACT_FRAMES in contact after its pre-contact frames (``config.precontact``, or the default
    mixture of gelsim/assets/motions.toml: its early range, and its late starts when their fraction is above 0)."""
    from .motion import MIN_CONTACT_FRAMES, load_motion_ranges

    lo, hi = config.frames
    if config.precontact is not None:
        most = config.precontact[1]
        what = f"--precontact {config.precontact[0]}-{most}"
        fix = f"keep --precontact's maximum at most {lo - MIN_CONTACT_FRAMES}"
    else:
        t = load_motion_ranges().timing
        # late starts are drawn only when their fraction is above 0
        most = max(t.precontact_frames[1], t.late_start_frames[1] if t.late_start_fraction > 0 else 0)
        what = f"the default pre-contact frames (up to {most}, gelsim/assets/motions.toml)"
        fix = "give --precontact (e.g. 0-1)"
    if lo - most < MIN_CONTACT_FRAMES:
        raise GelsimError(f"--frames {lo}-{hi} with {what} can leave fewer than {MIN_CONTACT_FRAMES} frames in contact; "
                          f"raise the frame minimum to {most + MIN_CONTACT_FRAMES} or {fix}")


def unit_seed(seed: int, unit: int) -> int:
    """The draw seed of sensor unit ``unit`` of the dataset seeded ``seed`` (its own stream)."""
    return int(np.random.SeedSequence([seed, unit, 0x0D17]).generate_state(1)[0])


def dataset_flat_frame(manifest: dict, sequence: dict | None = None):
    """The flat gel of a dataset's sensor as its frames show it (:func:`gelsim.annotate.flat_frame`): uint8 RGB
    (H, W, 3) at the dataset's resolution, rendered from the manifest's options for ``sequence``'s sensor unit
    (its manifest entry; None or no ``unit``: the profile itself)."""
    from .annotate import flat_frame

    known = {f.name for f in dataclasses.fields(GenerateConfig)}
    opts = {k: tuple(v) if isinstance(v, list) else v for k, v in manifest.get("options", {}).items() if k in known}
    config = GenerateConfig(**opts)
    profile = resolve_profile(config)
    unit = int((sequence or {}).get("unit", -1))
    if unit >= 0:
        profile = unit_profiles(config, profile)[unit]
    return flat_frame(profile, config.fidelity, config.seed)


def unit_profiles(config: GenerateConfig, profile) -> list:
    """The ``config.units`` sensor units drawn from ``profile`` (empty for units = 0)."""
    from .units import draw_unit

    if config.units and profile.unit_variation is None:
        raise GelsimError(f"--units {config.units}: profile {profile.name!r} has no [unit_variation] section; add one "
                          "(see assets/sensors/vitac.toml) or drop --units")
    return [draw_unit(profile, unit_seed(config.seed, k)) for k in range(config.units)]


# ---------------------------------------------------------------- files

class StaleOutput(GelsimError):
    """``--out`` holds a gelsim dataset that this code cannot resume: made with other options, library
    versions or gelsim code, so the same seed would give other sequences. :func:`set_aside_stale` moves
    such a dataset out of the way."""


def check_out_dir(root: str | Path, options: dict) -> dict | None:
    """What ``root`` holds, read only: its manifest if it is the dataset ``options`` describe (to resume,
    or complete), None if it is new or empty. Raises :class:`StaleOutput` for a gelsim dataset made
    otherwise, and GelsimError for a file or for files that are not a dataset."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise GelsimError(f"--out {root} is a file; give a directory")
    if not (root.exists() and any(root.iterdir())):
        return None
    if not (root / schema.MANIFEST).exists():
        raise GelsimError(f"--out {root} holds files that are not a gelsim dataset; give an empty or new directory")
    m = load_manifest(root)
    # An option added after the dataset was made takes its default there.
    made = {**GenerateConfig().options(), **m.get("options", {})}
    if made != options:
        diff = [k for k in options if made.get(k) != options[k]]
        raise StaleOutput(f"--out {root} holds a dataset made with other options ({', '.join(diff)}); "
                          "rerun with the same options to resume, choose another --out, or add --replace-stale to set it "
                          "aside and start anew")
    what, diff = _made_otherwise(m)
    if what == "libraries":
        raise StaleOutput(f"--out {root} was made with other library versions ({diff}), which give other bytes "
                          "from the same seed; resume it where those are installed, choose another --out, or add "
                          "--replace-stale to set it aside and start anew")
    if what == "source":
        fix = "" if m.get("complete") else "finish it with the code that began it, "
        raise StaleOutput(f"--out {root} was made by other gelsim code or assets (its manifest's source digest "
                          f"differs), which give other sequences from the same seed; {fix}choose another --out, or "
                          "add --replace-stale to set it aside and make it anew with this code")
    return m


def stale_place(root: str | Path) -> Path:
    """Where :func:`set_aside_stale` would move ``root``: ``ROOT.stale-N`` beside it, the first N free."""
    root = Path(root)
    n = 1
    while root.with_name(f"{root.name}.stale-{n}").exists():
        n += 1
    return root.with_name(f"{root.name}.stale-{n}")


def set_aside_stale(root: str | Path, config: GenerateConfig) -> Path | None:
    """If ``root`` holds a gelsim dataset that ``config`` cannot resume (:class:`StaleOutput`), rename it
    to :func:`stale_place` (one rename in the same directory: nothing is copied or deleted) and return
    the new path; None if ``root`` is new, empty or resumable. Anything that is not a gelsim dataset is
    left where it is (GelsimError)."""
    root = Path(root)
    try:
        check_out_dir(root, config.options())
        return None
    except StaleOutput:
        dest = stale_place(root)
        try:
            os.rename(root, dest)
        except OSError as e:
            raise GelsimError(f"could not move the stale dataset {root} to {dest} ({e.strerror}); "
                              "move or delete it yourself, or choose another --out") from None
        return dest


def _prepare_out_dir(root: Path, options: dict) -> dict | None:
    """:func:`check_out_dir`, then, for a new dataset, create ``root`` and check it is writable."""
    m = check_out_dir(root, options)
    if m is not None:
        return m
    # Writability is checked by creating the directory (nothing else is touched).
    try:
        root.mkdir(parents=True, exist_ok=True)
        probe = root / f".write-probe-{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as e:
        raise GelsimError(f"--out {root} is not writable ({e.strerror}); choose a writable directory") from None
    return None


def resume_state(root: str | Path, config: GenerateConfig, specs: list[SequenceSpec] | None = None) -> dict:
    """What :func:`generate` would do with ``root``, read only: ``{"state": "new" | "resume" | "complete",
    "done": finished sequences, "total": planned, "frames_to_go": frames of the unfinished ones}``.
    Raises as :func:`check_out_dir` does."""
    from .fabrics import load_catalog

    specs = specs if specs is not None else plan(config, len(load_catalog()))
    m = check_out_dir(root, config.options())
    done = {} if m is None else _load_records(Path(root), specs)
    state = "new" if m is None else ("complete" if len(done) == len(specs) else "resume")
    return {"state": state, "done": len(done), "total": len(specs),
            "frames_to_go": sum(s.num_frames for s in specs if s.id not in done)}


def estimate_bytes(specs: list[SequenceSpec], fmt: str, width: int, height: int) -> int:
    frames = sum(s.num_frames for s in specs)
    return int(frames * (BYTES_PER_PIXEL[fmt] * width * height + LABELS_BYTES_PER_FRAME))


# ---------------------------------------------------------------- workers

_WORKER: dict[str, Any] = {}


def _worker_init(config: GenerateConfig, root: str) -> None:
    from .runtime import configure_worker

    # One process per core (OpenCV on one thread; frame arrays reused from the heap).
    configure_worker()
    from .fabrics import load_catalog
    from .fidelity import get_fidelity
    from .motion import load_motion_ranges
    from .sensor import load_profile

    profile = load_profile(config.profile)
    if config.resolution is not None:
        profile = profile.with_resolution(*config.resolution)
    fidelity = get_fidelity(config.fidelity)
    route = Route.of(config, fidelity)
    _WORKER.update(config=config, root=Path(root), catalog=load_catalog(), profile=profile, fidelity=fidelity,
                   ranges=load_motion_ranges(), units=unit_profiles(config, profile), unit_renderers={},
                   route=route, **nuisance_level(config))
    if route.backend == "torch":
        import torch

        torch.set_num_threads(1)  # one process per core, as for OpenCV (a GPU does the heavy work)
    _WORKER["renderer"] = _renderer(profile)


def nuisance_level(config: GenerateConfig) -> dict:
    """``config.nuisance``'s stages at ``config.nuisance_severity``: ``nuisance`` (stage -> severity; empty for
    ``none``, which loads nothing)
    and ``nuisance_stages`` (their parameters, or None). An unknown level is a one-line GelsimError."""
    if config.nuisance == "none":
        if config.nuisance_severity is not None:   # it would change nothing, yet be recorded
            raise GelsimError("--nuisance-severity scales the stages of a --nuisance level, and none is set; add "
                              "--nuisance camera or handheld, or drop --nuisance-severity")
        return dict(nuisance={}, nuisance_stages=None)
    from .nuisance import load_nuisance

    model = load_nuisance()
    return dict(nuisance=model.level(config.nuisance, config.nuisance_severity),
                nuisance_stages=model.stages_for(config.nuisance))


def _renderer(profile):
    """This worker's renderer for ``profile`` (:meth:`Route.renderer`; built once per worker and sensor unit)."""
    w = _WORKER
    return w["route"].renderer(profile, w["fidelity"], w["config"].seed)


def _device_name(renderer) -> str:
    """Where this worker's frames are made, as a dataset records it: ``cpu`` for the numpy backends (``opengl``
    for pyrender), the torch device for the torch backend (``cuda:0 (NVIDIA H200)``: its model named, as
    ``--stages all``'s labels are the same bytes only on the same kind of device)."""
    dev = getattr(renderer, "device", None)
    if dev is None:
        return "opengl" if getattr(renderer, "backend", None) == "pyrender" else "cpu"
    if dev.type != "cuda":
        return dev.type
    import torch

    index = dev.index if dev.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"


def _unit(k: int):
    """(profile, renderer) of sensor unit ``k`` in this worker (-1: the profile itself); a unit's renderer
    is built once per worker (0.2-0.3 s at 960x720)."""
    w = _WORKER
    if k < 0:
        return w["profile"], w["renderer"]
    if k not in w["unit_renderers"]:
        w["unit_renderers"][k] = _renderer(w["units"][k])
    return w["units"][k], w["unit_renderers"][k]


def _options(**kw):
    """A sequence's options in this worker: the dataset's sensor seed and nuisance level, and ``kw``."""
    from .sequence import SequenceOptions

    return SequenceOptions(sensor_seed=_WORKER["config"].seed, nuisance=_WORKER["nuisance"],
                           nuisance_stages=_WORKER["nuisance_stages"], **kw)


@contextlib.contextmanager
def _frame_sinks(renderer, video: Path, fps: float):
    """(sequence options, sinks) that write one sequence's frames to ``video``: rendered by the sequence with
    ``renderer`` (a :class:`gelsim.optics.Renderer`), or with the torch backend's optics (a
    :class:`gelsim.optics.torch_backend.BatchRenderer`) by a :class:`gelsim.sinks.DeviceFrames` sink,
    :attr:`Route.batch` frames at a time from the records' optics inputs, while a writer thread encodes the
    previous batch. Leaving the block by an error discards the video."""
    from .sinks import DeviceFrames, VideoSink

    config: GenerateConfig = _WORKER["config"]
    route: Route = _WORKER["route"]
    with contextlib.ExitStack() as stack:
        writer = stack.enter_context(VideoSink(video, fmt=config.format, fps=fps))
        if route.backend != "torch":
            yield _options(renderer=renderer), [writer]
            return
        device = stack.enter_context(DeviceFrames(renderer, route.batch, [writer]))
        yield _options(outputs={"imprint", "markers"}), [device]


def _motion(spec: SequenceSpec):
    """The hand's motion of ``spec`` (its frame and pre-contact counts as planned)."""
    from .motion import sample_motion

    return sample_motion(spec.action, spec.seed, frames=(spec.num_frames, spec.num_frames),
                         precontact=None if spec.precontact_frames is None
                         else (spec.precontact_frames, spec.precontact_frames),
                         ranges=_WORKER["ranges"])


def generate_sequence(spec: SequenceSpec) -> dict:
    """Simulate, render, encode and record one sequence (in a worker). Returns its record."""
    from .nuisance.record import NuisanceLog
    from .sequence import render_sequence
    from .sinks import drain
    from .stream import stage_clock
    from .video import video_path

    w = _WORKER
    config: GenerateConfig = w["config"]
    root: Path = w["root"]
    (profile, renderer), fidelity = _unit(spec.unit), w["fidelity"]
    fabric = w["catalog"][spec.fabric_id]
    t0 = time.perf_counter()
    motion = _motion(spec)
    vpath = root / video_path(spec.video_stem(), config.format)
    npath = root / spec.nuisance_rel()
    with _frame_sinks(renderer, vpath, profile.image.fps_hz) as (options, sinks):
        labels, timings = drain(render_sequence(fabric, motion, profile, fidelity, seed=spec.seed, options=options),
                                [*sinks, NuisanceLog(npath)])
    te = stage_clock()
    lpath = root / spec.labels_rel()
    atomic_write_npz(lpath, **labels)
    timings["encode"] = timings.get("encode", 0.0) + stage_clock() - te
    return _record(spec, motion, root, vpath, lpath, labels, timings, time.perf_counter() - t0,
                   _device_name(renderer), npath)


def generate_group(specs: list[SequenceSpec], write: Iterable[str] | None = None) -> list[dict]:
    """``--stages all``: the sequences of one :func:`device_groups` group in step on the torch engine
    (:func:`gelsim.sequence.render_sequences`: the contact simulation and the fabric's patch of each on the CPU,
    then frame t of each in one batch of the pipeline: imprint, nuisance, markers, labels, frames), each
    sequence's records into its own video (:func:`gelsim.sinks.drain_each`), its labels and record written (in a
    worker). ``write``: the ids to write (default: all; a resumed run recomputes a group whose other members are
    written already, so that each sequence is made in its own group). Returns their records, whose stage times
    are their shares of the group's (the CPU part, ``fabric`` and ``physics``, their own)."""
    from .engines import TorchEngine
    from .nuisance.record import NuisanceLog
    from .sequence import render_sequences
    from .sinks import VideoSink, drain_each
    from .stream import stage_clock
    from .video import video_path

    w = _WORKER
    config: GenerateConfig = w["config"]
    root: Path = w["root"]
    (profile, renderer), fidelity = _unit(specs[0].unit), w["fidelity"]
    fabric = w["catalog"][specs[0].fabric_id]
    write = {s.id for s in specs} if write is None else set(write)
    t0 = time.perf_counter()
    motions = [_motion(spec) for spec in specs]
    paths = {s.id: root / video_path(s.video_stem(), config.format) for s in specs if s.id in write}
    npaths = {s.id: root / s.nuisance_rel() for s in specs if s.id in write}
    h, wd = profile.shape
    # H.264 at an even size encodes 4:2:0: the frames converted on the device come back as I420 (half the bytes,
    # the same planes as the host's conversion: gelsim.video_torch)
    engine = TorchEngine(renderer.device, optics_batch=w["route"].batch,
                         i420=config.format == "h264" and h % 2 == 0 and wd % 2 == 0)
    with contextlib.ExitStack() as stack:
        sinks = [[stack.enter_context(VideoSink(paths[s.id], fmt=config.format, fps=profile.image.fps_hz)),
                  NuisanceLog(npaths[s.id])] if s.id in write else [] for s in specs]
        results = drain_each(render_sequences([(fabric, m, s.seed) for s, m in zip(specs, motions)], profile, fidelity,
                                              options=_options(renderer=renderer), engine=engine), sinks)
    wall = time.perf_counter() - t0
    frames = sum(m.num_frames for m in motions)
    device = _device_name(renderer)
    records = []
    for spec, motion, (labels, timings) in zip(specs, motions, results):
        if spec.id not in write:
            continue
        te = stage_clock()
        lpath = root / spec.labels_rel()
        atomic_write_npz(lpath, **labels)
        timings["encode"] = timings.get("encode", 0.0) + stage_clock() - te
        records.append(_record(spec, motion, root, paths[spec.id], lpath, labels, timings,
                               wall * motion.num_frames / frames, device, npaths[spec.id]))
    return records


def _record(spec: SequenceSpec, motion, root: Path, vpath: Path, lpath: Path, labels: dict, timings: dict,
            seconds: float, device: str, npath: Path | None = None) -> dict:
    """Write and return the record of ``spec`` (its ``motion``), whose video, labels and nuisance record (at
    ``npath``; None: not written) are in place: written last, it marks the sequence finished."""
    in_contact = np.asarray(labels["in_contact"], bool)
    onset = int(np.argmax(in_contact)) if in_contact.any() else -1
    record = dict(id=spec.id, fabric_id=spec.fabric_id, action=spec.action, num_frames=motion.num_frames,
                  contact_onset=onset, precontact_frames=motion.precontact_frames, split=spec.split,
                  video=str(vpath.relative_to(root)), labels=spec.labels_rel(), seed=spec.seed,
                  sha256={"video": sha256_of(vpath), "labels": sha256_of(lpath)},
                  peak_force_n=float(np.max(labels["normal_force_n"])),
                  timings_s={k: round(v, 4) for k, v in timings.items()},
                  seconds=round(seconds, 3), device=device)
    if npath is not None:
        record["nuisance"] = str(npath.relative_to(root))
        record["sha256"]["nuisance"] = sha256_of(npath)
    if spec.unit >= 0:
        record["unit"] = spec.unit
    atomic_write_json(root / schema.record_path(spec.id), record)
    return record


# ---------------------------------------------------------------- generate

def _manifest(config: GenerateConfig, profile, catalog, specs, records: dict[str, dict]) -> dict:
    seqs = [schema.sequence_entry(records[s.id]) if s.id in records else
            dict(id=s.id, fabric_id=s.fabric_id, action=s.action, num_frames=s.num_frames, split=s.split)
            for s in specs]
    fabric_ids = sorted({s.fabric_id for s in specs})
    return schema.make_manifest(
        complete=len(records) == len(specs), generator_version=__version__, seed=config.seed,
        options=config.options(), catalog_version=catalog.version,
        profile={"name": profile.name, "width_px": profile.image.width_px, "height_px": profile.image.height_px,
                 "mm_per_px": profile.image.mm_per_px, "fps_hz": profile.image.fps_hz},
        fabrics=[{k: getattr(catalog[i], k) for k in schema.FABRIC_FIELDS} for i in fabric_ids],
        sequences=seqs, libraries=library_versions(), source=source_digest(), render=_render_section(config, records),
        **(_units_section(config, profile) if config.units else {}))


def _render_section(config: GenerateConfig, records: dict[str, dict]) -> dict:
    """The manifest's record of what made the frames and labels: the backend, what ran on its device
    (``stages``), the devices that made the finished sequences (from their records: a dataset resumed
    elsewhere lists each), torch's version for the torch backend, and where the labels come from."""
    from .fidelity import get_fidelity

    route = Route.of(config, get_fidelity(config.fidelity))
    out: dict[str, Any] = {"backend": route.backend, "stages": route.stages,
                           "devices": sorted({r["device"] for r in records.values() if "device" in r})}
    if route.backend == "torch":
        import torch

        out["torch"] = torch.__version__
    out["labels"] = route.labels_origin
    return out


def library_versions() -> dict[str, str]:
    """This process's versions of :data:`gelsim.schema.LIBRARIES`: a dataset resumed under others would
    mix sequences that the same seed makes differently."""
    import av
    import cv2
    import mujoco
    import numba
    import scipy

    found = {"numpy": np.__version__, "scipy": scipy.__version__, "opencv": cv2.__version__,
             "numba": numba.__version__, "mujoco": mujoco.__version__, "av": av.__version__}
    return {k: found[k] for k in schema.LIBRARIES}


def _library_difference(made_with: dict | None) -> str | None:
    """The libraries whose version differs from ``made_with`` (a manifest's ``libraries``), as
    ``name recorded (here this)``, or None when they agree or the manifest predates the field."""
    here = library_versions()
    if made_with is None or made_with == here:
        return None
    return ", ".join(f"{k} {made_with.get(k)} (here {here[k]})" for k in here if made_with.get(k) != here[k])


def _units_section(config: GenerateConfig, profile) -> dict:
    """The manifest's record of the sensor units: the ranges drawn from and each unit's parameters."""
    from .units import unit_record, variation_ranges

    return {"unit_variation": variation_ranges(profile),
            "units": [unit_record(u) | {"unit": k, "seed": unit_seed(config.seed, k)}
                      for k, u in enumerate(unit_profiles(config, profile))]}


def _clean_partials(root: Path) -> None:
    """Remove temporary files an interrupted run left behind (they are never valid output)."""
    for p in root.rglob(".*.partial-*"):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _load_records(root: Path, specs: list[SequenceSpec]) -> dict[str, dict]:
    """Records of finished sequences whose files are still in place."""
    done = {}
    for s in specs:
        rp = root / schema.record_path(s.id)
        if not rp.exists():
            continue
        try:
            r = json.loads(rp.read_text())
        except json.JSONDecodeError:
            continue
        if (root / r["video"]).exists() and (root / r["labels"]).exists():
            done[s.id] = r
    return done


def check_render(config: GenerateConfig, fidelity) -> Route:
    """``config``'s render backend, device, batch and stages, checked before anything is written (:meth:`Route.of`):
    its route."""
    return Route.of(config, fidelity)


def resolve_profile(config: GenerateConfig):
    from .sensor import load_profile

    profile = load_profile(config.profile)
    if config.resolution is not None:
        profile = profile.with_resolution(*config.resolution)
    return profile


#: Sequences per Ray task at most. One driver schedules a few hundred tasks per second (docs/scale.md),
#: and a sequence takes about a second at 960x720: tasks of several sequences keep the driver far from
#: that limit on hundreds of workers; 16 (about 15 s of work) still spreads a run evenly.
MAX_SEQUENCES_PER_TASK = 16
#: Tasks per worker at least, for an even finish: the last tasks then hold an eighth of a worker's share.
TASKS_PER_WORKER = 8


def sequences_per_task(sequences: int, cpus: int) -> int:
    """How many sequences one Ray task generates: 1 for small runs, up to :data:`MAX_SEQUENCES_PER_TASK`
    when every CPU would still get :data:`TASKS_PER_WORKER` tasks."""
    return max(1, min(MAX_SEQUENCES_PER_TASK, sequences // (TASKS_PER_WORKER * max(1, cpus))))


def _task_label(specs: list[SequenceSpec]) -> str:
    return f"sequence {specs[0].id}" if len(specs) == 1 else f"sequences {specs[0].id} to {specs[-1].id}"


def ray_sequences(config: GenerateConfig, root: str, specs: list[SequenceSpec]) -> list[dict]:
    """:func:`generate_sequence` of each spec, as one Ray task: the worker process is set up on its first
    task of a run (as a pool worker is by its initializer) and reused for the next ones. A sequence whose
    record is already there (a retry of a task whose worker died half-way) is not generated again."""
    if _WORKER.get("config") != config or _WORKER.get("root") != Path(root):
        _worker_init(config, root)
    if not (Path(root) / schema.MANIFEST).is_file():
        # A node that joined after the start-up check (an autoscaler's) and cannot see --out.
        from .cluster import node_description

        raise GelsimError(f"Ray node {node_description()} does not see --out {root} (no {schema.MANIFEST} there); "
                          "mount the output directory at the same path on every node")
    if _WORKER.get("libraries_checked") != root:
        _check_node_libraries(root)
        _WORKER["libraries_checked"] = root
    done = _load_records(Path(root), specs)
    return [done.get(spec.id) or generate_sequence(spec) for spec in specs]


def ray_group(config: GenerateConfig, root: str, job: tuple[list[SequenceSpec], list[str]]) -> list[dict]:
    """``--stages all``'s Ray task: :func:`generate_group` of ``job`` (the group, the ids to write), set up as
    :func:`ray_sequences`; the records of a retry's members already written are returned as they are."""
    group, ids = job
    ray_sequences(config, root, [])          # the worker's set-up and checks
    done = _load_records(Path(root), [s for s in group if s.id in ids])
    new = {r["id"]: r for r in generate_group(group, [i for i in ids if i not in done])} \
        if any(i not in done for i in ids) else {}
    return [done.get(i) or new[i] for i in ids]


def _made_otherwise(manifest: dict) -> tuple[str | None, str]:
    """What of this process differs from what made ``manifest``'s dataset, first found: ``("libraries",
    the versions that differ)``, ``("source", "")`` for other gelsim code or assets (a manifest from before
    the ``source`` field records none: not other), or ``(None, "")``."""
    diff = _library_difference(manifest.get("libraries"))
    if diff:
        return "libraries", diff
    if manifest.get("source", source_digest()) != source_digest():
        return "source", ""
    return None, ""


def _check_node_libraries(root: str) -> None:
    """A Ray node whose numeric libraries or gelsim code differ from those the manifest records (the
    driver's) would write sequences that the same seed makes differently elsewhere: refused, one line
    naming them."""
    from .cluster import node_description

    what, diff = _made_otherwise(load_manifest(root))
    if what == "libraries":
        raise GelsimError(f"Ray node {node_description()} has other library versions than the dataset's ({diff}), "
                          "which give other bytes from the same seed; install the same versions on every node "
                          "(make install)")
    if what == "source":
        raise GelsimError(f"Ray node {node_description()} has other gelsim code or assets than the dataset's (the "
                          "manifest's source digest differs); install the same commit on every node (make install)")


def _pool_start_method() -> str:
    """How the worker pool starts its processes: forked (fast, the parent's imports shared), unless this
    process has already initialised CUDA (a torch-backend dataset generated in-process before, or a
    caller's own GPU work), which a forked child cannot use: its initializer would fail and the pool
    would replace it forever. Then spawned. The output is the same either way (each sequence is a pure
    function of its spec)."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_initialized():
        return "spawn"
    return "fork"


def _group_jobs(todo: list[SequenceSpec], config: GenerateConfig) -> list[tuple[list[SequenceSpec], list[str]]]:
    """``--stages all``'s jobs: (the whole group, its members still to do) for each group with any to do."""
    ids = {s.id for s in todo}
    groups = device_groups(plan(config, len(_catalog())))
    return [(g, [s.id for s in g if s.id in ids]) for g in groups if any(s.id in ids for s in g)]


def _group_job(job: tuple[list[SequenceSpec], list[str]]) -> list[dict]:
    return generate_group(*job)


def _flat(results, route: Route):
    """One record at a time from per-sequence results, or from ``--stages all``'s per-group lists."""
    if not route.in_step:
        yield from results
        return
    for recs in results:
        yield from recs


def _catalog():
    from .fabrics import load_catalog

    return load_catalog()


@contextlib.contextmanager
def _sequence_results(config: GenerateConfig, route: Route, root: Path, todo: list[SequenceSpec], workers: int | None,
                      cluster):
    """The records of ``todo`` as they finish (``route``: one sequence per job, or a group in step): from Ray tasks
    (``cluster``), in this process (one worker) or from a pool of forked workers."""
    if cluster is not None:
        from .cluster import cluster_cpus, run_unordered

        if route.in_step:   # a group per task (its members still to do written)
            yield (rec for recs in run_unordered(cluster, ray_group, _group_jobs(todo, config),
                                                 args=(config, str(root)), label=lambda job: _task_label(job[0]))
                   for rec in recs)
            return
        k = sequences_per_task(len(todo), cluster_cpus(cluster))
        tasks = [todo[i:i + k] for i in range(0, len(todo), k)]
        yield (rec for recs in run_unordered(cluster, ray_sequences, tasks, args=(config, str(root)),
                                             label=_task_label) for rec in recs)
        return
    workers = max(1, workers or os.cpu_count() or 1)
    fn, jobs = generate_sequence, todo
    if route.in_step:     # whole groups, each sequence written where it is still to do
        fn, jobs = _group_job, _group_jobs(todo, config)
    if workers == 1:
        _worker_init(config, str(root))
        yield _flat(map(fn, jobs), route)
        return
    import multiprocessing as mp

    pool = mp.get_context(_pool_start_method()).Pool(workers, initializer=_worker_init,
                                                      initargs=(config, str(root)))
    try:
        yield _flat(pool.imap_unordered(fn, jobs, chunksize=1), route)
    finally:
        pool.terminate()
        pool.join()


def check_workers(workers: int | None) -> int:
    """The worker processes a local run starts: ``workers`` (None: one per core), checked to be 1 to the
    machine's cores (more processes than cores only share them, and a typo of 100,000 would fork as many)."""
    cores = os.cpu_count() or 1
    if workers is None:
        return cores
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= cores:
        raise GelsimError(f"--workers {workers} is out of range; give 1 to {cores} (this machine's cores; "
                          "the default is all of them)")
    return workers


def generate(config: GenerateConfig, out: str | Path, *, workers: int | None = None,
             progress: Callable[[int, int, dict], None] | None = None, previews: bool = True,
             ray: str | None = None, replace_stale: bool = False,
             notify: Callable[[str], None] | None = None) -> dict:
    """Generate (or finish) the dataset ``config`` under ``out``; returns the final manifest.

    ``progress(done, total, record)`` is called after each sequence (for a progress bar).
    ``ray``: run each sequence as a Ray task instead of in the local pool: ``"local"`` starts a Ray
    instance on this machine (``workers`` CPUs), ``"auto"`` or ``HOST:PORT`` joins a cluster, whose
    nodes must all see ``out`` (checked first). The output is the same bytes either way.
    ``replace_stale``: a dataset in ``out`` that this code cannot resume is renamed aside
    (:func:`set_aside_stale`) once the options are checked, and ``notify`` (if given) is told where, in
    one line.
    """
    from .fabrics import load_catalog
    from .fidelity import get_fidelity
    from .video import EXTENSIONS

    if config.format not in EXTENSIONS:
        raise GelsimError(f"--format {config.format!r} is unknown; choose one of {', '.join(EXTENSIONS)}")
    catalog = load_catalog()
    profile = resolve_profile(config)
    route = check_render(config, get_fidelity(config.fidelity))
    if not 0 <= config.units <= MAX_UNITS:
        raise GelsimError(f"--units {config.units} is out of range; give 0 (the profile itself) to {MAX_UNITS}")
    unit_profiles(config, profile)  # a profile without [unit_variation] fails here, before anything is written
    nuisance_level(config)          # an unknown level fails here too
    if ray is None or ray == "local":   # (a cluster's CPUs are its own: gelsim.cluster.connect says so)
        check_workers(workers)
    specs = plan(config, len(catalog))
    root = Path(out)
    connection = contextlib.nullcontext(None)
    if ray is not None:
        from .cluster import connect

        connection = connect(ray, num_cpus=workers)
    with connection as cluster:  # joined before anything is written: a bad address leaves no trace
        if cluster is not None:
            root = Path(os.path.abspath(root))  # Ray's workers do not start in this directory
        if replace_stale:  # (after every check of the options: bad input moves nothing)
            moved = set_aside_stale(root, config)
            if moved is not None and notify is not None:
                notify(f"{out} held a dataset this code cannot resume: moved to {moved}")
        _prepare_out_dir(root, config.options())
        if cluster is not None:
            from .cluster import check_shared_dir

            check_shared_dir(cluster, root)
        return _generate_in(config, route, root, catalog, profile, specs, workers, progress, previews, cluster)


def _generate_in(config, route: Route, root: Path, catalog, profile, specs, workers, progress, previews,
                 cluster) -> dict:
    """The rest of :func:`generate` once ``root`` is checked (and, with Ray, seen by every node)."""
    _clean_partials(root)
    records = _load_records(root, specs)
    todo = [s for s in specs if s.id not in records]
    need = estimate_bytes(todo, config.format, profile.image.width_px, profile.image.height_px)
    free = shutil.disk_usage(root).free
    if need > free:
        raise GelsimError(f"too little disk under {root}: about {need / 1e9:.1f} GB needed, {free / 1e9:.1f} GB free; "
                          "free space or choose another --out")
    atomic_write_json(root / schema.MANIFEST, _manifest(config, profile, catalog, specs, records))
    total = len(specs)
    done = len(records)
    if todo:
        with _sequence_results(config, route, root, todo, workers, cluster) as results:
            for rec in results:
                records[rec["id"]] = rec
                done += 1
                if progress:
                    progress(done, total, rec)
        if cluster is not None:
            _clean_partials(root)  # a killed worker's half-written files (its retry wrote the real ones)
    manifest = _manifest(config, profile, catalog, specs, records)
    if previews:
        from .previews import write_previews

        write_previews(root, manifest, lambda sequence: dataset_flat_frame(manifest, sequence))
    atomic_write_json(root / schema.MANIFEST, manifest)
    if previews and manifest["complete"]:
        from .stats import write_stats

        write_stats(root, manifest=manifest)  # previews/dataset_stats.{json,md,png}, dataset_actions.png
    return manifest


def summarize_timings(root: str | Path, manifest: dict) -> dict:
    """Per-stage and end-to-end time per frame (ms) from the sequences' records."""
    root = Path(root)
    stages: dict[str, float] = {}
    frames = 0
    wall = 0.0
    for s in manifest["sequences"]:
        rp = root / schema.record_path(s["id"])
        if not rp.exists():
            continue
        r = json.loads(rp.read_text())
        frames += r["num_frames"]
        wall += r["seconds"]
        for k, v in r["timings_s"].items():
            stages[k] = stages.get(k, 0.0) + v
    if frames == 0:
        return {"frames": 0}
    return {"frames": frames, "ms_per_frame": 1000 * wall / frames,
            "stages_ms_per_frame": {k: 1000 * v / frames for k, v in sorted(stages.items())}}


# ---------------------------------------------------------------- verify

def verify(root: str | Path, *, decode: bool = True, progress: Callable[[int, int], None] | None = None) -> list[str]:
    """Check every file against the manifest; returns a list of faults (empty when sound).

    Checks: manifest complete; each sequence's video and labels (and per-frame nuisance record, in datasets
    that have one) present, their checksums as recorded, the video decodes to ``num_frames`` frames, the labels
    hold every key of :data:`gelsim.schema.LABELS` and the record every key of
    :data:`gelsim.nuisance.record.RECORD`, with their shapes (one row per frame) and dtypes.
    """
    from .nuisance.record import record_problems
    from .video import count_frames

    root = Path(root)
    m = load_manifest(root)
    faults = []
    if not m.get("complete"):
        faults.append("manifest: the dataset is incomplete (complete=false); rerun gelsim generate with the same options")
    seqs = m.get("sequences", [])
    for k, s in enumerate(seqs):
        sid = s.get("id", f"#{k}")
        if "video" not in s or "labels" not in s or "sha256" not in s:
            faults.append(f"{sid}: not generated yet")
            continue
        v, lab = root / s["video"], root / s["labels"]
        nui = root / s["nuisance"] if "nuisance" in s else None
        for kind, p in (("video", v), ("labels", lab)) + ((("nuisance", nui),) if nui is not None else ()):
            if not p.exists():
                faults.append(f"{sid}: {kind} {s[kind]} is missing")
            elif sha256_of(p) != s["sha256"][kind]:
                faults.append(f"{sid}: {kind} {s[kind]} does not match its checksum (changed or truncated)")
        if decode and v.exists():
            try:
                n = count_frames(v)
            except GelsimError as e:
                faults.append(f"{sid}: {e}")
            else:
                if n != s["num_frames"]:
                    faults.append(f"{sid}: video has {n} frames, manifest says {s['num_frames']}")
        if lab.exists():
            try:
                with np.load(lab) as z:
                    faults += [f"{sid}: {p}" for p in schema.label_problems(z, s["num_frames"])]
            except Exception as e:  # any unreadable npz is a fault to report, not to crash on
                faults.append(f"{sid}: labels unreadable ({type(e).__name__})")
        if nui is not None and nui.exists():
            try:
                with np.load(nui) as z:
                    faults += [f"{sid}: {p}" for p in record_problems(z, s["num_frames"])]
            except Exception as e:  # as above
                faults.append(f"{sid}: nuisance record unreadable ({type(e).__name__})")
        if progress:
            progress(k + 1, len(seqs))
    return faults
