"""``gelsim sensors list``: the shipped sensor profiles, their geometry and measured realism."""
from __future__ import annotations


def register(sub) -> None:
    from . import HelpFormatter

    p = sub.add_parser("sensors", formatter_class=HelpFormatter, help="list the shipped sensor profiles",
                       description="Sensor profiles shipped in assets/sensors/ (any profile .toml elsewhere works "
                                   "too: --profile PATH).")
    sp = p.add_subparsers(dest="sensors_command", metavar="SUBCOMMAND")
    ls = sp.add_parser("list", formatter_class=HelpFormatter,
                       help="resolution, field of view, markers, shading, held-out realism where measured",
                       description=(
                           "One line per shipped profile: resolution (px), pixel size and field of view (mm),\n"
                           "markers (size and pitch, mm), the fast backend's shading model, and the held-out\n"
                           "realism skill where the profile was fitted to real ball presses (assets/realism.toml:\n"
                           "fitted on even frames, scored on odd, the balls where the calibration placed them:\n"
                           "'registered' where the pack's annotated centres were off; the background alone\n"
                           "scores 0).\n"
                           "--json adds every measured score and each profile's [unit_variation] ranges."))
    ls.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    ls.set_defaults(handler=run_list)
    p.set_defaults(handler=lambda args: _no_subcommand(p))


def _no_subcommand(parser) -> int:
    parser.print_help()
    return 2


def sensors_table() -> list[dict]:
    """What ``gelsim sensors list --json`` prints under ``"sensors"``."""
    import dataclasses

    from ..realism import realism_records
    from ..sensor import list_profiles, load_profile
    from ..units import variation_ranges

    records = realism_records()
    rows = []
    for name in list_profiles():
        p = load_profile(name)
        fw, fh = p.field_mm
        rec = records.get(name)
        rows.append({
            "name": name, "description": p.description,
            "width_px": p.image.width_px, "height_px": p.image.height_px, "mm_per_px": p.image.mm_per_px,
            "field_mm": [round(fw, 3), round(fh, 3)], "fps_hz": p.image.fps_hz,
            "markers": ({"size_mm": p.markers.size_mm, "pitch_mm": p.markers.pitch_mm, "layout": p.markers.layout}
                        if p.markers.enabled else None),
            "shading": p.shading.model, "lights": len(p.lights),
            "realism": None if rec is None else dataclasses.asdict(rec),
            "unit_variation": variation_ranges(p),
        })
    return rows


def run_list(args) -> int:
    from . import print_json

    rows = sensors_table()
    if args.json:
        print_json({"sensors": rows})
        return 0
    print(f"{'profile':14s} {'pixels':>9s} {'mm/px':>7s} {'field mm':>11s} {'markers':>13s} {'shading':>7s} "
          f"{'held-out skill':>24s}  unit variation")
    for r in rows:
        mk = r["markers"]
        markers = f"{mk['size_mm']:g} @ {mk['pitch_mm']:g}" if mk else "none"
        rec = r["realism"]
        skill = "not measured"
        if rec:
            where = ", registered" if rec["centres"] == "registered" else ""
            skill = f"{rec['skill']:.3f} ({rec['datapack']}{where})"
        print(f"{r['name']:14s} {r['width_px']:>4d}x{r['height_px']:<4d} {r['mm_per_px']:7.4f} "
              f"{r['field_mm'][0]:5.1f}x{r['field_mm'][1]:<5.1f} {markers:>13s} {r['shading']:>7s} {skill:>24s}  "
              f"{'yes' if r['unit_variation'] else 'no'}")
    return 0
