"""``gelsim fabrics``: list the catalog, preview one fabric, draw the contact sheet."""
from __future__ import annotations

import argparse

from . import HelpFormatter, needs_subcommand, print_json, seed_arg


def register(subparsers) -> None:
    p = subparsers.add_parser("fabrics", help="the fabric catalog: list, preview, contact sheet",
                              description="The procedural fabric catalog (gelsim/assets/fabrics/).",
                              formatter_class=HelpFormatter)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--catalog", default=None, metavar="PATH",
                        help="catalog folder or .toml file (None: the shipped gelsim/assets/fabrics/)")
    sub = p.add_subparsers(dest="fabrics_command", metavar="SUBCOMMAND")

    q = sub.add_parser("list", help="table of all fabrics", formatter_class=HelpFormatter, parents=[common],
                       description="All fabrics with family, material and physical parameters.")
    q.add_argument("--json", action="store_true",
                   help="print a JSON document {version, fabrics: [...]} instead of the table")
    q.set_defaults(handler=_list)

    q = sub.add_parser("show", help="hillshade preview of one fabric", formatter_class=HelpFormatter, parents=[common],
                       description="Write a shaded-relief PNG of one fabric, with its name and a mm scale bar.")
    q.add_argument("id", type=int, help="fabric id (see `gelsim fabrics list`)")
    q.add_argument("--out", required=True, default=argparse.SUPPRESS, metavar="FILE.png",
                   help="output PNG file (required)")
    q.add_argument("--size-mm", type=float, default=10.0, help="side of the square patch shown, mm")
    q.add_argument("--mm-per-px", type=float, default=0.01, help="resolution, mm per pixel")
    q.add_argument("--seed", type=seed_arg, default=0, help="random seed of the fabric's irregularities (integer)")
    q.add_argument("--rotation-deg", type=float, default=0.0, help="rotation of the fabric, degrees")
    q.set_defaults(handler=_show)

    q = sub.add_parser("sheet", help="contact sheet of every fabric", formatter_class=HelpFormatter, parents=[common],
                       description="Write one PNG with a labelled hillshade tile per fabric.")
    q.add_argument("--out", required=True, default=argparse.SUPPRESS, metavar="FILE.png",
                   help="output PNG file (required)")
    q.add_argument("--tile-mm", type=float, default=5.0, help="side of each fabric's tile, mm")
    q.add_argument("--mm-per-px", type=float, default=0.025, help="resolution of the tiles, mm per pixel")
    q.add_argument("--columns", type=int, default=10, help="tiles per row (count)")
    q.add_argument("--seed", type=seed_arg, default=0, help="random seed of the fabrics' irregularities (integer)")
    q.set_defaults(handler=_sheet)
    needs_subcommand(p, sub)


def _catalog(args):
    from ..fabrics import load_catalog
    return load_catalog(args.catalog)


def _list(args) -> int:
    cat = _catalog(args)
    if args.json:
        print_json({"version": cat.version, "count": len(cat), "fabrics": [f.to_dict() for f in cat]})
        return 0
    cols = [("id", 3), ("name", 26), ("family", 11), ("material", 16), ("friction", 8), ("thick_mm", 8),
            ("EMC", 5), ("Es_mpa", 6), ("relief_mm", 9), ("pitch_mm", 11)]
    print("  ".join(f"{c:<{w}}" for c, w in cols))
    for f in cat:
        pitch = "-"
        if f.warp_pitch_mm is not None:
            pitch = f"{f.warp_pitch_mm:g}" + (f"x{f.weft_pitch_mm:g}" if f.weft_pitch_mm is not None else "")
        elif f.feature_mm is not None:
            pitch = f"~{f.feature_mm:g}"
        vals = [f.id, f.name, f.family, f.material, f"{f.friction:g}", f"{f.thickness_mm:g}",
                f"{f.compressibility:g}", f"{f.surface_modulus_mpa:g}", f"{f.relief_mm:g}", pitch]
        print("  ".join(f"{str(v):<{w}}" for v, (_, w) in zip(vals, cols)))
    print(f"{len(cat)} fabrics, catalog version {cat.version}")
    return 0


def _show(args) -> int:
    from ..atomic import check_out_file, write_png
    from ..fabrics.preview import preview
    check_out_file(args.out)
    fab = _catalog(args)[args.id]
    img = preview(fab, size_mm=args.size_mm, mm_per_px=args.mm_per_px, seed=args.seed,
                  rotation_deg=args.rotation_deg)
    path = write_png(args.out, img, rgb=False)  # preview images are BGR
    print(f"wrote {path} ({img.shape[1]}x{img.shape[0]} px): {fab.id} {fab.name}")
    return 0


def _sheet(args) -> int:
    from ..atomic import check_out_file, write_png
    from ..fabrics.preview import contact_sheet
    check_out_file(args.out)
    cat = _catalog(args)
    img = contact_sheet(cat, tile_mm=args.tile_mm, mm_per_px=args.mm_per_px, columns=args.columns,
                        seed=args.seed)
    path = write_png(args.out, img, rgb=False)  # preview images are BGR
    print(f"wrote {path} ({img.shape[1]}x{img.shape[0]} px): {len(cat)} fabrics")
    return 0
