"""``gelsim generate`` and ``gelsim verify`` (with ``--stats``: the dataset's statistics, gelsim.stats)."""
from __future__ import annotations

import argparse
import os
import sys
import time

from ..errors import GelsimError


def register(sub) -> None:
    from ..optics import BACKENDS
    from ..optics.torch_backend import DEFAULT_BATCH, TOL_MAX_DN
    from . import HelpFormatter, seed_arg

    p = sub.add_parser(
        "generate", formatter_class=HelpFormatter,
        help="write a synthetic ViTac-style dataset (videos, labels, manifest)",
        description=(
            "Simulate hand-held press, slip and twist sequences on procedural fabrics and write one video\n"
            "per sequence, per-frame labels and DIR/manifest.json. Deterministic: each sequence has its own\n"
            "seed, so the output is the same for any --workers. Interrupted (Ctrl-C, kill -9), rerun the same\n"
            "command to finish without redoing finished sequences.\n\n"
            "Presets: quick = 10 fabrics x 4 sequences at 320x240, fast, split 2:1:1 (`make demo`; a test split\n"
            "                 for `stam train --config quick` and `stam evaluate`; docs/quickstart.md);\n"
            "         cpu   = 100 fabrics x 20 sequences at 320x240, balanced, split 7:2:11 (sized for\n"
            "                 `stam experiment --config cpu`: 1,100 test sequences resolve a few points;\n"
            "                 13 min on 2 cores). With --resolution 960x720, the camera's own frames: about\n"
            "                 2.5x the time, and every Tables I/II cell 11-19 points higher (docs/stam_results.md).\n"
            "Options given with a preset override it."),
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (new, empty, or a dataset to resume)")
    p.add_argument("--preset", choices=["quick", "cpu"], help="a named set of defaults (see above)")
    p.add_argument("--fabrics", type=int, metavar="N", help="use fabrics 1..N of the catalog [default: 100]")
    p.add_argument("--sequences-per-fabric", type=int, metavar="N",
                   help="sequences per fabric; ViTac Cloth has about 50 (5,036 in all) [default: 50]")
    p.add_argument("--actions", metavar="P:S:T", help="press:slip:twist weights, as in ViTac Cloth [default: 7:1:2]")
    p.add_argument("--split", metavar="TRAIN:VAL:TEST",
                   help="train:val:test weights, apportioned per fabric by sequence [default: 7:2:1, the paper's]")
    p.add_argument("--frames", metavar="MIN-MAX", help="frames per sequence, pre-contact included [default: 25-36]")
    p.add_argument("--precontact", metavar="MIN-MAX",
                   help="pre-contact frames per sequence (sensor approaching, nothing touching), uniform in the "
                        "range [default: gelsim/assets/motions.toml's: 0-1 frames, as both rows of the paper's Table II "
                        "imply (docs/nuisance.md)]")
    p.add_argument("--nuisance", metavar="LEVEL",
                   help="what a real, hand-held sensor adds before and around the touch, a level of "
                        "gelsim/assets/nuisance.toml: none; camera (the webcam's start-up, caught by the first "
                        "recording of a cloth, one in 30); handheld (camera + loose fibres of hairy fabrics); "
                        "webcam-restart (a stream started with every recording: dark first frames; contradicts "
                        "ViTac). Labels never change; nuisance/ records what each frame got (docs/nuisance.md) "
                        "[default: none]")
    p.add_argument("--nuisance-severity", metavar="S", type=float,
                   help="every stage of --nuisance's level at severity S: 0 off, 1 the data file's, up to 4 "
                        "(a sweep's knob: more recordings catch the start-up, more fibres stand); only with a "
                        "--nuisance level other than none [default: the level's]")
    p.add_argument("--profile", metavar="NAME|PATH", help="sensor profile [default: vitac, 960x720]")
    p.add_argument("--resolution", metavar="WxH", help="render at this size, same field of view in mm [default: the profile's]")
    p.add_argument("--fidelity", choices=["fast", "balanced", "reference"], help="speed/accuracy level [default: balanced]")
    p.add_argument("--backend", choices=BACKENDS,
                   help="renderer: fast (numpy/OpenCV), pyrender (OpenGL), or torch (the fast backend's optics "
                        f"in PyTorch, frames rendered in batches on --device; equal to fast within {TOL_MAX_DN:g} DN "
                        "before noise, the same labels) [default: the fidelity level's]")
    p.add_argument("--stages", choices=["optics", "all"],
                   help="with --backend torch: what runs on --device. optics: the camera image only; the imprint, "
                        "markers and labels come from the numpy path, byte for byte. all: the whole frame after "
                        "the physics (imprint, contact labels, markers, nuisance, image: the frame pipeline's torch engine), a fabric's "
                        "sequences in step, the physics on the CPU; labels within the stated tolerance of the "
                        "numpy path's (docs/device.md), the same bytes on the same device. The manifest records "
                        "the backend, the stages and the device [default: optics]")
    p.add_argument("--device", metavar="cpu|cuda",
                   help="with --backend torch: where the frames are rendered (cuda: on the GPU, while the CPU "
                        "simulates and encodes) [default: cpu]")
    p.add_argument("--batch", type=int, metavar="FRAMES",
                   help="with --backend torch: frames rendered at once; the output is the same bytes for any "
                        f"batch [default: {DEFAULT_BATCH}]")
    p.add_argument("--seed", type=seed_arg, metavar="N", help="dataset seed [default: 0]")
    p.add_argument("--workers", type=int, metavar="N", default=None,
                   help="worker processes, 1 to this machine's cores [default: all cores]")
    p.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="run each sequence as a Ray task: alone, on a Ray instance started on this machine "
                        "(--workers CPUs); 'auto', on the cluster `ray start` made here; HOST:PORT, on that "
                        "head's cluster, whose nodes must all mount --out at the same path (checked first). "
                        "Same bytes as a local run; needs `make ray` [default: the local worker pool]")
    p.add_argument("--format", choices=["h264", "ffv1", "png"], help="video format: H.264 .mp4, lossless FFV1 .mkv, or PNG frames [default: h264]")
    p.add_argument("--units", type=int, metavar="K",
                   help="draw K sensor units from the profile's [unit_variation] (LEDs, gel, markers, camera; "
                        "ranges and sources in the profile) and give each sequence one in turn; the manifest "
                        "records every unit's parameters [default: 0, the profile itself]")
    p.add_argument("--replace-stale", action="store_true",
                   help="if --out holds a gelsim dataset this code cannot resume (made by other gelsim code, "
                        "options or library versions), rename it to DIR.stale-N beside it and start anew; "
                        "nothing is deleted, and a directory that is not a gelsim dataset is never moved "
                        "(`make demo` uses this, so it works again after `git pull`)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the plan with estimated time and disk size, and what would happen to --out (new, "
                        "resumed, complete, or refused); write nothing")
    p.add_argument("--no-previews", action="store_true", help="skip the preview images")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout (no progress bar)")
    p.set_defaults(handler=run_generate)

    v = sub.add_parser("verify", formatter_class=HelpFormatter, help="check a dataset's files against its manifest",
                       description="Check every file of a dataset against DIR/manifest.json: present, checksum, "
                                   "decodable, expected frame count. Exit status 1 on any fault.")
    v.add_argument("dir", metavar="DIR", help="dataset directory")
    v.add_argument("--no-decode", action="store_true", help="skip decoding the videos (checksums only)")
    v.add_argument("--stats", action="store_true",
                   help="also report the dataset's statistics per action from the labels (contact area in mm^2 and "
                        "share of the pad, normal force, indentation, shear and twist labels, marker-field "
                        "translation/rotation/dilation, frames in contact, label-vs-marker agreement, how often "
                        "stam's crop holds the contact) and write dataset_stats.json/.md/.png and "
                        "dataset_actions.png (press/slip/twist frames across families) to --stats-out")
    v.add_argument("--stats-out", metavar="OUT", help="folder for the --stats files [default: DIR/previews]")
    v.add_argument("--crop", type=float, metavar="FRACTION", default=None,
                   help="side of stam's centred crop as a fraction of the frame's shorter side, for --stats "
                        "[default: 0.5, stam/configs/cpu.toml]")
    v.add_argument("--no-sheet", action="store_true", help="with --stats: skip dataset_actions.png (no video decoding)")
    v.add_argument("--json", action="store_true", help="print {ok, sequences, faults} as JSON (with --stats: "
                                                       "also stats and stats_files)")
    v.set_defaults(handler=run_verify)


def config_from_args(args: argparse.Namespace):
    from ..dataset import PRESETS, GenerateConfig, parse_range, parse_ratio, parse_resolution

    values: dict = {}
    if args.preset:
        values.update(PRESETS[args.preset])
    # An option given overrides the preset; these are parsed from their text, the others taken as they are.
    parse = {"actions": parse_ratio,
             "split": lambda text: parse_ratio(text, "--split", "train:val:test", "7:2:1"),
             "frames": lambda text: parse_range(text, "--frames", lo=2),
             "precontact": lambda text: parse_range(text, "--precontact", lo=0),
             "resolution": parse_resolution}
    for name in ("fabrics", "sequences_per_fabric", "actions", "split", "frames", "precontact", "profile",
                 "resolution", "fidelity", "seed", "format", "backend", "stages", "device", "batch", "nuisance",
                 "nuisance_severity"):
        value = getattr(args, name)
        if value is not None:
            values[name] = parse[name](value) if name in parse else value
    if args.units is not None:
        if not 0 <= args.units <= 1000:
            raise GelsimError(f"--units {args.units} is out of range; give 0 (the profile itself) to 1000")
        values["units"] = args.units
    return GenerateConfig(**values)


def run_generate(args: argparse.Namespace) -> int:
    from .. import dataset
    from . import print_json

    cfg = config_from_args(args)
    if args.ray is None or args.ray == "local":
        dataset.check_workers(args.workers)
    if args.dry_run:
        return _dry_run(cfg, args)
    if args.ray is not None:
        from ..cluster import import_ray

        import_ray()  # not installed: one line, before anything is written
    from . import say_first_run

    say_first_run("gelsim generate")   # said by whichever worker compiles first
    bar = None
    frames_done = [0]
    t0 = time.perf_counter()

    def progress(done, total, rec):
        nonlocal bar
        frames_done[0] += rec["num_frames"]
        if args.json:
            return
        if bar is None:  # created on the first result, so bad input never shows a bar
            from tqdm import tqdm

            bar = tqdm(total=total, initial=done - 1, unit="seq", desc="generating", dynamic_ncols=True,
                       file=sys.stderr)
        bar.update(1)
        bar.set_postfix(frames_per_s=f"{frames_done[0] / (time.perf_counter() - t0):.1f}")

    try:
        manifest = dataset.generate(cfg, args.out, workers=args.workers, progress=progress,
                                    previews=not args.no_previews, ray=args.ray, replace_stale=args.replace_stale,
                                    notify=lambda line: print(line, file=sys.stderr))
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    timing = dataset.summarize_timings(args.out, manifest)
    summary = {"out": str(args.out), "sequences": len(manifest["sequences"]), "complete": manifest["complete"],
               "frames": sum(s["num_frames"] for s in manifest["sequences"]), "splits": manifest["splits"],
               "wall_s": round(wall, 2), "new_frames_per_s": round(frames_done[0] / wall, 2) if wall > 0 else None,
               "per_frame_ms": timing, "ray": args.ray}
    if args.json:
        print_json(summary)
    else:
        print(f"wrote {summary['sequences']} sequences ({summary['frames']} frames) to {args.out} "
              f"in {wall:.1f} s; manifest: {os.path.join(args.out, 'manifest.json')}")
        if timing.get("frames"):
            st = ", ".join(f"{k} {v:.1f}" for k, v in timing["stages_ms_per_frame"].items())
            print(f"per frame (one worker): {timing['ms_per_frame']:.1f} ms end to end; {st} ms")
    return 0


def _dry_run(cfg, args) -> int:
    from .. import dataset, schema
    from ..fabrics import load_catalog
    from . import print_json

    catalog = load_catalog()
    profile = dataset.resolve_profile(cfg)
    dataset.unit_profiles(cfg, profile)  # a profile without [unit_variation] fails here
    from ..fidelity import get_fidelity

    dataset.check_render(cfg, get_fidelity(cfg.fidelity))  # and a device this machine lacks
    dataset.nuisance_level(cfg)                           # and a nuisance level that does not exist
    specs = dataset.plan(cfg, len(catalog))
    frames = sum(s.num_frames for s in specs)
    try:
        out_state = dataset.resume_state(args.out, cfg, specs)
    except dataset.StaleOutput:
        if not args.replace_stale:
            raise  # what the run itself would say: one line, exit 2
        out_state = {"state": "replace", "moved_to": str(dataset.stale_place(args.out)), "done": 0,
                     "total": len(specs), "frames_to_go": frames}
    # The estimates are for what this run would do: the whole plan, less what a resumed dataset holds.
    to_go = out_state["frames_to_go"]
    w, h = profile.image.width_px, profile.image.height_px
    nbytes = dataset.estimate_bytes(specs, cfg.format, w, h) * to_go // max(frames, 1)
    fid = get_fidelity(cfg.fidelity)
    workers = args.workers or os.cpu_count() or 1
    est_s = fid.estimate_seconds(to_go, w, h, workers) if to_go else 0.0
    counts = {a: sum(1 for s in specs if s.action == a) for a in schema.ACTIONS}
    splits = {k: sum(1 for s in specs if s.split == k) for k in schema.SPLITS}
    plan = {"out": str(args.out), "out_state": out_state, "options": cfg.options(), "sequences": len(specs),
            "frames": frames, "actions": counts, "splits": splits, "resolution": [w, h], "workers": workers,
            "estimated_seconds": round(est_s, 1), "estimated_bytes": nbytes}
    if cfg.units:
        from ..units import variation_ranges

        plan["units"] = cfg.units
        plan["unit_variation"] = variation_ranges(profile)
    if args.json:
        print_json(plan)
    else:
        print(f"plan: {len(specs)} sequences, {frames} frames at {w}x{h}, fidelity {cfg.fidelity}, format {cfg.format}")
        print(f"  actions {counts}; splits {splits}")
        left = f" for the {to_go} frames to go" if out_state["done"] else ""
        print(f"  estimated time{left} {est_s / 60:.1f} min on {workers} workers; disk about {nbytes / 1e9:.2f} GB")
        print(f"  --out {args.out}: {_describe_out(out_state)}")
        print("  (dry run: nothing written)")
    return 0


def _describe_out(st: dict) -> str:
    if st["state"] == "new":
        return "new dataset"
    if st["state"] == "replace":
        return f"holds a dataset this code cannot resume; --replace-stale would move it to {st['moved_to']}"
    if st["state"] == "complete":
        return f"complete ({st['total']} sequences): nothing to do"
    return f"resumes: {st['done']} of {st['total']} sequences done, {st['total'] - st['done']} to go"


def run_verify(args: argparse.Namespace) -> int:
    from ..dataset import load_manifest, verify
    from . import print_json

    m = load_manifest(args.dir)
    if not args.stats and (args.stats_out or args.crop is not None or args.no_sheet):
        raise GelsimError("--stats-out, --crop and --no-sheet go with --stats; add --stats")
    from ..stats import STAM_CPU_CROP, check_crop, write_stats

    crop = check_crop(STAM_CPU_CROP if args.crop is None else args.crop)
    faults = verify(args.dir, decode=not args.no_decode)
    summary, paths = None, []
    if args.stats:
        summary, paths = write_stats(args.dir, args.stats_out, crop=crop, sheet=not args.no_sheet)
    if args.json:
        doc = {"ok": not faults, "sequences": len(m.get("sequences", [])), "faults": faults}
        if summary is not None:
            doc.update(stats=summary, stats_files=[str(p) for p in paths])
        print_json(doc)
    else:
        for f in faults:
            print(f)
        if summary is not None:
            from ..stats import stats_report

            print(stats_report(summary))
            print("wrote " + ", ".join(str(p) for p in paths))
        print(f"{len(m.get('sequences', []))} sequences checked: " + ("OK" if not faults else f"{len(faults)} fault(s)"))
    return 1 if faults else 0
