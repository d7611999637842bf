"""``gelsim sensors list``: the shipped sensor profiles, their geometry and measured realism."""
from __future__ import annotations


def register(sub) -> None:
    from . import HelpFormatter, needs_subcommand

    p = sub.add_parser("sensors", formatter_class=HelpFormatter, help="list the shipped sensor profiles",
                       description="Sensor profiles shipped in assets/sensors/ (any profile .toml elsewhere works "
                                   "too: --profile PATH).")
    sp = p.add_subparsers(dest="sensors_command", metavar="SUBCOMMAND")
    ls = sp.add_parser("list", formatter_class=HelpFormatter,
                       help="resolution, field of view, markers, shading, held-out realism where measured",
                       description=(
                           "One line per shipped profile: resolution (px), pixel size and field of view (mm),\n"
                           "markers (size and pitch, mm), the fast backend's shading model, and the held-out\n"
                           "realism skill with its 95% interval where the profile was fitted to real ball\n"
                           "presses (assets/realism.toml: fitted on even frames, scored on odd, the scored balls\n"
                           "placed independently of the profile: at the pack's annotated centres, or 'detected'\n"
                           "where those were off; the background alone scores 0); 'not measured' where no real\n"
                           "frames exist.\n"
                           "--json adds every measured score and each profile's [unit_variation] ranges."))
    ls.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    ls.set_defaults(handler=run_list)
    sh = sp.add_parser("show", formatter_class=HelpFormatter,
                       help="every parameter of a profile with its source (measured, published or assumed)",
                       description=(
                           "Every parameter of a profile, its value and where it comes from: the comment\n"
                           "beside it in the profile's file (measured on real frames, a peer's published\n"
                           "value with the reference, or assumed with the reason), the file's header, and\n"
                           "the held-out realism where measured. A parameter the file does not set takes\n"
                           "its default, and says so."))
    sh.add_argument("name", metavar="NAME|PATH", help="profile name (gelsim sensors list) or .toml path")
    sh.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    sh.set_defaults(handler=run_show)
    needs_subcommand(p, sp)


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


def _flat(d: dict, prefix: str = ""):
    """(dotted key, value) of a profile's plain data (:func:`gelsim.params.to_dict`); the n-th entry of a
    list of tables is ``name[n]``, as :func:`gelsim.params.toml_entries` names it."""
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict):
            yield from _flat(v, key)
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for i, x in enumerate(v):
                yield from _flat(x, f"{key}[{i}]")
        else:
            yield key, v


NOT_IN_FILE = "default: not set in the profile's file"
NO_SOURCE = "no comment beside it (see the file's header)"
LABELS = ("name", "description")     # what a profile calls itself: no physical value, no source


def profile_sources(name: str) -> dict:
    """What ``gelsim sensors show NAME --json`` prints: ``name``, ``file``, ``header`` (the file's leading
    comment), ``parameters`` (``{"key", "value", "source"}`` for every parameter: the comment beside it
    in the file; NO_SOURCE where the file sets it without one, NOT_IN_FILE where it does not set it; the
    profile's ``name`` and ``description`` are labels) and ``realism`` (assets/realism.toml's record, or None)."""
    import dataclasses
    from pathlib import Path

    from ..params import to_dict, toml_entries
    from ..realism import realism_records
    from ..sensor import load_profile

    p = load_profile(name)
    notes = {k: n for k, _, n in toml_entries(p.source)}
    header = []
    for line in Path(p.source).read_text().splitlines():
        if not line.startswith("#"):
            break
        header.append(line.lstrip("#").strip())

    def source(key):
        if key in LABELS:
            return "label"
        return notes[key] or NO_SOURCE if key in notes else NOT_IN_FILE

    params = [{"key": k, "value": v, "source": source(k)}
              for k, v in _flat({k: v for k, v in to_dict(p).items() if k != "source"})]
    rec = realism_records().get(p.name)
    return {"name": p.name, "file": str(p.source), "header": "\n".join(header), "parameters": params,
            "realism": None if rec is None else dataclasses.asdict(rec)}


def run_show(args) -> int:
    import json

    from . import print_json

    doc = profile_sources(args.name)
    if args.json:
        print_json(doc)
        return 0
    print(f"{doc['name']} ({doc['file']})")
    for line in doc["header"].splitlines():
        print(f"  {line}")
    print("held-out realism: " + realism_text(doc["realism"]))
    width = max(len(r["key"]) for r in doc["parameters"])
    for r in doc["parameters"]:
        print(f"{r['key']:{width}s} = {json.dumps(r['value']):<20s} {r['source']}")
    return 0


def realism_text(rec: dict | None) -> str:
    """The held-out skill of a :class:`gelsim.realism.RealismRecord` (as a dict) in words, with its interval;
    "not measured" without one."""
    if rec is None:
        return "not measured (no real frames)"
    lo, hi = rec["skill_ci95"]
    return f"{rec['skill']:.3f} [{lo:.3f}-{hi:.3f}] ({rec['datapack']}, {rec['centres']})"


def run_list(args) -> int:
    from . import print_json

    rows = sensors_table()
    if args.json:
        print_json({"sensors": rows})
        return 0
    print(f"{'profile':14s} {'pixels':>9s} {'mm/px':>7s} {'field mm':>11s} {'markers':>13s} {'shading':>7s} "
          f"{'held-out skill [95% interval]':>39s}  unit variation")
    for r in rows:
        mk = r["markers"]
        markers = f"{mk['size_mm']:g} @ {mk['pitch_mm']:g}" if mk else "none"
        skill = realism_text(r["realism"]) if r["realism"] else "not measured"
        print(f"{r['name']:14s} {r['width_px']:>4d}x{r['height_px']:<4d} {r['mm_per_px']:7.4f} "
              f"{r['field_mm'][0]:5.1f}x{r['field_mm'][1]:<5.1f} {markers:>13s} {r['shading']:>7s} {skill:>39s}  "
              f"{'yes' if r['unit_variation'] else 'no'}")
    return 0
