"""The bench's scenes and settings: which objects it presses, how, at what sizes (:class:`BenchConfig`,
:class:`Scene`), and each scene's motion and object."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import GelsimError
from ..fidelity import fidelity_levels
from ..motion import ACTIONS, Motion, sample_motion
from ..sensor import SensorProfile, load_profile


DEFAULT_RESOLUTION = (320, 240)
# Both resolutions of the default bench: the dataset's (ViTac's 960x720 webcam) and the quick and
# cpu presets' 320x240, at which the finest weaves are below the imprint's texture resolution.
DEFAULT_RESOLUTIONS = ((320, 240), (960, 720))
DEFAULT_FRAMES = 6
DEFAULT_PRECONTACT = 1
# Above 640x480 the reference's elastic imprint takes 10-25 s per fabric frame (measured at
# 960x720 on the 2-core machine): 4 frames, 3 of them in contact (the fewest a press, a slip or a
# twist sequence can have), keep the default bench's reference near 10 minutes.
LARGE_PIXELS = 640 * 480
LARGE_FRAMES = 4
# The shortcut study runs ViTac-like sequences instead (25-36 frames, 2-8 before contact): what
# the shortcuts save depends on the share of pre-contact frames, so it is measured at that share.
SHORTCUT_FRAMES = 30
SHORTCUT_PRECONTACT = 5
# The texture issue's three kinds of cloth: a fine weave (cotton percale, 0.2 mm pitch both ways:
# 3.4 px per period at 320x240, 10 at 960x720), a coarse knit (wool jersey, 0.62-0.78 mm loops,
# 0.14 mm relief) and a pile fabric (pinwale corduroy: 0.3 mm tufts on 1.6 mm wales, 0.5 mm deep).
# Thicker knits (the cotton purl and wool garter knits, 1.6-2 mm thick) bottom the elastic
# reference out at 1-2 N, where no model's texture can be compared with it.
DEFAULT_FABRICS = (2, 50, 64)
# `--quick`: a smoke run of the whole bench in seconds (tests): the coarse knit, whose loops are
# 5-7 px per period at 160x120, pressed and slid.
QUICK = dict(resolution=(160, 120), frames=4, precontact=1, fabrics=(50,), actions=("press", "slip"),
             sphere=False, shortcut_level="")
# Scene seeds: config.seed times this, plus a number per (object, action) below it (catalog ids
# stay below 1000, three actions each).
SCENE_SEED_STRIDE = 10_000
# The sphere scene: a 10 mm ball pressed with 0.5 N indents the vitac gel about 0.4 mm
# (elastic model), well inside its 1 mm travel, with a contact about 4 mm across.
SPHERE_DIAMETER_MM = 10.0
SPHERE_FORCE_N = 0.5
SPHERE_FRICTION = 0.6  # assumed: a smooth plastic ball on silicone


def default_frames(resolution: tuple[int, int]) -> tuple[int, int]:
    """(frames, before contact) of the bench's sequences at ``resolution`` (W, H): see LARGE_FRAMES."""
    w, h = resolution
    return (LARGE_FRAMES if w * h > LARGE_PIXELS else DEFAULT_FRAMES), DEFAULT_PRECONTACT


@dataclass(frozen=True)
class Scene:
    """One benchmark sequence: ``object`` is "sphere" or a catalog fabric id."""
    name: str
    object: str | int
    action: str
    seed: int


@dataclass(frozen=True)
class BenchConfig:
    """What `gelsim bench` runs. Sizes: ``resolution`` (W, H) px; ``frames`` per sequence,
    ``precontact`` of them before contact; ``fabrics`` catalog ids, each under every action
    of ``actions``; plus a pressed sphere if ``sphere``."""
    resolution: tuple[int, int] = DEFAULT_RESOLUTION
    frames: int = DEFAULT_FRAMES
    precontact: int = DEFAULT_PRECONTACT
    fabrics: tuple[int, ...] = DEFAULT_FABRICS
    actions: tuple[str, ...] = ACTIONS
    sphere: bool = True
    levels: tuple[str, ...] = ()          # empty: every level of assets/fidelity.toml
    reference: str = "reference"
    profile: str = "vitac"
    seed: int = 0
    video_format: str = "h264"
    shortcut_level: str = "balanced"      # "" skips the shortcut study
    shortcut_frames: int = SHORTCUT_FRAMES
    shortcut_precontact: int = SHORTCUT_PRECONTACT
    cache_dir: str = ""                   # where yardstick runs are kept ('' for nowhere, see RunCache)

    @classmethod
    def at(cls, resolution: tuple[int, int], **kw) -> "BenchConfig":
        """The bench at ``resolution`` (W, H), with its default sequence length (:func:`default_frames`)
        unless ``frames``/``precontact`` are given."""
        frames, pre = default_frames(resolution)
        kw.setdefault("frames", frames)
        kw.setdefault("precontact", pre)
        return cls(resolution=tuple(resolution), **kw)

    def validate(self) -> None:
        for f, p, what in ((self.frames, self.precontact, ""), (self.shortcut_frames, self.shortcut_precontact,
                                                                     "shortcut study: ")):
            if f - p < 3 or p < 0:
                raise GelsimError(f"{what}{f} frames with {p} before contact; give frames >= precontact + 3 "
                                  "and precontact >= 0")
        for a in self.actions:
            if a not in ACTIONS:
                raise GelsimError(f"unknown action {a!r}; choose from {', '.join(ACTIONS)}")
        if not self.sphere and not (self.fabrics and self.actions):
            raise GelsimError("no scenes: give at least one fabric and action, or keep the sphere")
        levels = fidelity_levels()
        for name in (*self.levels, self.reference) + ((self.shortcut_level,) if self.shortcut_level else ()):
            if name not in levels:
                raise GelsimError(f"unknown fidelity {name!r}; choose from {', '.join(levels)}")

    def level_names(self) -> list[str]:
        names = list(self.levels) if self.levels else list(fidelity_levels())
        return names if self.reference in names else names + [self.reference]


def scenes_for(config: BenchConfig) -> list[Scene]:
    """The bench's scenes, in a fixed order. A scene's seed depends on ``config.seed``, its object
    and its action only (not on which other scenes run), so that a scene is the same sequence in
    every selection of scenes (and its cached reference run is found again)."""
    base = config.seed * SCENE_SEED_STRIDE
    out = []
    if config.sphere:
        out.append(Scene("sphere-press", "sphere", "press", base))
    for fid in config.fabrics:
        for a in config.actions:
            out.append(Scene(f"fabric{fid}-{a}", int(fid), a, base + 1 + int(fid) * len(ACTIONS) + ACTIONS.index(a)))
    return out


def scene_motion(scene: Scene, config: BenchConfig) -> Motion:
    """The scene's hand motion: sampled from motions.toml with the scene's seed; the sphere is
    pressed centred, level, with :data:`SPHERE_FORCE_N`."""
    m = sample_motion(scene.action, scene.seed, frames=(config.frames, config.frames),
                      precontact=(config.precontact, config.precontact))
    if scene.object == "sphere":
        m = dataclasses.replace(m, start_xy_mm=(0.0, 0.0), tilt_deg=(0.0, 0.0), peak_force_n=SPHERE_FORCE_N,
                                fabric_rotation_deg=0.0)
    return m


def prepare_scene(scene: Scene, motion: Motion, profile: SensorProfile, catalog):
    """(the touched object, its physics surface): a rigid ball or a catalog fabric."""
    from ..scene import FabricObject, Sphere, physics_surface

    if scene.object == "sphere":
        obj = Sphere(SPHERE_DIAMETER_MM, friction=SPHERE_FRICTION)
    else:
        obj = FabricObject(catalog[int(scene.object)])
    return obj, physics_surface(obj, motion, profile, seed=scene.seed)


def bench_profile(config: BenchConfig) -> SensorProfile:
    return load_profile(config.profile).with_resolution(*config.resolution)
