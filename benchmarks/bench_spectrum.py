"""The gel's relief by wavelength: a fidelity level against the elastic reference, per octave-ish band.

Presses a fabric flat over the whole pad (vitac, 480x360 by default, on a flat gel unless ``--domed``) with
a fidelity level and with the elastic reference, and compares the gel surface's amplitude with the
fabric's own in wavelength bins (Hann-windowed spectra of the central three quarters of the field): the
transfer of each model (gel amplitude / fabric amplitude) and their ratio. A model that maps a cell's
texture as one wave passes every wavelength about alike; elastic contact passes long waves more than short
ones. ``--support rigid|cloth|yarns`` takes the fabric's support away, keeps it (the default), or keeps only
its yarn crowns' pointwise compliance (the cloth's compression removed). Usage:

    python benchmarks/bench_spectrum.py [--fabric 78] [--force-n 1] [--level balanced] [--resolution 480]
                                        [--support cloth] [--domed] [--json]

Takes 5-30 s per fabric at 480x360 (the reference's elastic solve).
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from gelsim.cli import print_json, run_script

# Wavelength bin edges, mm (long to short).
EDGES_MM = (2.0, 1.0, 0.7, 0.5, 0.35, 0.25, 0.18, 0.12, 0.08)


def spectrum(a: np.ndarray, mm_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(power, wavelength mm) of the central three quarters of ``a`` (mean removed, Hann window); rfft2 layout."""
    h, w = a.shape
    c = a[h // 8:h - h // 8, w // 8:w - w // 8].astype(np.float64)
    c = c - c.mean()
    win = np.hanning(c.shape[0])[:, None] * np.hanning(c.shape[1])[None, :]
    power = np.abs(np.fft.rfft2(c * win)) ** 2
    qy = np.fft.fftfreq(c.shape[0], mm_per_px)[:, None]
    qx = np.fft.rfftfreq(c.shape[1], mm_per_px)[None, :]
    return power, 1.0 / np.maximum(np.hypot(qx, qy), 1e-12)


def transfer_by_bin(model: np.ndarray, reference: np.ndarray, fabric: np.ndarray, mm_per_px: float) -> list[dict]:
    """Per wavelength bin of EDGES_MM: the model's and the reference's amplitude over the fabric's, and the
    model's over the reference's (RMS over the bin's wavenumbers)."""
    pm, lam = spectrum(model, mm_per_px)
    pr, _ = spectrum(reference, mm_per_px)
    pf, _ = spectrum(fabric, mm_per_px)
    rows = []
    for long_mm, short_mm in zip(EDGES_MM[:-1], EDGES_MM[1:]):
        m = (lam <= long_mm) & (lam > short_mm)
        if not m.any() or pf[m].sum() == 0.0:
            continue
        rows.append({"wavelength_mm": [short_mm, long_mm],
                     "model_transfer": float(np.sqrt(pm[m].sum() / pf[m].sum())),
                     "reference_transfer": float(np.sqrt(pr[m].sum() / pf[m].sum())),
                     "model_over_reference": float(np.sqrt(pm[m].sum() / pr[m].sum()))})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fabric", type=int, default=78, help="catalog id (default: 78, wool felt)")
    ap.add_argument("--force-n", type=float, default=1.0)
    ap.add_argument("--level", default="balanced", help="fidelity level compared with the reference")
    ap.add_argument("--resolution", type=int, default=480, help="image width, px (same field of view)")
    ap.add_argument("--support", choices=("cloth", "yarns", "rigid"), default="cloth",
                    help="the fabric's support: all of it, its yarn crowns only, or none")
    ap.add_argument("--domed", action="store_true", help="keep the profile's domed gel (default: flat)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from gelsim.fabrics import load_catalog
    from gelsim.gel import FabricSupport, press
    from gelsim.runtime import configure_worker
    from gelsim.scene import as_object, field_heights, press_properties
    from gelsim.sensor import load_profile

    configure_worker()
    profile = load_profile("vitac").with_resolution(args.resolution)
    if not args.domed:
        profile = dataclasses.replace(profile, gel=dataclasses.replace(profile.gel, dome_radius_mm=0.0))
    fab = load_catalog()[args.fabric]
    obj = as_object(fab)
    support = obj.support()
    if args.support == "rigid":
        support = None
    elif args.support == "yarns" and support is not None:
        support = FabricSupport(support.thickness_mm, 0.0, support.surface_modulus_mpa)
    heights = field_heights(obj, profile, seed=0)
    kw = dict(force_n=args.force_n, **{**press_properties(obj), "support": support})
    model = press(heights, profile, args.level, **kw).depth_mm
    ref = press(heights, profile, "reference", **kw).depth_mm
    rows = transfer_by_bin(model, ref, heights, profile.image.mm_per_px)
    if args.json:
        print_json({"fabric": args.fabric, "family": fab.family, "force_n": args.force_n, "level": args.level,
                    "resolution": list(profile.shape[::-1]), "support": args.support, "domed": args.domed,
                    "bins": rows})
        return 0
    print(f"fabric {args.fabric} ({fab.family}), {args.force_n} N, {args.level} against the reference, "
          f"{profile.shape[1]}x{profile.shape[0]}, support: {args.support}, {'domed' if args.domed else 'flat'} gel")
    print("wavelength mm   reference / fabric   model / fabric   model / reference")
    for r in rows:
        lo, hi = r["wavelength_mm"]
        print(f"  {lo:.2f}-{hi:.2f}      {r['reference_transfer']:8.3f}         {r['model_transfer']:8.3f}"
              f"        {r['model_over_reference']:6.2f}")
    return 0


if __name__ == "__main__":
    run_script(main)
