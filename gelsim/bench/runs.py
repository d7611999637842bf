"""Running one fidelity level on one scene, timed by stage (:func:`run_level`): a stream of frame records
(:func:`gelsim.sequence.render_sequence`) into the bench's sinks (a throw-away video, the frames, the
imprints)."""
from __future__ import annotations

import contextlib
import datetime
import os
import platform
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..contact import ContactFrames, simulate
from ..fidelity import Fidelity
from ..motion import Motion
from ..sensor import SensorProfile
from ..sequence import SequenceOptions, render_sequence
from ..sinks import ImprintCapture, KeepFrames, VideoSink, drain
from ..stream import stage_clock
from .scenes import BenchConfig, Scene, prepare_scene, scene_motion

#: The stages a run is timed by: the main thread's CPU time (:data:`gelsim.stream.stage_clock`, as a
#: generation worker is timed: one thread on one core; wall time would count the other processes' turns
#: on a shared machine). The end-to-end figure is the process's CPU time, which also counts helper
#: threads (OpenGL's).
TIMED_STAGES = ("fabric", "physics", "imprint", "markers", "labels", "optics", "encode")


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


def run_level(scene: Scene, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *, catalog,
              renderer=None, contact: ContactFrames | None = None, shortcuts: bool = True,
              outputs=("frames", "imprint", "markers"), encode: str | None = "h264",
              sensor_seed: int = 0, tmpdir: str | None = None, keep_imprints: bool = False) -> LevelRun:
    """Run ``fidelity`` on one scene: its own physics (timed; gives its forces), then imprint,
    markers and optics on ``contact`` (default: its own), then encoding to a throw-away video.
    Frames are kept for comparison; with ``keep_imprints`` also the imprint of every frame that
    pressed (``LevelRun.imprints``, an :class:`gelsim.sinks.ImprintCapture` of the sequence's records)."""
    from ..video import video_path

    c0, w0, th0 = time.process_time(), time.perf_counter(), stage_clock()
    t0 = th0
    obj, surface = prepare_scene(scene, motion, profile, catalog)
    fab_s = stage_clock() - t0
    t0 = stage_clock()
    own = simulate(motion, surface, profile, fidelity)
    phys_s = stage_clock() - t0
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
    secs = {s: 0.0 for s in TIMED_STAGES}
    secs.update(seconds)
    secs["fabric"] += fab_s
    secs["physics"] = phys_s
    # CPU of the process's other threads: OpenGL's (llvmpipe) under pyrender, which the main
    # thread's clock does not see; the encoder and OpenCV run on the main thread (one core). Only
    # when frames were rendered: idle threads of other libraries (a torch pool) tick otherwise.
    if "frames" in outputs:
        secs["optics"] += max(0.0, (time.process_time() - c0) - (stage_clock() - th0))
    labels["normal_force_n"] = own.normal_force_n  # this level's own physics
    fr = np.stack(frames.frames) if frames.frames and frames.frames[0] is not None else None
    run = LevelRun(fr, labels, use, secs, time.process_time() - c0, time.perf_counter() - w0)
    if keep_imprints:
        run.imprints = capture.imprints
    return run


def make_renderer(profile, fid: Fidelity, sensor_seed: int):
    from ..optics import Renderer

    return Renderer(profile, fid.render_backend, supersample=fid.supersample, seed=sensor_seed)


def warm_up(scene: Scene, config: BenchConfig, profile: SensorProfile, catalog, fids: list[Fidelity]) -> None:
    """Run ``scene`` once at each of ``fids``, untimed: the first run in a process pays one-off costs
    (tables read, libraries initialised: measured 4x a fast level's frame at 160x120), which would
    otherwise land on whichever level runs first."""
    motion = scene_motion(scene, config)
    for fid in fids:
        renderer = make_renderer(profile, fid, config.seed)
        try:
            run_level(scene, motion, profile, fid, catalog=catalog, renderer=renderer, encode=config.video_format,
                      sensor_seed=config.seed)
        finally:
            renderer.close()


def load_avg() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def bench_settings(config: BenchConfig, scenes: list[Scene]) -> dict:
    return {"resolution": list(config.resolution), "frames": config.frames, "precontact": config.precontact,
            "scenes": [s.name for s in scenes], "reference": config.reference, "profile": config.profile,
            "seed": config.seed, "video_format": config.video_format, "cpu_count": os.cpu_count(),
            "shortcut_frames": config.shortcut_frames, "shortcut_precontact": config.shortcut_precontact,
            "load_avg": load_avg(), "python": platform.python_version(),
            "date": datetime.datetime.now().isoformat(timespec="seconds")}
