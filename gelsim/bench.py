"""``gelsim bench``: time per frame and error of each fidelity level, and the convergence study.

:func:`run_bench` runs every level on the same fixed scenes (a pressed sphere and catalog fabrics
under each action: a fine weave, a coarse knit and a pile fabric by default) at one resolution
and reports, per level, the CPU time per frame (end to end, and by stage) and the error against
the ``reference`` level on the same scenes:

* **texture** (fabric scenes, in each fabric's pitch band and over the reference's contact region,
  :mod:`gelsim.texture`): *kept relief*, the RMS of the gel surface's relief in the band over the
  reference's, and *image texture*, the RMS of the texture's own share of the image (a noiseless,
  markerless frame minus the frame of the same imprint smoothed beyond the band,
  :func:`gelsim.texture.texture_frames`) over the reference's, once with each level's own renderer
  (``image_texture``: the reference's is pyrender) and once with the fast shader for both
  (``image_texture_fast``: only the gel differs). Ratios per scene (pooled over its in-contact
  frames), then the geometric mean, the smallest and the largest over the scenes; the ``*_err``
  are the mean of ``|1 - ratio|`` over the scenes (0: the reference's texture, 0.5: half of it
  lost or half again);
* **contact area**: mean ``|A - A_ref| / A_ref`` over the in-contact frames (the gel's contact
  area, texture-scale contact included);
* **markers**: mean distance between a level's and the reference's marker centres over the
  in-contact frames, mm, for all markers and for those inside the reference's contact patch;
* **force**: mean ``|normal force|`` difference over all frames, N, each level with its own
  physics timestep;
* **image**: L1 (DN, 0-255), PSNR (dB, from the MSE pooled over frames) and SSIM (Wang et al. 2004:
  11x11 Gaussian window, sigma 1.5, per RGB channel) over the in-contact frames, whole image.

So that image, marker and texture differences measure the image knobs, every level renders on the
*reference* level's contact simulation (same positions, forces, shear and twist); each level's own
physics run is timed and gives the force error. Same scenes, seeds and camera noise for every
level. :func:`run_shortcut_study` times the balanced level with and without the shortcuts of
:mod:`gelsim.sequence` and with labels only. :func:`run_convergence` sweeps one knob at a time
with the same metrics; :func:`run_pitch_study` measures the kept texture against the pixels per
texture period on the finest weaves.

The yardstick runs (the reference level, a sweep's finest value) cost seconds per 960x720 frame
(the elastic imprint): :class:`RunCache` keeps them on disk, keyed by everything they depend on
(scene, sizes, sensor, fidelity, contact, and the source of every module but this one).

Reports: :func:`write_reports` writes ``bench.json``, ``bench.md`` and ``bench_pareto.png``;
:func:`write_convergence` writes ``convergence.json``, ``convergence.md`` and ``convergence.png``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime
import hashlib
import json
import math
import os
import platform
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from .atomic import atomic_write_json, atomic_write_npz, atomic_write_text, write_figure
from .contact import ContactFrames, simulate
from .errors import GelsimError
from .runtime import configure_worker
from .scene import press_properties
from .fidelity import Fidelity, fidelity_levels, get_fidelity
from .metrics import psnr, ssim_map
from .motion import ACTIONS, Motion, sample_motion
from .provenance import source_digest
from .sensor import SensorProfile, load_profile
from .sequence import SequenceOptions, render_sequence
from .sinks import ImprintCapture, KeepFrames, VideoSink, drain
from .texture import RIM_SIGMAS, Band, band_for, band_rms, contact_region, pitches_mm, texture_frames

STAGES = ("fabric", "physics", "imprint", "markers", "optics", "encode")
# Stage clock: the main thread's CPU time, as gelsim.sequence times its stages (a generation worker
# is one thread on one core; wall time would count the other processes' turns on a shared machine).
# The end-to-end figure is the process's CPU time, which also counts helper threads (OpenGL's).
_stage_clock = time.thread_time
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


# --------------------------------------------------------------------------------------
# Image metrics
# --------------------------------------------------------------------------------------
def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """The bench's SSIM of two 8-bit ``(H, W[, C])`` images: :func:`gelsim.metrics.ssim_map` averaged over
    every pixel, border included (as the bench has always reported it), 1 = identical."""
    return float(ssim_map(a, b).mean())


def psnr_from_mse(mse: float) -> float | None:
    """:func:`gelsim.metrics.psnr` for JSON: None for identical images (infinite)."""
    p = psnr(mse)
    return None if math.isinf(p) else p


def _r(v, n: int):
    return None if v is None else round(float(v), n)


@dataclass
class ErrorAcc:
    """Pools errors over frames and scenes: image L1, squared error and SSIM, marker distances (all
    markers, and those in the reference's contact), forces, relative contact-area errors, and the
    texture's band RMS per scene (sums of squares of the level's and the reference's gel relief,
    mm^2, image texture through each one's renderer and through the fast shader, DN^2)."""
    l1_sum: float = 0.0
    se_sum: float = 0.0
    px: int = 0
    ssim_sum: float = 0.0
    frames: int = 0
    marker_sum_mm: float = 0.0
    marker_n: int = 0
    contact_marker_sum_mm: float = 0.0
    contact_marker_n: int = 0
    force_sum_n: float = 0.0
    force_n: int = 0
    area_rel_sum: float = 0.0
    area_n: int = 0
    texture: dict = field(default_factory=dict)  # scene -> sums [gel^2, ref, img^2, ref, fast img^2, ref]

    def add_frame(self, a: np.ndarray, ref: np.ndarray) -> None:
        d = a.astype(np.float64) - ref.astype(np.float64)
        self.l1_sum += float(np.abs(d).sum())
        self.se_sum += float((d * d).sum())
        self.px += d.size
        self.ssim_sum += ssim(a, ref)
        self.frames += 1

    def add_markers(self, xy: np.ndarray, ref: np.ndarray, mm_per_px: float) -> None:
        if xy.size:
            self.marker_sum_mm += float(np.linalg.norm(xy - ref, axis=-1).sum()) * mm_per_px
            self.marker_n += int(np.prod(xy.shape[:-1]))

    def add_contact_markers(self, xy: np.ndarray, ref: np.ndarray, mm_per_px: float) -> None:
        """Markers (N, 2) px inside the reference's contact patch, and the reference's."""
        if xy.size:
            self.contact_marker_sum_mm += float(np.linalg.norm(xy - ref, axis=-1).sum()) * mm_per_px
            self.contact_marker_n += int(np.prod(xy.shape[:-1]))

    def add_forces(self, f: np.ndarray, ref: np.ndarray) -> None:
        self.force_sum_n += float(np.abs(np.asarray(f, np.float64) - ref).sum())
        self.force_n += len(f)

    def add_area(self, area_mm2: float, ref_mm2: float) -> None:
        if ref_mm2 > 0:
            self.area_rel_sum += abs(float(area_mm2) - float(ref_mm2)) / float(ref_mm2)
            self.area_n += 1

    def add_texture(self, scene: str, gel: float, ref_gel: float, img: float, ref_img: float,
                    img_fast: float = math.nan, ref_img_fast: float = math.nan) -> None:
        """One frame's band RMS, the level's and the reference's: gel relief (mm), image texture through
        each one's renderer and through the fast shader (DN; NaN: not measured). Frames with no region
        (NaN relief or image) are left out."""
        if not all(math.isfinite(v) for v in (gel, ref_gel, img, ref_img)):
            return
        t = self.texture.setdefault(scene, [0.0] * 6)
        fast = (img_fast, ref_img_fast) if math.isfinite(img_fast) and math.isfinite(ref_img_fast) else (0.0, 0.0)
        for k, v in enumerate((gel, ref_gel, img, ref_img, *fast)):
            t[k] += v * v

    def texture_ratios(self) -> dict[str, tuple[float | None, float | None, float | None]]:
        """Per scene: (kept relief, image texture, image texture through the fast shader) ratios to
        the reference (None where it has none or it was not measured)."""
        def ratio(a, b):
            return math.sqrt(a / b) if b > 0 else None

        return {sc: (ratio(t[0], t[1]), ratio(t[2], t[3]), ratio(t[4], t[5])) for sc, t in self.texture.items()}

    def summary(self) -> dict:
        mse = self.se_sum / self.px if self.px else 0.0
        out = {"image_l1": _r(self.l1_sum / self.px if self.px else None, 4),
               "psnr": _r(psnr_from_mse(mse) if self.px else None, 3),
               "ssim": _r(self.ssim_sum / self.frames if self.frames else None, 5),
               "marker_err_mm": _r(self.marker_sum_mm / self.marker_n if self.marker_n else None, 6),
               "marker_err_contact_mm": _r(self.contact_marker_sum_mm / self.contact_marker_n
                                           if self.contact_marker_n else None, 6),
               "force_err_n": _r(self.force_sum_n / self.force_n if self.force_n else 0.0, 5),
               "contact_area_err": _r(self.area_rel_sum / self.area_n if self.area_n else None, 4)}
        # None: not measured (no frames, markers or fabric scenes compared); PSNR also None for
        # identical images
        ratios = self.texture_ratios()
        for k, name, err in ((0, "kept_relief", "texture_err"), (1, "image_texture", "image_texture_err"),
                             (2, "image_texture_fast", "image_texture_fast_err")):
            vals = [v[k] for v in ratios.values() if v[k] is not None and v[k] > 0]
            out[name] = _r(math.exp(sum(math.log(v) for v in vals) / len(vals)) if vals else None, 4)
            out[f"{name}_min"] = _r(min(vals) if vals else None, 4)
            out[f"{name}_max"] = _r(max(vals) if vals else None, 4)
            out[err] = _r(sum(abs(1 - v) for v in vals) / len(vals) if vals else None, 4)
        return out


# --------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------
# Running one level on one scene
# --------------------------------------------------------------------------------------
@dataclass
class LevelRun:
    """One level on one scene: frames (uint8 (T, H, W, 3) or None), labels, the contact it rendered
    on, CPU seconds by stage (main thread), CPU seconds (process) and wall seconds in all, and
    (while it is measured) the imprints of the frames that pressed: ``{frame: (depth mm float32
    (H, W), contact mask bool (H, W))}``. ``cached``: read back from a :class:`RunCache`."""
    frames: np.ndarray | None
    labels: dict
    contact: ContactFrames
    seconds: dict[str, float] = field(default_factory=dict)
    cpu_s: float = 0.0
    wall_s: float = 0.0
    imprints: dict | None = None
    cached: bool = False


def _prepare(scene: Scene, motion: Motion, profile: SensorProfile, catalog):
    """(the touched object, its physics surface): a rigid ball or a catalog fabric."""
    from .scene import FabricObject, Sphere, physics_surface

    if scene.object == "sphere":
        obj = Sphere(SPHERE_DIAMETER_MM, friction=SPHERE_FRICTION)
    else:
        obj = FabricObject(catalog[int(scene.object)])
    return obj, physics_surface(obj, motion, profile, seed=scene.seed)


def run_level(scene: Scene, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *, catalog,
              renderer=None, contact: ContactFrames | None = None, shortcuts: bool = True,
              outputs=("frames", "imprint", "markers"), encode: str | None = "h264",
              sensor_seed: int = 0, tmpdir: str | None = None, keep_imprints: bool = False) -> LevelRun:
    """Run ``fidelity`` on one scene: its own physics (timed; gives its forces), then imprint,
    markers and optics on ``contact`` (default: its own), then encoding to a throw-away video.
    Frames are kept for comparison; with ``keep_imprints`` also the imprint of every frame that
    pressed (``LevelRun.imprints``, an :class:`gelsim.sinks.ImprintCapture` of the sequence's records)."""
    from .video import video_path

    c0, w0, th0 = time.process_time(), time.perf_counter(), _stage_clock()
    t0 = th0
    obj, surface = _prepare(scene, motion, profile, catalog)
    fab_s = _stage_clock() - t0
    t0 = _stage_clock()
    own = simulate(motion, surface, profile, fidelity)
    phys_s = _stage_clock() - t0
    use = contact if contact is not None else own
    frames, capture = KeepFrames(), ImprintCapture()
    sinks: list = [frames, capture] if keep_imprints else [frames]
    options = SequenceOptions(renderer=renderer, sensor_seed=sensor_seed, shortcuts=shortcuts, outputs=outputs,
                              contact=use, surface=surface)
    with contextlib.ExitStack() as stack:
        if encode and "frames" in outputs:
            td = stack.enter_context(tempfile.TemporaryDirectory(dir=tmpdir))
            sinks.insert(0, stack.enter_context(VideoSink(video_path(Path(td) / "bench", encode), fmt=encode,
                                                          fps=profile.image.fps_hz)))
        labels, seconds = drain(render_sequence(obj, motion, profile, fidelity, seed=scene.seed, options=options),
                                sinks)
    secs = {s: 0.0 for s in STAGES}
    secs.update(seconds)
    secs["fabric"] += fab_s
    secs["physics"] = phys_s
    # CPU of the process's other threads: OpenGL's (llvmpipe) under pyrender, which the main
    # thread's clock does not see; the encoder and OpenCV run on the main thread (one core). Only
    # when frames were rendered: idle threads of other libraries (a torch pool) tick otherwise.
    if "frames" in outputs:
        secs["optics"] += max(0.0, (time.process_time() - c0) - (_stage_clock() - th0))
    labels["normal_force_n"] = own.normal_force_n  # this level's own physics
    fr = np.stack(frames.frames) if frames.frames and frames.frames[0] is not None else None
    run = LevelRun(fr, labels, use, secs, time.process_time() - c0, time.perf_counter() - w0)
    if keep_imprints:
        run.imprints = capture.imprints
    return run


def _make_renderer(profile, fid: Fidelity, sensor_seed: int):
    from .optics import Renderer

    return Renderer(profile, fid.render_backend, supersample=fid.supersample, seed=sensor_seed)


def _bench_profile(config: BenchConfig) -> SensorProfile:
    return load_profile(config.profile).with_resolution(*config.resolution)


# --------------------------------------------------------------------------------------
# Texture of a run, against its yardstick
# --------------------------------------------------------------------------------------
@dataclass
class SceneTexture:
    """The texture of one run over the in-contact frames it pressed (``frames``, indices into the
    sequence): band RMS of the gel's relief (mm) and of the image's texture (DN; through the run's own
    renderer, and through the fast shader at the image's resolution, which separates the gel's part
    from the renderer's) per frame, NaN where not measured (no texture: the sphere; an empty region). A yardstick's also holds the regions
    the others are measured over (bool (n, H, W)): ``region``, the contact patch in the fabric's
    pitch band (:func:`gelsim.texture.contact_region`), and ``patch``, the apparent contact (for the
    markers in contact)."""
    frames: np.ndarray
    gel_rms: np.ndarray
    img_rms: np.ndarray
    region: np.ndarray | None = None
    patch: np.ndarray | None = None
    img_fast_rms: np.ndarray | None = None   # the image texture through the fast shader, DN


def _texture_band(fabric, profile: SensorProfile) -> tuple[Band | None, float, float]:
    """(band or None for an object without texture, closing px, rim px) of the texture metric."""
    if fabric is None:
        return None, 1.0, 0.0
    mm = profile.image.mm_per_px
    band = band_for(fabric, min(profile.field_mm))
    return band, pitches_mm(fabric)[1] / mm, RIM_SIGMAS * band.sigmas_px(mm)[1]


def measure_texture(run: LevelRun, fabric, profile: SensorProfile, renderer,
                    yardstick: SceneTexture | None = None, shader=None) -> SceneTexture:
    """The texture of ``run`` (which kept its imprints) over the yardstick's regions, or, without a
    yardstick, over its own: then the result is a yardstick for other runs on this contact.
    ``renderer``: the run's own; ``shader``: the fast shader at supersample 1 (None: ``renderer`` is
    that already), for the image texture that only the gel changes."""
    band, close_px, rim_px = _texture_band(fabric, profile)
    mm = profile.image.mm_per_px
    frames = np.array(sorted(run.imprints or {}), dtype=int) if yardstick is None else yardstick.frames
    gel = np.full(len(frames), np.nan)
    img = np.full(len(frames), np.nan)
    img_fast = np.full(len(frames), np.nan)
    regions, patches = [], []

    def image_rms(ren, depth, region):
        clean, macro = texture_frames(ren, depth, band, mm)
        return band_rms(clean.astype(np.float32) - macro.astype(np.float32), region, band, mm)

    for k, i in enumerate(frames):
        if int(i) not in (run.imprints or {}):
            raise GelsimError(f"frame {i} of the yardstick was not pressed by this run; compare runs on one contact")
        depth, mask = run.imprints[int(i)]
        if yardstick is None:
            region = contact_region(mask, close_px, rim_px) if band is not None else None
            regions.append(region)
            patches.append(contact_region(mask, close_px, 0.0))
        else:
            region = None if yardstick.region is None else yardstick.region[k]
        if band is not None and region.any():
            gel[k] = band_rms(depth, region, band, mm)
            img[k] = image_rms(renderer, depth, region)
            img_fast[k] = img[k] if shader is None else image_rms(shader, depth, region)
    if yardstick is not None:
        return SceneTexture(frames, gel, img, img_fast_rms=img_fast)
    shape = (len(frames), *profile.shape)
    return SceneTexture(frames, gel, img,
                        np.stack(regions) if band is not None and regions else None,
                        np.stack(patches) if patches else np.zeros(shape, bool), img_fast)


def _fast_shader(profile: SensorProfile, fid: Fidelity, seed: int):
    """The fast shader at supersample 1 for a level whose own renderer is another (None if not)."""
    if fid.render_backend == "fast" and fid.supersample == 1:
        return None
    from .optics import Renderer

    return Renderer(profile, "fast", supersample=1, seed=seed)


def _accumulate(acc: ErrorAcc, run: LevelRun, ref: LevelRun, mmpp: float, scene: str = "",
                tex: SceneTexture | None = None, ref_tex: SceneTexture | None = None) -> None:
    """Add one scene's errors of ``run`` against ``ref`` (same contact) to ``acc``."""
    touch = np.asarray(ref.contact.in_contact, bool)
    if run.frames is not None and ref.frames is not None:
        for i in np.flatnonzero(touch):
            acc.add_frame(run.frames[i], ref.frames[i])
    if "markers_xy_px" in run.labels and "markers_xy_px" in ref.labels:
        acc.add_markers(run.labels["markers_xy_px"][touch], ref.labels["markers_xy_px"][touch], mmpp)
        if ref_tex is not None and ref_tex.patch is not None:
            for k, i in enumerate(ref_tex.frames):
                xy, rxy = run.labels["markers_xy_px"][i], ref.labels["markers_xy_px"][i]
                if not len(rxy):
                    continue
                h, w = ref_tex.patch.shape[1:]
                col = np.clip(np.rint(rxy[:, 0]).astype(int), 0, w - 1)
                row = np.clip(np.rint(rxy[:, 1]).astype(int), 0, h - 1)
                inside = ref_tex.patch[k][row, col]
                acc.add_contact_markers(xy[inside], rxy[inside], mmpp)
    if "contact_area_mm2" in run.labels and "contact_area_mm2" in ref.labels:
        for i in np.flatnonzero(touch):
            acc.add_area(run.labels["contact_area_mm2"][i], ref.labels["contact_area_mm2"][i])
    if tex is not None and ref_tex is not None:
        for k in range(len(ref_tex.frames)):
            fast = (math.nan, math.nan) if tex.img_fast_rms is None or ref_tex.img_fast_rms is None else \
                (tex.img_fast_rms[k], ref_tex.img_fast_rms[k])
            acc.add_texture(scene, tex.gel_rms[k], ref_tex.gel_rms[k], tex.img_rms[k], ref_tex.img_rms[k], *fast)
    acc.add_forces(run.labels["normal_force_n"], np.asarray(ref.labels["normal_force_n"], np.float64))


# --------------------------------------------------------------------------------------
# The yardstick cache
# --------------------------------------------------------------------------------------
def _array_digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k} {a.dtype} {a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class RunCache:
    """Yardstick results on disk (``root/<key>.npz``), so that the seconds-per-frame reference is paid
    once per scene and source version; ``root`` None or '': nothing is kept. A key covers the
    caller's description of the run and :func:`source_digest`: any change to a gelsim module (but
    the bench's) or an asset makes a new key."""

    def __init__(self, root: str | Path | None):
        self.root = Path(root) if root else None

    def key(self, parts: dict) -> str:
        doc = json.dumps({**parts, "source": source_digest()}, sort_keys=True, default=str)
        return hashlib.sha256(doc.encode()).hexdigest()[:24]

    def load(self, key: str) -> dict | None:
        """The arrays stored under ``key`` (``meta``: a JSON document), or None."""
        path = None if self.root is None else self.root / f"{key}.npz"
        if path is None or not path.exists():
            return None
        with np.load(path) as z:
            d = {k: z[k] for k in z.files}
        d["meta"] = json.loads(str(d["meta"])) if "meta" in d else {}
        return d

    def save(self, key: str, arrays: dict, meta: dict) -> None:
        if self.root is None:
            return
        meta = {**meta, "date": datetime.datetime.now().isoformat(timespec="seconds"), "load_avg": _load_avg()}
        atomic_write_npz(self.root / f"{key}.npz", **arrays, meta=np.array(json.dumps(meta)))

    def run_key(self, scene: Scene, config: BenchConfig, profile: SensorProfile, fid: Fidelity,
                contact: ContactFrames | None, outputs=("frames", "imprint", "markers")) -> str:
        return self.key({"scene": dataclasses.asdict(scene), "frames": config.frames,
                         "precontact": config.precontact,
                         "profile": hashlib.sha256(repr(profile).encode()).hexdigest(),
                         "fidelity": {**dataclasses.asdict(fid), "name": ""}, "seed": config.seed,
                         "video_format": config.video_format, "outputs": sorted(outputs),
                         "contact": None if contact is None else _array_digest(contact.to_dict())})

    def get_run(self, key: str) -> tuple[LevelRun, SceneTexture | None] | None:
        d = self.load(key)
        if d is None:
            return None
        meta = d.pop("meta")
        pick = lambda prefix: {k[len(prefix):]: v for k, v in d.items() if k.startswith(prefix)}  # noqa: E731
        contact = ContactFrames(**pick("contact__"), **meta["contact_scalars"])
        imprints = None
        if "imp_frames" in d:
            imprints = {int(i): (d["imp_depth"][k], d["imp_mask"][k]) for k, i in enumerate(d["imp_frames"])}
        run = LevelRun(d.get("frames"), pick("label__"), contact, meta["seconds"], meta["cpu_s"], meta["wall_s"],
                       imprints=imprints, cached=True)
        tex = None if "tex_frames" not in d else SceneTexture(d["tex_frames"], d["tex_gel"], d["tex_img"],
                                                             d.get("tex_region"), d.get("tex_patch"),
                                                             d.get("tex_img_fast"))
        return run, tex

    def put_run(self, key: str, run: LevelRun, tex: SceneTexture | None) -> None:
        arrays = {f"contact__{k}": v for k, v in run.contact.to_dict().items()}
        arrays.update({f"label__{k}": np.asarray(v) for k, v in run.labels.items()})
        if run.frames is not None:
            arrays["frames"] = run.frames
        if run.imprints:
            # The imprints themselves (a metric added later is measured from them, not re-solved).
            order = sorted(run.imprints)
            arrays.update(imp_frames=np.array(order), imp_depth=np.stack([run.imprints[i][0] for i in order]),
                          imp_mask=np.stack([run.imprints[i][1] for i in order]))
        if tex is not None:
            arrays.update(tex_frames=tex.frames, tex_gel=tex.gel_rms, tex_img=tex.img_rms)
            for name, value in (("tex_img_fast", tex.img_fast_rms), ("tex_region", tex.region), ("tex_patch", tex.patch)):
                if value is not None:
                    arrays[name] = value
        self.save(key, arrays, {"seconds": run.seconds, "cpu_s": run.cpu_s, "wall_s": run.wall_s,
                                "contact_scalars": {"first_contact_frame": int(run.contact.first_contact_frame),
                                                    "contact_time_s": float(run.contact.contact_time_s)}})


def _measured_run(scene: Scene, motion: Motion, profile: SensorProfile, fid: Fidelity, *, catalog, renderer,
                  contact: ContactFrames | None, config: BenchConfig, yardstick: SceneTexture | None = None,
                  cache: RunCache | None = None, encode: str | None = None, shader=None,
                  outputs=("frames", "imprint", "markers")) -> tuple[LevelRun, SceneTexture | None]:
    """``run_level`` with the texture measured (``yardstick`` None: this run is the yardstick, read
    from and written to ``cache``; a cached run whose texture lacks a measure is measured again from
    its stored imprints). ``shader``: see :func:`measure_texture`. Outputs without frames: no
    texture (None)."""
    textured = "frames" in outputs
    fabric = None if scene.object == "sphere" else catalog[int(scene.object)]
    key = None
    if yardstick is None and cache is not None and cache.root is not None:
        key = cache.run_key(scene, config, profile, fid, contact, outputs)
        hit = cache.get_run(key)
        if hit is not None:
            run, tex = hit
            if textured and (tex is None or tex.img_fast_rms is None) and run.imprints is not None:
                tex = measure_texture(run, fabric, profile, renderer, shader=shader)
                cache.put_run(key, run, tex)
            if not textured or (tex is not None and tex.img_fast_rms is not None):
                run.imprints = None
                return run, tex
    run = run_level(scene, motion, profile, fid, catalog=catalog, renderer=renderer, contact=contact,
                    encode=encode, sensor_seed=config.seed, outputs=outputs, keep_imprints=textured)
    tex = measure_texture(run, fabric, profile, renderer, yardstick, shader) if textured else None
    if key is not None:
        cache.put_run(key, run, tex)
    run.imprints = None
    return run, tex


def _warm_up(scene: Scene, config: BenchConfig, profile: SensorProfile, catalog, fids: list[Fidelity]) -> None:
    """Run ``scene`` once at each of ``fids``, untimed: the first run in a process pays one-off costs
    (tables read, libraries initialised: measured 4x a fast level's frame at 160x120), which would
    otherwise land on whichever level runs first."""
    motion = scene_motion(scene, config)
    for fid in fids:
        renderer = _make_renderer(profile, fid, config.seed)
        try:
            run_level(scene, motion, profile, fid, catalog=catalog, renderer=renderer, encode=config.video_format,
                      sensor_seed=config.seed)
        finally:
            renderer.close()


def _load_avg() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def _settings(config: BenchConfig, scenes: list[Scene]) -> dict:
    return {"resolution": list(config.resolution), "frames": config.frames, "precontact": config.precontact,
            "scenes": [s.name for s in scenes], "reference": config.reference, "profile": config.profile,
            "seed": config.seed, "video_format": config.video_format, "cpu_count": os.cpu_count(),
            "shortcut_frames": config.shortcut_frames, "shortcut_precontact": config.shortcut_precontact,
            "load_avg": _load_avg(), "python": platform.python_version(),
            "date": datetime.datetime.now().isoformat(timespec="seconds")}


def run_bench(config: BenchConfig = BenchConfig(), progress: Callable[[str], None] | None = None) -> dict:
    """Run every level on every scene at ``config.resolution``; returns ``{"levels": [...],
    "settings", "shortcuts"}``.

    Each level entry: name, cpu_ms_per_frame (process CPU, end to end), wall_ms_per_frame,
    stages_ms (main-thread CPU ms per frame by stage) and ms_per_frame (their sum), the errors of
    :meth:`ErrorAcc.summary` (image_l1, psnr, ssim, marker_err_mm, marker_err_contact_mm,
    force_err_n, contact_area_err, kept_relief[_min, _max], image_texture[_min, _max] (through each
    one's renderer), image_texture_fast[_min, _max] (both through the fast shader: the gel's part),
    texture_err, image_texture_err, image_texture_fast_err), the level's knobs, per_scene (the same errors per scene), and
    cached_scenes (how many of its scenes came from the cache: their times are those measured then).
    """
    from .fabrics import load_catalog

    config.validate()
    configure_worker()  # timings are per core, like a `gelsim generate` worker
    say = progress or (lambda s: None)
    t_start, c_start = time.perf_counter(), time.process_time()
    profile = _bench_profile(config)
    catalog = load_catalog()
    scenes = scenes_for(config)
    levels = config.level_names()
    ref_name = config.reference
    order = [ref_name] + [n for n in levels if n != ref_name]
    cache = RunCache(config.cache_dir)
    _warm_up(scenes[0], config, profile, catalog, [get_fidelity(n) for n in levels if n != ref_name])
    ref_runs: dict[str, tuple[LevelRun, SceneTexture]] = {}
    results = {}
    mmpp = profile.image.mm_per_px
    for name in order:
        fid = get_fidelity(name)
        renderer = _make_renderer(profile, fid, config.seed)
        shader = _fast_shader(profile, fid, config.seed)
        acc = ErrorAcc()
        secs = {s: 0.0 for s in STAGES}
        cpu = wall = 0.0
        nframes = cached = 0
        per_scene = []
        try:
            for sc in scenes:
                motion = scene_motion(sc, config)
                ref = ref_runs.get(sc.name)
                run, tex = _measured_run(sc, motion, profile, fid, catalog=catalog, renderer=renderer,
                                         contact=None if ref is None else ref[0].contact, config=config,
                                         yardstick=None if ref is None else ref[1],
                                         cache=cache if ref is None else None, encode=config.video_format,
                                         shader=shader)
                if ref is None:
                    ref_runs[sc.name] = ref = (run, tex)
                sacc = ErrorAcc()
                for a in (acc, sacc):
                    _accumulate(a, run, ref[0], mmpp, sc.name, tex, ref[1])
                for k, v in run.seconds.items():
                    secs[k] += v
                cpu += run.cpu_s
                wall += run.wall_s
                cached += run.cached
                nframes += motion.num_frames
                per_scene.append({"scene": sc.name, **sacc.summary(), "cached": run.cached,
                                  "cpu_ms_per_frame": round(1000 * run.cpu_s / motion.num_frames, 2)})
                ps = per_scene[-1]
                say(f"{name:>10} {sc.name:<18} {ps['cpu_ms_per_frame']:9.1f} CPU ms/frame"
                    + (" (cached)" if run.cached else "")
                    + (f"  kept relief {ps['kept_relief']:.3f} image texture {ps['image_texture']:.3f}"
                       f" (fast shader {ps['image_texture_fast']:.3f})"
                       if ps["kept_relief"] is not None and ps["image_texture"] is not None else ""))
        finally:
            renderer.close()
            if shader is not None:
                shader.close()
        stages_ms = {k: round(1000 * v / nframes, 3) for k, v in secs.items()}
        results[name] = {"name": name, "cpu_ms_per_frame": round(1000 * cpu / nframes, 2),
                         "wall_ms_per_frame": round(1000 * wall / nframes, 2),
                         "ms_per_frame": round(sum(stages_ms.values()), 2), "stages_ms": stages_ms,
                         **acc.summary(), "knobs": _knobs(fid), "cached_scenes": cached, "per_scene": per_scene}
    out = {"levels": [results[n] for n in levels], "settings": _settings(config, scenes)}
    if config.shortcut_level:
        out["shortcuts"] = run_shortcut_study(config, profile, catalog, scenes, progress=say)
    out["settings"]["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    out["settings"]["bench_cpu_seconds"] = round(time.process_time() - c_start, 1)
    return out


def run_benches(configs: list[BenchConfig], progress: Callable[[str], None] | None = None) -> dict:
    """:func:`run_bench` at each config (e.g. each resolution): ``{"runs": [result, ...]}``."""
    t0 = time.perf_counter()
    runs = []
    for c in configs:
        if progress:
            progress(f"bench at {c.resolution[0]}x{c.resolution[1]}, {c.frames} frames per scene")
        runs.append(run_bench(c, progress))
    return {"runs": runs, "bench_seconds": round(time.perf_counter() - t0, 1)}


def _runs(doc: dict) -> list[dict]:
    """The single-resolution results in a :func:`run_benches` document (or a single result)."""
    return doc["runs"] if "runs" in doc else [doc]


def _knobs(fid: Fidelity) -> dict:
    d = dataclasses.asdict(fid)
    d.pop("name")
    for k in ("est_ms_per_frame_vga", "est_ms_per_frame_960", "est_worker_efficiency"):
        d.pop(k)
    return d


def run_shortcut_study(config: BenchConfig, profile, catalog, scenes, *, progress=None) -> list[dict]:
    """The shortcut level with all shortcuts, without them, and with labels only, on the bench's
    scenes as ViTac-like sequences (``config.shortcut_frames`` frames, ``shortcut_precontact``
    before contact), all three on one contact simulation per scene.

    Each row: variant, ms_per_frame (main-thread CPU, sum of the stages), cpu_ms_per_frame
    (process CPU), stages_ms, and the largest difference from the run with all shortcuts:
    max_abs_dn (frame pixels), max_marker_px, max_indentation_mm.
    """
    say = progress or (lambda s: None)
    fid = get_fidelity(config.shortcut_level)
    long = dataclasses.replace(config, frames=config.shortcut_frames, precontact=config.shortcut_precontact)
    contacts = {}
    for sc in scenes:
        motion = scene_motion(sc, long)
        _, surface = _prepare(sc, motion, profile, catalog)
        contacts[sc.name] = simulate(motion, surface, profile, fid)
    rows = []
    base_runs: dict[str, LevelRun] = {}
    variants = (("all shortcuts", True, ("frames", "imprint", "markers")),
                ("no shortcuts", False, ("frames", "imprint", "markers")),
                ("labels only", True, ()))
    for label, sc_on, outputs in variants:
        renderer = _make_renderer(profile, fid, config.seed) if outputs else None
        secs = {s: 0.0 for s in STAGES}
        n = 0
        cpu = 0.0
        dmax = {"max_abs_dn": 0.0, "max_marker_px": 0.0, "max_indentation_mm": 0.0}
        try:
            for sc in scenes:
                motion = scene_motion(sc, long)
                run = run_level(sc, motion, profile, fid, catalog=catalog, renderer=renderer, contact=contacts[sc.name],
                                shortcuts=sc_on, outputs=outputs, encode=config.video_format if outputs else None,
                                sensor_seed=config.seed)
                base = base_runs.setdefault(sc.name, run)
                if run is not base:
                    if run.frames is not None:
                        dmax["max_abs_dn"] = max(dmax["max_abs_dn"], float(np.abs(
                            run.frames.astype(np.int16) - base.frames.astype(np.int16)).max()))
                    if "markers_xy_px" in run.labels:
                        dmax["max_marker_px"] = max(dmax["max_marker_px"], float(np.abs(
                            run.labels["markers_xy_px"] - base.labels["markers_xy_px"]).max(initial=0.0)))
                    if "indentation_mm" in run.labels:
                        dmax["max_indentation_mm"] = max(dmax["max_indentation_mm"], float(np.abs(
                            run.labels["indentation_mm"] - base.labels["indentation_mm"]).max()))
                for k, v in run.seconds.items():
                    secs[k] += v
                cpu += run.cpu_s
                n += motion.num_frames
        finally:
            if renderer is not None:
                renderer.close()
        stages_ms = {k: round(1000 * v / n, 3) for k, v in secs.items()}
        rows.append({"variant": label, "level": fid.name, "ms_per_frame": round(sum(stages_ms.values()), 2),
                     "cpu_ms_per_frame": round(1000 * cpu / n, 2), "stages_ms": stages_ms, **{k: round(v, 6) for k, v in dmax.items()}})
        say(f"{fid.name:>10} {label:<18} {rows[-1]['cpu_ms_per_frame']:8.1f} CPU ms/frame")
    return rows


# --------------------------------------------------------------------------------------
# Reports
# --------------------------------------------------------------------------------------
def _fmt(v, nd: int) -> str:
    if v is None:
        return "-"
    return f"{v:.{nd}f}"


def _ratio(lv: dict, name: str) -> str:
    v, lo, hi = lv.get(name), lv.get(f"{name}_min"), lv.get(f"{name}_max")
    if v is None:
        return "-"
    return f"{v:.2f}" if lo is None or hi is None or hi - lo < 0.005 else f"{v:.2f} ({lo:.2f}-{hi:.2f})"


def _header(r: dict) -> str:
    s = r["settings"]
    w, h = s["resolution"]
    cached = sum(lv.get("cached_scenes", 0) for lv in r["levels"])
    return (f"{w}x{h} px, {len(s['scenes'])} scenes ({', '.join(s['scenes'])}), {s['frames']} frames each "
            f"({s['precontact']} before contact), errors against `{s['reference']}` on the same contact; "
            f"{s['cpu_count']} CPUs, load average {s['load_avg']}, {s['date']}, {s.get('bench_seconds', '?')} s in all"
            + (f" ({s['bench_cpu_seconds']} s of CPU)" if "bench_cpu_seconds" in s else "")
            + (f"; {cached} level-scene runs read from the cache (their times are those measured when they ran)"
               if cached else "") + ".")


def markdown_table(doc: dict) -> str:
    """The bench result (one :func:`run_bench` result or a :func:`run_benches` document) as Markdown:
    per resolution, the level table (texture, contact, markers, force, image), the texture ratios
    per scene, the time by stage and the shortcut table."""
    lines = []
    for r in _runs(doc):
        s = r["settings"]
        w, h = s["resolution"]
        levels = r["levels"]
        lines += [f"### {w}x{h}", "", "Bench: " + _header(r), "",
                  "| level | CPU ms/frame | kept relief | image texture, fast shader | image texture, own renderer "
                  "| contact area err | marker err (mm) | in contact (mm) | force err (N) | image L1 (DN) | PSNR (dB) "
                  "| SSIM |",
                  "|---" * 12 + "|"]
        for lv in levels:
            lines.append(f"| {lv['name']} | {lv['cpu_ms_per_frame']:.1f} | {_ratio(lv, 'kept_relief')} | "
                         f"{_ratio(lv, 'image_texture_fast')} | {_ratio(lv, 'image_texture')} | "
                         f"{_fmt(lv.get('contact_area_err'), 3)} | "
                         f"{_fmt(lv['marker_err_mm'], 4)} | {_fmt(lv.get('marker_err_contact_mm'), 4)} | "
                         f"{_fmt(lv['force_err_n'], 4)} | {_fmt(lv['image_l1'], 3)} | {_fmt(lv['psnr'], 2)} | "
                         f"{_fmt(lv['ssim'], 4)} |")
        fabric_scenes = [sc for sc in s["scenes"] if any(
            p["scene"] == sc and p.get("kept_relief") is not None for lv in levels for p in lv.get("per_scene", []))]
        if fabric_scenes:
            lines += ["", "Texture per scene, kept relief / image texture through the fast shader / through the "
                      "level's own renderer (ratios to the reference; contact-area error in brackets):", "", "| scene | " + " | ".join(lv["name"] for lv in levels) + " |",
                      "|---" * (1 + len(levels)) + "|"]
            for sc in fabric_scenes:
                cells = []
                for lv in levels:
                    p = next((p for p in lv.get("per_scene", []) if p["scene"] == sc), {})
                    cells.append(f"{_fmt(p.get('kept_relief'), 2)} / {_fmt(p.get('image_texture_fast'), 2)} / "
                                 f"{_fmt(p.get('image_texture'), 2)} ({_fmt(p.get('contact_area_err'), 2)})")
                lines.append(f"| {sc} | " + " | ".join(cells) + " |")
        lines += ["", "Time per frame: end to end (process CPU, all threads; wall) and by stage (CPU ms; "
                  "pyrender's OpenGL threads count under optics):", "",
                  "| level | CPU ms/frame | wall ms/frame | " + " | ".join(STAGES) + " |",
                  "|---" * (3 + len(STAGES)) + "|"]
        for lv in levels:
            st = lv["stages_ms"]
            lines.append(f"| {lv['name']} | {lv['cpu_ms_per_frame']:.1f} | {_fmt(lv.get('wall_ms_per_frame'), 1)} | "
                         + " | ".join(f"{st.get(k, 0.0):.1f}" for k in STAGES) + " |")
        if r.get("shortcuts"):
            lines += ["", f"Shortcuts: the same scenes as {s.get('shortcut_frames', '?')}-frame sequences "
                      f"({s.get('shortcut_precontact', '?')} before contact, as in ViTac Cloth), one contact each; "
                      "differences against the run with all shortcuts:", "",
                      "| level | variant | CPU ms/frame | " + " | ".join(STAGES)
                      + " | max pixel diff (DN) | max marker diff (px) | max indentation diff (mm) |",
                      "|---" * (3 + len(STAGES) + 3) + "|"]
            for row in r["shortcuts"]:
                st = row["stages_ms"]
                lines.append(f"| {row['level']} | {row['variant']} | {row.get('cpu_ms_per_frame', float('nan')):.1f} | "
                             + " | ".join(f"{st.get(k, 0.0):.1f}" for k in STAGES)
                             + f" | {row['max_abs_dn']:.0f} | {row['max_marker_px']:.4f} | "
                               f"{row['max_indentation_mm']:.2e} |")
        lines.append("")
    return "\n".join(lines)


# Pareto panels: (key, axis label), each against CPU ms per frame; the ratios with their range over
# the fabric scenes as bars and the reference's 1 as a line (a level may keep too much texture as
# well as too little: the errors below count both).
PARETO_PANELS = (("kept_relief", "kept relief (ratio to reference; bars: scenes' range)"),
                 ("image_texture_fast", "image texture, fast shader (ratio; bars: range)"),
                 ("texture_err", "texture error: mean |1 - kept relief|"),
                 ("image_texture_fast_err", "image texture error, fast shader: mean |1 - ratio|"),
                 ("marker_err_contact_mm", "marker error in the contact (mm)"),
                 ("contact_area_err", "contact-area error (relative)"))


def pareto_plot(doc: dict, path: Path) -> None:
    """The texture ratios and the texture, image-texture, marker (in contact) and contact-area
    errors against CPU ms per frame (log), one point per level, one line per resolution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = _runs(doc)
    fig, axes = plt.subplots(3, 2, figsize=(11, 11))
    for ax, (key, label) in zip(axes.ravel(), PARETO_PANELS):
        ratio = key in ("kept_relief", "image_texture_fast")
        for j, r in enumerate(runs):
            w, h = r["settings"]["resolution"]
            levels = sorted((lv for lv in r["levels"] if lv.get(key) is not None), key=lambda lv: lv["cpu_ms_per_frame"])
            if not levels:
                continue
            xs = [lv["cpu_ms_per_frame"] for lv in levels]
            ys = [lv[key] for lv in levels]
            line, = ax.plot(xs, ys, "-o" if j % 2 == 0 else "--s", label=f"{w}x{h}")
            if ratio:
                lo = [y - lv[f"{key}_min"] for y, lv in zip(ys, levels)]
                hi = [lv[f"{key}_max"] - y for y, lv in zip(ys, levels)]
                ax.errorbar(xs, ys, yerr=[lo, hi], fmt="none", ecolor=line.get_color(), capsize=3, alpha=0.7)
            for i, lv in enumerate(levels):  # staggered labels: neighbouring levels may nearly coincide
                ax.annotate(lv["name"], (xs[i], ys[i]), textcoords="offset points",
                            xytext=(6, 6 if (i + j) % 2 == 0 else -12), fontsize=8)
        if ratio:
            ax.axhline(1.0, color="black", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("CPU ms per frame, end to end (log)")
        ax.set_ylabel(label, fontsize=9)
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
        if sum(1 for r in runs if any(lv.get(key) is not None for lv in r["levels"])) > 1:
            ax.legend(fontsize=8)
    scenes = runs[0]["settings"]["scenes"]
    fig.suptitle(f"gelsim fidelity levels against `{runs[0]['settings']['reference']}`, {len(scenes)} scenes "
                 "(errors: lower left is better)")
    fig.tight_layout()
    write_figure(path, fig, dpi=100)


def write_reports(doc: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write bench.json, bench.md and bench_pareto.png under ``out_dir``; returns their paths."""
    return _write_report(doc, out_dir, "bench", "bench_pareto", markdown_table, pareto_plot)


def _write_report(result: dict, out_dir: str | Path, stem: str, plot_stem: str, markdown, plot) -> dict[str, Path]:
    """``stem``.json, ``stem``.md (from ``markdown(result)``) and ``plot_stem``.png (``plot(result, path)``)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise GelsimError(f"--out {out} is a file; give a directory")
    paths = {"json": out / f"{stem}.json", "markdown": out / f"{stem}.md", "plot": out / f"{plot_stem}.png"}
    atomic_write_json(paths["json"], result)
    atomic_write_text(paths["markdown"], markdown(result))
    plot(result, paths["plot"])
    return paths


# --------------------------------------------------------------------------------------
# Convergence: one knob at a time
# --------------------------------------------------------------------------------------
# Errors the imprint knobs are judged by (texture first: what the data is for).
IMPRINT_METRICS = ("texture_err", "image_texture_err", "contact_area_err", "marker_err_contact_mm", "image_l1")
# Each sweep: knob, values from cheapest to dearest (the last is the converged value the others are
# compared with), the stage whose time is its cost, and the errors it reports (the first is plotted
# first). macro_cells: the two-scale model's coarse grid, 64 cells across the touched region by
# default (gelsim.fidelity), swept without the valley rule (SWEEP_HOLD), which
# macro_cells_per_valley sweeps on its own (it refines the grid only for objects with narrow envelope
# valleys: the corduroys); imprint_model: the old pyramid, the two-scale model, the elastic reference.
SWEEPS = (
    ("physics_dt_s", (0.004, 0.002, 0.001, 0.0005, 0.00025, 0.000125), "physics", ("force_err_n",)),
    ("imprint_scale", (0.25, 0.5, 0.75, 1.0), "imprint", IMPRINT_METRICS),
    ("macro_cells", (16, 32, 64, 128, 256), "imprint", IMPRINT_METRICS),
    ("macro_cells_per_valley", (0.0, 1.0, 2.0, 3.0, 4.0), "imprint", IMPRINT_METRICS),
    ("imprint_model", ("pyramid", "twoscale", "elastic"), "imprint", IMPRINT_METRICS),
    ("supersample", (1, 2, 3, 4), "optics", ("image_texture_err", "image_l1")),
    ("marker_model", ("gaussian", "elastic"), "markers", ("marker_err_contact_mm", "marker_err_mm")),
    ("render_backend", ("fast", "pyrender"), "optics", ("image_texture_err", "image_l1")),
)
# Knobs held at another value while a sweep runs: the grid alone, not its refinement for narrow valleys.
SWEEP_HOLD = {"macro_cells": {"macro_cells_per_valley": 0.0}}


def run_convergence(config: BenchConfig = BenchConfig(), base: str = "balanced", knobs: tuple[str, ...] = (),
                    progress: Callable[[str], None] | None = None) -> dict:
    """Sweep each knob of ``base`` alone over :data:`SWEEPS` on the bench's scenes.

    For every value: the cost (main-thread CPU ms per frame of the knob's stage, pyrender's GL
    threads counted under optics, and of the whole run) and the errors of :meth:`ErrorAcc.summary`
    against the sweep's last (finest) value on the same contact (the base level's; the physics
    sweep compares forces, each value with its own physics), with the texture ratios per fabric
    scene. The finest value's runs are the yardstick, kept in ``config.cache_dir`` if given.
    Returns ``{"base", "settings", "sweeps": [{"knob", "resolution", "stage", "metrics",
    "converged_value", "base_value", "points": [{"value", "stage_ms", "ms_per_frame", errors...,
    "per_scene": {scene: {"kept_relief", "image_texture", "contact_area_err"}}}]}]}``.
    """
    from .fabrics import load_catalog

    config.validate()
    configure_worker()
    say = progress or (lambda s: None)
    t_start = time.perf_counter()
    profile = _bench_profile(config)
    catalog = load_catalog()
    scenes = scenes_for(config)
    base_fid = get_fidelity(base)
    cache = RunCache(config.cache_dir)
    mmpp = profile.image.mm_per_px
    _warm_up(scenes[0], config, profile, catalog, [base_fid])
    sweeps = []
    contacts: dict[str, ContactFrames] = {}
    for knob, values, stage, metrics in SWEEPS:
        if knobs and knob not in knobs:
            continue
        fids = [dataclasses.replace(base_fid, name=f"{knob}={v}", **{**SWEEP_HOLD.get(knob, {}), knob: v})
                for v in values]
        finest = fids[-1]
        yard: dict[str, tuple[LevelRun, SceneTexture | None]] = {}
        points = []
        physics_only = knob == "physics_dt_s"
        outputs = () if physics_only else ("frames", "imprint", "markers")
        for fid in reversed(fids):
            renderer = None if physics_only else _make_renderer(profile, fid, config.seed)
            shader = None if physics_only else _fast_shader(profile, fid, config.seed)
            acc = ErrorAcc()
            secs = {s: 0.0 for s in STAGES}
            n = 0
            per_scene = {}
            try:
                for sc in scenes:
                    motion = scene_motion(sc, config)
                    if not physics_only and sc.name not in contacts:
                        _, surf = _prepare(sc, motion, profile, catalog)
                        contacts[sc.name] = simulate(motion, surf, profile, base_fid)
                    y = yard.get(sc.name)
                    run, tex = _measured_run(sc, motion, profile, fid, catalog=catalog, renderer=renderer,
                                             contact=None if physics_only else contacts[sc.name], config=config,
                                             yardstick=None if y is None else y[1],
                                             cache=cache if y is None else None, outputs=outputs, shader=shader)
                    if y is None:
                        yard[sc.name] = y = (run, tex)
                    sacc = ErrorAcc()
                    for a in (acc, sacc):
                        _accumulate(a, run, y[0], mmpp, sc.name, tex, y[1])
                    ss = sacc.summary()
                    if ss["kept_relief"] is not None:
                        per_scene[sc.name] = {k: ss[k] for k in ("kept_relief", "image_texture", "contact_area_err")}
                    for k, v in run.seconds.items():
                        secs[k] += v
                    n += motion.num_frames
            finally:
                for r in (renderer, shader):
                    if r is not None:
                        r.close()
            value = getattr(fid, knob)
            pt = {"value": value, "stage_ms": round(1000 * secs[stage] / n, 3),
                  "ms_per_frame": round(1000 * sum(secs.values()) / n, 2), **acc.summary(), "per_scene": per_scene}
            points.append(pt)
            say(f"{config.resolution[0]}x{config.resolution[1]} {knob}={value}: {pt['stage_ms']:.2f} ms ({stage}), "
                + ", ".join(f"{m} {pt[m]}" for m in metrics[:2]))
        points.reverse()
        sweeps.append({"knob": knob, "resolution": list(config.resolution), "stage": stage, "metrics": list(metrics),
                       "metric": metrics[0], "converged_value": getattr(finest, knob),
                       "base_value": getattr(base_fid, knob), "points": points})
    settings = _settings(config, scenes)
    settings["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    return {"base": base, "settings": settings, "sweeps": sweeps}


_METRIC_LABELS = {"force_err_n": "force err (N)", "texture_err": "texture err", "image_texture_err": "image texture err",
                  "contact_area_err": "contact area err", "marker_err_contact_mm": "marker err in contact (mm)",
                  "marker_err_mm": "marker err (mm)", "image_l1": "image L1 (DN)"}


def convergence_markdown(result: dict) -> str:
    s = result["settings"]
    lines = [f"Convergence from `{result['base']}`, one knob at a time: {len(s['scenes'])} scenes "
             f"({', '.join(s['scenes'])}); error against the knob's finest value on the same contact (in bold: "
             f"the base level's value); texture as kept relief / image texture ratios to the finest value "
             f"(geometric mean over the fabric scenes, then per fabric scene); load average {s['load_avg']}, "
             f"{s['date']}, {s.get('bench_seconds', '?')} s in all.", ""]
    for sw in result["sweeps"]:
        res = "x".join(str(v) for v in sw.get("resolution", s["resolution"]))
        metrics = sw.get("metrics", [sw["metric"]])
        fabric_scenes = sorted({sc for p in sw["points"] for sc in p.get("per_scene", {})})
        textured = any(p.get("kept_relief") is not None for p in sw["points"])
        lines += [f"**{sw['knob']}** at {res} px (cost: {sw['stage']} stage, CPU ms per frame)", "",
                  "| value | stage ms/frame | ms/frame | " + " | ".join(_METRIC_LABELS.get(m, m) for m in metrics)
                  + (" | kept relief / image texture | " + " | ".join(fabric_scenes) if textured else "") + " |",
                  "|---" * (3 + len(metrics) + ((1 + len(fabric_scenes)) if textured else 0)) + "|"]
        for p in sw["points"]:
            v = f"**{p['value']}**" if p["value"] == sw["base_value"] else f"{p['value']}"
            row = (f"| {v} | {p['stage_ms']:.2f} | {p['ms_per_frame']:.1f} | "
                   + " | ".join(_fmt(p.get(m), 4 if m.endswith("_mm") else 3) for m in metrics))
            if textured:
                row += f" | {_fmt(p.get('kept_relief'), 2)} / {_fmt(p.get('image_texture'), 2)} | " + " | ".join(
                    f"{_fmt(p['per_scene'].get(sc, {}).get('kept_relief'), 2)} / "
                    f"{_fmt(p['per_scene'].get(sc, {}).get('image_texture'), 2)}" for sc in fabric_scenes)
            lines.append(row + " |")
        lines.append("")
    return "\n".join(lines)


def convergence_plot(result: dict, path: Path) -> None:
    """One panel per sweep: its first two errors (second on the right axis) against its stage's CPU
    ms per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    sw = result["sweeps"]
    n = len(sw)
    cols = min(3, n)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows), squeeze=False)
    for ax, s in zip(axes.ravel(), sw):
        pts = s["points"]  # the last (finest) value has zero error by construction
        metrics = [m for m in s.get("metrics", [s["metric"]]) if any(p.get(m) is not None for p in pts)][:2]
        xs = [p["stage_ms"] for p in pts]
        for j, (m, a, colour) in enumerate(zip(metrics, (ax, ax.twinx() if len(metrics) > 1 else None),
                                               ("tab:blue", "tab:orange"))):
            ok = [(x, p[m], p) for x, p in zip(xs, pts) if p.get(m) is not None]
            a.plot([o[0] for o in ok], [o[1] for o in ok], "-o" if j == 0 else "--s", color=colour, ms=4)
            a.set_ylabel(_METRIC_LABELS.get(m, m), color=colour, fontsize=8)
            a.set_ylim(bottom=0)
            if j == 0:
                for x, y, p in ok:
                    style = dict(fontweight="bold") if p["value"] == s["base_value"] else {}
                    a.annotate(str(p["value"]), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8, **style)
        res = "x".join(str(v) for v in s.get("resolution", result["settings"]["resolution"]))
        ax.set_title(f"{s['knob']} (vs {s['converged_value']}), {res}", fontsize=10)
        ax.set_xlabel(f"{s['stage']} CPU ms per frame")
        if all(x > 0 for x in xs) and max(xs) > 5 * min(xs):
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(True, alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    write_figure(path, fig, dpi=100)


def write_convergence(result: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write convergence.json, convergence.md and convergence.png under ``out_dir``."""
    return _write_report(result, out_dir, "convergence", "convergence", convergence_markdown, convergence_plot)


# --------------------------------------------------------------------------------------
# Texture against pixels per period: the finest weaves
# --------------------------------------------------------------------------------------
# The catalog's finest textures (texture scale 0.11-0.36 mm), and a weave either side of 4 px per
# period at the fast level's half-scale 960x720 imprint grid (0.039 mm per px: 0.158 mm).
PITCH_FABRICS = (13, 44, 15, 30, 14, 17, 2, 4, 1, 8)
# Mid-range hand press (assets/motions.toml: 1-4 N).
PITCH_FORCE_N = 2.5
# (model, imprint scale) variants of the balanced level compared with its elastic model at full scale.
PITCH_VARIANTS = (("twoscale", 0.5), ("twoscale", 1.0), ("pyramid", 0.5), ("pyramid", 1.0))


def run_pitch_study(resolution: tuple[int, int], *, fabrics: tuple[int, ...] = PITCH_FABRICS,
                    force_n: float = PITCH_FORCE_N, variants=PITCH_VARIANTS, base: str = "balanced",
                    profile: str = "vitac", seed: int = 0, cache_dir: str = "",
                    progress: Callable[[str], None] | None = None) -> dict:
    """Each fabric pressed flat over the whole pad at ``force_n`` (N), as `gelsim texture` presses
    it, by each (imprint model, imprint scale) of ``variants`` and by the elastic model at full
    scale (the yardstick, kept in ``cache_dir``): the kept relief and image texture (fast renderer
    for all, so that only the imprint differs) in the fabric's pitch band over the elastic model's
    contact region, and the contact-area ratio, against the pixels per period of the fabric's
    texture scale and finest pitch on the imprint's grid. Returns ``{"settings", "rows"}``."""
    from .fabrics import heightfield, load_catalog
    from .gel import press, work_shape
    from .gel.twoscale import MIN_TEXTURE_PX
    from .optics import Renderer

    configure_worker()
    say = progress or (lambda s: None)
    t_start = time.perf_counter()
    prof = load_profile(profile).with_resolution(*resolution)
    catalog = load_catalog()
    base_fid = get_fidelity(base)
    elastic = dataclasses.replace(base_fid, name="elastic", imprint_model="elastic", imprint_scale=1.0)
    cache = RunCache(cache_dir)
    renderer = Renderer(prof, "fast", seed=seed)
    h, w = prof.shape
    mm = prof.image.mm_per_px
    rows = []
    try:
        for fid in fabrics:
            fab = catalog[fid]
            prot = heightfield(fab, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                               mm_per_px=mm, seed=seed, rotation_deg=fab.orientation_deg)
            kw = dict(force_n=force_n, **press_properties(fab))
            key = cache.key({"pitch": fid, "force_n": force_n, "resolution": list(resolution), "seed": seed,
                             "profile": hashlib.sha256(repr(prof).encode()).hexdigest(),
                             "fidelity": {**dataclasses.asdict(elastic), "name": ""}})
            hit = cache.load(key)
            if hit is None:
                c0 = _stage_clock()
                im = press(prot, prof, elastic, **kw)
                ref_depth, ref_mask, ref_area, ref_s = im.depth_mm, im.contact_mask, im.contact_area_mm2, _stage_clock() - c0
                cache.save(key, {"depth": ref_depth, "mask": ref_mask}, {"area_mm2": ref_area, "cpu_s": ref_s})
            else:
                ref_depth, ref_mask = hit["depth"], hit["mask"]
                ref_area, ref_s = hit["meta"]["area_mm2"], hit["meta"]["cpu_s"]
            band, close_px, rim_px = _texture_band(fab, prof)
            region = contact_region(ref_mask, close_px, rim_px)

            def texture(depth):
                clean, macro = texture_frames(renderer, depth, band, mm)
                return (band_rms(depth, region, band, mm),
                        band_rms(clean.astype(np.float32) - macro.astype(np.float32), region, band, mm))

            g0, i0 = texture(ref_depth)
            fine, _ = pitches_mm(fab)
            for model, scale in variants:
                fid_v = dataclasses.replace(base_fid, imprint_model=model, imprint_scale=scale)
                press(prot, prof, fid_v, **kw)  # warm: one-off tables and kernels
                c0 = _stage_clock()
                im = press(prot, prof, fid_v, **kw)
                cpu = _stage_clock() - c0
                g, i = texture(im.depth_mm)
                dx = mm * w / work_shape(prof, scale)[1]
                tex_px = min(fab.texture_mm, prof.gel.thickness_mm) / dx
                rows.append({"fabric": fid, "name": fab.name, "family": fab.family, "texture_mm": fab.texture_mm,
                             "finest_pitch_mm": fine, "model": model, "imprint_scale": scale,
                             "px_per_period": round(tex_px, 2), "px_per_finest_period": round(fine / dx, 2),
                             "texture_stage": model == "twoscale" and tex_px >= MIN_TEXTURE_PX,
                             "kept_relief": _r(g / g0 if g0 > 0 else None, 4),
                             "image_texture": _r(i / i0 if i0 > 0 else None, 4),
                             "contact_area_ratio": _r(im.contact_area_mm2 / ref_area if ref_area > 0 else None, 4),
                             "imprint_ms": round(1000 * cpu, 1), "elastic_s": round(ref_s, 1),
                             "elastic_gel_relief_um": round(1000 * g0, 3), "elastic_image_dn": round(i0, 3)})
                r = rows[-1]
                say(f"{resolution[0]}x{resolution[1]} fabric {fid} ({fab.name}, {fab.texture_mm} mm) {model} {scale}: "
                    f"{r['px_per_period']} px/period, kept {r['kept_relief']}, image {r['image_texture']}")
    finally:
        renderer.close()
    settings = {"resolution": list(resolution), "force_n": force_n, "base": base, "profile": profile, "seed": seed,
                "min_texture_px": MIN_TEXTURE_PX, "load_avg": _load_avg(),
                "date": datetime.datetime.now().isoformat(timespec="seconds"),
                "bench_seconds": round(time.perf_counter() - t_start, 1)}
    return {"settings": settings, "rows": rows}


def pitch_markdown(studies: list[dict]) -> str:
    lines = []
    for st in studies:
        s = st["settings"]
        lines += [f"Kept texture against pixels per period at {s['resolution'][0]}x{s['resolution'][1]}: each fabric "
                  f"pressed flat over the pad at {s['force_n']} N, ratios to the elastic model at full scale over its "
                  f"contact region (fast renderer for all); px/period: the texture scale (finest pitch) on the "
                  f"imprint grid; the two-scale model's texture stage needs {s['min_texture_px']:g}. Load average "
                  f"{s['load_avg']}, {s['date']}, {s['bench_seconds']} s.", "",
                  "| fabric | texture mm (finest) | model | scale | px/period (finest) | texture stage | kept relief "
                  "| image texture | contact area ratio | imprint ms |", "|---" * 10 + "|"]
        for r in st["rows"]:
            lines.append(f"| {r['fabric']} {r['name']} | {r['texture_mm']} ({r['finest_pitch_mm']}) | {r['model']} | "
                         f"{r['imprint_scale']} | {r['px_per_period']:.1f} ({r['px_per_finest_period']:.1f}) | "
                         f"{'yes' if r['texture_stage'] else 'no'} | {_fmt(r['kept_relief'], 2)} | "
                         f"{_fmt(r['image_texture'], 2)} | {_fmt(r['contact_area_ratio'], 2)} | {r['imprint_ms']:.0f} |")
        lines.append("")
    return "\n".join(lines)


def pitch_plot(studies: list[dict], path: Path) -> None:
    """Kept relief (left) and image texture (right) against px per period, one series per (model,
    scale) and resolution; the two-scale model's texture threshold dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    markers = {"twoscale": "o", "pyramid": "s"}
    for ax, key, label in ((axes[0], "kept_relief", "kept relief (gel, ratio to elastic)"),
                           (axes[1], "image_texture", "image texture (ratio to elastic)")):
        for st in studies:
            res = "x".join(str(v) for v in st["settings"]["resolution"])
            for model, scale in sorted({(r["model"], r["imprint_scale"]) for r in st["rows"]}):
                pts = sorted((r["px_per_period"], r[key]) for r in st["rows"]
                             if r["model"] == model and r["imprint_scale"] == scale and r[key] is not None)
                ax.plot(*zip(*pts), markers.get(model, "^") + ("-" if scale == 1.0 else ":"), ms=4,
                        label=f"{model} {scale} @ {res}")
        ax.axvline(studies[0]["settings"]["min_texture_px"], color="grey", ls="--", lw=1)
        ax.axhline(1.0, color="black", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("texture period in imprint-grid px (log)")
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle("Fine weaves: texture kept against the imprint grid's pixels per period")
    fig.tight_layout()
    write_figure(path, fig, dpi=100)
