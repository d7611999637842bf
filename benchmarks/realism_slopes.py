"""The shading's colour change against the real frames' by surface slope (issue #11, part 4).

On each scored ball press the gel takes the ball's shape inside the annotated contact, so the
surface slope there is known (``gelsim.realism.ball_slope``). For slope bins this prints, per
channel, the RMS difference of the colour change (simulated minus its background against real
minus ``f0``) and the gain per unit slope, simulated over real (``gelsim.realism``'s small-slope
metric restricted to the bin). ``gelsim realism`` reports the bin below 0.2.

    .venv/bin/python benchmarks/realism_slopes.py [--profile gelsight-r15] [--frames odd] [--json]

Uses the cached R1.5 data pack (``gelsim realism`` fetches it once), or ``--datapack PATH``.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from gelsim.cli import print_json, run_script
from gelsim.optics import Renderer
from gelsim.realism import ball_depth, load_datapack, resolve_datapack, small_slope_frame, small_slope_summary
from gelsim.sensor import load_profile

# 0-0.05 and 0.05-0.1: a fine weave's tilts; 0.1-0.2: coarser relief; above: the ball's rim
BINS = (0.0, 0.05, 0.1, 0.2, 0.4, np.inf)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", default="gelsight-r15", help="sensor profile; default gelsight-r15")
    ap.add_argument("--datapack", default=None, help="data pack .npz; default the cached R1.5 pack")
    ap.add_argument("--frames", default="odd", choices=["odd", "even", "all"], help="frames to score; default odd")
    ap.add_argument("--mm-per-px", type=float, default=0.0295, help="pixel size on the gel, mm; default 0.0295")
    ap.add_argument("--ball-diameter-mm", type=float, default=4.0, help="ball diameter, mm; default 4")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    args = ap.parse_args()
    pack = load_datapack(resolve_datapack(args.datapack))
    prof = load_profile(args.profile)
    if prof.shape != pack.shape:
        prof = prof.with_resolution(pack.shape[1], pack.shape[0])
    prof = dataclasses.replace(prof, image=dataclasses.replace(prof.image, mm_per_px=args.mm_per_px))
    ren = Renderer(prof)
    bg, f0 = ren.background_float(), pack.f0.astype(np.float32)
    parts = {b: [] for b in zip(BINS[:-1], BINS[1:])}
    for i in pack.select(args.frames):
        c, r = pack.centers_px[i], pack.radii_px[i]
        sim = ren.render(ball_depth(prof, c, r, args.ball_diameter_mm), None, noise=False)
        for lo, hi in parts:
            parts[(lo, hi)].append(small_slope_frame(sim - bg, pack.imgs[i] - f0, c, r, args.mm_per_px,
                                                     args.ball_diameter_mm, limit=hi, lower=lo))
    rows = []
    for (lo, hi), p in parts.items():
        s = small_slope_summary(p, hi)
        rows.append({"slope_from": lo, "slope_to": None if np.isinf(hi) else hi, **s})
    if args.json:
        print_json({"profile": prof.name, "frames": args.frames, "bins": rows})
        return 0
    print(f"profile {prof.name}, {args.frames} frames; colour change vs slope (sim - real, per channel R/G/B)")
    print("| slope | pixels | RMS DN | RMS R / G / B | background alone | gain sim/real R / G / B | real gain DN per unit slope |")
    print("|---|---:|---:|---|---:|---|---|")
    for r in rows:
        rng = f"{r['slope_from']:g}-{r['slope_to']:g}" if r["slope_to"] is not None else f"> {r['slope_from']:g}"
        f = lambda v, fmt: "n/a" if v is None else format(v, fmt)  # noqa: E731
        print(f"| {rng} | {r['pixels']} | {f(r['rms_dn'], '.2f')} | {' / '.join(f(v, '.1f') for v in r['rms_dn_rgb'])} | "
              f"{f(r['baseline_rms_dn'], '.2f')} | {' / '.join(f(v, '.2f') for v in r['gain_ratio'])} | "
              f"{' / '.join(f(v, '.0f') for v in r['gain_real_dn'])} |")
    return 0


if __name__ == "__main__":
    run_script(main)
