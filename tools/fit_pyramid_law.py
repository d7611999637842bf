"""Fit the pyramid imprint's force law to the elastic model and write gelsim/assets/imprint_law.toml.

The pyramid model (gelsim/gel/pyramid.py) is no longer a default level (the two-scale model
replaced it); its law is kept so that it can be compared. A few minutes:

    .venv/bin/python tools/fit_pyramid_law.py           # print the fit and its residuals
    .venv/bin/python tools/fit_pyramid_law.py --write   # also write gelsim/assets/imprint_law.toml
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
from typing import Any

import numpy as np

from gelsim.atomic import atomic_write_text
from gelsim.cli import run_script
from gelsim.fidelity import get_fidelity
from gelsim.gel import press
from gelsim.gel.layer import disk_layer_factor, effective_modulus_mpa
from gelsim.gel.pyramid import LAW_FILE, LawSamples, imprint_law, press_pyramid
from gelsim.gel.util import membrane_blur
from gelsim.params import dump_toml
from gelsim.sensor import load_profile


def _fit_cases(profile, diameters=(2.0, 4.0, 10.0, 20.0), forces=(0.003, 0.01, 0.03, 0.1, 0.3)):
    """Spheres of the fit over two decades of force: (name, protrusion, force N)."""
    from gelsim import indenters

    return [(f"sphere {d:g} mm", indenters.sphere(d, profile), f) for d in diameters for f in forces]


def _broad_cases(profile, forces=(0.5, 2.0)):
    """Contacts much wider than the gel is thick: the whole pad on a plane and on gentle
    domes (radius 60 and 300 mm), as when a fabric lies over the pad: (name, protrusion, force N)."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    y = (np.arange(h) - (h - 1) / 2)[:, None] * mm
    x = (np.arange(w) - (w - 1) / 2)[None, :] * mm
    out = [(f"plane (whole pad)", np.zeros((h, w), np.float32), f) for f in forces]
    for r in (60.0, 300.0):
        dome = (-(x * x + y * y) / (2 * r)).astype(np.float32)
        out += [(f"dome R {r:g} mm", dome - dome.min(), f) for f in forces]
    return out


def fit_pyramid_law(profile=None, resolution_px: int = 480) -> dict[str, Any]:
    """Fit the pyramid model's constants to the elastic model; returns them with residuals.

    c from spheres on a thick gel (20 mm: a half-space for these contacts); kappa and beta
    by least squares on log force from spheres on the profile's gel and from broad contacts
    (the whole pad on a plane and on gentle domes, at a quarter of the resolution: smooth
    shapes); the coarsest blur from the depth outside a sphere's contact. A cylinder on its
    side is reported as a check that took no part in the fit. A few minutes;
    ``tools/fit_pyramid_law.py --write`` writes the result to LAW_FILE.
    """
    from scipy.optimize import least_squares

    from gelsim import indenters

    base = (profile or load_profile("vitac")).with_resolution(resolution_px)
    broad = base.with_resolution(max(64, resolution_px // 2))
    elastic = dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0)
    law0 = imprint_law()
    dx = base.image.mm_per_px

    def surface_volume(prot, delta, prof, trial):
        # Volume under the pyramid's gel surface at approach delta (mm^3), and the apparent area.
        mm = prof.image.mm_per_px
        depth, *_ = press_pyramid(prot.astype(np.float32), mm, prof.gel, None, delta, None, "touched", law=trial)
        app = LawSamples(prot.max() - prot, mm, prof.gel, prof.gel.max_indentation_mm, trial).at(delta)[1]
        return float(depth.sum(dtype=np.float64)) * mm * mm, app

    def law_force(vol, area, gel, c, kappa, beta):
        area = np.asarray(area, dtype=np.float64)
        r = disk_layer_factor(kappa * np.sqrt(area / math.pi) / gel.thickness_mm, gel.poisson_ratio)
        return c * effective_modulus_mpa(gel) * np.asarray(vol) / np.sqrt(area) / r ** beta

    thick = dataclasses.replace(base, gel=dataclasses.replace(base.gel, thickness_mm=20.0))
    runs, broad_runs, thick_runs = [], [], []
    for name, prot, f in _fit_cases(base):
        runs.append((name, prot, f, press(prot, base, elastic, force_n=f)))
    for name, prot, f in _broad_cases(broad):
        broad_runs.append((name, prot, f, press(prot, broad, elastic, force_n=f)))
    for name, prot, f in _fit_cases(thick, diameters=(4.0, 10.0), forces=(0.003, 0.03, 0.3)):
        thick_runs.append((name, prot, f, press(prot, thick, elastic, force_n=f)))
    # Coarsest blur first (the law's volume depends on it): depth outside the contact of a
    # mid-size sphere case, same approach.
    name, prot, f, im = runs[7]
    best = None
    for ratio in np.geomspace(0.05, 2.0, 25):
        trial = dataclasses.replace(law0, pyramid_sigma_per_thickness=float(ratio))
        depth_w, *_ = press_pyramid(prot.astype(np.float32), dx, base.gel, None, im.indentation_mm, None,
                                    "touched", law=trial)
        depth_w = membrane_blur(depth_w, base.gel.membrane_smoothing_mm / dx)
        err = float(np.sqrt(np.mean((depth_w - im.depth_mm)[~im.contact_mask] ** 2)))
        if best is None or err < best[1]:
            best = (float(ratio), err)
    law = dataclasses.replace(law0, pyramid_sigma_per_thickness=best[0])
    cs = []
    for _, prot, f, im in thick_runs:
        cs.append(f / float(law_force(*surface_volume(prot, im.indentation_mm, thick, law), thick.gel, 1.0, 1.0, 0.0)))
    c = float(np.exp(np.mean(np.log(cs))))
    rows = [(f, *surface_volume(prot, im.indentation_mm, base, law)) for _, prot, f, im in runs if not im.bottomed_out]
    rows += [(f, *surface_volume(prot, im.indentation_mm, broad, law)) for _, prot, f, im in broad_runs
             if not im.bottomed_out]
    rows = np.array(rows)

    def resid(x):
        return np.log(law_force(rows[:, 1], rows[:, 2], base.gel, c, math.exp(x[0]), x[1]) / rows[:, 0])

    sol = least_squares(resid, [0.0, 1.0])
    kappa, beta = float(math.exp(sol.x[0])), float(sol.x[1])
    law = dataclasses.replace(law, force_coef=c, layer_kappa=kappa, layer_exponent=beta)
    check = [(f"cylinder 4 mm x 6 mm (check)", indenters.cylinder(4.0, base, length_mm=6.0), f)
             for f in (0.01, 0.1)]
    res = []
    cases = ([(n, p, f, im, base) for n, p, f, im in runs]
             + [(n, p, f, im, broad) for n, p, f, im in broad_runs]
             + [(n, p, f, press(p, base, elastic, force_n=f), base) for n, p, f in check])
    for name, prot, f, im, prof in cases:
        d = press_pyramid(prot.astype(np.float32), prof.image.mm_per_px, prof.gel, f, None, None,
                          "touched", law=law)[2]
        res.append({"case": name, "force_n": f, "elastic_mm": round(im.indentation_mm, 5),
                    "pyramid_mm": round(d, 5), "rel": round(d / im.indentation_mm - 1, 4)})
    # Contact: penetration at least a fraction of the approach; the fraction that best
    # matches the elastic model's contact radii at the pyramid law's approach.
    fracs = np.linspace(0.2, 0.7, 51)
    errs = np.zeros_like(fracs)
    for r, (name, prot, f, im) in zip(res, runs):
        pen = np.maximum(r["pyramid_mm"] - (prot.max() - prot), 0.0)
        for i, fr in enumerate(fracs):
            area = float(np.count_nonzero(pen >= fr * r["pyramid_mm"])) * dx * dx
            errs[i] += math.log(max(area, dx * dx) / im.contact_area_mm2) ** 2 / 4  # (log radius ratio)^2
    frac = float(fracs[int(np.argmin(errs))])
    return {"force_coef": round(c, 4), "layer_kappa": round(kappa, 4), "layer_exponent": round(beta, 4),
            "contact_fraction": round(frac, 3),
            "contact_radius_rms_log": round(math.sqrt(float(errs.min()) / len(runs)), 4),
            "pyramid_sigma_per_thickness": round(best[0], 4),
            "fitted_poisson_ratio": base.gel.poisson_ratio, "fitted_thickness_mm": base.gel.thickness_mm,
            "fit_resolution_px": resolution_px,
            "c_per_case": [round(float(x), 4) for x in cs], "force_resid_max": round(float(np.abs(sol.fun).max()), 4),
            "outside_rms_mm": best[1], "residuals": res}


def write_law(values: dict[str, Any], path=LAW_FILE) -> None:
    """Write fitted constants to the law file (temporary name, then rename)."""
    keep = ("force_coef", "layer_kappa", "layer_exponent", "pyramid_sigma_per_thickness", "contact_fraction",
            "fitted_poisson_ratio", "fitted_thickness_mm")
    law = {k: values[k] for k in keep}
    current = imprint_law()
    for k in ("apparent_cell_per_thickness", "support_length_mm"):  # chosen, not fitted
        law[k] = getattr(current, k)
    law["note"] = ("fitted by tools/fit_pyramid_law.py: c on a 20 mm gel (half-space), kappa and beta on "
                   "spheres and broad contacts on the profile's gel, blur on the depth outside a sphere's contact; "
                   f"max |log F error| {values.get('force_resid_max')}, "
                   f"rms log contact-radius error {values.get('contact_radius_rms_log')}")
    header = ("Force law and smoothing of the pyramid imprint model (gelsim/gel/pyramid.py), fitted to the\n"
              "elastic model. Regenerate: .venv/bin/python tools/fit_pyramid_law.py --write\n"
              "contact_fraction: 0.5 would be exact for Hertz (penetration d/2 at r = a); the fit matches the\n"
              "elastic layer's contact radii, which exceed Hertz's as the contact grows against the thickness.\n"
              "Chosen, not fitted: apparent_cell_per_thickness (valleys narrower than h/4 count as apparent\n"
              "contact: the gel spans them); support_length_mm (a fabric support's Pasternak shear length when\n"
              "the caller gives none: 0.5 mm, a typical cloth thickness; pass the fabric's own thickness).")
    text = dump_toml({"law": law}, header=header)
    atomic_write_text(path, text)
    imprint_law.cache_clear()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--write", action="store_true", help="write the fitted constants to gelsim/assets/imprint_law.toml")
    ap.add_argument("--resolution", type=int, default=480, help="fit resolution, px across [default: 480]")
    args = ap.parse_args()
    values = fit_pyramid_law(resolution_px=args.resolution)
    print(json.dumps(values, indent=1))
    if args.write:
        write_law(values)
        print(f"wrote {LAW_FILE}")
    return 0


if __name__ == "__main__":
    run_script(main)
