"""``gelsim render``: one tactile frame of a fabric or an indenter, for a first look (gelsim.frame)."""
from __future__ import annotations

import time

from . import HelpFormatter, print_result, seed_arg, warn_if_bottomed
from ..frame import DEFAULT_FORCE_N
from ..optics import BACKENDS


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="render one frame (fabric or indenter) to a PNG", formatter_class=HelpFormatter,
        description="Press a fabric (--fabric ID) or an indenter (--indenter) into the gel and render one "
                    "camera frame with markers and noise. Give the press as --force-n or --depth-mm.")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--fabric", type=int, default=None, metavar="ID",
                      help="fabric id from `gelsim fabrics list` (default: an indenter)")
    what.add_argument("--indenter", default=None, metavar="sphere|cylinder|PATH.stl",
                      help="indenter shape or mesh file (default: sphere when no --fabric)")
    p.add_argument("--diameter-mm", type=float, default=None,
                   help="sphere or cylinder diameter, mm (default 4; not for a fabric or a mesh)")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--force-n", type=float, default=None,
                     help=f"normal force, N (default {DEFAULT_FORCE_N} when --depth-mm is not given)")
    how.add_argument("--depth-mm", type=float, default=None, help="approach past first touch, mm")
    p.add_argument("--profile", default="vitac", metavar="NAME|PATH", help="sensor profile name or .toml path")
    p.add_argument("--backend", default=None, choices=BACKENDS,
                   help="renderer (default: the fidelity level's)")
    p.add_argument("--device", default=None, metavar="cpu|cuda",
                   help="with --backend torch: where it renders (default: cpu)")
    p.add_argument("--fidelity", default="balanced", choices=["fast", "balanced", "reference"],
                   help="fidelity level (imprint model, supersampling, default backend)")
    p.add_argument("--seed", type=seed_arg, default=0,
                   help="random seed: fabric irregularities, background field, marker jitter, noise (integer)")
    p.add_argument("--out", required=True, metavar="FILE.png", help="output PNG file (required)")
    p.add_argument("--json", action="store_true", help="also print what was rendered and each stage's time (ms)")
    p.set_defaults(handler=run)


#: The sphere's or cylinder's diameter when none is given, mm.
DEFAULT_DIAMETER_MM = 4.0


def make_object(fabric: int | None, indenter: str | None, diameter_mm: float | None):
    """The touched object the options name: catalog fabric ``fabric``, or the indenter (sphere by default).
    ``diameter_mm`` (None: DEFAULT_DIAMETER_MM) is for a sphere or cylinder only: given with a fabric or a
    mesh it would change nothing, and is refused."""
    from ..errors import GelsimError
    from ..scene import FabricObject, indenter as make_indenter

    sized = fabric is None and (indenter or "sphere") in ("sphere", "cylinder")
    if diameter_mm is not None and not sized:
        raise GelsimError("--diameter-mm is for --indenter sphere or cylinder, and would change nothing here; "
                          "drop it")
    diameter_mm = DEFAULT_DIAMETER_MM if diameter_mm is None else diameter_mm
    if fabric is not None:
        from ..fabrics import load_catalog

        return FabricObject(load_catalog()[fabric])
    name = indenter or "sphere"
    return make_indenter(name, diameter_mm=diameter_mm if name in ("sphere", "cylinder") else None)


def run(args) -> int:
    from ..atomic import check_out_file, write_png
    from ..frame import render_frame

    from . import say_first_run

    t0 = time.perf_counter()
    out = check_out_file(args.out)     # before the work, not after it
    say_first_run("gelsim render")
    rgb, info = render_frame(make_object(args.fabric, args.indenter, args.diameter_mm), args.profile, args.fidelity,
                             force_n=args.force_n, depth_mm=args.depth_mm, backend=args.backend, seed=args.seed,
                             device=args.device)
    t = time.perf_counter()
    write_png(out, rgb)
    imp = info["imprint"]
    asked = None if args.depth_mm is not None else (DEFAULT_FORCE_N if args.force_n is None else args.force_n)
    warn_if_bottomed("gelsim render", imp["bottomed_out"], imp["normal_force_n"], asked)
    info["stages_ms"]["write_png"] = round((time.perf_counter() - t) * 1e3, 2)
    info["total_ms"] = round((time.perf_counter() - t0) * 1e3, 2)
    info["out"] = str(out)
    return print_result(args.json, info,
                        f"wrote {out} ({rgb.shape[1]}x{rgb.shape[0]}, {info['backend']}, {info['total_ms']:.0f} ms)")
