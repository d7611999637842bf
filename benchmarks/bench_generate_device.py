"""``gelsim generate`` end to end on the three ways of making a frame, side by side (issue 45).

* ``numpy``: the default CPU path (``--backend fast``): imprint, markers, labels and optics in numpy/OpenCV;
* ``optics``: ``--backend torch --stages optics``: the same, the camera image rendered by the torch optics on
  ``--device`` (gelsim.sinks.DeviceFrames);
* ``all``: ``--backend torch --stages all``: the whole frame after the physics on ``--device`` (the frame
  pipeline's torch engine, gelsim.engines.TorchEngine: a fabric's sequences in step).

Each run is a fresh ``python -m gelsim generate`` process writing a small dataset (``--fabrics`` x
``--sequences-per-fabric``, the default frame counts) to a temporary directory; the variants alternate within each
repetition (``--reps``), so that the machine's load falls on all of them alike, and the best repetition is kept.
Rows: frames/s of the whole call (process start, imports and the run's set-up included) and of the sequences'
own time (the records' ``seconds``: what every further frame costs), with the stage times per frame that the
records hold (``fabric``, ``physics`` and ``encode`` CPU seconds; the device stages' wall seconds for ``all``;
CPU seconds for the numpy stages), and the process's peak resident memory.

    .venv/bin/python benchmarks/bench_generate_device.py [--resolutions 320x240,960x720] [--device cpu|cuda]
        [--fabrics 2] [--sequences-per-fabric 2] [--workers 1] [--reps 2] [--variants numpy,optics,all] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelsim.cli import print_json, run_script  # noqa: E402

VARIANTS = {"numpy": ["--backend", "fast"],
            "optics": ["--backend", "torch", "--stages", "optics"],
            "all": ["--backend", "torch", "--stages", "all"]}
# Runs `gelsim generate` in this child and prints its summary and peak RSS (MB) as one JSON line.
CHILD = """
import json, resource, sys, io, contextlib
from gelsim.cli import main
buf = io.StringIO()
with contextlib.redirect_stdout(buf):
    rc = main(sys.argv[1:])
print(json.dumps({"rc": rc, "summary": json.loads(buf.getvalue()) if rc == 0 else None,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "children_peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))
"""


def machine() -> dict:
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import torch

    info = {"cpu": model, "cpus": os.cpu_count(), "torch": torch.__version__, "python": platform.python_version()}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def run_once(variant: str, resolution: str, args, tmp: Path) -> dict:
    out = tmp / f"{variant}-{resolution}"
    shutil.rmtree(out, ignore_errors=True)
    cmd = ["generate", "--out", str(out), "--fabrics", str(args.fabrics), "--sequences-per-fabric",
           str(args.sequences_per_fabric), "--resolution", resolution, "--fidelity", args.fidelity,
           "--workers", str(args.workers), "--no-previews", "--json", "--seed", str(args.seed), *VARIANTS[variant]]
    if variant != "numpy":
        cmd += ["--device", args.device]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", CHILD, *cmd], capture_output=True, text=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    wall = time.perf_counter() - t0
    try:
        got = json.loads(p.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return {"error": (p.stderr.strip().splitlines() or ["no output"])[-1]}
    if got["rc"] != 0:
        return {"error": (p.stderr.strip().splitlines() or [f"exit {got['rc']}"])[-1]}
    s = got["summary"]
    t = s["per_frame_ms"]
    shutil.rmtree(out, ignore_errors=True)
    return {"frames": s["frames"], "process_wall_s": round(wall, 2),
            "fps_call": round(s["frames"] / wall, 2),
            "fps_steady": round(1000 / t["ms_per_frame"] * args.workers, 2),
            "ms_per_frame_by_stage": {k: round(v, 1) for k, v in t["stages_ms_per_frame"].items()},
            "peak_rss_mb": round(max(got["peak_rss_mb"], got["children_peak_rss_mb"]), 0),
            "load_avg_before": round(load, 2)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolutions", default="320x240,960x720")
    ap.add_argument("--device", default="cpu", help="the torch variants' --device [default: cpu]")
    ap.add_argument("--fabrics", type=int, default=2)
    ap.add_argument("--sequences-per-fabric", type=int, default=2)
    ap.add_argument("--fidelity", default="balanced")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--variants", default="numpy,optics,all")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--out", metavar="FILE.json", help="also write the result there")
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise SystemExit(f"unknown variants {bad}; choose from {', '.join(VARIANTS)}")
    tmp = Path(tempfile.mkdtemp(prefix="gelsim-bench-gendev-"))
    best: dict = {}
    try:
        for res in [r for r in args.resolutions.split(",") if r]:
            for _ in range(args.reps):
                for v in variants:               # alternating: the load falls on every variant alike
                    r = run_once(v, res, args, tmp)
                    prev = best.get((res, v))
                    if prev is None or "error" in prev or ("error" not in r and r["fps_steady"] > prev["fps_steady"]):
                        best[(res, v)] = r
                    print(f"  {res} {v}: {r}", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rows = [{"resolution": res, "variant": v, **r} for (res, v), r in best.items()]
    result = {"machine": machine(), "device": args.device, "workers": args.workers, "fidelity": args.fidelity,
              "sample": f"{args.fabrics} fabrics x {args.sequences_per_fabric} sequences, seed {args.seed}",
              "reps": args.reps, "best_of": "fps_steady", "rows": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    if args.json:
        print_json(result)
        return 0
    m = result["machine"]
    print(f"{m['cpu']}, {m['cpus']} CPUs, torch {m['torch']}; device {args.device}; {args.workers} worker(s); "
          f"{result['sample']}, {args.fidelity}; best of {args.reps}")
    print("| resolution | variant | frames | frames/s (call) | frames/s (steady) | peak RSS MB | ms per frame by stage |")
    print("|---|---|---:|---:|---:|---:|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['resolution']} | {r['variant']} | | FAILED: {r['error']} | | | |")
            continue
        st = ", ".join(f"{k} {v}" for k, v in r["ms_per_frame_by_stage"].items())
        print(f"| {r['resolution']} | {r['variant']} | {r['frames']} | {r['fps_call']} | {r['fps_steady']} | "
              f"{r['peak_rss_mb']:.0f} | {st} |")
    return 0


if __name__ == "__main__":
    run_script(main)
