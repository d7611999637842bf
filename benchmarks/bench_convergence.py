"""Convergence of each fidelity knob alone, on texture: error against its finest value vs its cost.

    .venv/bin/python benchmarks/bench_convergence.py [--out out/convergence] [--png docs/convergence.png]
        [--resolution 320x240] [--hires 960x720] [--knobs LIST] [--hires-knobs LIST] [--fabrics IDS]
        [--pitch] [--pitch-png docs/texture_pitch.png] [--report-only]

Sweeps (gelsim.bench.SWEEPS) from the balanced level, one knob at a time, on the bench's scenes (a
pressed sphere; a fine weave, a coarse knit and a pile fabric under press, slip and twist): the
physics timestep (force error), imprint scale, the two-scale model's macro_cells (without the
valley rule) and macro_cells_per_valley (its refinement for corduroys), and the imprint
model (pyramid, twoscale, elastic: texture kept in the fabric's pitch band, contact area, markers in
the contact, image L1), supersampling and render backend (image texture, image L1) and the marker
model (marker error). The imprint and marker knobs are swept again at ``--hires`` (the ViTac
camera's 960x720), where the dataset is made. ``--pitch`` adds the fine-weave study
(gelsim.bench.run_pitch_study: kept texture against pixels per period, both resolutions).

Each sweep is saved as OUT/sweeps/KNOB@WxH.json when done, and the report (convergence.json,
convergence.md, convergence.png under --out, the plot copied to --png) is assembled from every
sweep file there: a long study can be run a few knobs at a time (``--knobs``, ``--hires-knobs ''``)
and ``--report-only`` reassembles it. The yardsticks (each sweep's finest value) are kept in
OUT/cache. Time on the 2 shared cores (see docs/fidelity.md): the 320x240 sweeps about 6 minutes,
the 960x720 imprint-model sweep about 10 (its elastic yardstick: 10-35 s per frame), the other
960x720 sweeps 2-3, the pitch study about 5; a second run with the cache, a few minutes.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from gelsim import bench  # noqa: E402
from gelsim.atomic import atomic_write_bytes, atomic_write_json, atomic_write_text  # noqa: E402
from gelsim.cli import run_script  # noqa: E402
from gelsim.dataset import parse_resolution  # noqa: E402

HIRES_KNOBS = ("imprint_scale", "macro_cells", "macro_cells_per_valley", "imprint_model", "marker_model")


def _split(text: str) -> tuple[str, ...]:
    return tuple(t.strip() for t in text.split(",") if t.strip())


def _copy(src: Path, dst: str) -> None:
    if dst:
        atomic_write_bytes(dst, src.read_bytes())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/convergence", help="output directory [default: out/convergence]")
    ap.add_argument("--png", default="docs/convergence.png", help="copy the plot here ('' for no copy) "
                    "[default: docs/convergence.png]")
    ap.add_argument("--resolution", default="320x240", help="resolution of the full sweep, WxH px ('' to skip) "
                    "[default: 320x240]")
    ap.add_argument("--hires", default="960x720", help="resolution of the --hires-knobs sweeps, WxH px ('' to skip) "
                    "[default: 960x720]")
    ap.add_argument("--knobs", default="", help="comma-separated knobs at --resolution [default: all]")
    ap.add_argument("--hires-knobs", default=",".join(HIRES_KNOBS),
                    help=f"comma-separated knobs at --hires [default: {','.join(HIRES_KNOBS)}]")
    ap.add_argument("--fabrics", default=None, help="comma-separated fabric ids [default: the bench's, "
                    f"{','.join(str(f) for f in bench.DEFAULT_FABRICS)}]")
    ap.add_argument("--pitch", action="store_true", help="also run the fine-weave pitch study at both resolutions")
    ap.add_argument("--pitch-png", default="docs/texture_pitch.png", help="copy the pitch plot here ('' for no copy)")
    ap.add_argument("--report-only", action="store_true", help="only reassemble the report from OUT/sweeps")
    args = ap.parse_args(argv)
    out = Path(args.out)
    cache = str(out / "cache")
    t0 = time.perf_counter()
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    extra = {} if args.fabrics is None else {"fabrics": tuple(int(v) for v in _split(args.fabrics))}
    runs = []
    if not args.report_only:
        if args.resolution:
            runs.append((parse_resolution(args.resolution), _split(args.knobs)))
        if args.hires and _split(args.hires_knobs):
            runs.append((parse_resolution(args.hires), _split(args.hires_knobs)))
    for res, knobs in runs:
        cfg = bench.BenchConfig.at(res, cache_dir=cache, **extra)
        for knob in knobs or [s[0] for s in bench.SWEEPS]:
            r = bench.run_convergence(cfg, knobs=(knob,), progress=say)
            for sw in r["sweeps"]:
                sw["settings"] = r["settings"]
                atomic_write_json(out / "sweeps" / f"{knob}@{res[0]}x{res[1]}.json", sw)
    # Assemble every sweep done so far, in SWEEPS order, low resolution first.
    order = {s[0]: i for i, s in enumerate(bench.SWEEPS)}
    sweeps = [json.loads(p.read_text()) for p in sorted((out / "sweeps").glob("*.json"))] if (out / "sweeps").exists() else []
    sweeps.sort(key=lambda sw: (sw["resolution"][0], order.get(sw["knob"], 99)))
    if sweeps:
        settings = dict(sweeps[-1]["settings"])
        settings["scenes"] = sorted({sc for sw in sweeps for sc in sw["settings"]["scenes"]})
        settings["bench_seconds"] = round(sum(sw["settings"].get("bench_seconds", 0) for sw in sweeps), 1)
        loads = [sw["settings"]["load_avg"][0] for sw in sweeps if sw["settings"].get("load_avg")]
        settings["load_avg"] = f"{min(loads)}-{max(loads)} (1-minute, over the sweeps)" if loads else None
        result = {"base": "balanced", "settings": settings, "sweeps": sweeps}
        paths = bench.write_convergence(result, out)
        _copy(paths["plot"], args.png)
        print(bench.convergence_markdown(result))
        say("wrote " + ", ".join(str(p) for p in paths.values()))
    if args.pitch:
        studies = []
        for res in (args.resolution, args.hires):
            if res:
                studies.append(bench.run_pitch_study(parse_resolution(res), cache_dir=cache, progress=say))
        atomic_write_json(out / "pitch.json", studies)
        atomic_write_text(out / "pitch.md", bench.pitch_markdown(studies))
        bench.pitch_plot(studies, out / "pitch.png")
        _copy(out / "pitch.png", args.pitch_png)
        print(bench.pitch_markdown(studies))
    say(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    run_script(main)
