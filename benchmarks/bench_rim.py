"""The weave's relief across the field: the two-scale imprint against the elastic reference, centre and rim.

Presses each fabric flat over the whole pad (vitac at 960x720 by default) at one force, with a fidelity
level and with the elastic reference, and compares the gel's relief in the fabric's pitch band (RMS of the
depth map, band-passed as `gelsim texture` does) inside the reference's apparent contact, in the field's
centre (within half of the way to its edge) and at its rim (half to nine tenths of the way out). The vitac
gel is domed, so its surface slopes towards the rim: a model whose texture depends on where in the field a
fabric lies shows it here. ``--flat`` takes the dome away (the same profile otherwise). Usage:

    python benchmarks/bench_rim.py [--fabrics 2,8,21,50,64,80] [--force-n 3] [--level balanced] [--flat] [--json]

The reference takes 10-25 s per fabric at 960x720.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from gelsim.cli import print_json, run_script

RINGS = {"centre": (0.0, 0.5), "rim": (0.5, 0.9)}


def rings(shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """bool masks of the rings, by the larger of |x| and |y| as a fraction of the way to the field's edge."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.maximum(np.abs(xx - w / 2) / (w / 2), np.abs(yy - h / 2) / (h / 2))
    return {name: (r >= lo) & (r < hi) for name, (lo, hi) in RINGS.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fabrics", default="2,8,21,50,64,80", help="catalog ids (default: fine weaves, twill, "
                                                                 "jersey, corduroy, felt)")
    ap.add_argument("--force-n", type=float, default=3.0)
    ap.add_argument("--level", default="balanced", help="fidelity level compared with the reference")
    ap.add_argument("--resolution", type=int, default=None, help="image width, px (default: the profile's)")
    ap.add_argument("--flat", action="store_true", help="a flat gel (the profile's dome removed)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from gelsim.fabrics import load_catalog
    from gelsim.gel import press
    from gelsim.runtime import configure_worker
    from gelsim.scene import as_object, field_heights, press_properties
    from gelsim.sensor import load_profile
    from gelsim.texture import band_for, band_rms, contact_region, pitches_mm

    configure_worker()
    profile = load_profile("vitac")
    if args.resolution:
        profile = profile.with_resolution(args.resolution)
    if args.flat:
        profile = dataclasses.replace(profile, gel=dataclasses.replace(profile.gel, dome_radius_mm=0.0))
    catalog = load_catalog()
    masks = rings(profile.shape)
    mpp = profile.image.mm_per_px
    rows = []
    for fid in (int(v) for v in args.fabrics.split(",")):
        fab = catalog[fid]
        obj = as_object(fab)
        heights = field_heights(obj, profile, seed=0)
        kw = dict(force_n=args.force_n, **press_properties(obj))
        model = press(heights, profile, args.level, **kw)
        ref = press(heights, profile, "reference", **kw)
        band = band_for(fab, profile.field_mm[0])
        coarse = pitches_mm(fab)[1] / mpp
        region = contact_region(ref.contact_mask, coarse, 2 * coarse)
        row = {"fabric": fid, "family": fab.family,
               "contact_area_ratio": model.contact_area_mm2 / ref.contact_area_mm2}
        for name, m in masks.items():
            sel = region & m
            a, b = band_rms(model.depth_mm, sel, band, mpp), band_rms(ref.depth_mm, sel, band, mpp)
            row[name] = {"relief_um": 1e3 * a, "reference_um": 1e3 * b, "ratio": a / b, "px": int(sel.sum())}
        rows.append(row)
        if not args.json:
            print(f"fabric {fid:3d} {fab.family:12s} relief / reference: centre {row['centre']['ratio']:.3f}, "
                  f"rim {row['rim']['ratio']:.3f}; contact area {row['contact_area_ratio']:.3f}", flush=True)
    if args.json:
        print_json({"profile": profile.name, "resolution": list(profile.shape[::-1]), "flat": args.flat,
                    "level": args.level, "force_n": args.force_n, "rows": rows})
    return 0


if __name__ == "__main__":
    run_script(main)
