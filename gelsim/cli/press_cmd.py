"""``gelsim press``: press an indenter into the simulated gel and compare with Hertz."""
from __future__ import annotations

import argparse
import math
import sys
import time

from ..errors import GelsimError


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
    p.add_argument("--diameter-mm", type=float, default=4.0,
                   help="sphere or cylinder diameter, mm (ignored for meshes)")
    p.add_argument("--length-mm", type=float, default=None,
                   help="cylinder length, mm [default: longer than the field of view]")
    p.add_argument("--angle-deg", type=float, default=0.0, help="cylinder axis angle from +x towards +y, degrees")
    p.add_argument("--force-n", type=float, required=True, help="normal force, N (> 0)")
    p.add_argument("--profile", default="vitac", metavar="NAME|PATH", help="sensor profile")
    p.add_argument("--fidelity", default="reference", choices=["fast", "balanced", "reference"],
                   help="fidelity level: reference = elastic model at every pixel, fast/balanced = two-scale model")
    p.add_argument("--resolution-px", type=int, default=None, metavar="W",
                   help="image width, px, same field of view [default: the profile's]")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.set_defaults(handler=run_press)


def press_report(indenter: str, force_n: float, *, diameter_mm: float | None = 4.0, length_mm: float | None = None,
                 angle_deg: float = 0.0, profile="vitac", fidelity="reference",
                 resolution_px: int | None = None) -> dict:
    """Simulate one press and return the report ``gelsim press --json`` prints (lengths in mm)."""
    from ..fidelity import get_fidelity
    from ..gel import hertz, measure_contact_radius_mm, press
    from ..indenters import load_indenter
    from ..sensor import load_profile

    if not (isinstance(force_n, (int, float)) and math.isfinite(force_n) and force_n > 0):
        raise GelsimError(f"--force-n {force_n} is not a positive force; give a force > 0 N")
    prof = load_profile(profile)
    if resolution_px is not None:
        prof = prof.with_resolution(resolution_px)
    fid = get_fidelity(fidelity)
    kw = {}
    if indenter == "cylinder":
        kw = {"length_mm": length_mm, "angle_deg": angle_deg}
    t0 = time.perf_counter()
    prot = load_indenter(indenter, prof, diameter_mm=diameter_mm if indenter in ("sphere", "cylinder") else None,
                         **kw)
    imp = press(prot, prof, fid, force_n=force_n)
    elapsed = time.perf_counter() - t0
    a = measure_contact_radius_mm(imp, prof.image.mm_per_px)
    out = {
        "indenter": indenter,
        "diameter_mm": diameter_mm if indenter in ("sphere", "cylinder") else None,
        "force_n": force_n,
        "model": fid.imprint_model,
        "fidelity": fid.name,
        "profile": prof.name,
        "resolution_px": list(prof.shape[::-1]),
        "mm_per_px": prof.image.mm_per_px,
        "contact_radius_mm": a,
        "indentation_mm": imp.indentation_mm,
        "hertz_contact_radius_mm": None,
        "hertz_indentation_mm": None,
        "contact_radius_ratio": None,
        "indentation_ratio": None,
        "contact_area_mm2": imp.contact_area_mm2,
        "gel_force_n": imp.normal_force_n,
        "max_depth_mm": float(imp.depth_mm.max()),
        "bottomed_out": imp.bottomed_out,
        "gel_thickness_mm": prof.gel.thickness_mm,
        "gel_dome_radius_mm": prof.gel.dome_radius_mm or None,
        "young_modulus_mpa": prof.gel.young_modulus_mpa,
        "poisson_ratio": prof.gel.poisson_ratio,
        "contact_radius_over_thickness": a / prof.gel.thickness_mm,
        "elapsed_ms": round(elapsed * 1000.0, 1),
    }
    if indenter == "sphere":
        # A domed gel adds its curvature to the sphere's: 1/R = 1/R_sphere + 1/R_dome.
        dome = prof.gel.dome_radius_mm
        d_eff = diameter_mm if not dome else 2.0 / (2.0 / diameter_mm + 1.0 / dome)
        ha, hd = hertz(d_eff, force_n, prof.gel)
        out.update(hertz_contact_radius_mm=ha, hertz_indentation_mm=hd,
                   contact_radius_ratio=a / ha, indentation_ratio=imp.indentation_mm / hd)
    return out


def run_press(args: argparse.Namespace) -> int:
    from . import print_json

    rep = press_report(args.indenter, args.force_n, diameter_mm=args.diameter_mm, length_mm=args.length_mm,
                       angle_deg=args.angle_deg, profile=args.profile, fidelity=args.fidelity,
                       resolution_px=args.resolution_px)
    if args.json:
        print_json(rep)
        return 0

    def fmt(v):
        return "-" if v is None else f"{v:.4f}"

    w = sys.stdout.write
    w(f"{rep['indenter']} pressed with {rep['force_n']:g} N into {rep['profile']} "
      f"({rep['model']} model, {rep['resolution_px'][0]}x{rep['resolution_px'][1]} px)\n")
    w(f"{'':22}{'simulated':>12}{'Hertz':>12}{'ratio':>9}\n")
    w(f"{'contact radius (mm)':22}{fmt(rep['contact_radius_mm']):>12}{fmt(rep['hertz_contact_radius_mm']):>12}"
      f"{fmt(rep['contact_radius_ratio']):>9}\n")
    w(f"{'indentation (mm)':22}{fmt(rep['indentation_mm']):>12}{fmt(rep['hertz_indentation_mm']):>12}"
      f"{fmt(rep['indentation_ratio']):>9}\n")
    w(f"contact area {rep['contact_area_mm2']:.4f} mm^2, a/h = {rep['contact_radius_over_thickness']:.3f}"
      f"{', BOTTOMED OUT' if rep['bottomed_out'] else ''}, {rep['elapsed_ms']:.0f} ms\n")
    return 0
