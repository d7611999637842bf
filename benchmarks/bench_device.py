"""Frames per second of the whole frame on a torch device (issue 45), and sensor renders per second against N.

Three measurements, each naming the device and its clock:

* ``imprint`` and ``frame`` (per resolution): catalog fabrics pressed, slipped and twisted (the dataset's
  motions), their physics and patches prepared once on the CPU (:class:`gelsim.sequence.SequenceRun`),
  then ``--batch`` sequences rendered in step on the device (:func:`gelsim.sequence.render_sequences` on the torch
  engine: frame t
  of every sequence in one batch). Rows: frames/s of the imprint alone (patch sampling, press_batch, labels) and
  of the whole frame (plus markers, optics, the uint8 frames back on the host), wall time with the device
  synchronised at each stage; and the CPU seconds per frame the physics and the patch cost on one core (the part
  that stays on the CPU), which bounds ``gelsim generate`` at ``cores / that`` frames/s. The numpy path's
  imprint on one core is the row beside (``numpy``). The sequences are ``--distinct`` prepared ones, repeated to
  fill the batch (the device's work does not depend on which sequence a row is).
* ``sensor`` (when ``--sensors`` is given): :class:`gelsim.mujoco.batch.BatchGelSightSensor` rendering N pads of N
  MuJoCo scenes (a ball pressed into each pad, :func:`gelsim.mujoco.batch.ball_scenes`) per call at 320x240:
  renders/s, and the part of a call spent on the host (contacts, rays, stick-slip).

    .venv/bin/python benchmarks/bench_device.py [--device cuda] [--resolutions 320x240,960x720] [--batch 64]
        [--sensors 1,16,256] [--json] [--out FILE.json]

Issue 45's goals, one GPU: 1,000 frames/s end to end at 960x720, 10,000 sensor renders/s at 320x240.
"""
from __future__ import annotations

import argparse
import functools
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")   # before numpy, OpenCV and torch load their thread pools


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelsim.cli import print_result, run_script  # noqa: E402

GOAL_FPS_960 = 1000.0
GOAL_SENSOR_RPS = 10000.0
ACTIONS = ("press", "slip", "twist")


def machine(device) -> dict:
    import torch

    info = {"cpu": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "torch": torch.__version__,
            "load_avg": [round(v, 2) for v in os.getloadavg()], "device": str(device)}
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def _sync(device):
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


@functools.lru_cache(maxsize=4)
def _prepared(resolution: tuple[int, int], fidelity: str, distinct: int, frames: int):
    """(profile, fidelity, ``distinct`` sequences prepared on the CPU, their CPU seconds): catalog fabrics of several
    families, press, slip and twist in turn (kept: a retry at a smaller batch reuses them)."""
    from gelsim.fabrics import load_catalog
    from gelsim.fidelity import get_fidelity
    from gelsim.gel.parity_cases import family_sample
    from gelsim.motion import sample_motion
    from gelsim.sensor import load_profile
    from gelsim.sequence import SequenceRun

    w, h = resolution
    profile = load_profile("vitac").with_resolution(w, h)
    fid = get_fidelity(fidelity)
    cat = load_catalog()
    ids = family_sample(cat)
    prepared = []
    cpu_s = 0.0
    for k in range(distinct):
        fab = cat[ids[(7 * k) % len(ids)]]
        m = sample_motion(ACTIONS[k % 3], 1000 + k, frames=(frames, frames), precontact=(1, 1))
        p = SequenceRun(fab, m, profile, fid, seed=1000 + k)
        cpu_s += sum(p.seconds.values())
        prepared.append(p)
    return profile, fid, prepared, cpu_s


def frame_rows(device, resolution: tuple[int, int], fidelity: str, batch: int, distinct: int, frames: int,
               reps: int, numpy_frames: int) -> list[dict]:
    """The imprint and whole-frame rows at one resolution (see the module docstring)."""
    from gelsim.engines import TorchEngine
    from gelsim.gel import press
    from gelsim.optics import Renderer
    from gelsim.optics.torch_backend import BatchRenderer
    from gelsim.sequence import SequenceOptions, render_sequences

    w, h = resolution
    profile, fid, prepared, cpu_s = _prepared(resolution, fidelity, distinct, frames)
    host_per_frame = cpu_s / (distinct * frames)
    # the numpy imprint on one core, on the same frames (the distinct sequences'), the thread's CPU time
    np_s, np_n = 0.0, 0
    warmed = False
    for p in prepared:
        prev = None
        c = p.contact
        for i in range(min(frames, numpy_frames)):
            f = float(c.normal_force_n[i])
            if not (c.in_contact[i] and f > 0):
                prev = None
                continue
            pose = (profile.shape, profile.image.mm_per_px, c.position_mm[i, 0], c.position_mm[i, 1], c.yaw_deg[i],
                    tuple(c.tilt_deg[i]))
            prot = p.patch.sample(*pose)
            env = None if p.envelope is None else p.envelope.sample(*pose)
            if not warmed:          # (the compiled kernels load on the first press)
                press(prot, profile, fid, force_n=f, envelope_mm=env, **p.props)
                warmed = True
            t = time.thread_time()
            prev = press(prot, profile, fid, force_n=f, warm=prev, envelope_mm=env, **p.props)
            np_s += time.thread_time() - t
            np_n += 1
    seqs = [prepared[k % distinct] for k in range(batch)]
    renderer = BatchRenderer(Renderer(profile, "torch", seed=0, device=str(device)))
    engine = TorchEngine(device, sync=True)

    def run(runs, outputs):
        """The frames of ``runs`` in step: (frames, seconds per stage)."""
        n, seconds = 0, {}
        for _, rec in render_sequences(runs, profile, fid, options=SequenceOptions(renderer=renderer, outputs=outputs),
                                       engine=engine):
            n += 1
            for k, v in rec.seconds.items():
                seconds[k] = seconds.get(k, 0.0) + v
        return n, seconds

    run([p.again() for p in seqs[:min(batch, 4)]], ("frames", "imprint", "markers"))   # warm-up: kernels, FFT plans
    _sync(device)
    rows = []
    for outputs, what in ((("imprint",), "imprint"), (("frames", "imprint", "markers"), "frame")):
        best = None
        for _ in range(reps):
            runs = [p.again() for p in seqs]                                   # (their set-up: not timed)
            _sync(device)
            t = time.perf_counter()
            out = run(runs, outputs)
            _sync(device)
            wall = time.perf_counter() - t
            if best is None or wall < best[0]:
                best = (wall, out)
        wall, (n, seconds) = best
        stages = {k: round(1e3 * v / n, 3) for k, v in seconds.items() if v > 0}
        rows.append({"resolution": f"{w}x{h}", "what": what, "device": str(device), "batch": batch,
                     "frames": n, "fps": round(n / wall, 1), "ms_per_frame_by_stage": stages,
                     "clock": "wall, device synchronised per stage"})
    rows.append({"resolution": f"{w}x{h}", "what": "host: physics + patch (stays on the CPU)", "device": "cpu",
                 "ms_per_frame": round(1e3 * host_per_frame, 3), "fps_one_core": round(1.0 / host_per_frame, 1),
                 "clock": "CPU, one core"})
    if np_n:
        rows.append({"resolution": f"{w}x{h}", "what": "numpy imprint (the reference path)", "device": "cpu",
                     "ms_per_frame": round(1e3 * np_s / np_n, 3), "fps_one_core": round(np_n / np_s, 1),
                     "clock": "CPU, one core"})
    return rows


def sensor_rows(device, counts: list[int], resolution: tuple[int, int], reps: int) -> list[dict]:
    """Batched MuJoCo sensor renders per second at each N (see the module docstring)."""
    from gelsim.mujoco.batch import BatchGelSightSensor, ball_scenes

    rows = []
    w, h = resolution
    for n in counts:
        scenes = ball_scenes(n)
        sensor = BatchGelSightSensor([(s.model, s.data, s.pad) for s in scenes], resolution=(w, h),
                                     device=str(device), noise=True)
        for s in scenes:
            s.settle()
        sensor.render()                          # warm-up
        _sync(device)
        best = None
        for _ in range(reps):
            for s in scenes:
                s.step()
            t = time.perf_counter()
            sensor.render()
            _sync(device)
            wall = time.perf_counter() - t
            if best is None or wall < best[0]:
                best = (wall, dict(sensor.timings_ms))
        wall, stages = best
        rows.append({"resolution": f"{w}x{h}", "what": "sensor renders", "device": str(device), "n": n,
                     "renders_per_s": round(n / wall, 1), "ms_per_call": round(1e3 * wall, 3),
                     "ms_by_stage": {k: round(v, 3) for k, v in stages.items()}, "clock": "wall, synchronised"})
    return rows


def _attempt(fn, size: int, what: str, device) -> list[dict]:
    """``fn(size)``'s rows; on the device running out of memory, again at half the size (down to 1), and a row
    saying so; any other error becomes a row naming it (so that one case cannot lose the others)."""
    import torch

    while True:
        try:
            return fn(size)
        except torch.OutOfMemoryError:
            torch.cuda.empty_cache() if device.type == "cuda" else None
            if size <= 1:
                return [{"what": what, "error": "out of device memory at size 1"}]
            print(f"{what}: out of device memory at {size}; trying {size // 2}", file=sys.stderr)
            size //= 2
        except Exception as e:  # noqa: BLE001 - recorded in the results, the next case runs
            return [{"what": what, "error": f"{type(e).__name__}: {e}"[:400]}]


def run(device_name: str, resolutions, fidelity: str, batch: int, distinct: int, frames: int, reps: int,
        sensors, sensor_resolution, numpy_frames: int, out: str | None = None) -> dict:
    import torch

    from gelsim.optics.torch_backend import resolve_device
    from gelsim.runtime import configure_worker

    configure_worker()
    dev = resolve_device(device_name)
    if dev.type == "cpu":
        torch.set_num_threads(1)
    info = {"machine": machine(dev), "fidelity": fidelity, "goal_fps_960x720": GOAL_FPS_960,
            "goal_sensor_renders_per_s_320x240": GOAL_SENSOR_RPS, "rows": []}

    def keep(rows):
        info["rows"] += rows
        if out:              # after every case: a run stopped by its time limit keeps what it measured
            from gelsim.atomic import atomic_write_json

            atomic_write_json(out, info)

    for res in resolutions:
        keep(_attempt(lambda b: frame_rows(dev, res, fidelity, b, distinct, frames, reps, numpy_frames), batch,
                      f"frame {res[0]}x{res[1]}", dev))
    for n in sensors:
        keep(_attempt(lambda k: sensor_rows(dev, [k], sensor_resolution, reps), n, f"sensors N={n}", dev))
    return info


def markdown(info: dict) -> str:
    m = info["machine"]
    head = (f"{m.get('gpu', m['cpu'])} ({m['device']}); {m['cpus']} CPUs, load {m['load_avg'][0]:.2f}; "
            f"torch {m['torch']}; fidelity {info['fidelity']}")
    lines = [head, "", "| resolution | what | device | batch / N | frames/s or renders/s | ms | clock |",
             "|---|---|---|---:|---:|---|---|"]
    for r in info["rows"]:
        if "error" in r:
            lines.append(f"| | {r['what']} | | | | failed: {r['error']} | |")
        elif "renders_per_s" in r:
            lines.append(f"| {r['resolution']} | {r['what']} | {r['device']} | {r['n']} | {r['renders_per_s']} | "
                         f"{r['ms_per_call']} per call: {r['ms_by_stage']} | {r['clock']} |")
        elif "fps" in r:
            lines.append(f"| {r['resolution']} | {r['what']} | {r['device']} | {r['batch']} | {r['fps']} | "
                         f"{r['ms_per_frame_by_stage']} | {r['clock']} |")
        else:
            lines.append(f"| {r['resolution']} | {r['what']} | {r['device']} | | {r['fps_one_core']} (one core) | "
                         f"{r['ms_per_frame']} per frame | {r['clock']} |")
    return "\n".join(lines)


def _resolutions(text: str) -> list[tuple[int, int]]:
    out = []
    for part in text.split(","):
        if part.strip():
            w, h = part.lower().split("x")
            out.append((int(w), int(h)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N; default cpu")
    ap.add_argument("--resolutions", default="320x240,960x720", help="WxH list for the frame rows ('' for none)")
    ap.add_argument("--fidelity", default="balanced", help="fast or balanced; default balanced (the dataset's)")
    ap.add_argument("--batch", type=int, default=16, help="sequences rendered in step; default 16")
    ap.add_argument("--distinct", type=int, default=6, help="distinct sequences prepared on the CPU; default 6")
    ap.add_argument("--frames", type=int, default=8, help="frames per sequence; default 8")
    ap.add_argument("--reps", type=int, default=2, help="timed runs per case (the fastest is kept); default 2")
    ap.add_argument("--numpy-frames", type=int, default=100, help="frames per sequence of the numpy row (all of the "
                    "distinct sequences' frames up to this); default 100")
    ap.add_argument("--sensors", default="", help="N list for the sensor rows, e.g. 1,16,256 ('' for none)")
    ap.add_argument("--sensor-resolution", default="320x240", help="WxH of the sensor rows; default 320x240")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    ap.add_argument("--out", metavar="FILE.json", help="also write the JSON document there")
    args = ap.parse_args(argv)
    sensors = [int(v) for v in args.sensors.split(",") if v.strip()]
    info = run(args.device, _resolutions(args.resolutions), args.fidelity, args.batch, args.distinct, args.frames,
               args.reps, sensors, _resolutions(args.sensor_resolution)[0], args.numpy_frames, args.out)
    return print_result(args.json, info, markdown(info))


if __name__ == "__main__":
    run_script(main)
