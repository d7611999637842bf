"""``gelsim bench``: speed and accuracy of each fidelity level (and the convergence study)."""
from __future__ import annotations

import sys

from ..errors import GelsimError


def register(sub) -> None:
    from ..bench import DEFAULT_FABRICS, DEFAULT_FRAMES, DEFAULT_PRECONTACT, DEFAULT_RESOLUTIONS, LARGE_FRAMES, QUICK
    from . import HelpFormatter, seed_arg

    res = ",".join(f"{w}x{h}" for w, h in DEFAULT_RESOLUTIONS)
    qres = "{}x{}".format(*QUICK["resolution"])
    p = sub.add_parser(
        "bench", formatter_class=HelpFormatter,
        help="time each fidelity level and measure its error against the reference level",
        description=(
            "Run every fidelity level on the same scenes (a pressed 10 mm sphere and fabrics under press,\n"
            "slip and twist) and report CPU ms per frame, end to end and by stage (fabric, physics, imprint,\n"
            "markers, optics, encode), and the error against the reference level on the same contact: the\n"
            "texture kept in the fabric's pitch band (gel relief and image texture, ratios to the reference),\n"
            "contact-area error, marker error (all markers and those in the contact, mm), force error (N),\n"
            "image L1 (DN), PSNR (dB) and SSIM. Writes DIR/bench.md, DIR/bench.json and\n"
            "DIR/bench_pareto.png. The reference's elastic imprint takes 10-25 s per 960x720 fabric frame:\n"
            "the defaults take about 15-25 minutes on 2 cores the first time; the reference's runs are kept\n"
            "in DIR/cache and reused while the code and assets are unchanged (then a few minutes).\n"
            f"--quick: a smoke run in seconds ({qres}, fabric {QUICK['fabrics'][0]}, press and slip).\n"
            "--convergence instead sweeps each knob alone (DIR/convergence.{md,json,png})."),
    )
    p.add_argument("--out", metavar="DIR", default="out/bench", help="output directory for the reports")
    p.add_argument("--resolution", metavar="WxH[,WxH]", default=None,
                   help=f"image sizes in px, same field of view in mm [default: {res}; --quick: {qres}]")
    p.add_argument("--frames", type=int, metavar="N", default=None,
                   help=f"frames per sequence, pre-contact included [default: {DEFAULT_FRAMES}, "
                        f"{LARGE_FRAMES} above 640x480]")
    p.add_argument("--precontact", type=int, metavar="N", default=None,
                   help=f"frames before contact per sequence [default: {DEFAULT_PRECONTACT}]")
    p.add_argument("--fabrics", metavar="IDS", default=None,
                   help="comma-separated catalog fabric ids, each run under every action ('' for none) "
                        f"[default: {','.join(str(f) for f in DEFAULT_FABRICS)}: fine weave, coarse knit, pile]")
    p.add_argument("--actions", metavar="LIST", default=None, help="comma-separated actions [default: press,slip,twist]")
    p.add_argument("--no-sphere", action="store_true", help="leave out the pressed-sphere scene")
    p.add_argument("--levels", metavar="LIST", default="",
                   help="comma-separated fidelity levels (the reference is always run) [default: all]")
    p.add_argument("--reference", metavar="LEVEL", default="reference", help="level the errors are measured against")
    p.add_argument("--profile", metavar="NAME|PATH", default="vitac", help="sensor profile")
    p.add_argument("--seed", type=seed_arg, metavar="N", default=0, help="scene seed")
    p.add_argument("--format", choices=["h264", "ffv1", "png"], default="h264", help="video format timed as 'encode'")
    p.add_argument("--no-shortcut-study", action="store_true",
                   help="skip timing the balanced level without shortcuts and with labels only")
    p.add_argument("--quick", action="store_true", help="a smoke run in seconds (see above); other options still apply")
    p.add_argument("--cache", metavar="DIR", default=None,
                   help="where the reference's (and sweeps' finest) runs are kept [default: DIR/cache under --out]")
    p.add_argument("--no-cache", action="store_true", help="recompute the reference's runs and keep nothing")
    p.add_argument("--convergence", action="store_true",
                   help="run the one-knob-at-a-time convergence study from the balanced level instead")
    p.add_argument("--knobs", metavar="LIST", default="",
                   help="with --convergence: comma-separated knobs to sweep [default: all]")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout (no progress lines)")
    p.set_defaults(handler=run_bench_cmd)


def _split(text: str) -> tuple[str, ...]:
    return tuple(t.strip() for t in text.split(",") if t.strip())


def configs_from_args(args) -> list:
    """One BenchConfig per resolution of ``--resolution``."""
    from pathlib import Path

    from ..bench import DEFAULT_FABRICS, DEFAULT_RESOLUTIONS, QUICK, BenchConfig
    from ..dataset import parse_resolution
    from ..fabrics import load_catalog

    quick = dict(QUICK) if args.quick else {}
    if args.resolution is not None:
        resolutions = [parse_resolution(r) for r in _split(args.resolution)]
        if not resolutions:
            raise GelsimError(f"--resolution {args.resolution!r} names no size; give WxH[,WxH], e.g. 320x240,960x720")
    else:
        resolutions = [quick["resolution"]] if quick else list(DEFAULT_RESOLUTIONS)
    quick.pop("resolution", None)
    if args.fabrics is not None:
        try:
            quick["fabrics"] = tuple(int(v) for v in _split(args.fabrics))
        except ValueError:
            raise GelsimError(f"--fabrics {args.fabrics!r} is malformed; give comma-separated ids, e.g. 2,57,64") from None
    quick.setdefault("fabrics", DEFAULT_FABRICS)
    if args.actions is not None:
        quick["actions"] = _split(args.actions)
    for name in ("frames", "precontact"):
        if getattr(args, name) is not None:
            quick[name] = getattr(args, name)
    if args.no_sphere:
        quick["sphere"] = False
    if args.no_shortcut_study:
        quick["shortcut_level"] = ""
    cache = "" if args.no_cache else (args.cache if args.cache is not None else str(Path(args.out) / "cache"))
    if cache and Path(cache).exists() and not Path(cache).is_dir():
        raise GelsimError(f"--cache {cache} is a file, not a folder; give a folder for the reference runs, or --no-cache")
    cat = load_catalog()
    for f in quick["fabrics"]:
        cat[f]  # an unknown id raises GelsimError naming the valid ids
    from ..sensor import load_profile

    profile = load_profile(args.profile)
    for w, h in resolutions:
        profile.with_resolution(w, h)   # a size outside the sensor's range: one line, before any work
    cfgs = [BenchConfig.at(r, levels=_split(args.levels), reference=args.reference, profile=args.profile,
                           seed=args.seed, video_format=args.format, cache_dir=cache, **quick) for r in resolutions]
    for c in cfgs:
        c.validate()
    return cfgs


def run_bench_cmd(args) -> int:
    from ..atomic import out_folder

    with out_folder(args.out):      # a file of that name: one line before minutes of work
        return _run_bench(args, configs_from_args(args))


def _run_bench(args, cfgs) -> int:
    from .. import bench
    from . import print_result, say_first_run

    say_first_run("gelsim bench")

    def say(line: str) -> None:
        if not args.json:
            print(line, file=sys.stderr, flush=True)

    if args.convergence:
        knobs = _split(args.knobs)
        known = [s[0] for s in bench.SWEEPS]
        bad = [k for k in knobs if k not in known]
        if bad:
            raise GelsimError(f"--knobs: unknown {', '.join(bad)}; choose from {', '.join(known)}")
        result = bench.run_convergence(cfgs[0], knobs=knobs, progress=say)
        for c in cfgs[1:]:
            result["sweeps"] += bench.run_convergence(c, knobs=knobs, progress=say)["sweeps"]
        paths = bench.write_convergence(result, args.out)
        text = bench.convergence_markdown(result)
    else:
        result = bench.run_benches(cfgs, progress=say)
        paths = bench.write_reports(result, args.out)
        text = bench.markdown_table(result)
    return print_result(args.json, result, text, "wrote " + ", ".join(str(p) for p in paths.values()))
