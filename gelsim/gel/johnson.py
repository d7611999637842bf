"""Contact of a wavy surface with the gel at texture scale (Johnson's sinusoidal contact).

Theory (K. L. Johnson, Contact Mechanics, 1985, sec. 13.2; Johnson, Greenwood and
Higginson, Int. J. Mech. Sci. 27, 1985). A rigid wave pressed on an elastic half-space
(``E* = E / (1 - nu^2)``) at mean pressure ``p``:

* 1-D, ``z = h cos(2 pi x / L)``: complete contact at ``p* = pi E* h / L``; below it the
  contact covers the fraction ``2a/L = (2/pi) asin(sqrt(p / p*))`` of each period. The
  fundamental of the gel surface keeps ``s (2 - s)`` of the wave, ``s = p / p*`` (the
  pressure's first harmonic is ``p (2 - s)``; derived from Westergaard's solution and
  checked against :func:`periodic_contact` in the tests), and the contact's edge lies
  ``s`` of the crown-to-valley depth below the crowns.
* 2-D, ``z = h cos(2 pi x / L) cos(2 pi y / L)``: complete contact at
  ``p* = sqrt(2) pi E* h / L``; at light load each crown is a Hertz contact (radius of
  curvature ``L^2 / (4 pi^2 h)``, load ``p L^2 / 2``). In between there is no closed form;
  :func:`periodic_contact` solves it (exact for the discretised problem) and the table in
  ``gelsim/assets/johnson.toml`` holds the result.

Written with the wave's crown-to-valley depth ``D`` and the wavenumber ``q = rms slope /
rms height`` (``2 pi / L`` in 1-D, ``sqrt(2) 2 pi / L`` for the 2-D wave), both cases share
``p* = E* q D / 4``, which is what the two-scale imprint estimates locally on any texture.

The two-scale imprint (:mod:`gelsim.gel.twoscale`) maps a texture's depth below its crowns,
``t <= 0`` (mm), to the gel surface's, pointwise:
``g = t`` where ``t >= -c`` (in contact) and ``g = -c + lam (t + c)`` below (the gel spans the
valley), with the cut ``c = zeta D``. ``zeta(s)`` is the contact edge's depth fraction and
``lam(s)`` is chosen so that the map keeps the theory's fundamental exactly (zeta is the level
whose bearing area is the exact contact fraction: the contact's edge in 1-D); both are
tabulated for the 1-D and 2-D waves (:func:`map_parameters`). On the exact solutions the map's
surface is within 4% of the wave's depth everywhere and its RMS slope within 2%
(docs/imprint.md).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import GelsimError
from ..params import ASSETS_DIR, load_toml
from .layer import pk_solve

TABLE_FILE = ASSETS_DIR / "johnson.toml"


# --------------------------------------------------------------------------------------
# Closed forms
# --------------------------------------------------------------------------------------
def complete_contact_pressure_mpa(e_star_mpa: float, amplitude_mm: float, wavelength_mm: float,
                                  dims: int = 1) -> float:
    """p* (MPa): complete contact of a 1-D wave (dims=1) or the 2-D wave cos x cos y (dims=2)."""
    f = math.pi if dims == 1 else math.sqrt(2.0) * math.pi
    return f * e_star_mpa * amplitude_mm / wavelength_mm


def contact_fraction_1d(s: np.ndarray | float) -> np.ndarray:
    """Share of a 1-D wave in contact at p / p* = s: (2/pi) asin(sqrt(s)), 1 from s = 1."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    return 2.0 / math.pi * np.arcsin(np.sqrt(s))


def kept_relief_1d(s: np.ndarray | float) -> np.ndarray:
    """Fundamental of the gel surface over the wave's, 1-D, at p / p* = s: s (2 - s), 1 from s = 1."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    return s * (2.0 - s)


def hertz_crown_contact_fraction_2d(s: float) -> float:
    """Light-load limit of the 2-D wave: each crown a Hertz contact.

    Two crowns per L x L cell, each carrying ``p L^2 / 2`` with curvature radius
    ``R = L^2 / (4 pi^2 h)``; ``a = (3 F R / (4 E*))^(1/3)``. In units of h = L = E* = 1.
    """
    p = s * math.sqrt(2.0) * math.pi
    R = 1.0 / (4.0 * math.pi ** 2)
    a = (3.0 * (p / 2.0) * R / 4.0) ** (1.0 / 3.0)
    return 2.0 * math.pi * a * a


# --------------------------------------------------------------------------------------
# Periodic half-space contact (exact, for the tables and the tests)
# --------------------------------------------------------------------------------------
class PeriodicHalfSpace:
    """u = K * p for a periodic pressure on an elastic half-space: ``u(q) = 2 p(q) / (E* q)``.

    The mean (q = 0) mode is left out: a periodic load's mean displacement is the approach,
    which the solver carries separately.
    """

    def __init__(self, shape: tuple[int, ...], dx: float, e_star_mpa: float):
        self.shape = shape
        if len(shape) == 1:
            q = 2 * math.pi * np.fft.rfftfreq(shape[0], d=dx)
        else:
            qy = 2 * math.pi * np.fft.fftfreq(shape[0], d=dx)[:, None]
            qx = 2 * math.pi * np.fft.rfftfreq(shape[1], d=dx)[None, :]
            q = np.hypot(qx, qy)
        self.comp = np.zeros_like(q)
        self.comp[q > 0] = 2.0 / (e_star_mpa * q[q > 0])

    def __call__(self, p: np.ndarray) -> np.ndarray:
        if len(self.shape) == 1:
            return np.fft.irfft(np.fft.rfft(p) * self.comp, self.shape[0])
        return np.fft.irfft2(np.fft.rfft2(p) * self.comp, s=self.shape)


@dataclass(frozen=True)
class PeriodicResult:
    """One period (or cell) of a periodic contact. surface_mm: the gel surface in the wave's
    frame (equal to the wave where in contact); contact: bool mask; pressure_mpa."""
    surface_mm: np.ndarray
    contact: np.ndarray
    pressure_mpa: np.ndarray
    iterations: int

    @property
    def contact_fraction(self) -> float:
        return float(self.contact.mean())


def periodic_contact(z_mm: np.ndarray, dx_mm: float, mean_pressure_mpa: float, e_star_mpa: float,
                     tol: float = 1e-10) -> PeriodicResult:
    """Exact contact of the periodic rigid surface ``z_mm`` (1-D or 2-D, one period) with a
    half-space at ``mean_pressure_mpa`` (Polonsky-Keer on the periodic Green's function)."""
    z = np.asarray(z_mm, dtype=np.float64)
    op = PeriodicHalfSpace(z.shape, dx_mm, e_star_mpa)
    area = 1.0 / z.size  # pk_solve's force = sum(p) * area = mean pressure
    h = z - z.max()
    p, _, it = pk_solve(op, h, area, force=mean_pressure_mpa, p0=np.ones_like(z), tol=tol, maxit=20000)
    u = op(p)
    ic = p > 0
    w = u - float((u[ic] - z[ic]).mean())
    return PeriodicResult(w, ic, p, it)


def fundamental_ratio(surface: np.ndarray, wave: np.ndarray) -> float:
    """Amplitude of ``surface``'s component at ``wave``'s dominant non-zero frequency over ``wave``'s."""
    fs, fw = np.fft.rfftn(surface), np.fft.rfftn(wave)
    mag = np.abs(fw)
    mag.flat[0] = 0.0  # the mean is not the wave
    k = int(np.argmax(mag))
    return float(abs(fs.flat[k]) / abs(fw.flat[k]))


def wave(kind: str, n: int) -> np.ndarray:
    """One period of the unit wave (h = 1, L = 1) on n (x n) cell centres: '1d' or '2d'."""
    x = (np.arange(n) + 0.5) / n
    if kind == "1d":
        return np.cos(2 * math.pi * x)
    if kind == "2d":
        return np.cos(2 * math.pi * x)[None, :] * np.cos(2 * math.pi * x)[:, None]
    raise GelsimError(f"unknown wave {kind!r}; use '1d' or '2d'")


def depth_map(t: np.ndarray, cut: np.ndarray | float, lam: np.ndarray | float) -> np.ndarray:
    """The pointwise texture map: ``t`` (depth below the crowns, <= 0) to the gel surface's."""
    return np.where(t >= -cut, t, -cut + lam * (t + cut))


# --------------------------------------------------------------------------------------
# Tables of the map (gelsim/assets/johnson.toml, written by tools/johnson_tables.py)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MapTable:
    """zeta (contact edge's depth fraction) and lam (span slope) against s = p / p*, and the
    theory's contact fraction and kept fundamental, for one wave kind."""
    s: np.ndarray
    contact_fraction: np.ndarray
    kept: np.ndarray
    zeta: np.ndarray
    lam: np.ndarray


# The tables' columns besides s, in the order segment_arrays stacks them.
KEYS = ("contact_fraction", "kept", "zeta", "lam")


@functools.cache
def map_tables() -> dict[str, MapTable]:
    """The '1d' and '2d' tables from ``gelsim/assets/johnson.toml`` (both on one grid of s)."""
    data = load_toml(TABLE_FILE)
    out = {}
    for kind in ("1d", "2d"):
        t = data.get(kind)
        if not isinstance(t, dict):
            raise GelsimError(f"{TABLE_FILE}: missing [{kind}]; regenerate with tools/johnson_tables.py")
        cols = {k: np.asarray(t[k], dtype=np.float64) for k in ("s",) + KEYS}
        n = len(cols["s"])
        if any(len(v) != n for v in cols.values()) or n < 2 or np.any(np.diff(cols["s"]) <= 0):
            raise GelsimError(f"{TABLE_FILE} [{kind}]: columns must have equal length >= 2 and increasing s; "
                              "regenerate with tools/johnson_tables.py")
        out[kind] = MapTable(**cols)
    if not np.array_equal(out["1d"].s, out["2d"].s):
        raise GelsimError(f"{TABLE_FILE}: [1d] and [2d] must share one column s; regenerate with tools/johnson_tables.py")
    return out


@functools.cache
def _segments() -> tuple["_Grid", dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]]:
    """The tables as float32 line segments: their grid of s, and per (kind, column) each segment's
    start value and slope per unit of s."""
    tabs = map_tables()
    s = tabs["1d"].s
    seg = {}
    for kind, tab in tabs.items():
        for key in KEYS:
            v = getattr(tab, key)
            seg[kind, key] = (v[:-1].astype(np.float32), (np.diff(v) / np.diff(s)).astype(np.float32))
    return _Grid(s), seg


class _Grid:
    """A sorted grid's segment lookup by uniform buckets (np.searchsorted's binary search costs
    about 30 ns per value, 2 ms on a frame's statistics grid; this about a tenth of that).

    Buckets half the narrowest segment wide hold at most one node each: a bucket's first segment,
    stepped once past the node it may hold, is the value's segment."""

    def __init__(self, nodes: np.ndarray):
        self.nodes = nodes.astype(np.float32)
        self.lo, self.hi = self.nodes[0], self.nodes[-1]
        width = float(np.min(np.diff(nodes))) / 2.0
        n = int(math.ceil((nodes[-1] - nodes[0]) / width)) + 1
        self.per_unit = np.float32(1.0 / width)
        edges = nodes[0] + np.arange(n) * width
        self.first = np.clip(np.searchsorted(nodes, edges, side="right") - 1, 0, len(nodes) - 2).astype(np.intp)

    def locate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(segment index, offset from its start) of each value of float32 ``x``; values past the
        grid's ends sit at the end (offset clamped), so their end values hold, as np.interp's do."""
        x = np.clip(x, self.lo, self.hi)
        b = np.minimum(((x - self.lo) * self.per_unit).astype(np.intp), len(self.first) - 1)
        i = self.first[b]
        i = np.minimum(i + (x >= self.nodes[np.minimum(i + 1, len(self.nodes) - 1)]), len(self.nodes) - 2)
        return i, x - self.nodes[i]


# A table whose nodes do not all sit on one grid step is resampled this much finer than its
# narrowest segment for the compiled kernels (linear in between: the error is confined to the
# segments around an off-grid node).
RESAMPLE_PER_NARROWEST = 16


@functools.cache
def segment_arrays() -> tuple:
    """The tables on a uniform grid of s, for compiled kernels (``texture_kernels`` reads them
    with one multiply and one gather per value, which vectorises where a search does not):
    (lo, hi, 1 / step; start values float32 (2, len(KEYS), segments): kind ('1d', '2d') x key;
    slopes per grid step, likewise).

    The grid's step is the tables' narrowest segment when every node lies on it (as in
    gelsim/assets/johnson.toml: 0.005), so the lookup is the tables' own linear interpolation."""
    tabs = map_tables()
    s = tabs["1d"].s
    step = float(np.min(np.diff(s)))
    k = (s - s[0]) / step
    if not np.allclose(k, np.round(k), rtol=0.0, atol=1e-6):
        step /= RESAMPLE_PER_NARROWEST
    n = int(round((s[-1] - s[0]) / step))
    grid = s[0] + step * np.arange(n + 1)
    grid[-1] = s[-1]
    vals = np.stack([np.stack([np.interp(grid, s, getattr(tabs[kind], key)) for key in KEYS])
                     for kind in ("1d", "2d")])
    v0 = np.ascontiguousarray(vals[..., :-1], dtype=np.float32)
    slope = np.ascontiguousarray(np.diff(vals, axis=-1), dtype=np.float32)
    return np.float32(s[0]), np.float32(s[-1]), np.float32(1.0 / step), v0, slope


class TableLookup:
    """The tables read at p / p* = ``s`` (array) for textures of ``anisotropy`` 0 (the isotropic
    2-D wave) to 1 (a 1-D wave), linear in between; None reads the 2-D wave alone.

    One search of the tables' shared grid of s serves every column (a texture's statistics read
    four to six of them per frame, each a full-grid ``np.interp`` before); values are the tables'
    linear interpolation, held at their end values outside the grid, in float32."""

    def __init__(self, s: np.ndarray, anisotropy: np.ndarray | None):
        grid, self._seg = _segments()
        self.s = np.asarray(s, dtype=np.float32)
        self.a = None if anisotropy is None else np.clip(np.asarray(anisotropy, dtype=np.float32), 0.0, 1.0)
        self._i, self._dx = grid.locate(self.s)

    def column(self, kind: str, key: str) -> np.ndarray:
        """One table's column at s (float32, shaped like s), no blend, no complete-contact rule."""
        v0, slope = self._seg[kind, key]
        return v0[self._i] + slope[self._i] * self._dx

    def blend(self, key: str, v1: np.ndarray | None = None, v2: np.ndarray | None = None) -> np.ndarray:
        """``key`` blended over the anisotropy (1 at s >= 1: complete contact); ``v1``/``v2``
        replace the 1-D/2-D columns when given."""
        v2 = self.column("2d", key) if v2 is None else v2
        if self.a is not None:
            v1 = self.column("1d", key) if v1 is None else v1
            v2 = v2 + self.a * (v1 - v2)
        return np.where(self.s >= 1.0, np.float32(1.0), v2)

    def map_parameters(self) -> tuple[np.ndarray, np.ndarray]:
        """(zeta, lam): see :func:`map_parameters`."""
        tabs = map_tables()
        s = self.s
        v2 = self.column("2d", "zeta")
        v1 = self.column("1d", "zeta") if self.a is not None else None
        s0 = np.float32(tabs["2d"].s[0])
        low = s < s0
        if np.any(low):
            v2 = np.where(low, np.float32(tabs["2d"].zeta[0]) * (np.maximum(s, 0) / s0) ** np.float32(2 / 3), v2)
            if v1 is not None:
                v1 = np.where(s < np.float32(tabs["1d"].s[0]), s, v1)
        return self.blend("zeta", v1, v2), self.blend("lam")


def map_parameters(s: np.ndarray, anisotropy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(zeta, lam) at p / p* = ``s`` for a texture of ``anisotropy`` 0 (the isotropic 2-D wave)
    to 1 (a 1-D wave), linear in between; s >= 1 gives complete contact (zeta 1, lam 1).

    Below the table's first s the cut follows the 2-D Hertz scaling (zeta ~ s^(2/3)) and the
    1-D one (zeta = s); lam keeps its first value.
    """
    return TableLookup(s, anisotropy).map_parameters()


def contact_fraction(s: np.ndarray, anisotropy: np.ndarray) -> np.ndarray:
    """Share of a wave in contact at p / p* = s (tables; anisotropy 0 = 2-D wave, 1 = 1-D)."""
    return TableLookup(s, anisotropy).blend("contact_fraction")


def kept_relief(s: np.ndarray, anisotropy: np.ndarray | None) -> np.ndarray:
    """Kept fundamental of a wave at p / p* = s (tables; anisotropy 0 = 2-D wave, 1 = 1-D; None:
    the 2-D wave)."""
    return TableLookup(s, anisotropy).blend("kept")


def fit_map_row(kind: str, s: float, n: int) -> dict[str, float]:
    """One row of the tables: solve the wave exactly at p / p* = s, then find the span slope
    that makes the map keep the same fundamental. Unit wave (h = 1, L = 1, E* = 1)."""
    from scipy.optimize import brentq

    z = wave(kind, n)
    dims = 1 if kind == "1d" else 2
    pstar = complete_contact_pressure_mpa(1.0, 1.0, 1.0, dims)
    res = periodic_contact(z, 1.0 / n, s * pstar, 1.0)
    kept = fundamental_ratio(res.surface_mm, z)
    t = z - 1.0                                   # depth below the crowns, D = 2
    # The cut whose bearing area is the exact contact (in 1-D the contact's deepest point; in
    # 2-D the contact is not quite a level set, and the area is what the map must keep).
    cf = res.contact_fraction
    zeta = float(-np.quantile(t, 1.0 - cf) / 2.0) if cf > 0 else 0.0
    cut = 2.0 * zeta

    def err(lam):
        return fundamental_ratio(depth_map(t, cut, lam), t) - kept

    lam = brentq(err, 0.0, 1.0) if err(0.0) < 0 < err(1.0) else (0.0 if err(0.0) >= 0 else 1.0)
    return {"s": s, "contact_fraction": res.contact_fraction, "kept": kept, "zeta": zeta, "lam": float(lam)}


# --------------------------------------------------------------------------------------
# A wave pressed over a whole flat pad (the tests' and benchmarks/bench_johnson.py's case)
# --------------------------------------------------------------------------------------
WAVE_SLOPE = 0.15        # 2 pi h / L: small slopes, as on cloth
WAVE_PX_PER_PERIOD = 24


def wave_profile(base, wavelength_mm: float, px_per_period: int = WAVE_PX_PER_PERIOD, width_px: int = 192,
                 height_px: int = 128):
    """``base`` (a SensorProfile) with a flat gel, no membrane smoothing and a field of
    ``width_px`` x ``height_px`` pixels of wavelength / px_per_period mm: the imprint alone, resolved."""
    import dataclasses

    return dataclasses.replace(
        base, image=dataclasses.replace(base.image, width_px=width_px, height_px=height_px,
                                        mm_per_px=wavelength_mm / px_per_period),
        gel=dataclasses.replace(base.gel, dome_radius_mm=0.0, membrane_smoothing_mm=0.0))


def wave_field(prof, kind: str, wavelength_mm: float, amplitude_mm: float, angle_deg: float = 0.0) -> np.ndarray:
    """The wave over ``prof``'s field, float32 (H, W) mm, turned by ``angle_deg``."""
    h, w = prof.shape
    mm = prof.image.mm_per_px
    x = ((np.arange(w) + 0.5) * mm)[None, :]
    y = ((np.arange(h) + 0.5) * mm)[:, None]
    a = math.radians(angle_deg)
    u, v = x * math.cos(a) + y * math.sin(a), -x * math.sin(a) + y * math.cos(a)
    z = np.cos(2 * np.pi * u / wavelength_mm)
    if kind == "2d":
        z = z * np.cos(2 * np.pi * v / wavelength_mm)
    elif kind != "1d":
        raise GelsimError(f"unknown wave {kind!r}; use '1d' or '2d'")
    return (amplitude_mm * np.broadcast_to(z, (h, w))).astype(np.float32)


def central_region(prof, px_per_period: int) -> tuple[slice, slice]:
    """The central half of the pad, a whole number of periods across."""
    h, w = prof.shape
    nh = max(1, (h // 2) // px_per_period) * px_per_period
    nw = max(1, (w // 2) // px_per_period) * px_per_period
    r0, c0 = (h - nh) // 2, (w - nw) // 2
    return slice(r0, r0 + nh), slice(c0, c0 + nw)


def theory(kind: str, s: float) -> tuple[float, float]:
    """(contact fraction, kept fundamental) at p / p* = s: closed forms in 1-D, the tables in 2-D."""
    if kind == "1d":
        return float(contact_fraction_1d(s)), float(kept_relief_1d(s))
    a = np.zeros(1, np.float32)
    return float(contact_fraction(np.float32([s]), a)[0]), float(kept_relief(np.float32([s]), a)[0])
