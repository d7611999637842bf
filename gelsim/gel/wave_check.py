"""Johnson's theory checked against the press: a wave pressed over the whole pad, its contact fraction and
kept relief measured beside :mod:`gelsim.gel.johnson`'s closed forms and tables (used by
``tests/gelsim/test_johnson.py`` and ``benchmarks/bench_johnson.py``).

Kept apart from :mod:`gelsim.gel.johnson` because it runs the package's :func:`gelsim.gel.press`, which
itself uses the theory: in one module that would be an import circle."""
from __future__ import annotations

import numpy as np

from . import press
from .johnson import (WAVE_PX_PER_PERIOD, WAVE_SLOPE, central_region, complete_contact_pressure_mpa, theory,
                      wave_field, wave_profile)
from .layer import effective_modulus_mpa


def press_wave(base, fidelity, kind: str, wavelength_mm: float, s_target: float, *,
               px_per_period: int = WAVE_PX_PER_PERIOD, width_px: int = 192, height_px: int = 128,
               angle_deg: float = 0.0) -> dict:
    """Press a wave of steepness WAVE_SLOPE over the whole flat pad at the mean pressure s_target p*;
    measure over the central region the contact fraction, the kept fundamental (the depth map
    regressed on the wave) and the local mean pressure, and the theory at that local s (the pad's
    pressure is not uniform: a layer pressed by a flat punch carries more at its centre)."""
    prof = wave_profile(base, wavelength_mm, px_per_period, width_px, height_px)
    h = WAVE_SLOPE * wavelength_mm / (2 * np.pi)
    pstar = complete_contact_pressure_mpa(effective_modulus_mpa(prof.gel), h, wavelength_mm, 1 if kind == "1d" else 2)
    fw, fh = prof.field_mm
    z = wave_field(prof, kind, wavelength_mm, h, angle_deg)
    im = press(z, prof, fidelity, force_n=s_target * pstar * fw * fh, texture_mm=wavelength_mm)
    region = central_region(prof, px_per_period)
    d = im.depth_mm[region].astype(np.float64)
    zz = z[region].astype(np.float64)
    zz = zz - zz.mean()
    kept = float(((d - d.mean()) * zz).sum() / (zz * zz).sum())
    cf = float(im.contact_mask[region].mean())
    pressure = im.pressure_mpa()
    s = float(pressure[region].mean()) / pstar if pressure is not None else s_target
    cf_th, kept_th = theory(kind, s)
    return {"kind": kind, "wavelength_mm": wavelength_mm, "s_target": s_target, "s": s, "contact_fraction": cf,
            "kept": kept, "theory_contact_fraction": cf_th, "theory_kept": kept_th,
            "work_px_per_period": px_per_period * fidelity.imprint_scale}
