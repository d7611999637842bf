"""The held-out realism checks of issue #44, each fitted on frames it does not score:

- ``mini``: `gelsim calibrate` on the GelSight Mini pack's even frames, scored on its odd frames with
  the headline protocol (centres independent of the scored profile, gelsim.calibrate.choose_centres),
  the annotated and the registered (pose fitted: an upper bound) scores beside it;
- ``r15``: the same on the GelSight R1.5 pack;
- ``r15-320``: the R1.5 pack at 320x240 (each frame area-averaged 2 x 2, centres and radii halved,
  0.059 mm/px), calibrated on its even frames and scored on its odd ones;
- ``r15-six``: the R1.5 calibrated on six frames only (frames 0, 2, ..., 10), scored on all 24 odd
  frames of the pack (none of them fitted);
- ``r15-six-spread``: the same with six frames spread over the pack's order (0, 8, ..., 40).

Skill with its 95% interval (bootstrap over the scored presses, gelsim.realism.skill_interval).

    GELSIM_CACHE=... .venv/bin/python benchmarks/realism_checks.py [--only mini,r15-six] [--json]

Uses the cached taxim packs (`gelsim realism --datapack mini` fetches them once); writes its profiles
into a temporary folder.
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from gelsim.calibrate import calibrate, centre_scores, choose_centres
from gelsim.cli import print_json, run_script
from gelsim.realism import DataPack, fetch_taxim_pack, load_datapack
from gelsim.sensor import load_profile

MM_PER_PX = {"mini": 0.0317, "r15": 0.0295}
BALL_MM = 4.0
CHECKS = ("mini", "r15", "r15-320", "r15-six", "r15-six-spread")
# the fitting pack of the six-frame checks: its even positions are the six fitted frames (the odd ones
# only satisfy calibrate's check for frames to score; the scores are on the whole pack's odd frames)
SIX = {"r15-six": list(range(12)), "r15-six-spread": [i + k for i in range(0, 48, 8) for k in (0, 1)]}


def half_size(pack: DataPack) -> DataPack:
    """``pack`` at half the resolution: frames area-averaged 2 x 2, centres in the halved pixel grid
    (pixel centres at integers: (c + 0.5) / 2 - 0.5), radii halved."""
    def down(img):
        h, w = img.shape[:2]
        return cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)

    return DataPack(f0=down(pack.f0), imgs=np.stack([down(i) for i in pack.imgs]),
                    centers_px=(pack.centers_px + 0.5) / 2.0 - 0.5, radii_px=pack.radii_px / 2.0,
                    source=pack.source)


def frames_subset(pack: DataPack, idx: list[int]) -> DataPack:
    """The frames ``idx`` of ``pack``, in that order."""
    return dataclasses.replace(pack, imgs=pack.imgs[idx], centers_px=pack.centers_px[idx], radii_px=pack.radii_px[idx])


def scores(profile_path: Path, pack: DataPack, mm_per_px: float) -> dict:
    """The profile scored on ``pack``'s odd frames: the headline (centres chosen on the even frames) and the
    annotated and registered scores beside it; skill and its interval per source."""
    choice = choose_centres(pack, "even", mm_per_px, BALL_MM)
    head = choice["headline"]
    sources = [head] + [s for s in ("annotated", "registered") if s != head]
    got = centre_scores(load_profile(profile_path), pack, "odd", choice, BALL_MM, sources)
    return {"headline": head, "frames": got[head]["frames"],
            **{s: {"skill": r["skill"], "skill_ci95": r["skill_ci95"], "contact_psnr_db": r["contact"]["psnr"]}
               for s, r in got.items()}}


def run(name: str, out: Path) -> dict:
    t = time.time()
    pack = load_datapack(fetch_taxim_pack("mini" if name == "mini" else "r15"))
    mm = MM_PER_PX["mini" if name == "mini" else "r15"]
    fit_pack = pack
    if name == "r15-320":
        pack = fit_pack = half_size(pack)
        mm *= 2.0
    elif name in SIX:
        fit_pack = frames_subset(pack, SIX[name])
    rep = calibrate(fit_pack, load_profile("gelsight-r15"), out / f"{name}.toml", frames="even", mm_per_px=mm,
                    ball_diameter_mm=BALL_MM)
    res = scores(out / f"{name}.toml", pack, mm)
    res.update(fitted_frames=len(rep["frames"]), size=[pack.shape[1], pack.shape[0]], mm_per_px=mm,
               seconds=round(time.time() - t, 1))
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=",".join(CHECKS), help=f"comma-separated checks of {', '.join(CHECKS)}")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args()
    names = [n for n in args.only.split(",") if n]
    bad = [n for n in names if n not in CHECKS]
    if bad:
        ap.error(f"unknown check {bad[0]!r}; choose from {', '.join(CHECKS)}")
    with tempfile.TemporaryDirectory() as d:
        results = {}
        for n in names:
            results[n] = run(n, Path(d))
            if not args.json:
                r = results[n]
                line = ", ".join(f"{s} {r[s]['skill']:.3f} [{r[s]['skill_ci95'][0]:.3f}, {r[s]['skill_ci95'][1]:.3f}]"
                                 for s in dict.fromkeys((r["headline"], "annotated", "registered")))
                print(f"{n}: {r['size'][0]}x{r['size'][1]}, fitted on {r['fitted_frames']} frames, scored on "
                      f"{r['frames']} odd ones; headline ({r['headline']} centres): {line} ({r['seconds']} s)", flush=True)
    if args.json:
        print_json(results)
    return 0


if __name__ == "__main__":
    run_script(main)
