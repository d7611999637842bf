"""``gelsim bench``: time per frame and error of each fidelity level, and the convergence study.

:func:`run_bench` runs every level on the same fixed scenes (a pressed sphere and a few
catalog fabrics under each action) and reports, per level, the wall time per frame of
each stage (fabric, physics, imprint, markers, optics, encode) and end to end, and the
error against the ``reference`` level on the same scenes:

* image L1 (DN, 0-255), PSNR (dB, from the MSE pooled over frames) and SSIM (Wang et al.
  2004: 11x11 Gaussian window, sigma 1.5, per RGB channel) over the *in-contact* frames
  (pre-contact frames show the flat gel and would only dilute the numbers);
* marker position error, mm: mean distance between a level's and the reference's marker
  centres over the in-contact frames;
* force error, N: mean |normal force| difference over all frames, each level with its own
  physics timestep.

So that image differences measure the image knobs, every level renders on the *reference*
level's contact simulation (same positions, forces, shear and twist); each level's own
physics run is timed and gives the force error. Same scenes, seeds and camera noise for
every level. :func:`run_shortcut_study` times the balanced level with and without the
shortcuts of :mod:`gelsim.sequence` and with labels only, and reports the largest
difference the shortcuts make. :func:`run_convergence` sweeps one knob at a time.

Reports: :func:`write_reports` writes ``bench.json``, ``bench.md`` and ``bench_pareto.png``;
:func:`write_convergence` writes ``convergence.json``, ``convergence.md`` and
``convergence.png``.
"""
from __future__ import annotations

import dataclasses
import datetime
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

from .contact import ContactFrames, Surface, simulate
from .errors import GelsimError
from .runtime import configure_worker
from .fidelity import Fidelity, fidelity_levels, get_fidelity
from .motion import ACTIONS, Motion, sample_motion
from .sensor import SensorProfile, load_profile
from .sequence import PHYSICS_MM_PER_PX, FabricPatch, SequenceOutput, render_sequence

STAGES = ("fabric", "physics", "imprint", "markers", "optics", "encode")
# Default scene set, sized so that the default bench (all three levels, the reference's
# pyrender and elastic imprint included) runs in under 5 minutes on 2 shared cores.
DEFAULT_RESOLUTION = (320, 240)
DEFAULT_FRAMES = 6
DEFAULT_PRECONTACT = 1
# The shortcut study runs ViTac-like sequences instead (25-36 frames, 2-8 before contact): what
# the shortcuts save depends on the share of pre-contact frames, so it is measured at that share.
SHORTCUT_FRAMES = 30
SHORTCUT_PRECONTACT = 5
# A plain-weave cotton poplin (fine relief) and a corduroy (coarse pile ridges): two ends of the
# catalog. More fabrics (e.g. 55, an interlock knit) cost the reference level about 20 s per
# sequence: its elastic imprint takes seconds per frame on a fabric that touches the whole pad.
DEFAULT_FABRICS = (1, 64)
# The sphere scene: a 10 mm ball pressed with 0.5 N indents the vitac gel about 0.4 mm
# (elastic model), well inside its 1 mm travel, with a contact about 4 mm across.
SPHERE_DIAMETER_MM = 10.0
SPHERE_FORCE_N = 0.5
SPHERE_FRICTION = 0.6  # assumed: a smooth plastic ball on silicone
# SSIM constants of Wang et al. (2004) for 8-bit images.
_SSIM_C1 = (0.01 * 255) ** 2
_SSIM_C2 = (0.03 * 255) ** 2
_SSIM_SIGMA = 1.5


# --------------------------------------------------------------------------------------
# Image metrics
# --------------------------------------------------------------------------------------
def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two uint8 ``(H, W[, C])`` images (Gaussian window, per channel), 1 = identical."""
    if a.shape != b.shape:
        raise GelsimError(f"images differ in shape {a.shape} vs {b.shape}; compare frames of one size")
    x = a.astype(np.float64)
    y = b.astype(np.float64)

    def blur(img):
        return cv2.GaussianBlur(img, (11, 11), _SSIM_SIGMA, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    num = (2 * mx * my + _SSIM_C1) * (2 * sxy + _SSIM_C2)
    den = (mx * mx + my * my + _SSIM_C1) * (sxx + syy + _SSIM_C2)
    return float(np.mean(num / den))


def psnr_from_mse(mse: float) -> float | None:
    """PSNR in dB for 8-bit images; None for identical images (infinite)."""
    return None if mse <= 0 else 10.0 * math.log10(255.0 ** 2 / mse)


@dataclass
class ErrorAcc:
    """Pools frame errors over scenes: sums of L1, squared error, SSIM and marker distance."""
    l1_sum: float = 0.0
    se_sum: float = 0.0
    px: int = 0
    ssim_sum: float = 0.0
    frames: int = 0
    marker_sum_mm: float = 0.0
    marker_n: int = 0
    force_sum_n: float = 0.0
    force_n: int = 0

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

    def add_forces(self, f: np.ndarray, ref: np.ndarray) -> None:
        self.force_sum_n += float(np.abs(np.asarray(f, np.float64) - ref).sum())
        self.force_n += len(f)

    def summary(self) -> dict:
        mse = self.se_sum / self.px if self.px else 0.0
        r = lambda v, n: round(v, n) if v is not None else None  # noqa: E731
        # None: not measured (no frames or markers compared); PSNR also None for identical images
        return {"image_l1": r(self.l1_sum / self.px if self.px else None, 4),
                "psnr": r(psnr_from_mse(mse) if self.px else None, 3),
                "ssim": r(self.ssim_sum / self.frames if self.frames else None, 5),
                "marker_err_mm": r(self.marker_sum_mm / self.marker_n if self.marker_n else None, 6),
                "force_err_n": r(self.force_sum_n / self.force_n if self.force_n else 0.0, 5)}


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
    """The bench's scenes, in a fixed order; seeds derive from ``config.seed``."""
    out = []
    k = 0
    if config.sphere:
        out.append(Scene("sphere-press", "sphere", "press", config.seed * 1000 + k))
        k += 1
    for fid in config.fabrics:
        for a in config.actions:
            out.append(Scene(f"fabric{fid}-{a}", int(fid), a, config.seed * 1000 + k))
            k += 1
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


def sphere_heights(diameter_mm: float, x0_mm: float, y0_mm: float, w: int, h: int, mm_per_px: float) -> np.ndarray:
    """Heightfield (mm, float32 (h, w)) of a ball of ``diameter_mm`` resting on a plane at the origin."""
    r = diameter_mm / 2.0
    x = x0_mm + np.arange(w) * mm_per_px
    y = y0_mm + np.arange(h) * mm_per_px
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    return np.sqrt(np.maximum(r * r - r2, 0.0)).astype(np.float32)


def sphere_scene(motion: Motion, profile: SensorProfile, diameter_mm: float = SPHERE_DIAMETER_MM
                 ) -> tuple[Surface, FabricPatch]:
    """Physics surface and image-resolution patch of a rigid ball under the sensor's travel."""
    xmin, ymin, xmax, ymax = motion.travel_bounds_mm()
    fw, fh = profile.field_mm
    rad = 0.5 * math.hypot(fw, fh) + 2 * PHYSICS_MM_PER_PX
    out = []
    for p in (PHYSICS_MM_PER_PX, profile.image.mm_per_px):
        x0 = math.floor((xmin - rad) / p) * p
        y0 = math.floor((ymin - rad) / p) * p
        w = int(math.ceil((xmax + rad - x0) / p)) + 1
        h = int(math.ceil((ymax + rad - y0) / p)) + 1
        out.append((sphere_heights(diameter_mm, x0, y0, w, h, p), (x0, y0), p))
    (hs, os_, ps), (hp, op, pp) = out
    return Surface(hs, ps, os_, SPHERE_FRICTION), FabricPatch(hp, op, pp)


# --------------------------------------------------------------------------------------
# Running one level on one scene
# --------------------------------------------------------------------------------------
@dataclass
class LevelRun:
    """One level on one scene: frames (uint8 (T, H, W, 3) or None), labels, stage seconds, CPU s."""
    frames: np.ndarray | None
    labels: dict
    contact: ContactFrames
    seconds: dict[str, float] = field(default_factory=dict)
    cpu_s: float = 0.0


def _prepare(scene: Scene, motion: Motion, profile: SensorProfile, catalog):
    """(fabric or None, surface, patch or None, fabric seconds)."""
    t0 = time.perf_counter()
    if scene.object == "sphere":
        from .scene import Sphere

        surface, patch = sphere_scene(motion, profile)
        return Sphere(SPHERE_DIAMETER_MM, friction=SPHERE_FRICTION), surface, patch, time.perf_counter() - t0
    fabric = catalog[int(scene.object)]
    surface = Surface.from_fabric(fabric, motion, profile, mm_per_px=PHYSICS_MM_PER_PX, seed=scene.seed)
    return fabric, surface, None, time.perf_counter() - t0


def run_level(scene: Scene, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *, catalog,
              renderer=None, contact: ContactFrames | None = None, shortcuts: bool = True,
              outputs=("frames", "imprint", "markers"), encode: str | None = "h264",
              sensor_seed: int = 0, tmpdir: str | None = None) -> LevelRun:
    """Run ``fidelity`` on one scene: its own physics (timed; gives its forces), then imprint,
    markers and optics on ``contact`` (default: its own), then encoding to a throw-away video.
    Frames are kept for comparison."""
    from .video import VideoWriter, video_path

    c0 = time.process_time()
    fabric, surface, patch, fab_s = _prepare(scene, motion, profile, catalog)
    t0 = time.perf_counter()
    own = simulate(motion, surface, profile, fidelity)
    phys_s = time.perf_counter() - t0
    use = contact if contact is not None else own
    out = SequenceOutput({}, {})
    frames = []
    enc_s = 0.0
    gen = render_sequence(fabric, motion, profile, fidelity, seed=scene.seed, renderer=renderer,
                          sensor_seed=sensor_seed, out=out, shortcuts=shortcuts, outputs=outputs,
                          contact=use, surface=surface, patch=patch)
    if encode and "frames" in outputs:
        with tempfile.TemporaryDirectory(dir=tmpdir) as td:
            with VideoWriter(video_path(Path(td) / "bench", encode), fmt=encode,
                             fps=profile.image.fps_hz) as writer:
                for frame in gen:
                    te = time.perf_counter()
                    writer.write(frame)
                    enc_s += time.perf_counter() - te
                    frames.append(frame)
                te = time.perf_counter()
            enc_s += time.perf_counter() - te  # closing flushes the encoder
    else:
        frames = [f for f in gen]
    secs = {s: 0.0 for s in STAGES}
    secs.update(out.timings_s)
    secs["fabric"] += fab_s
    secs["physics"] = phys_s
    secs["encode"] = enc_s
    labels = dict(out.labels)
    labels["normal_force_n"] = own.normal_force_n  # this level's own physics
    fr = np.stack(frames) if frames and frames[0] is not None else None
    return LevelRun(fr, labels, use, secs, time.process_time() - c0)


def _make_renderer(profile, fid: Fidelity, sensor_seed: int):
    from .optics import Renderer

    return Renderer(profile, fid.render_backend, supersample=fid.supersample, seed=sensor_seed)


def _bench_profile(config: BenchConfig) -> SensorProfile:
    return load_profile(config.profile).with_resolution(*config.resolution)


def _settings(config: BenchConfig, scenes: list[Scene]) -> dict:
    try:
        load = [round(v, 2) for v in os.getloadavg()]
    except OSError:
        load = None
    return {"resolution": list(config.resolution), "frames": config.frames, "precontact": config.precontact,
            "scenes": [s.name for s in scenes], "reference": config.reference, "profile": config.profile,
            "seed": config.seed, "video_format": config.video_format, "cpu_count": os.cpu_count(),
            "shortcut_frames": config.shortcut_frames, "shortcut_precontact": config.shortcut_precontact,
            "load_avg": load, "python": platform.python_version(),
            "date": datetime.datetime.now().isoformat(timespec="seconds")}


def run_bench(config: BenchConfig = BenchConfig(), progress: Callable[[str], None] | None = None) -> dict:
    """Run every level on every scene; returns ``{"levels": [...], "settings", "shortcuts", "scenes"}``.

    Each level entry: name, ms_per_frame (wall, end to end), cpu_ms_per_frame, stages_ms
    (wall ms per frame by stage), image_l1 (DN), psnr (dB; None for the reference itself),
    ssim, marker_err_mm, force_err_n, and the level's knobs.
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
    ref_runs: dict[str, LevelRun] = {}
    results = {}
    mmpp = profile.image.mm_per_px
    for name in order:
        fid = get_fidelity(name)
        renderer = _make_renderer(profile, fid, config.seed)
        acc = ErrorAcc()
        secs = {s: 0.0 for s in STAGES}
        cpu = 0.0
        nframes = 0
        per_scene = []
        try:
            for sc in scenes:
                motion = scene_motion(sc, config)
                ref = ref_runs.get(sc.name)
                run = run_level(sc, motion, profile, fid, catalog=catalog, renderer=renderer,
                                contact=None if ref is None else ref.contact, encode=config.video_format,
                                sensor_seed=config.seed)
                if ref is None:
                    ref_runs[sc.name] = ref = run
                sacc = ErrorAcc()
                for a in (acc, sacc):
                    _accumulate(a, run, ref, mmpp)
                for k, v in run.seconds.items():
                    secs[k] += v
                cpu += run.cpu_s
                nframes += motion.num_frames
                per_scene.append({"scene": sc.name, **sacc.summary(),
                                  "ms_per_frame": round(1000 * sum(run.seconds.values()) / motion.num_frames, 2)})
                say(f"{name:>10} {sc.name:<18} {per_scene[-1]['ms_per_frame']:8.1f} ms/frame")
        finally:
            renderer.close()
        stages_ms = {k: round(1000 * v / nframes, 3) for k, v in secs.items()}
        results[name] = {"name": name, "ms_per_frame": round(sum(stages_ms.values()), 2),
                         "cpu_ms_per_frame": round(1000 * cpu / nframes, 2), "stages_ms": stages_ms,
                         **acc.summary(), "knobs": _knobs(fid), "per_scene": per_scene}
    out = {"levels": [results[n] for n in levels], "settings": _settings(config, scenes)}
    if config.shortcut_level:
        out["shortcuts"] = run_shortcut_study(config, profile, catalog, scenes, progress=say)
    out["settings"]["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    out["settings"]["bench_cpu_seconds"] = round(time.process_time() - c_start, 1)
    return out


def _knobs(fid: Fidelity) -> dict:
    d = dataclasses.asdict(fid)
    d.pop("name")
    d.pop("est_ms_per_frame_vga")
    return d


def _accumulate(acc: ErrorAcc, run: LevelRun, ref: LevelRun, mmpp: float) -> None:
    touch = np.asarray(ref.contact.in_contact, bool)
    if run.frames is not None and ref.frames is not None:
        for i in np.flatnonzero(touch):
            acc.add_frame(run.frames[i], ref.frames[i])
    if "markers_xy_px" in run.labels and "markers_xy_px" in ref.labels:
        acc.add_markers(run.labels["markers_xy_px"][touch], ref.labels["markers_xy_px"][touch], mmpp)
    acc.add_forces(run.labels["normal_force_n"], np.asarray(ref.labels["normal_force_n"], np.float64))


def run_shortcut_study(config: BenchConfig, profile, catalog, scenes, *, progress=None) -> list[dict]:
    """The shortcut level with all shortcuts, without them, and with labels only, on the bench's
    scenes as ViTac-like sequences (``config.shortcut_frames`` frames, ``shortcut_precontact``
    before contact), all three on one contact simulation per scene.

    Each row: variant, ms_per_frame, cpu_ms_per_frame, stages_ms, and the largest difference
    from the run with all shortcuts: max_abs_dn (frame pixels), max_marker_px,
    max_indentation_mm.
    """
    say = progress or (lambda s: None)
    fid = get_fidelity(config.shortcut_level)
    long = dataclasses.replace(config, frames=config.shortcut_frames, precontact=config.shortcut_precontact)
    contacts = {}
    for sc in scenes:
        motion = scene_motion(sc, long)
        _, surface, _, _ = _prepare(sc, motion, profile, catalog)
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
        say(f"{fid.name:>10} {label:<18} {rows[-1]['ms_per_frame']:8.1f} ms/frame")
    return rows


# --------------------------------------------------------------------------------------
# Reports
# --------------------------------------------------------------------------------------
def _fmt(v, nd: int) -> str:
    if v is None:
        return "-"
    return f"{v:.{nd}f}"


def markdown_table(result: dict) -> str:
    """The bench result as Markdown: settings, the level table and the shortcut table."""
    s = result["settings"]
    w, h = s["resolution"]
    lines = [f"Bench: {w}x{h} px, {len(s['scenes'])} scenes ({', '.join(s['scenes'])}), {s['frames']} frames each "
             f"({s['precontact']} before contact), errors against `{s['reference']}` on the same contact; "
             f"{s['cpu_count']} CPUs, load average {s['load_avg']}, {s['date']}, "
             f"{s.get('bench_seconds', '?')} s in all"
             + (f" ({s['bench_cpu_seconds']} s of CPU). " if "bench_cpu_seconds" in s else ". ")
             +
             "Times are wall ms per frame by stage; CPU ms/frame is the steadier figure on a shared machine.", "",
             "| level | ms/frame | CPU ms/frame | " + " | ".join(STAGES) + " | image L1 (DN) | PSNR (dB) | SSIM "
             "| marker err (mm) | force err (N) |",
             "|---" * (5 + len(STAGES) + 3) + "|"]
    for lv in result["levels"]:
        st = lv["stages_ms"]
        lines.append(f"| {lv['name']} | {lv['ms_per_frame']:.1f} | {lv['cpu_ms_per_frame']:.1f} | "
                     + " | ".join(f"{st.get(k, 0.0):.1f}" for k in STAGES)
                     + f" | {_fmt(lv['image_l1'], 3)} | {_fmt(lv['psnr'], 2)} | {_fmt(lv['ssim'], 4)} | "
                       f"{_fmt(lv['marker_err_mm'], 4)} | {_fmt(lv['force_err_n'], 4)} |")
    if result.get("shortcuts"):
        lines += ["", f"Shortcuts: the same scenes as {s.get('shortcut_frames', '?')}-frame sequences "
                  f"({s.get('shortcut_precontact', '?')} before contact, as in ViTac Cloth), one contact each; "
                  "differences against the run with all shortcuts:", "",
                  "| level | variant | ms/frame | CPU ms/frame | " + " | ".join(STAGES)
                  + " | max pixel diff (DN) | max marker diff (px) | max indentation diff (mm) |",
                  "|---" * (4 + len(STAGES) + 3) + "|"]
        for r in result["shortcuts"]:
            st = r["stages_ms"]
            lines.append(f"| {r['level']} | {r['variant']} | {r['ms_per_frame']:.1f} | "
                         f"{r.get('cpu_ms_per_frame', float('nan')):.1f} | "
                         + " | ".join(f"{st.get(k, 0.0):.1f}" for k in STAGES)
                         + f" | {r['max_abs_dn']:.0f} | {r['max_marker_px']:.4f} | {r['max_indentation_mm']:.2e} |")
    return "\n".join(lines) + "\n"


def pareto_plot(result: dict, path: Path) -> None:
    """Image L1 and marker error against CPU ms per frame (log; steadier than wall time on a
    shared machine), one point per level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    levels = sorted(result["levels"], key=lambda lv: lv["cpu_ms_per_frame"])
    for ax, key, label in ((axes[0], "image_l1", "image L1 vs reference (DN)"),
                           (axes[1], "marker_err_mm", "marker error vs reference (mm)")):
        xs = [lv["cpu_ms_per_frame"] for lv in levels]
        ys = [lv[key] for lv in levels]
        ax.plot(xs, ys, "-o", color="tab:blue")
        for i, lv in enumerate(levels):  # staggered labels: neighbouring levels may nearly coincide
            ax.annotate(lv["name"], (lv["cpu_ms_per_frame"], lv[key]), textcoords="offset points",
                        xytext=(8, 8 if i % 2 == 0 else -14))
        ax.set_xscale("log")
        ax.set_xlabel("CPU ms per frame, end to end (log)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    s = result["settings"]
    fig.suptitle(f"gelsim fidelity levels at {s['resolution'][0]}x{s['resolution'][1]}, "
                 f"{len(s['scenes'])} scenes (lower left is better)")
    fig.tight_layout()
    _save_fig(fig, path)
    plt.close(fig)


def _save_fig(fig, path: Path) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}.png")
    fig.savefig(tmp, dpi=100)
    os.replace(tmp, path)


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_reports(result: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write bench.json, bench.md and bench_pareto.png under ``out_dir``; returns their paths."""
    return _write_report(result, out_dir, "bench", "bench_pareto", markdown_table, pareto_plot)


def _write_report(result: dict, out_dir: str | Path, stem: str, plot_stem: str, markdown, plot) -> dict[str, Path]:
    """``stem``.json, ``stem``.md (from ``markdown(result)``) and ``plot_stem``.png (``plot(result, path)``)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise GelsimError(f"--out {out} is a file; give a directory")
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / f"{stem}.json", "markdown": out / f"{stem}.md", "plot": out / f"{plot_stem}.png"}
    _write_text(paths["json"], json.dumps(result, indent=1) + "\n")
    _write_text(paths["markdown"], markdown(result))
    plot(result, paths["plot"])
    return paths


# --------------------------------------------------------------------------------------
# Convergence: one knob at a time
# --------------------------------------------------------------------------------------
# Each sweep: knob, values from cheapest to dearest (the last is the converged value the
# others are compared with), the stage whose time is its cost, and the error it reports.
SWEEPS = (
    ("physics_dt_s", (0.004, 0.002, 0.001, 0.0005, 0.00025, 0.000125), "physics", "force_err_n"),
    ("imprint_scale", (0.25, 0.5, 0.75, 1.0), "imprint", "image_l1"),
    ("imprint_model", ("pyramid", "elastic"), "imprint", "image_l1"),
    ("supersample", (1, 2, 3, 4), "optics", "image_l1"),
    ("marker_model", ("gaussian", "elastic"), "markers", "marker_err_mm"),
    ("render_backend", ("fast", "pyrender"), "optics", "image_l1"),
)


def run_convergence(config: BenchConfig = BenchConfig(), base: str = "balanced", knobs: tuple[str, ...] = (),
                    progress: Callable[[str], None] | None = None) -> dict:
    """Sweep each knob of ``base`` alone over :data:`SWEEPS` on the bench's scenes.

    For every value: the cost (wall ms per frame of the knob's stage and end to end) and the
    error against the sweep's last (finest) value on the same contact (the finest timestep's
    for the physics sweep, whose error is the force error). Returns ``{"base", "settings",
    "sweeps": [{"knob", "stage", "metric", "points": [{"value", "stage_ms", "ms_per_frame",
    image_l1, psnr, ssim, marker_err_mm, force_err_n}]}]}``.
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
    mmpp = profile.image.mm_per_px
    sweeps = []
    contacts: dict[str, ContactFrames] = {}
    for knob, values, stage, metric in SWEEPS:
        if knobs and knob not in knobs:
            continue
        fids = [dataclasses.replace(base_fid, name=f"{knob}={v}", **{knob: v}) for v in values]
        finest = fids[-1]
        refs: dict[str, LevelRun] = {}
        points = []
        for fid in reversed(fids):
            physics_only = knob == "physics_dt_s"
            renderer = None if physics_only else _make_renderer(profile, fid, config.seed)
            acc = ErrorAcc()
            secs = {s: 0.0 for s in STAGES}
            n = 0
            try:
                for sc in scenes:
                    motion = scene_motion(sc, config)
                    if not physics_only and sc.name not in contacts:
                        fab, surf, _, _ = _prepare(sc, motion, profile, catalog)
                        contacts[sc.name] = simulate(motion, surf, profile, base_fid)
                    run = run_level(sc, motion, profile, fid, catalog=catalog, renderer=renderer,
                                    contact=None if physics_only else contacts[sc.name],
                                    outputs=() if physics_only else ("frames", "imprint", "markers"),
                                    encode=None, sensor_seed=config.seed)
                    ref = refs.setdefault(sc.name, run)
                    _accumulate(acc, run, ref, mmpp)
                    for k, v in run.seconds.items():
                        secs[k] += v
                    n += motion.num_frames
            finally:
                if renderer is not None:
                    renderer.close()
            value = getattr(fid, knob)
            pt = {"value": value, "stage_ms": round(1000 * secs[stage] / n, 3),
                  "ms_per_frame": round(1000 * sum(secs.values()) / n, 2), **acc.summary()}
            points.append(pt)
            say(f"{knob}={value}: {pt['stage_ms']:.2f} ms ({stage}), {metric} {pt[metric]}")
        points.reverse()
        sweeps.append({"knob": knob, "resolution": list(config.resolution), "stage": stage, "metric": metric,
                       "converged_value": getattr(finest, knob),
                       "base_value": getattr(base_fid, knob), "points": points})
    settings = _settings(config, scenes)
    settings["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    return {"base": base, "settings": settings, "sweeps": sweeps}


def convergence_markdown(result: dict) -> str:
    s = result["settings"]
    lines = [f"Convergence from `{result['base']}`, one knob at a time: {s['resolution'][0]}x{s['resolution'][1]} px, "
             f"{len(s['scenes'])} scenes, {s['frames']} frames each; error against the knob's finest value "
             f"(in bold: the base level's value); load average {s['load_avg']}, {s['date']}.", ""]
    for sw in result["sweeps"]:
        res = "x".join(str(v) for v in sw.get("resolution", s["resolution"]))
        lines += [f"**{sw['knob']}** at {res} px (cost: {sw['stage']} stage; error: {sw['metric']})", "",
                  "| value | stage ms/frame | ms/frame | image L1 (DN) | PSNR (dB) | SSIM | marker err (mm) "
                  "| force err (N) |", "|---" * 8 + "|"]
        for p in sw["points"]:
            v = f"**{p['value']}**" if p["value"] == sw["base_value"] else f"{p['value']}"
            lines.append(f"| {v} | {p['stage_ms']:.2f} | {p['ms_per_frame']:.1f} | {_fmt(p['image_l1'], 3)} | "
                         f"{_fmt(p['psnr'], 2)} | {_fmt(p['ssim'], 4)} | {_fmt(p['marker_err_mm'], 5)} | "
                         f"{_fmt(p['force_err_n'], 5)} |")
        lines.append("")
    return "\n".join(lines)


def convergence_plot(result: dict, path: Path) -> None:
    """One panel per knob: its error against its stage's ms per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    sw = result["sweeps"]
    n = len(sw)
    cols = min(3, n)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, s in zip(axes.ravel(), sw):
        pts = s["points"]  # the last (finest) value has zero error by construction
        xs = [p["stage_ms"] for p in pts]
        ys = [p[s["metric"]] for p in pts]
        ax.plot(xs, ys, "-o")
        for p in pts:
            style = dict(fontweight="bold") if p["value"] == s["base_value"] else {}
            ax.annotate(str(p["value"]), (p["stage_ms"], p[s["metric"]]), textcoords="offset points",
                        xytext=(4, 4), fontsize=8, **style)
        res = "x".join(str(v) for v in s.get("resolution", result["settings"]["resolution"]))
        ax.set_title(f"{s['knob']} (vs {s['converged_value']}), {res}", fontsize=10)
        ax.set_xlabel(f"{s['stage']} ms per frame")
        ax.set_ylabel(s["metric"])
        if all(x > 0 for x in xs) and max(xs) > 5 * min(xs):
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(True, alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    _save_fig(fig, path)
    plt.close(fig)


def write_convergence(result: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write convergence.json, convergence.md and convergence.png under ``out_dir``."""
    return _write_report(result, out_dir, "convergence", "convergence", convergence_markdown, convergence_plot)
