"""``gelsim bench``: speed and accuracy of each fidelity level (and the convergence study)."""
from __future__ import annotations

import sys

from ..errors import GelsimError


def register(sub) -> None:
    from ..bench import DEFAULT_FABRICS, DEFAULT_FRAMES, DEFAULT_PRECONTACT, DEFAULT_RESOLUTION
    from . import HelpFormatter

    p = sub.add_parser(
        "bench", formatter_class=HelpFormatter,
        help="time each fidelity level and measure its error against the reference level",
        description=(
            "Run every fidelity level on the same scenes (a pressed 10 mm sphere and fabrics under press,\n"
            "slip and twist) and report wall ms per frame by stage (fabric, physics, imprint, markers,\n"
            "optics, encode) and end to end, and the error against the reference level on the same contact:\n"
            "image L1 (DN), PSNR (dB), SSIM, marker position error (mm), force error (N). Writes\n"
            "DIR/bench.md, DIR/bench.json and DIR/bench_pareto.png. The defaults run in under 5 minutes\n"
            "on 2 cores. --convergence instead sweeps each knob alone (DIR/convergence.{md,json,png})."),
    )
    p.add_argument("--out", metavar="DIR", default="out/bench", help="output directory for the reports")
    p.add_argument("--resolution", metavar="WxH", default="{}x{}".format(*DEFAULT_RESOLUTION),
                   help="image size in px, same field of view in mm")
    p.add_argument("--frames", type=int, metavar="N", default=DEFAULT_FRAMES,
                   help="frames per sequence, pre-contact included")
    p.add_argument("--precontact", type=int, metavar="N", default=DEFAULT_PRECONTACT,
                   help="frames before contact per sequence")
    p.add_argument("--fabrics", metavar="IDS", default=",".join(str(f) for f in DEFAULT_FABRICS),
                   help="comma-separated catalog fabric ids, each run under every action ('' for none)")
    p.add_argument("--actions", metavar="LIST", default="press,slip,twist", help="comma-separated actions")
    p.add_argument("--no-sphere", action="store_true", help="leave out the pressed-sphere scene")
    p.add_argument("--levels", metavar="LIST", default="",
                   help="comma-separated fidelity levels (the reference is always run) [default: all]")
    p.add_argument("--reference", metavar="LEVEL", default="reference", help="level the errors are measured against")
    p.add_argument("--profile", metavar="NAME|PATH", default="vitac", help="sensor profile")
    p.add_argument("--seed", type=int, metavar="N", default=0, help="scene seed")
    p.add_argument("--format", choices=["h264", "ffv1", "png"], default="h264", help="video format timed as 'encode'")
    p.add_argument("--no-shortcut-study", action="store_true",
                   help="skip timing the balanced level without shortcuts and with labels only")
    p.add_argument("--convergence", action="store_true",
                   help="run the one-knob-at-a-time convergence study from the balanced level instead")
    p.add_argument("--knobs", metavar="LIST", default="",
                   help="with --convergence: comma-separated knobs to sweep [default: all]")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout (no progress lines)")
    p.set_defaults(handler=run_bench_cmd)


def _split(text: str) -> tuple[str, ...]:
    return tuple(t.strip() for t in text.split(",") if t.strip())


def config_from_args(args):
    from ..bench import BenchConfig
    from ..dataset import parse_resolution

    try:
        fabrics = tuple(int(v) for v in _split(args.fabrics))
    except ValueError:
        raise GelsimError(f"--fabrics {args.fabrics!r} is malformed; give comma-separated ids, e.g. 1,55,64") from None
    cfg = BenchConfig(resolution=parse_resolution(args.resolution), frames=args.frames, precontact=args.precontact,
                      fabrics=fabrics, actions=_split(args.actions), sphere=not args.no_sphere,
                      levels=_split(args.levels), reference=args.reference, profile=args.profile, seed=args.seed,
                      video_format=args.format, shortcut_level="" if args.no_shortcut_study else "balanced")
    from ..fabrics import load_catalog

    cat = load_catalog()
    for f in fabrics:
        cat[f]  # an unknown id raises GelsimError naming the valid ids
    cfg.validate()
    return cfg


def run_bench_cmd(args) -> int:
    from .. import bench
    from . import print_json

    cfg = config_from_args(args)

    def say(line: str) -> None:
        if not args.json:
            print(line, file=sys.stderr, flush=True)

    if args.convergence:
        knobs = _split(args.knobs)
        known = [s[0] for s in bench.SWEEPS]
        bad = [k for k in knobs if k not in known]
        if bad:
            raise GelsimError(f"--knobs: unknown {', '.join(bad)}; choose from {', '.join(known)}")
        result = bench.run_convergence(cfg, knobs=knobs, progress=say)
        paths = bench.write_convergence(result, args.out)
        text = bench.convergence_markdown(result)
    else:
        result = bench.run_bench(cfg, progress=say)
        paths = bench.write_reports(result, args.out)
        text = bench.markdown_table(result)
    if args.json:
        print_json(result)
    else:
        print(text)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0
