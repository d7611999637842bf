"""What the host's CPU does per frame of ``gelsim generate --backend torch --stages all`` (issue 51).

With ``--stages all`` the device makes every frame after the physics (patch sampling, imprint, labels, markers,
optics); what stays on the host's CPU bounds a GPU host at ``cores / host time`` frames/s, whatever the GPU. That
host work does not depend on the device, so it is measured here on any build (the CPU build included), two ways:

* **steps** (always): the host's own steps for the sequences of a sample of the default dataset, each timed alone
  in CPU seconds of this thread, through the functions a sequence is prepared with (:mod:`gelsim.sequence`) and
  the dataset's writer call: the physics surface, the contact simulation (MuJoCo), the image-resolution patch's host
  part (the fabric's axis-aligned grid, :func:`gelsim.scene.travel_patch_parts`; once per sequence), then per frame
  the H.264 encoder given the device's I420 planes (:class:`gelsim.video.VideoWriter` with a
  :class:`gelsim.video.I420`), and the labels' file. Beside them, the steps ``--stages all`` now makes on the device
  (a rotated patch's resampling, its crown envelope, the RGB to YUV 4:2:0 conversion), timed in their numpy twins:
  what they cost a host that made them (the route before 2026-11-29), not host time of this route. The frames
  encoded are the numpy path's (:func:`gelsim.sequence.render_sequence`): the device path's are the same within a
  DN, and the encoder's time depends on what it encodes;
* **run** (``--run``): ``gelsim.dataset.generate`` with ``backend="torch", stages="all"`` on ``--device`` (default
  the CPU), one worker in this process: the records' host stages (``fabric``, ``physics``: CPU; ``encode``: CPU of
  the writer and the labels), the device stages' wall seconds, and this process's CPU time per frame beside them.
  On the CPU build the device's work runs on this core too, so only the records' host stages are host time there;
  and even they are not all host time: on the torch engine the records' ``fabric`` also holds the device's patch
  work (the patches finished, each frame's heights sampled: wall seconds; 80-95 ms per frame on the CPU build),
  so **steps** is this script's measure of the host.

    .venv/bin/python benchmarks/bench_host.py [--fabrics 4] [--sequences-per-fabric 2] [--resolution 960x720]
        [--run] [--device cpu] [--json]

The issue's target: at most 2 ms of host CPU per frame at 960x720, the step that remains on the CPU named.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")   # before numpy, OpenCV and torch start their thread pools

from gelsim.cli import print_json, run_script  # noqa: E402

TARGET_MS_960 = 2.0
#: What stays on the host's CPU per frame of --stages all (see the module docstring).
HOST_STEPS = ("physics_surface", "contact_simulation", "image_grid", "h264", "labels_file")
#: What --stages all makes on the device (since 2026-11-29), timed here in its numpy twin.
DEVICE_STEPS = ("image_resample", "crown_envelope", "rgb_to_yuv420")


def _sample(args):
    """(profile, fidelity, catalog, plan specs, motion ranges) of a sample of the default dataset: ``--fabrics``
    spread over the catalog, the first ``--sequences-per-fabric`` sequences of each (their planned motions)."""
    from gelsim.dataset import GenerateConfig, plan
    from gelsim.fabrics import load_catalog
    from gelsim.fidelity import get_fidelity
    from gelsim.motion import load_motion_ranges
    from gelsim.sensor import load_profile

    cat = load_catalog()
    cfg = GenerateConfig()
    profile = load_profile(cfg.profile)
    if args.resolution:
        profile = profile.with_resolution(*(int(v) for v in args.resolution.split("x")))
    n = len(cat)
    fabrics = sorted({1 + (k * n) // args.fabrics for k in range(args.fabrics)})
    specs = [s for s in plan(cfg, n) if s.fabric_id in fabrics and s.index < args.sequences_per_fabric]
    return profile, get_fidelity(cfg.fidelity), cat, specs, load_motion_ranges()


def measure_steps(args) -> dict:
    """The host's steps, each timed alone (see the module docstring): ms per frame by step, and in all."""
    import cv2
    import numpy as np

    from gelsim.atomic import atomic_write_npz
    from gelsim.contact import simulate
    from gelsim.motion import sample_motion
    from gelsim.optics import Renderer
    from gelsim.scene import as_object, physics_surface, travel_patch_parts
    from gelsim.sequence import SequenceOptions, crown_envelope_patch, render_sequence
    from gelsim.stream import sequence_labels
    from gelsim.video import I420, VideoWriter

    profile, fid, cat, specs, ranges = _sample(args)
    renderer = Renderer(profile, fid.render_backend, supersample=fid.supersample)
    clock = time.thread_time
    took = dict.fromkeys(HOST_STEPS, 0.0)
    moved = dict.fromkeys(DEVICE_STEPS, 0.0)
    frames = 0
    with tempfile.TemporaryDirectory(prefix="gelsim-bench-host-") as tmp:
        # the first sequence twice, its first pass untimed: what a process pays once (imports, MuJoCo's and
        # the encoder's set-up, compiled kernels loaded) is not a frame's cost
        for k, spec in enumerate([specs[0], *specs]):
            if k == 1:
                took, moved, frames = dict.fromkeys(took, 0.0), dict.fromkeys(moved, 0.0), 0
            obj = as_object(cat[spec.fabric_id])
            motion = sample_motion(spec.action, spec.seed, frames=(spec.num_frames, spec.num_frames),
                                   precontact=None if spec.precontact_frames is None
                                   else (spec.precontact_frames, spec.precontact_frames), ranges=ranges)
            t = clock()
            surface = physics_surface(obj, motion, profile, seed=spec.seed)
            took["physics_surface"] += clock() - t
            t = clock()
            contact = simulate(motion, surface, profile, fid)
            took["contact_simulation"] += clock() - t
            t = clock()
            parts = travel_patch_parts(obj, motion, profile, profile.image.mm_per_px, seed=spec.seed,
                                       poses=(contact.position_mm, contact.yaw_deg))
            took["image_grid"] += clock() - t
            t = clock()
            patch = parts.finish()
            moved["image_resample"] += clock() - t
            t = clock()
            crown_envelope_patch(patch, obj, profile, fid)
            moved["crown_envelope"] += clock() - t
            opts = SequenceOptions(renderer=renderer, contact=contact, surface=surface, patch=patch)
            records = list(render_sequence(obj, motion, profile, fid, seed=spec.seed, options=opts))
            with VideoWriter(Path(tmp) / f"{spec.id}.mp4", fps=profile.image.fps_hz) as writer:
                for r in records:
                    t = clock()
                    planes = cv2.cvtColor(np.ascontiguousarray(r.frame), cv2.COLOR_RGB2YUV_I420)
                    moved["rgb_to_yuv420"] += clock() - t
                    t = clock()
                    writer.write(I420(planes))
                    took["h264"] += clock() - t
            t = clock()
            atomic_write_npz(Path(tmp) / f"{spec.id}.npz", **sequence_labels([r.labels for r in records]))
            took["labels_file"] += clock() - t
            frames += len(records)
    per = {k: round(1000 * v / frames, 3) for k, v in took.items()}
    dev = {k: round(1000 * v / frames, 3) for k, v in moved.items()}
    groups = {"fabric": per["physics_surface"] + per["image_grid"], "physics": per["contact_simulation"],
              "encode": per["h264"] + per["labels_file"]}
    return {"sequences": len(specs), "frames": frames, "ms_per_frame_by_step": per,
            "ms_per_frame_as_the_records_group_them": {k: round(v, 3) for k, v in groups.items()},
            "host_ms_per_frame": round(sum(per.values()), 3),
            "on_the_device_numpy_twin_ms_per_frame": dev,
            "host_ms_per_frame_before": round(sum(per.values()) + sum(dev.values()), 3)}


def measure_run(args) -> dict:
    """``generate --backend torch --stages all`` on a sample, one worker in this process (see the docstring)."""
    from gelsim.dataset import GenerateConfig, generate, summarize_timings
    from gelsim.runtime import configure_worker

    configure_worker()
    res = tuple(int(v) for v in args.resolution.split("x")) if args.resolution else None
    cfg = GenerateConfig(fabrics=args.fabrics, sequences_per_fabric=args.sequences_per_fabric, backend="torch",
                         stages="all", device=args.device, resolution=res)
    with tempfile.TemporaryDirectory(prefix="gelsim-bench-host-run-") as tmp:
        c0 = time.process_time()
        manifest = generate(cfg, Path(tmp) / "ds", workers=1, previews=False)
        cpu = time.process_time() - c0
        timing = summarize_timings(Path(tmp) / "ds", manifest)
    st = timing["stages_ms_per_frame"]
    host = {k: round(st.get(k, 0.0), 3) for k in ("fabric", "physics", "encode")}
    device = {k: round(v, 3) for k, v in st.items() if k not in host}
    return {"device": args.device, "frames": timing["frames"], "host_stages_ms_per_frame": host,
            "host_ms_per_frame": round(sum(host.values()), 3), "device_stages_wall_ms_per_frame": device,
            "process_cpu_ms_per_frame": round(1000 * cpu / timing["frames"], 3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fabrics", type=int, default=4, help="fabrics in the sample, spread over the catalog [4]")
    ap.add_argument("--sequences-per-fabric", type=int, default=2, help="[2]")
    ap.add_argument("--resolution", default="960x720", help="WxH [960x720]")
    ap.add_argument("--run", action="store_true", help="also run generate --stages all on --device (slow on a CPU)")
    ap.add_argument("--device", default="cpu", help="torch device of --run [cpu]")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    from gelsim.errors import GelsimError
    from gelsim.runtime import configure_worker

    if args.fabrics < 1 or args.sequences_per_fabric < 1:
        raise GelsimError("--fabrics and --sequences-per-fabric must be at least 1")
    configure_worker()
    result = {"resolution": args.resolution, "steps": measure_steps(args), "load_avg": os.getloadavg()[0]}
    if args.run:
        result["run"] = measure_run(args)
    if args.json:
        print_json(result)
        return 0
    s = result["steps"]
    print(f"host CPU per frame, {s['sequences']} sequences ({s['frames']} frames) at {args.resolution}: "
          f"{s['host_ms_per_frame']:.2f} ms (target {TARGET_MS_960} ms at 960x720)")
    for k, v in s["ms_per_frame_by_step"].items():
        print(f"  {k:20s} {v:6.3f} ms")
    print(f"on the device with --stages all (their numpy twins on this host; {s['host_ms_per_frame_before']:.2f} ms "
          "per frame when the host made them too):")
    for k, v in s["on_the_device_numpy_twin_ms_per_frame"].items():
        print(f"  {k:20s} {v:6.3f} ms")
    if "run" in result:
        r = result["run"]
        print(f"generate --stages all on {r['device']}: host stages {r['host_stages_ms_per_frame']} "
              f"({r['host_ms_per_frame']:.2f} ms), device stages (wall) {r['device_stages_wall_ms_per_frame']}, "
              f"process CPU {r['process_cpu_ms_per_frame']:.1f} ms per frame")
    print(f"(load average {result['load_avg']:.2f})")
    return 0


if __name__ == "__main__":
    run_script(main)
