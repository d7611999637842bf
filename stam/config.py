"""stam's configuration: TOML configs (called presets in the code) into frozen, validated dataclasses.

A preset (``stam/configs/<name>.toml`` or any ``.toml`` path) has up to three sections:

* ``[pretrain]``  the single-frame backbone pretraining (:class:`PretrainConfig`), the stand-in for
  ImageNet weights; absent: the models start from random weights unless given a backbone;
* ``[train]``     one training run (:class:`TrainConfig`; keys left out keep their defaults);
* ``[sweep]``     the Tables I/II sweep of ``stam experiment`` (:class:`SweepConfig`).

Every file, and every override from the command line, goes through :func:`gelsim.params.build`, as
gelsim's own data files do: unknown keys, wrong types and out-of-range values are a StamError
naming the file and key. ``stam train`` and ``stam experiment`` read the same presets.
"""
from __future__ import annotations

import dataclasses
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from gelsim.errors import GelsimError
from gelsim.params import build, load_toml, package_dir, param

from .data import DEFAULT_ONSET_THRESHOLD
from .errors import StamError

CONFIG_DIR = package_dir("stam", "configs")
# Without a GPU, `stam train` with no --config uses the cpu config: the library defaults (full
# AlexNet from scratch at 224 px) take about 2 minutes an epoch on 2 cores and stay at chance for
# the first epochs; with one, the paper preset (the paper's setting).
CPU_PRESET = "cpu"
GPU_PRESET = "paper"


@dataclass(frozen=True)
class TrainConfig:
    """Everything one run depends on. Units: px for sizes, frames for n, sequences for batches."""

    data: str = ""                 # dataset directory (gelsim generate --out)
    out: str = ""                  # run directory
    preset: str = ""               # the preset this config was resolved from ("" = none), for the record
    model: str = "stam"            # cnn | cnn_sa | stam, or a named variant (stam.models.MODELS)
    frames: int = param(2, lo=1, hi=64, doc="n consecutive frames per window")
    start: Literal["contact", "zero"] = "contact"   # contact (clean, Table I) | zero (noisy, Table II)
    onset: Literal["detected", "true"] = "detected"
    onset_threshold: float = param(DEFAULT_ONSET_THRESHOLD, lo=0.0, lo_open=True, doc="DN, see stam.data")
    image_size: int = param(224, lo=64, hi=1024, doc="px, square model input")
    crop: float = param(1.0, lo=0.05, hi=1.0, doc="centred square kept, fraction of the shorter side")
    width: float = param(1.0, lo=0.0, hi=4.0, lo_open=True, doc="AlexNet channel multiplier")
    fusion: Literal["mean_logits", "mean_features", "max_features", "flatten", "joint", "onset"] = "mean_logits"
    modules: int = param(10, lo=1, doc="temporal attention modules in parallel")
    combine: Literal["mean", "concat"] = "mean"
    qk_reduction: int = param(8, lo=1, doc="q/k channels = C / qk_reduction")
    residual_gain: Literal["learned", "fixed"] = "learned"
    sa_batchnorm: bool = False
    dropout: float = param(0.5, lo=0.0, hi=1.0)
    hidden: int = param(0, lo=0, doc="fc6/fc7 width (0 = 4096 x width)")
    # where the attention reads the backbone: after its last max-pool (the paper's F) or before it
    attention_at: Literal["pool5", "conv5"] = "pool5"
    window_hidden: int = param(512, lo=1, doc="outputs of the position-aware fusions' FC on the flattened window")
    pretrained: str = ""           # backbone checkpoint from `stam pretrain` ("" = random init)
    freeze_backbone: bool = False
    epochs: int = param(30, lo=1)
    batch_size: int = param(32, lo=1, doc="sequences per step")
    optimizer: Literal["sgd", "adam"] = "sgd"
    lr: float = param(0.01, lo=0.0, lo_open=True)
    momentum: float = param(0.9, lo=0.0, hi=1.0)
    weight_decay: float = param(5e-4, lo=0.0)
    lr_schedule: Literal["cosine", "constant"] = "cosine"
    seed: int = param(0, lo=0)
    threads: int = param(0, lo=0, doc="torch CPU threads (0 = torch's default)")
    workers: int = param(0, lo=0, doc="DataLoader worker processes")
    device: Literal["auto", "cpu", "cuda"] = "auto"
    cache_dir: str = ""            # frame cache ("" = DIR/.stam-cache)
    progress: bool = True          # tqdm progress bar

    def validate(self, where: str) -> None:
        from .models import MODELS

        if self.model not in MODELS:
            raise StamError(f"{where}: model {self.model!r} unknown; choose one of {', '.join(MODELS)}")

    def model_options(self) -> dict:
        return {"width": self.width, "image_size": self.image_size, "fusion": self.fusion,
                "modules": self.modules, "combine": self.combine, "qk_reduction": self.qk_reduction,
                "residual_gain": self.residual_gain, "sa_batchnorm": self.sa_batchnorm, "dropout": self.dropout,
                "hidden": self.hidden, "attention_at": self.attention_at, "window_hidden": self.window_hidden}


@dataclass(frozen=True)
class PretrainConfig:
    """Single-frame AlexNet pretraining on the training split (``stam.train.pretrain``)."""

    width: float = param(1.0, lo=0.0, hi=4.0, lo_open=True, doc="AlexNet channel multiplier")
    image_size: int = param(224, lo=64, hi=1024, doc="px")
    epochs: int = param(10, lo=1)
    batch_size: int = param(64, lo=1, doc="frames per step")
    lr: float = param(0.001, lo=0.0, lo_open=True)
    optimizer: Literal["adam", "sgd"] = "adam"
    contact_only: bool = True      # frames from the detected onset on
    frame_stride: int = param(1, lo=1, doc="every k-th frame")
    batchnorm: bool = False        # while pretraining only; folded into the convolutions before saving
    seed: int = param(0, lo=0, doc="the backbone's own seed ([sweep] seeds are the heads')")


# The sweep's settings: what a model is trained on and tested on. clean (Table I): windows from the detected
# contact onset; noisy (Table II): from frame 0, in training and testing; transfer: trained as clean,
# tested on noisy windows (the models of the clean setting, tested again).
SETTINGS = ("clean", "noisy", "transfer")


@dataclass(frozen=True)
class SweepConfig:
    """The grid of ``stam experiment``: models x n x settings x seeds."""

    models: tuple[str, ...] = ("cnn", "cnn_sa", "stam")
    frames: tuple[int, ...] = (2, 3, 4, 5, 6, 7)
    settings: tuple[str, ...] = ("clean", "noisy")
    seeds: int = param(1, lo=1)

    def validate(self, where: str) -> None:
        from .models import MODELS

        for m in self.models:
            if m not in MODELS:
                raise StamError(f"{where}.models: {m!r} unknown; choose from {', '.join(MODELS)}")
        for s in self.settings:
            if s not in SETTINGS:
                raise StamError(f"{where}.settings: {s!r} unknown; choose from {', '.join(SETTINGS)}")
        if not self.frames or min(self.frames) < 1:
            raise StamError(f"{where}.frames: {list(self.frames)} must be frame counts of at least 1")


@dataclass(frozen=True)
class Preset:
    """A parsed preset file. ``name`` is the preset's name or path."""

    name: str = ""
    pretrain: PretrainConfig | None = None
    train: TrainConfig = TrainConfig()
    sweep: SweepConfig = SweepConfig()

    def describe(self) -> str:
        """One line: what a run of this preset trains (:func:`describe_run` of its sections)."""
        return describe_run(self.train, self.pretrain)


def describe_run(t: TrainConfig, pretrain: PretrainConfig | None) -> str:
    """One line: what a run trains as resolved (preset, options and ``--set`` applied): the model and its
    windows, its input, where the backbone starts (``pretrain``: the [pretrain] step the run takes; else
    ``t.pretrained``'s file, or random weights), what is trained and for how long."""
    window = "from the first contact frame" if t.start == "contact" else "from frame 0"
    what = (f"{t.model}, windows of {t.frames} frames {window}, AlexNet width {t.width:g} at {t.image_size} px"
            + (f" on the central {t.crop:g} of each frame" if t.crop < 1 else ""))
    if pretrain is not None:
        start = f"backbone pretrained on single frames for {pretrain.epochs} epoch{'s' * (pretrain.epochs != 1)}"
    elif t.pretrained:
        start = f"backbone from {t.pretrained}"
    else:
        start = "backbone from random weights"
    how = "then frozen, attention and head" if t.freeze_backbone else "then the whole model"
    return (f"{what}, {start}, {how} trained for {t.epochs} epoch{'s' * (t.epochs != 1)} "
            f"({t.optimizer}, lr {t.lr:g}, seed {t.seed})")


def preset_names() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))


def preset_path(preset: str | Path) -> Path:
    """``stam/configs/<preset>.toml`` for a name, the path itself for a ``.toml`` path."""
    s = str(preset)
    path = Path(s) if s.endswith(".toml") else CONFIG_DIR / f"{s}.toml"
    if not path.is_file():
        if s.endswith(".toml"):
            raise StamError(f"config file {path} not found; check the path")
        raise StamError(f"unknown config {s!r}; choose one of {', '.join(preset_names())} or a .toml path")
    return path


def load_preset(preset: str | Path) -> Preset:
    """Read and validate a preset (name or ``.toml`` path)."""
    path = preset_path(preset)
    try:
        raw = load_toml(path)
    except GelsimError as e:
        raise StamError(str(e)) from None
    flat = [k for k, v in raw.items() if not isinstance(v, dict)]
    if flat:
        raise StamError(f"{path}: key {flat[0]!r} is outside a section; put training keys under [train] "
                          "(sections: [pretrain], [train], [sweep])")
    name = path.stem if path.parent == CONFIG_DIR else str(path)
    return _build(Preset, {"name": name, **raw}, str(path))


#: ``resolve_train``'s source for the options of ``stam train`` (``--frames``, ``--epochs``, ...).
COMMAND_LINE = "the command line"


def resolve_train(base: TrainConfig, overrides: dict | None = None, source: str = COMMAND_LINE) -> TrainConfig:
    """``base`` with ``overrides`` (None values skipped), validated like a file. A bad value from the
    command line is named as its option (``--frames 0``), one from ``--set`` as ``--set frames``. A named
    variant's fixed options (``stam.models.VARIANTS``) are written into the result, so that its config says
    what was trained; one set to something else on purpose is an error."""
    from .models import variant

    values = dataclasses.asdict(base)
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    cfg = build_options(TrainConfig, values, source)
    _, options = variant(cfg.model, cfg.model_options())
    return dataclasses.replace(cfg, **{k: options[k] for k in cfg.model_options()})


def resolve_pretrain(base: PretrainConfig, overrides: dict | None = None,
                     source: str = COMMAND_LINE) -> PretrainConfig:
    """``base`` with ``overrides`` (None values skipped), validated like a file."""
    values = dataclasses.asdict(base)
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return build_options(PretrainConfig, values, source)


def build_options(cls, values: dict, source: str = COMMAND_LINE):
    """``cls`` (TrainConfig, PretrainConfig) built from ``values`` and validated like a file, a bad value
    named as its option: ``--frames`` from the command line (``source`` COMMAND_LINE), ``--set frames``
    from ``--set``, ``SOURCE.frames`` from elsewhere."""
    try:
        return _build(cls, values, source)
    except StamError as e:
        if source not in (COMMAND_LINE, "--set"):
            raise
        named = re.sub(rf"^{re.escape(source)}\.(\w+):",
                       lambda m: (f"--{m[1].replace('_', '-')}" if source == COMMAND_LINE else f"--set {m[1]}") + ":",
                       str(e))
        raise StamError(named) from None


def _build(cls, data: dict, where: str):
    """:func:`gelsim.params.build`, its errors as StamError."""
    try:
        return build(cls, data, where)
    except StamError:
        raise
    except GelsimError as e:
        raise StamError(str(e)) from None


def parse_sets(items: list[str]) -> dict:
    """``["key=value", ...]`` -> dict; values are read as TOML values (``0.001``, ``true``, ``"x"``),
    anything else as a plain string (``--set model=cnn``)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise StamError(f"--set {item!r} is not key=value; write e.g. --set lr=0.001")
        k, v = (x.strip() for x in item.split("=", 1))
        try:
            out[k] = tomllib.loads(f"v = {v}")["v"]
        except tomllib.TOMLDecodeError:
            out[k] = v
    return out


def default_preset(device: str, cuda_available: bool) -> str:
    """The preset ``stam train`` uses when none is given: the paper's setting where a CUDA device
    will be used, the cpu preset otherwise."""
    return GPU_PRESET if cuda_available and device in ("auto", "cuda") else CPU_PRESET
