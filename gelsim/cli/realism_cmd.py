"""``gelsim calibrate`` and ``gelsim realism``: fit a sensor profile to real ball presses and score it."""
from __future__ import annotations

import dataclasses
import math
import sys

from ..errors import GelsimError


def register(sub) -> None:
    from . import HelpFormatter

    c = sub.add_parser(
        "calibrate", formatter_class=HelpFormatter,
        help="fit a sensor profile (background, shading table, gel spread, noise) to real ball presses",
        description=(
            "Fit a sensor profile to a data pack of real ball presses (an .npz with f0, imgs,\n"
            "touch_center, touch_radius, colours stored BGR as OpenCV writes them; the format of\n"
            "taxim's calibration set). Writes PROFILE (.toml) and, beside it, PROFILE-background.png\n"
            "and PROFILE-shading.npz. Only the selected frames are used. The presses are placed at the\n"
            "pack's annotated centres, or, where registering the fitted presses against each other shows\n"
            "those are off, at each frame's flat point (gelsim.centres: found in that frame alone). The\n"
            "held-out frames are scored there, with the annotated and the registered scores (the pose\n"
            "fitted: an upper bound) beside it; each skill with its 95% interval over the presses."),
    )
    c.add_argument("datapack", metavar="DATAPACK", help="data pack .npz, or 'r15' / 'mini': taxim 1.4.1's GelSight "
                                                        "R1.5 / Mini set, fetched once into ~/.cache/gelsim")
    c.add_argument("--out", required=True, metavar="PROFILE", help="profile to write, .toml")
    c.add_argument("--frames", default="even", choices=["even", "odd", "all"],
                   help="frames to fit on; the others (odd for even, even for odd) are scored afterwards as the "
                        "held-out score (none for all)")
    c.add_argument("--mm-per-px", type=float, default=0.0295, help="size of one pixel on the gel, mm")
    c.add_argument("--ball-diameter-mm", type=float, default=4.0, help="diameter of the pressed ball, mm")
    c.add_argument("--base-profile", default="gelsight-r15", metavar="NAME|PATH",
                   help="profile giving the sections that are not fitted (gel stiffness, markers)")
    c.add_argument("--channel-order", default="bgr", choices=["bgr", "rgb"], help="colour order of the pack")
    c.add_argument("--description", default=None, metavar="TEXT",
                   help="the profile's description [default: its size and scale, and the pack it was fitted on]")
    c.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    c.set_defaults(handler=run_calibrate)

    r = sub.add_parser(
        "realism", formatter_class=HelpFormatter,
        help="render real ball presses with a profile and score them against the real frames",
        description=(
            "Render each selected ball press of a data pack from its centre and radius (the ball\n"
            "pressed to the depth that gives that contact radius), noiseless, with the fast backend,\n"
            "and compare with the real frame: SSIM/PSNR/L1 on a 400x400 crop around the contact,\n"
            "PSNR/L1 inside the disk of 1.5 contact radii (SSIM on its bounding box), and skill =\n"
            "1 - MSE(sim)/MSE(background) in that disk, with its 95% interval (bootstrap over the\n"
            "scored presses). The background frame f0 as the prediction is the baseline. The\n"
            "headline places the balls from a source independent of the profile (--centres auto);\n"
            "the scores at the annotated centres and at registered ones (an upper bound) follow. Small slopes: on the ball's flat top (true slope < 0.2, where fabric\n"
            "texture lies), the RMS difference of the colour change and its gain per unit slope,\n"
            "simulated over real, per channel."),
    )
    r.add_argument("--profile", default="gelsight-r15", metavar="NAME|PATH", help="sensor profile")
    r.add_argument("--datapack", default=None, metavar="PATH",
                   help="data pack .npz, or 'r15' / 'mini' (taxim 1.4.1's GelSight R1.5 / Mini set, fetched once "
                        "into ~/.cache/gelsim) [default: r15]")
    r.add_argument("--frames", default="odd", choices=["odd", "even", "all"], help="frames to score")
    r.add_argument("--mm-per-px", type=float, default=None,
                   help="size of one pixel on the gel, mm [default: the profile's]")
    r.add_argument("--ball-diameter-mm", type=float, default=4.0, help="diameter of the pressed ball, mm")
    r.add_argument("--channel-order", default="bgr", choices=["bgr", "rgb"], help="colour order of the pack")
    r.add_argument("--centres", default="auto", choices=["auto", "annotated", "detected", "registered"],
                   help="where the scored balls are placed for the headline score: auto = as `gelsim calibrate` "
                        "places held-out frames, never from the scored profile (the pack's annotated centres where "
                        "they hold, else each frame's flat point where that detector agrees with the registration "
                        "of the other frames); detected = each frame's flat point (where the colour change "
                        "vanishes); registered = each press registered against a table of the other frames "
                        "(odd against even, even against odd): the pose fitted, an upper bound. The annotated "
                        "and registered scores are printed beside the headline")
    r.add_argument("--out", default=None, metavar="FILE.png",
                   help="write real | simulated | 3 x |difference| of the first scored frame [default: none]")
    r.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    r.set_defaults(handler=run_realism)


def _positive(name: str, v: float) -> None:
    if not (math.isfinite(v) and v > 0):
        raise GelsimError(f"{name} {v} is not a positive number; give a value > 0")


R15_NOTE = ("Data: taxim 1.4.1's GelSight R1.5 calibration set (Si and Yuan, RA-L 2022; MIT licence).\n"
            "The background PNG is its f0 frame smoothed (sigma 1 px) at half resolution; no raw frame is shipped.")
MINI_NOTE = ("Data: taxim 1.4.1's GelSight Mini ball presses (taxim/calib/gelsight_mini/dataPack.npz; MIT licence).\n"
             "The background PNG is its f0 frame smoothed (sigma 1 px) at half resolution; no raw frame is shipped.")
NOTES = {"r15": R15_NOTE, "mini": MINI_NOTE}


def _pack(path, channel_order):
    from ..realism import load_datapack, resolve_datapack

    return load_datapack(resolve_datapack(path), channel_order)


def run_calibrate(args) -> int:
    from ..calibrate import calibrate, heldout_score
    from ..sensor import load_profile
    from . import print_json

    _positive("--mm-per-px", args.mm_per_px)
    _positive("--ball-diameter-mm", args.ball_diameter_mm)
    if not str(args.out).endswith(".toml"):     # (calibrate says it too, after minutes of fitting)
        raise GelsimError(f"--out {args.out} must end in .toml; the table and background go beside it")
    base = load_profile(args.base_profile)
    pack = _pack(args.datapack, args.channel_order)
    log = (lambda m: None) if args.json else (lambda m: print(m, file=sys.stderr, flush=True))
    rep = calibrate(pack, base, args.out, frames=args.frames, mm_per_px=args.mm_per_px,
                    ball_diameter_mm=args.ball_diameter_mm, log=log, description=args.description,
                    note=NOTES.get(args.datapack, ""))
    log("scoring the held-out frames")
    rep["heldout"] = heldout_score(rep["profile"], pack, args.frames, args.ball_diameter_mm, rep["centres"])
    if args.json:
        print_json(rep)
        return 0
    b = rep["best"]
    print(f"wrote {rep['profile']} (+ {rep['table']}, {rep['background']}) from {len(rep['frames'])} frames: "
          f"thickness {b['thickness_mm']} mm, smoothing {b['membrane_smoothing_mm']} mm, "
          f"shadow slope {b['shadow_tan']}, penumbra {b.get('shadow_soft_mm', 0.0)} mm, "
          f"table smoothness {b.get('smooth_weight', 3.0)}, "
          f"cross-validated MSE {b['cv_mse']:.1f}")
    c = rep["centres"]
    print(f"press centres: fitted frames {c['fit']}, held-out frames {c['headline']} ({centres_reason(c)})")
    h = rep["heldout"]
    if h is None:
        print("held-out score: none (fitted on all frames)")
    else:
        print(f"held-out score on the {h['frames']} {h['frame_set']} frames:")
        for line in score_lines(h):
            print("  " + line)
    return 0


# the frames a scored set's centres are chosen on (gelsim.calibrate.choose_centres): the others
REGISTER_AGAINST = {"odd": "even", "even": "odd", "all": "all"}
CENTRES = ("auto", "annotated", "detected", "registered")


def realism_report(profile="gelsight-r15", datapack=None, frames: str = "odd", *, mm_per_px: float | None = None,
                   ball_diameter_mm: float = 4.0, channel_order: str = "bgr", out=None,
                   centres: str = "auto") -> dict:
    """What ``gelsim realism --json`` prints: :func:`gelsim.calibrate.headline_report` of the scores at
    ``centres`` ("auto": the independent source :func:`gelsim.calibrate.choose_centres` picks on the
    other frames), with the annotated and registered scores beside it, and ``"choice"`` (that
    function's report). ``mm_per_px`` None keeps the profile's."""
    from ..atomic import write_png
    from ..calibrate import centre_scores, choose_centres, headline_report
    from ..errors import check_choice
    from ..realism import check_geometry, side_by_side
    from ..sensor import load_profile

    if mm_per_px is not None:
        _positive("--mm-per-px", mm_per_px)
    _positive("--ball-diameter-mm", ball_diameter_mm)
    check_choice("centres", centres, CENTRES)
    prof = load_profile(profile)
    pack = _pack(datapack, channel_order)
    h, w = pack.shape
    if prof.shape != (h, w):
        raise GelsimError(f"profile {prof.name} is {prof.image.width_px}x{prof.image.height_px} px but the data pack's "
                          f"frames are {w}x{h}; score a profile fitted to this pack (`gelsim calibrate`)")
    if mm_per_px is not None:
        prof = dataclasses.replace(prof, image=dataclasses.replace(prof.image, mm_per_px=mm_per_px))
    check_geometry(pack, prof.image.mm_per_px, ball_diameter_mm, pack.source or "data pack")
    if not pack.select(frames):
        raise GelsimError(f"the data pack has no {frames} frames; give --frames all or a larger pack")
    choice = choose_centres(pack, REGISTER_AGAINST[frames], prof.image.mm_per_px, ball_diameter_mm)
    chosen = choice["headline"] if centres == "auto" else centres
    sources = [chosen] + [s for s in (choice["headline"], "annotated", "registered") if s != chosen]
    keep = pack.select(frames)[0]
    scores = centre_scores(prof, pack, frames, dict(choice, headline=chosen), ball_diameter_mm,
                           list(dict.fromkeys(sources)), keep=keep if out else None)
    rep = headline_report(scores, chosen)
    rep["choice"] = choice
    example = rep.pop("example", None)
    if out and example is not None:
        write_png(out, side_by_side(*example))
        rep["image"] = str(out)
    rep["profile"] = prof.name
    return rep


LABELS = {"annotated": "annotated centres", "detected": "detected centres (flat points)",
          "registered": "registered centres (pose fitted: upper bound)"}


def centres_reason(choice: dict) -> str:
    """Why the held-out frames are placed where they are (:func:`gelsim.calibrate.choose_centres`)."""
    reg, det = choice["registration"], choice["detection"]
    if choice["headline"] == "detected":
        return (f"the annotation is off: registering the fitted frames removes {100 * reg['explained']:.0f}% of its "
                f"misfit; their flat points agree with that registration to {det['agreement_px']:.2f} px RMS")
    why = (f"registering the fitted frames would remove only {100 * reg['explained']:.0f}% of its misfit"
           if not reg["applied"] else f"the annotation is off, but the flat-point detector cannot stand in: "
                                      f"{det['reason']}")
    return f"the annotation: {why}"


def score_lines(rep: dict) -> list[str]:
    """Text lines of a :func:`gelsim.calibrate.headline_report`: the headline, then each comparison."""
    def one(label, r):
        lo, hi = r["skill_ci95"]
        return (f"{label}: skill {r['skill']:.3f} [{lo:.3f}, {hi:.3f}], contact PSNR {r['contact']['psnr']:.2f} dB "
                f"(background alone {r['baseline']['contact']['psnr']:.2f}), contact L1 {r['contact']['l1']:.2f} "
                f"(background alone {r['baseline']['contact']['l1']:.2f})")

    lines = [one("headline, " + LABELS[rep["centres"]], rep), "  " + small_slope_line(rep["small_slope"])]
    for name, r in rep["compare"].items():
        lines.append(one("beside it, " + LABELS[name], r))
    return lines


def run_realism(args) -> int:
    from . import print_json

    if args.out is not None:
        from ..atomic import check_out_file

        check_out_file(args.out)                 # before the data pack is read and scored
    rep = realism_report(args.profile, args.datapack, args.frames, mm_per_px=args.mm_per_px,
                         ball_diameter_mm=args.ball_diameter_mm, channel_order=args.channel_order, out=args.out,
                         centres=args.centres)
    if args.json:
        print_json(rep)
        return 0
    print(f"{rep['frames']} {args.frames} frames, profile {rep['profile']}, {LABELS[rep['centres']]}, "
          f"{rep['ms_per_frame']:.1f} ms per frame (imprint + render)")
    if args.centres == "auto":
        print(f"centres: {centres_reason(rep['choice'])}")
    print(f"{'':10s} {'crop SSIM':>9s} {'PSNR':>6s} {'L1':>5s} | {'contact SSIM':>12s} {'PSNR':>6s} {'L1':>5s} | skill")
    for name, r in (("simulated", rep), ("baseline", rep["baseline"])):
        print(f"{name:10s} {r['crop']['ssim']:9.4f} {r['crop']['psnr']:6.2f} {r['crop']['l1']:5.2f} | "
              f"{r['contact']['ssim']:12.4f} {r['contact']['psnr']:6.2f} {r['contact']['l1']:5.2f} | {r['skill']:.3f}")
    for line in score_lines(rep):
        print(line)
    if rep.get("image"):
        print(f"wrote {rep['image']}")
    return 0


def small_slope_line(ss: dict) -> str:
    """The text line of the small-slope metric (gelsim.realism.small_slope_summary)."""
    rgb = "RGB"
    if ss["pixels"] == 0:
        return f"small slopes (< {ss['slope_below']:g}): no contact pixel that flat"
    def num(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    per = ", ".join(f"{c} {num(v, '.1f')}" for c, v in zip(rgb, ss["rms_dn_rgb"]))
    ratio = " ".join(f"{c} {num(v, '.2f')}" for c, v in zip(rgb, ss["gain_ratio"]))
    real = "/".join(num(v, ".0f") for v in ss["gain_real_dn"])
    return (f"small slopes (< {ss['slope_below']:g}, {ss['pixels']} contact px): RMS {ss['rms_dn']:.2f} DN "
            f"({per}; background alone {ss['baseline_rms_dn']:.2f}); gain sim/real {ratio} "
            f"(real {real} DN per unit slope)")
