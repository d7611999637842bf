"""A parallel gripper with a GelSight sensor on each finger grasps three objects (#14).

For each object (a sphere, a cube grasped on two edges, a hexagonal bolt head built as a mesh) the
gripper descends, closes with 4 N, lifts and holds. The scene camera (MuJoCo's renderer, when a
headless GL context can be made) and both tactile streams go side by side into one video; the
sensor's per-step CPU cost is printed against mj_step's.

    .venv/bin/python examples/grasp.py [--out out/grasp.mp4] [--still docs/grasp.png] [--resolution 320x240]
        [--profile gelsight-mini]

``--still``: one row per object, the video frame where the two pads press hardest (the README's still).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")   # headless; osmesa also works (set it before running)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/grasp.mp4"), help="video file (default out/grasp.mp4)")
    ap.add_argument("--resolution", default="320x240", help="tactile and scene image size WxH px (default 320x240)")
    ap.add_argument("--profile", default="gelsight-mini", help="sensor profile (default gelsight-mini)")
    ap.add_argument("--still", type=Path, default=None,
                    help="also write a PNG: per object, the frame where the pads press hardest")
    return ap


if __name__ == "__main__":
    build_parser().parse_args()   # --help and bad options answer before the imports below (1.7 s)

import cv2  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from gelsim.atomic import write_png  # noqa: E402
from gelsim.errors import GelsimError  # noqa: E402
from gelsim.mujoco import GelSightSensor  # noqa: E402
from gelsim.mujoco.grasp import OBJECTS, build_grasp_scene, scripted_controls  # noqa: E402
from gelsim.video import write_video  # noqa: E402

DURATION_S = 1.8     # per object: descend, close, lift, hold (gelsim.mujoco.grasp.scripted_controls)
FPS = 30.0


def scene_view(model, data, shape):
    """A mujoco.Renderer looking at the grasp, or None without headless GL."""
    try:
        r = mujoco.Renderer(model, shape[0], shape[1])
    except Exception as e:  # noqa: BLE001 - any GL failure means: no scene pane
        print(f"no scene view ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}); "
              "tactile panes only", file=sys.stderr)
        return None
    cam = mujoco.MjvCamera()
    cam.lookat[:] = (0, 0, 0.03)
    cam.distance, cam.azimuth, cam.elevation = 0.22, 150.0, -20.0
    return r, cam


def label(img, text):
    out = img.copy()
    cv2.putText(out, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def run(out: Path, resolution: tuple[int, int], profile: str, still: Path | None = None) -> dict:
    frames, cost = [], {"sensor_ms": [], "step_ms": []}
    hardest = []   # per object: (summed normal force of both pads N, its frame)
    for kind in OBJECTS:
        hardest.append((-1.0, None))
        sc = build_grasp_scene(kind, profile=profile)
        m, d = sc.model, sc.data
        sensors = [GelSightSensor(m, d, pad, profile=profile, resolution=resolution, seed=i)
                   for i, pad in enumerate(sc.pads)]
        view = scene_view(m, d, resolution[::-1])
        steps_per_frame = int(round(1.0 / FPS / m.opt.timestep))
        n_frames = int(DURATION_S * FPS)
        z0 = m.body("object").id
        for k in range(n_frames):
            t0 = time.thread_time()
            for _ in range(steps_per_frame):
                z, grip = scripted_controls(d.time)
                d.ctrl[sc.act_hand] = z
                d.ctrl[sc.act_left] = d.ctrl[sc.act_right] = grip
                mujoco.mj_step(m, d)
            cost["step_ms"].append((time.thread_time() - t0) * 1e3 / steps_per_frame)
            tac, force_n = [], 0.0
            for s in sensors:
                t0 = time.thread_time()
                f = s.render()
                cost["sensor_ms"].append((time.thread_time() - t0) * 1e3)
                force_n += f.normal_force_n
                tac.append(label(f.rgb, f"{s.pad_name}: {f.normal_force_n:.1f} N"))
            if view is not None:
                view[0].update_scene(d, view[1])
                scene = view[0].render()
            else:
                scene = np.full((resolution[1], resolution[0], 3), 40, np.uint8)
            scene = label(scene, f"{kind}  t={d.time:.2f} s  lift {1e3 * d.xpos[z0][2]:.0f} mm")
            frames.append(np.concatenate([scene, *tac], axis=1))
            if force_n > hardest[-1][0]:
                hardest[-1] = (force_n, frames[-1])
        lifted = d.xpos[z0][2]
        print(f"{kind:9s} object height after the lift: {lifted * 1e3:.1f} mm "
              f"({'held' if lifted > 0.02 else 'dropped'})")
        if view is not None:
            view[0].close()
    write_video(out, frames, fps=FPS)
    if still is not None:
        write_png(still, np.concatenate([f for _, f in hardest], axis=0))
    return {k: float(np.median(v)) for k, v in cost.items()}


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    try:
        w, h = (int(v) for v in a.resolution.lower().split("x"))
        a.out.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        if a.still is not None:
            a.still.parent.mkdir(parents=True, exist_ok=True)
        cost = run(a.out, (w, h), a.profile, a.still)
    except (GelsimError, ValueError) as e:
        print(f"grasp: error: {e}", file=sys.stderr)
        return 2
    print(f"sensor: {cost['sensor_ms']:.2f} ms CPU per render (median, one sensor, {w}x{h}); "
          f"mj_step: {cost['step_ms']:.3f} ms; wall time {time.perf_counter() - t0:.1f} s; video: {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
