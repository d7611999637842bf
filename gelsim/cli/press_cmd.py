"""``gelsim press``: press an indenter into the simulated gel and compare with Hertz (gelsim.frame)."""
from __future__ import annotations

import argparse
import sys


def register(sub) -> None:
    from . import HelpFormatter

    p = sub.add_parser(
        "press", formatter_class=HelpFormatter,
        help="press a sphere, cylinder or mesh into the gel; contact radius and indentation vs Hertz",
        description=(
            "Press an indenter into the gel with a given normal force and print the simulated contact\n"
            "radius (from the contact area) and indentation, with Hertz's rigid sphere on an elastic\n"
            "half-space beside them (spheres only; on a domed gel with the sphere's and the dome's\n"
            "curvatures added). Hertz ignores the gel's finite thickness: expect the gel to be stiffer\n"
            "than Hertz once the contact radius is a sizeable fraction of it.\n"
            "The cylinder lies on its side, its axis in the gel plane."),
    )
    p.add_argument("--indenter", default="sphere", metavar="sphere|cylinder|PATH",
                   help="indenter: sphere, cylinder (on its side) or a mesh file (.stl/.obj, units mm)")
    p.add_argument("--diameter-mm", type=float, default=None,
                   help="sphere or cylinder diameter, mm (default 4; not for a mesh)")
    p.add_argument("--length-mm", type=float, default=None,
                   help="cylinder length, mm [default: longer than the field of view]")
    p.add_argument("--angle-deg", type=float, default=None,
                   help="cylinder axis angle from +x towards +y, degrees [default: 0]")
    p.add_argument("--force-n", type=float, required=True, help="normal force, N (> 0)")
    p.add_argument("--profile", default="vitac", metavar="NAME|PATH", help="sensor profile")
    p.add_argument("--fidelity", default="reference", choices=["fast", "balanced", "reference"],
                   help="fidelity level: reference = elastic model at every pixel, fast/balanced = two-scale model")
    p.add_argument("--resolution-px", type=int, default=None, metavar="W",
                   help="image width, px, same field of view [default: the profile's]")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.set_defaults(handler=run_press)


def run_press(args: argparse.Namespace) -> int:
    from . import print_json
    from ..frame import press_report
    from ..scene import indenter

    from . import say_first_run

    say_first_run("gelsim press")
    from ..errors import GelsimError
    from .render_cmd import DEFAULT_DIAMETER_MM

    sized = args.indenter in ("sphere", "cylinder")
    unused = [name for name, value, fits in (("--diameter-mm", args.diameter_mm, sized),
                                             ("--length-mm", args.length_mm, args.indenter == "cylinder"),
                                             ("--angle-deg", args.angle_deg, args.indenter == "cylinder"))
              if value is not None and not fits]
    if unused:   # it would change nothing
        raise GelsimError(f"{', '.join(unused)} not for --indenter {args.indenter}: drop "
                          f"{'it' if len(unused) == 1 else 'them'} (--diameter-mm: sphere or cylinder; --length-mm "
                          "and --angle-deg: cylinder)")
    diameter = DEFAULT_DIAMETER_MM if args.diameter_mm is None else args.diameter_mm
    obj = indenter(args.indenter, diameter_mm=diameter if sized else None, length_mm=args.length_mm,
                   angle_deg=0.0 if args.angle_deg is None else args.angle_deg)
    rep = press_report(obj, args.force_n, profile=args.profile, fidelity=args.fidelity,
                       resolution_px=args.resolution_px)
    from . import warn_if_bottomed

    warn_if_bottomed("gelsim press", rep["bottomed_out"], rep["gel_force_n"], args.force_n)
    if args.json:
        print_json(rep)
        return 0

    def fmt(v):
        # four decimals while they fit the 11 characters of a column, else four significant digits
        return "-" if v is None else (f"{v:.4f}" if abs(v) < 1e5 else f"{v:.4g}")

    w = sys.stdout.write
    w(f"{rep['indenter']} pressed with {rep['force_n']:g} N into {rep['profile']} "
      f"({rep['model']} model, {rep['resolution_px'][0]}x{rep['resolution_px'][1]} px)\n")
    w(f"{'':22}{'simulated':>12}{'Hertz':>12}{'ratio':>12}\n")
    for name, key in (("contact radius (mm)", "contact_radius"), ("indentation (mm)", "indentation")):
        w(f"{name:22}" + "".join(f" {fmt(rep[k]):>11}" for k in (f"{key}_mm", f"hertz_{key}_mm", f"{key}_ratio"))
          + "\n")
    w(f"contact area {rep['contact_area_mm2']:.4f} mm^2, a/h = {rep['contact_radius_over_thickness']:.3f}"
      f"{', BOTTOMED OUT' if rep['bottomed_out'] else ''}, {rep['elapsed_ms']:.0f} ms\n")
    return 0
