"""A nuisance copy of a `gelsim generate` dataset, for the robustness benchmark (docs/nuisance.md).

Until the nuisance stages are wired into the frame stream (issue 41's refactor), this applies them to a
finished dataset's decoded frames, sequence by sequence:

* ``fibres``: the sequence's fibres (drawn from its seed) dent the gel at each frame's gap (before contact
  from the approach, in contact from the labels' indentation, after it from the lift), and the dents'
  shading change (the dataset's renderer, flat gel + dents, minus the flat gel) is added to the frame;
* ``exposure``, ``white_balance``: the camera controllers meter each frame against the flat gel (with
  markers) and its per-channel gains multiply it;
then the frame is rounded to uint8 and encoded as the source was. Labels are copied byte for byte.

Differences from the wired stages, all small: the gains scale the source's camera noise and codec error
too (a sensor's read noise would not scale with exposure), the video is encoded a second time, and the
dents' shading is added to the frame rather than shaded with the imprint (dents sit outside the contact,
where shading is additive) and without the markers over them.

    .venv/bin/python benchmarks/nuisance_dataset.py SRC DST --level handheld [--severity S] [--only STAGE]
        [--workers 2]

Deterministic: the same bytes for any --workers.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from gelsim.atomic import atomic_write_json
from gelsim.errors import GelsimError

_W: dict = {}


def _setup(src: str, stages: dict) -> None:
    from gelsim.fabrics.catalog import load_catalog
    from gelsim.fidelity import get_fidelity
    from gelsim.markers import rest_markers
    from gelsim.motion import load_motion_ranges
    from gelsim.nuisance import frame_means, load_nuisance
    from gelsim.optics import Renderer
    from gelsim.sensor import load_profile

    m = json.loads((Path(src) / "manifest.json").read_text())
    opts = m["options"]
    if opts.get("units"):
        raise GelsimError("this harness handles one sensor unit; give a dataset made without --units")
    prof = load_profile(m["profile"]["name"]).with_resolution(m["profile"]["width_px"], m["profile"]["height_px"])
    fid = get_fidelity(opts.get("fidelity", "balanced"))
    renderer = Renderer(prof, "fast", supersample=fid.supersample, seed=m["seed"])
    markers = rest_markers(prof, seed=m["seed"]) if prof.markers.enabled else None
    flat = renderer.render_float(None, markers)
    _W.update(src=Path(src), manifest=m, profile=prof, renderer=renderer, stages=stages,
              model=load_nuisance(), catalog=load_catalog(), ranges=load_motion_ranges(),
              bg_means=frame_means(flat), bg=renderer.background_float())


def _gap_apex(i: int, motion, labels, fps: float) -> float:
    from gelsim.nuisance import approach_gap_mm

    P = motion.precontact_frames
    if i < P:
        return approach_gap_mm(i, P, motion.contact_phase, motion.approach_speed_mm_s, fps)
    ind = float(labels["indentation_mm"][i])
    if bool(labels["in_contact"][i]) and ind > 0:
        return -ind
    touching = np.flatnonzero(np.asarray(labels["in_contact"][:i + 1], bool))
    last = int(touching[-1]) if touching.size else P
    return motion.approach_speed_mm_s * max(i - last, 1) / fps      # lifting off at the approach speed


def _one(rec: dict) -> tuple[str, dict]:
    from gelsim.motion import sample_motion
    from gelsim.nuisance import (apply_gains, camera_start, camera_step, draw_fibres, fibre_dents_mm, gap_map_mm,
                                 stage_rng)
    from gelsim.optics.composite import to_uint8
    from gelsim.video import read_video

    w = _W
    prof, st, stages = w["profile"], w["model"].stages, w["stages"]
    # the motion as gelsim.dataset.generate_sequence drew it (an explicit --precontact was passed on as its value)
    given = w["manifest"]["options"].get("precontact") is not None
    motion = sample_motion(rec["action"], rec["seed"], frames=(rec["num_frames"], rec["num_frames"]), ranges=w["ranges"],
                           precontact=(rec["precontact_frames"],) * 2 if given else None)
    if motion.precontact_frames != rec["precontact_frames"]:
        raise GelsimError(f"{rec['id']}: the replayed motion has {motion.precontact_frames} pre-contact frames, "
                          f"the record {rec['precontact_frames']}; the dataset was made with another motions.toml")
    labels = dict(np.load(w["src"] / rec["labels"]))
    frames = read_video(w["src"] / rec["video"]).astype(np.float32)
    fps = prof.image.fps_hz
    stats = {"max_dent_mm": 0.0, "fibres": 0, "gains_first": None}
    if "fibres" in stages:
        fab = w["catalog"][rec["fabric_id"]]
        fib = draw_fibres(stage_rng(rec["seed"], "fibres"), prof.field_mm, fab.hairiness, st.fibres, stages["fibres"])
        stats["fibres"] = len(fib)
        if len(fib):
            for i in range(len(frames)):
                gap = gap_map_mm(prof.shape, prof.image.mm_per_px, _gap_apex(i, motion, labels, fps),
                                 prof.gel.dome_radius_mm, tuple(float(v) for v in labels["tilt_deg"][i]))
                dents = fibre_dents_mm(fib, gap, prof.image.mm_per_px, prof.gel.young_modulus_mpa,
                                       prof.gel.poisson_ratio, st.fibres)
                if dents.any():
                    stats["max_dent_mm"] = max(stats["max_dent_mm"], float(dents.max()))
                    frames[i] += w["renderer"].render_float(dents, None) - w["bg"]
    state = camera_start(rec["seed"], stages, st)
    out_frames = []
    for i, f in enumerate(frames):
        gains, state = camera_step(state, f, w["bg_means"], st)
        if i == 0:
            stats["gains_first"] = [round(float(g), 4) for g in gains]
        out_frames.append(to_uint8(apply_gains(f, gains) if not np.all(gains == 1.0) else f))
    return rec["id"], {"frames": np.stack(out_frames), "stats": stats}


def _write(dst: Path, rec: dict, frames: np.ndarray) -> str:
    from gelsim.schema import sha256_of
    from gelsim.video import VideoWriter

    m = _W["manifest"]
    vpath = dst / rec["video"]
    vpath.parent.mkdir(parents=True, exist_ok=True)
    with VideoWriter(vpath, fmt=m["options"].get("format", "h264"), fps=m["profile"]["fps_hz"]) as wr:
        for f in frames:
            wr.write(f)
    lpath = dst / rec["labels"]
    lpath.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(_W["src"] / rec["labels"], lpath)
    return sha256_of(vpath)


def _job(rec: dict):
    rid, res = _one(rec)
    return rid, res["stats"], _write(_W["dst"], rec, res["frames"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--level", required=True)
    p.add_argument("--severity", type=float, help="every stage of the level at this severity")
    p.add_argument("--only", help="keep only this stage of the level")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv)
    from gelsim.nuisance import load_nuisance

    try:
        stages = load_nuisance().level(a.level, a.severity)
        if a.only:
            if a.only not in stages:
                raise GelsimError(f"--only {a.only}: not a stage of level {a.level!r} ({', '.join(stages) or 'none'})")
            stages = {a.only: stages[a.only]}
        src, dst = Path(a.src), Path(a.dst)
        if dst.exists():
            raise GelsimError(f"{dst} exists; give a new directory")
        _setup(str(src), stages)
    except GelsimError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    m = _W["manifest"]
    dst.mkdir(parents=True)
    _W["dst"] = dst
    recs = [s for s in m["sequences"]]
    t0 = time.time()
    stats, shas = {}, {}
    with ProcessPoolExecutor(a.workers, initializer=_init, initargs=(str(src), str(dst), stages)) as ex:
        for rid, st, sha in ex.map(_job, recs, chunksize=4):
            stats[rid], shas[rid] = st, sha
    for s in m["sequences"]:
        s["sha256"]["video"] = shas[s["id"]]
    m["nuisance"] = {"level": a.level, "severity": a.severity, "stages": stages, "source": str(src),
                     "harness": "benchmarks/nuisance_dataset.py (post-processed frames)"}
    atomic_write_json(dst / "manifest.json", m)
    atomic_write_json(dst / "nuisance_stats.json", stats)
    print(f"{len(recs)} sequences in {time.time() - t0:.0f} s; stages {stages}", file=sys.stderr)
    return 0


def _init(src: str, dst: str, stages: dict) -> None:
    _setup(src, stages)
    _W["dst"] = Path(dst)


if __name__ == "__main__":
    sys.exit(main())
