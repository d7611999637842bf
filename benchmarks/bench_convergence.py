"""Convergence of each fidelity knob alone: error against its finest value vs its cost.

    .venv/bin/python benchmarks/bench_convergence.py [--out out/convergence] [--png docs/convergence.png]
        [--resolution 320x240] [--hires 960x720] [--knobs LIST]

Sweeps (gelsim.bench.SWEEPS) from the balanced level, one knob at a time, on the bench's
scenes (a pressed sphere; fabrics 1 and 64 under press, slip and twist; 8 frames): the
physics timestep (force error), imprint scale and model, supersampling and render backend
(image L1) and the marker model (marker error). The knobs whose cost grows with the pixel
count (imprint scale, marker model) are swept again at ``--hires`` (the ViTac camera's
960x720 by default), where their cost matters. Writes convergence.json, convergence.md and
convergence.png under --out and copies the plot to --png; docs/fidelity.md discusses the figures. 2-10 minutes on
2 shared cores.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from gelsim import bench  # noqa: E402
from gelsim.dataset import parse_resolution  # noqa: E402

HIRES_KNOBS = ("imprint_scale", "marker_model")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/convergence", help="output directory [default: out/convergence]")
    ap.add_argument("--png", default="docs/convergence.png", help="copy the plot here ('' for no copy) "
                    "[default: docs/convergence.png]")
    ap.add_argument("--resolution", default="320x240", help="resolution of the full sweep, WxH px [default: 320x240]")
    ap.add_argument("--hires", default="960x720",
                    help="resolution of the imprint_scale and marker_model sweeps, WxH px ('' to skip) "
                         "[default: 960x720]")
    ap.add_argument("--knobs", default="", help="comma-separated knobs [default: all]")
    args = ap.parse_args(argv)
    knobs = tuple(k for k in args.knobs.split(",") if k)
    t0 = time.perf_counter()
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    cfg = bench.BenchConfig(resolution=parse_resolution(args.resolution))
    result = bench.run_convergence(cfg, knobs=knobs, progress=say)
    if args.hires:
        hk = tuple(k for k in HIRES_KNOBS if not knobs or k in knobs)
        if hk:
            hi = bench.run_convergence(bench.BenchConfig(resolution=parse_resolution(args.hires)), knobs=hk,
                                       progress=say)
            result["sweeps"] += hi["sweeps"]
    result["settings"]["bench_seconds"] = round(time.perf_counter() - t0, 1)
    paths = bench.write_convergence(result, args.out)
    if args.png:
        tmp = f"{args.png}.partial-{os.getpid()}.png"
        shutil.copyfile(paths["plot"], tmp)
        os.replace(tmp, args.png)
    print(bench.convergence_markdown(result))
    print("wrote " + ", ".join(str(p) for p in paths.values()), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
