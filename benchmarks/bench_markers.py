"""The marker stage alone, on the imprints of a sample of the default dataset: its CPU per call and how far its
markers move between two versions of the code.

    python benchmarks/bench_markers.py --capture CASES.pkl [--fabrics 4] [--sequences-per-fabric 2]
    python benchmarks/bench_markers.py --cases CASES.pkl [--save POS.npz] [--against POS.npz] [--repeat 5]

``--capture`` generates a sample of the default dataset (balanced, 960x720, one worker, as
``profile_frame.py`` does) and keeps every call of the numpy engine's ``displace``: the imprint (cropped to
its touched box), shear, twist and rest markers, with the profile and fidelity. ``--cases`` replays them
through :func:`gelsim.markers.displace` as the code now stands: thread CPU ms per call (the best of
``--repeat`` passes over all cases, so that another process's load inflates it less), and with ``--against``
the largest and mean distance, px, of the centres and corners from a saved run's (``--save``), both as the
stage returns them (float32, as the labels hold them: about 3e-5 px apart near x = 500 px), with the count of
centres whose float32 value changes.

The cases file is a pickle this script writes and reads on the same machine; do not read one from elsewhere.
"""
from __future__ import annotations

import argparse
import functools
import pickle
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from gelsim.cli import print_json, run_script


def capture(path: Path, fabrics: int, per_fabric: int) -> int:
    import gelsim.engines as engines
    from gelsim.dataset import GenerateConfig, generate
    from gelsim.runtime import configure_worker

    configure_worker()
    cases: list[dict] = []
    setup: dict = {}
    f = engines.displace

    @functools.wraps(f)
    def keep(profile, fidelity, imprint, **kw):
        nz = (imprint.depth_mm > 0) | imprint.contact_mask
        rows, cols = np.flatnonzero(nz.any(1)), np.flatnonzero(nz.any(0))
        if rows.size:
            r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            setup.setdefault("profile", profile)
            setup.setdefault("fidelity", fidelity)
            cases.append({"shape": imprint.depth_mm.shape, "box": (r0, r1, c0, c1),
                          "depth": imprint.depth_mm[r0:r1, c0:c1].copy(), "mask": imprint.contact_mask[r0:r1, c0:c1].copy(),
                          "shear_mm": tuple(map(float, kw.get("shear_mm", (0.0, 0.0)))),
                          "twist_deg": float(kw.get("twist_deg", 0.0)), "rest": np.asarray(kw["rest"]).copy()})
        return f(profile, fidelity, imprint, **kw)

    engines.displace = keep
    out = Path(tempfile.mkdtemp(prefix="gelsim-bench-markers-"))
    try:
        generate(GenerateConfig(fabrics=fabrics, sequences_per_fabric=per_fabric), out / "ds", workers=1, previews=False)
    finally:
        engines.displace = f
        shutil.rmtree(out, ignore_errors=True)
    with open(path, "wb") as fh:
        pickle.dump({**setup, "cases": cases}, fh)
    print(f"{len(cases)} imprints in contact kept in {path}")
    return 0


def replay(args) -> int:
    from gelsim.gel import Imprint
    from gelsim.markers import displace

    with open(args.cases, "rb") as fh:
        doc = pickle.load(fh)
    profile, fidelity = doc["profile"], doc["fidelity"]
    imprints = []
    for c in doc["cases"]:
        depth = np.zeros(c["shape"], np.float32)
        mask = np.zeros(c["shape"], bool)
        r0, r1, c0, c1 = c["box"]
        depth[r0:r1, c0:c1] = c["depth"]
        mask[r0:r1, c0:c1] = c["mask"]
        imprints.append(Imprint(depth, mask, 0.0, 0.0, 0.0, False))

    def one_pass():
        return [displace(profile, fidelity, imp, shear_mm=c["shear_mm"], twist_deg=c["twist_deg"], rest=c["rest"])
                for imp, c in zip(imprints, doc["cases"])]

    one_pass()   # warm: caches and tables built
    best = float("inf")
    for _ in range(args.repeat):
        t = time.thread_time()
        markers = one_pass()
        best = min(best, time.thread_time() - t)
    xy = np.stack([m.xy_px for m in markers])
    corners = np.stack([m.corners_px for m in markers])
    res = {"cases": len(markers), "markers": int(xy.shape[1]), "cpu_ms_per_call": round(1000 * best / len(markers), 4),
           "repeat": args.repeat, "date": time.strftime("%Y-%m-%d %H:%M")}
    if args.against:
        with np.load(args.against) as z:
            xy0, corners0 = z["xy"], z["corners"]
        d_xy = np.hypot(*(xy.astype(np.float64) - xy0).transpose(2, 0, 1))
        d_c = np.hypot(*(corners.astype(np.float64) - corners0).reshape(-1, 2).T)
        res.update(max_dxy_px=float(d_xy.max()), mean_dxy_px=float(d_xy.mean()),
                   max_dcorner_px=float(d_c.max()), mean_dcorner_px=float(d_c.mean()),
                   centres_float32_changed=int((xy != xy0).any(-1).sum()), centres=int(d_xy.size))
    if args.save:
        np.savez(args.save, xy=xy, corners=corners)
    print_json(res)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, help="generate a sample and keep its imprints here")
    ap.add_argument("--fabrics", type=int, default=4)
    ap.add_argument("--sequences-per-fabric", type=int, default=2)
    ap.add_argument("--cases", type=Path, help="replay the imprints kept here")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--save", type=Path, help="write the markers (float32) here (.npz)")
    ap.add_argument("--against", type=Path, help="compare with the markers saved here")
    args = ap.parse_args()
    from gelsim.errors import GelsimError

    if args.capture:
        return capture(args.capture, args.fabrics, args.sequences_per_fabric)
    if not args.cases:
        raise GelsimError("give --capture FILE or --cases FILE")
    return replay(args)


if __name__ == "__main__":
    run_script(main)
