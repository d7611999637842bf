"""Texture-scale contact: the imprint models against Johnson's sinusoidal contact.

Theory (gelsim/gel/johnson.py): a rigid wave z = h cos(2 pi x / L) (1-D) or
h cos(2 pi x / L) cos(2 pi y / L) (2-D) on the gel at mean pressure p comes into complete contact
at p* = pi E* h / L (1-D) or sqrt(2) pi E* h / L (2-D); below it the 1-D contact covers
(2/pi) asin(sqrt(p/p*)) of the surface and the gel keeps s (2 - s) of the wave's fundamental,
s = p / p*; the 2-D values are the exact periodic solutions in gelsim/assets/johnson.toml, checked here
against the two limits Johnson, Greenwood and Higginson give (complete contact at p*, a Hertz
contact per crown at light load).

Each case presses a wave over a whole flat pad (no membrane smoothing: the imprint alone) and
measures, over the central half of the pad, the contact fraction and the kept fundamental (the
depth map regressed on the wave), and the local mean pressure there: the pad's pressure is not
uniform (a layer pressed by a flat punch carries more at its centre), so the theory is evaluated
at the local s, not at force / area.

Tolerance: within 10% of theory, plus two pixels of the period for the contact fraction (a contact
strip around a crown gains or loses a whole pixel on each side) and 0.02 for the kept fundamental (the grid's own error on a
resolved wave). "Where the theory holds": the wave resolved by at least 10 pixels per period; the
layer's thickness (2 mm) at least the wavelength (the half-space result).
"""
import dataclasses

import numpy as np
import pytest

from gelsim.fidelity import get_fidelity
from gelsim.gel import johnson, press, wave_check
from gelsim.sensor import load_profile

REFERENCE = dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0)
LEVELS = {"balanced": get_fidelity("balanced"), "fast": get_fidelity("fast"), "reference": REFERENCE}
PX_PER_PERIOD = 24
TOL_REL = 0.10
TOL_KEPT = 0.02


def press_wave(level, kind, wavelength_mm, s_target, px_per_period=PX_PER_PERIOD, width_px=192, height_px=128,
               angle_deg=0.0):
    r = wave_check.press_wave(load_profile("vitac"), LEVELS[level], kind, wavelength_mm, s_target,
                           px_per_period=px_per_period, width_px=width_px, height_px=height_px, angle_deg=angle_deg)
    return r["contact_fraction"], r["kept"], r["s"], (r["theory_contact_fraction"], r["theory_kept"])


def check(level, kind, wavelength_mm, s_target, px_per_period=PX_PER_PERIOD, **kw):
    cf, kept, s, (cf_th, kept_th) = press_wave(level, kind, wavelength_mm, s_target, px_per_period, **kw)
    msg = f"{level} {kind} L={wavelength_mm} s={s:.3f}: contact {cf:.3f} (theory {cf_th:.3f}), kept {kept:.3f} " \
          f"(theory {kept_th:.3f})"
    work_px = px_per_period * LEVELS[level].imprint_scale  # pixels per period where the level works
    assert abs(cf - cf_th) <= TOL_REL * cf_th + 2.0 / work_px, msg
    assert abs(kept - kept_th) <= TOL_REL * kept_th + TOL_KEPT, msg


# ---------------------------------------------------------------------------- the theory itself
@pytest.mark.parametrize("s", [0.05, 0.2, 0.5, 0.8])
def test_closed_forms_match_the_exact_periodic_solution(s):
    z = johnson.wave("1d", 1024)
    pstar = johnson.complete_contact_pressure_mpa(1.0, 1.0, 1.0, 1)
    res = johnson.periodic_contact(z, 1.0 / 1024, s * pstar, 1.0)
    assert res.contact_fraction == pytest.approx(float(johnson.contact_fraction_1d(s)), abs=2.0 / 1024)
    assert johnson.fundamental_ratio(res.surface_mm, z) == pytest.approx(float(johnson.kept_relief_1d(s)), abs=1e-3)


def test_tables_reproduce_from_the_solver():
    # A few rows of gelsim/assets/johnson.toml, refitted on a coarser grid: the file is what the tool writes.
    tabs = johnson.map_tables()
    for kind, n in (("1d", 512), ("2d", 64)):
        t = tabs[kind]
        for i in (3, 9, 18):
            row = johnson.fit_map_row(kind, float(t.s[i]), n)
            assert row["contact_fraction"] == pytest.approx(t.contact_fraction[i], abs=2.0 / n)
            assert row["kept"] == pytest.approx(t.kept[i], abs=0.01)


def test_two_dimensional_table_meets_jgh_limits():
    t = johnson.map_tables()["2d"]
    # Complete contact at p* = sqrt(2) pi E* h / L: the last rows approach 1.
    assert t.contact_fraction[-2] > 0.99 and t.contact_fraction[-1] == 1.0
    # Light load: each crown a Hertz contact (within 10% at s <= 0.01).
    for s, cf in zip(t.s, t.contact_fraction):
        if s <= 0.01:
            assert cf == pytest.approx(johnson.hertz_crown_contact_fraction_2d(float(s)), rel=0.10)


def test_map_keeps_the_theory_on_waves():
    # The pointwise map with the tables' parameters reproduces contact and kept fundamental.
    for kind, n in (("1d", 512), ("2d", 64)):
        t = johnson.map_tables()[kind]
        z = johnson.wave(kind, n) - 1.0
        for i in range(2, len(t.s) - 1, 4):
            zeta, lam = johnson.map_parameters(np.float32([t.s[i]]), np.float32([1.0 if kind == "1d" else 0.0]))
            g = johnson.depth_map(z, 2.0 * float(zeta[0]), float(lam[0]))
            assert float((z >= -2.0 * zeta[0]).mean()) == pytest.approx(t.contact_fraction[i], abs=2.0 / n + 0.01)
            assert johnson.fundamental_ratio(g, z) == pytest.approx(t.kept[i], abs=0.02)


# ------------------------------------------------------------------------ the models on waves
# Default suite: every level on a fine and a coarse weave at light, medium and complete contact.
QUICK = [(kind, L, s) for kind in ("1d", "2d") for L in (0.2, 1.0) for s in (0.1, 0.5, 3.0)]
# Slow: wavelengths 0.1-2 mm and p/p* from 0.05 to 3.
FULL = [(kind, L, s) for kind in ("1d", "2d") for L in (0.1, 0.2, 0.5, 1.0, 2.0) for s in (0.05, 0.2, 0.5, 1.0, 3.0)
        if (kind, L, s) not in QUICK]


@pytest.mark.parametrize("level", ["balanced", "fast", "reference"])
@pytest.mark.parametrize("kind, wavelength, s", QUICK)
def test_wave_follows_johnson(level, kind, wavelength, s):
    check(level, kind, wavelength, s)


# Known misses (measured, benchmarks/bench_johnson.py: balanced 49/50, fast 48/50): at L = 2 mm, the
# gel's own thickness, under light load the two-scale model keeps 18-29% less of the wave than theory
# and the reference do (its texture scale is capped at the thickness, where the crown envelope and the
# layer's response overlap); and the fast level, at half resolution, works a 0.2 mm 2-D wave on 12 px
# per period: at s = 0.11 it keeps 0.41 of it against theory's 0.34. Strict: a case that starts to
# pass is news, and the count in docs/physics.md changes with it.
KNOWN = {("1d", 2.0, 0.2, "balanced"): "two-scale model at L = gel thickness, light load",
         ("1d", 2.0, 0.05, "fast"): "two-scale model at L = gel thickness, light load",
         ("2d", 0.2, 0.2, "fast"): "fast level: 12 px per period of a 0.2 mm wave at half resolution"}


def full_cases():
    out = []
    for level in ("balanced", "fast", "reference"):
        for kind, wavelength, s in FULL:
            marks = [pytest.mark.slow]
            if (kind, wavelength, s, level) in KNOWN:
                marks.append(pytest.mark.xfail(reason=KNOWN[kind, wavelength, s, level], strict=True))
            out.append(pytest.param(level, kind, wavelength, s, marks=marks, id=f"{level}-{kind}-{wavelength}-{s}"))
    return out


@pytest.mark.parametrize("level, kind, wavelength, s", full_cases())
def test_wave_follows_johnson_full_range(level, kind, wavelength, s):
    check(level, kind, wavelength, s)


@pytest.mark.parametrize("level, wavelength", [("balanced", 0.2), ("balanced", 1.0), ("fast", 0.5)])
@pytest.mark.parametrize("kind", ["1d", "2d"])
def test_wave_at_the_datasets_pixel(level, kind, wavelength):
    # At the vitac profile's own pixel (0.0197 mm at 960x720; the fast level works at half that
    # resolution): a 0.2 mm weave is 10 px per period for balanced, a 0.5 mm one 13 px for fast.
    # The wave is turned by 7 degrees, as a cloth's weave always is (catalog orientation plus the
    # grip's jitter): a 1-D wave aligned with the pixel grid at 10-25 px per period turns its
    # bearing curve into a staircase of whole pixel pairs, and the two-scale model then keeps
    # 6-17% less of it (measured; the reference is unaffected, rotated waves match to 1%).
    mm = load_profile("vitac").image.mm_per_px
    check(level, kind, wavelength, 0.4, px_per_period=int(round(wavelength / mm)), width_px=256, height_px=192,
          angle_deg=7.0)


@pytest.mark.parametrize("nodes", [None, (0.01, 0.03, 0.1, 0.47, 1.0)])
def test_segment_arrays_reproduce_the_tables(monkeypatch, nodes):
    """The compiled kernels' uniform grid reads the tables' own interpolation: exactly when every
    node lies on the grid (the shipped tables), to a sixteenth of a segment's curvature otherwise."""
    tabs = johnson.map_tables()
    if nodes is not None:
        s = np.asarray(nodes)
        tabs = {k: johnson.MapTable(s, *(np.interp(s, t.s, getattr(t, key)) for key in johnson.KEYS))
                for k, t in tabs.items()}
        monkeypatch.setattr(johnson, "map_tables", lambda: tabs)
    lo, hi, per_step, v0, slope = johnson.segment_arrays.__wrapped__()
    s = tabs["2d"].s
    x = np.concatenate([s, np.linspace(s[0], s[-1], 777)])
    u = (x - lo) * per_step
    i = np.minimum(u.astype(int), v0.shape[2] - 1)
    for kind_i, kind in enumerate(("1d", "2d")):
        for k, key in enumerate(johnson.KEYS):
            got = v0[kind_i, k, i] + slope[kind_i, k, i] * (u - i)
            ref = np.interp(x, s, getattr(tabs[kind], key))
            tol = 2e-6 if nodes is None else 0.02 * np.ptp(ref)
            assert np.abs(got - ref).max() <= tol, (kind, key)
            assert np.abs(got[:len(s)] - ref[:len(s)]).max() <= (2e-6 if nodes is None else tol)
