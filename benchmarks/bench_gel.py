"""Time the gel imprint models and the markers at 960x720, ms per frame, on one core.

    .venv/bin/python benchmarks/bench_gel.py [--json] [--repeat N] [--agreement]

Cases: a 6 mm sphere pressed with 0.2 N, and a fabric-like texture (0.08 mm woven relief, 0.35 x
0.3 mm, over a gentle dome, touching most of the pad) pressed with 1 N, rigid and on a cotton
poplin's support (catalog fabric 1's compression and yarn flattening), texture scale 0.35 mm.
Imprint: the two-scale model at the fast (0.5) and balanced (1.0) imprint scales, the pyramid
(kept for comparison) at 1.0, the elastic reference. Markers: "gaussian" and "elastic" on the
sphere's and the fabric's balanced imprint with shear and twist. Reports the median of --repeat
runs, wall-clock and CPU time (CPU time is steadier on a shared machine). Also catalog fabrics
over the whole pad at 2 N on their support, as gelsim.sequence presses them (plain weave, knit,
leather; not the elastic reference: it takes 10-60 s there).
``--agreement`` compares the fast and balanced models with the elastic reference on seven catalog
fabrics (gelsim.gel.agreement, the cases of tests/gelsim/test_gel_fabrics.py: texture correlation,
slope, contact and approach ratios), rigid and on their support; a few minutes.
The pyramid's force law is refitted by tools/fit_pyramid_law.py.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from gelsim import indenters  # noqa: E402
from gelsim.cli import print_json, print_result, run_script  # noqa: E402
from gelsim.runtime import configure_worker  # noqa: E402
from gelsim.fabrics import load_catalog  # noqa: E402
from gelsim.fidelity import get_fidelity  # noqa: E402
from gelsim.gel import press  # noqa: E402
from gelsim.markers import displace  # noqa: E402
from gelsim.scene import FabricObject, field_heights  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402


# The fabric-like relief's larger pitch, mm: its texture scale for the two-scale model.
FABRIC_LIKE_TEXTURE_MM = 0.35


def fabric_like(profile, seed: int = 0) -> np.ndarray:
    """Woven-like relief (0.35 x 0.3 mm, 0.08 mm deep) on a 0.3 mm dome over the pad, mm."""
    h, w = profile.shape
    mmpp = profile.image.mm_per_px
    y = (np.arange(h) - (h - 1) / 2)[:, None] * mmpp
    x = (np.arange(w) - (w - 1) / 2)[None, :] * mmpp
    rng = np.random.default_rng(seed)
    weave = 0.04 * (np.sin(2 * np.pi * x / 0.35) * np.sin(2 * np.pi * y / 0.3) + 1.0)
    dome = 0.3 * (1.0 - (x * x + y * y) / 150.0)
    return (weave + dome + 0.005 * rng.standard_normal((h, w))).astype(np.float32)


def agreement_table(as_json: bool) -> int:
    """Print the agreement of the fast and balanced imprints with the elastic reference."""
    from gelsim.gel import agreement as ag

    rows = []
    for supported in (False, True):
        for name in ag.FABRICS:
            t0 = time.perf_counter()
            ref = ag.imprint(name, supported, "elastic")
            t_ref = time.perf_counter() - t0
            for level in ag.LEVELS:
                a = ag.agreement(ag.imprint(name, supported, level), ref)
                row = {"fabric": name, "id": ag.FABRICS[name], "support": supported, "level": level,
                       **{k: round(v, 3) for k, v in a.items()},
                       "contact_ref": round(float(ag.inner(ref.contact_mask).mean()), 3),
                       "approach_ref_mm": round(ref.indentation_mm, 4), "elastic_s": round(t_ref, 1)}
                rows.append(row)
                if not as_json:
                    print(f"{name:9} {'support' if supported else 'rigid':8} {level:9} corr {a['corr']:.3f}  "
                          f"slope {a['slope']:.2f}  contact {a['contact']:.2f} (ref {row['contact_ref']:.3f})  "
                          f"approach {a['approach']:.2f} (ref {ref.indentation_mm:.4f} mm)", flush=True)
    if as_json:
        print_json({"patch_px": list(ag.PATCH.shape[::-1]), "force_n": ag.FORCE_N, "rows": rows})
    return 0


def timed(fn, repeat: int) -> dict:
    fn()  # warm caches (kernels, tables)
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - t0) * 1000)
        cpu.append((time.process_time() - c0) * 1000)
    return {"wall_ms": round(statistics.median(wall), 3), "cpu_ms": round(statistics.median(cpu), 3)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    ap.add_argument("--repeat", type=int, default=20, help="runs per fast case (elastic: a quarter, at least 1)")
    ap.add_argument("--agreement", action="store_true", help="fast models vs elastic on seven fabrics (table)")
    args = ap.parse_args(argv)
    configure_worker()
    if args.agreement:
        return agreement_table(args.json)
    prof = load_profile("vitac")
    sphere = indenters.sphere(6.0, prof, center_mm=(0.8, -0.4))
    fabric = fabric_like(prof)
    poplin = load_catalog()[1]
    # (protrusion, force N, support or None, texture scale mm or None)
    cases = {"sphere": (sphere, 0.2, None, None), "fabric": (fabric, 1.0, None, FABRIC_LIKE_TEXTURE_MM),
             "fabric_supported": (fabric, 1.0, poplin.support(), FABRIC_LIKE_TEXTURE_MM)}
    for fid in (1, 47, 86):
        fab = load_catalog()[fid]
        cases[f"fabric{fid}_pad"] = (field_heights(FabricObject(fab), prof), 2.0, fab.support(), fab.texture_mm)
    bal = get_fidelity("balanced")
    levels = {"twoscale_fast": get_fidelity("fast"), "twoscale_balanced": bal,
              "pyramid_balanced": dataclasses.replace(bal, imprint_model="pyramid"),
              "elastic_reference": dataclasses.replace(get_fidelity("reference"), imprint_model="elastic")}
    results: dict = {"resolution": list(prof.shape[::-1]), "imprint": {}, "markers": {},
                     "load_avg": os.getloadavg()[0]}
    imprints = {}
    for lname, fid in levels.items():
        for cname, (prot, force, support, texture_mm) in cases.items():
            if fid.imprint_model == "elastic" and cname.endswith("_pad"):
                continue
            rep = max(1, args.repeat // 4) if fid.imprint_model == "elastic" else args.repeat
            run = lambda: press(prot, prof, fid, force_n=force, support=support, texture_mm=texture_mm)  # noqa: E731
            r = timed(run, rep)
            im = run()
            r.update(indentation_mm=round(im.indentation_mm, 5), contact_area_mm2=round(im.contact_area_mm2, 3),
                     imprint_model=fid.imprint_model, imprint_scale=fid.imprint_scale)
            results["imprint"][f"{lname}/{cname}"] = r
            if lname == "twoscale_balanced":
                imprints[cname] = im
            if not args.json:
                print(f"imprint {lname:18} {cname:17} {r['wall_ms']:9.2f} ms wall {r['cpu_ms']:9.2f} ms cpu  "
                      f"d={r['indentation_mm']:.4f} mm  A={r['contact_area_mm2']:.2f} mm^2", flush=True)
    for model in ("gaussian", "elastic"):
        fid = dataclasses.replace(get_fidelity("balanced"), marker_model=model)
        for cname in ("sphere", "fabric"):
            im = imprints[cname]
            r = timed(lambda: displace(prof, fid, im, shear_mm=(0.1, 0.05), twist_deg=2.0), args.repeat)
            results["markers"][f"{model}/{cname}"] = r
            if not args.json:
                print(f"markers {model:18} {cname:17} {r['wall_ms']:9.2f} ms wall {r['cpu_ms']:9.2f} ms cpu", flush=True)
    results["load_avg_end"] = os.getloadavg()[0]
    return print_result(args.json, results,
                        f"load average {results['load_avg']:.2f} -> {results['load_avg_end']:.2f} (2 cores shared)")


if __name__ == "__main__":
    run_script(main)
