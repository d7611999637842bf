"""Family renderers: the structure of each fabric family on an axis-aligned grid.

Every renderer takes the fabric, the sample positions as 1-D vectors ``u``
(along image columns, mm, float64) and ``v`` (along rows, mm, float64) and a
32-bit key, and returns the structure ``S``, float32 ``(len(v), len(u))`` in
[0, 1] (1 = the highest yarn tops). Everything random is hashed from integer
lattice or yarn indices (see :mod:`.noise`), so ``S`` at a point depends only
on the point's coordinates, the fabric and the key.

Conventions: warp yarns (knit wales, corduroy ridges) run along ``v`` and are
spaced along ``u``; weft yarns (knit courses) run along ``u``.
"""
from __future__ import annotations

import math

import numpy as np

from .catalog import Fabric
from .noise import fbm, hash_unit, jittered_index, make_key, noise_1d, value_noise

F32 = np.float32


def _profile(x2: np.ndarray) -> np.ndarray:
    """Elliptical yarn cross-section from the squared normalised distance: sqrt(1 - x^2), 0 outside."""
    p = np.subtract(F32(1.0), x2, dtype=F32)
    np.maximum(p, 0.0, out=p)
    np.sqrt(p, out=p)
    return p


def _blend_weight(off: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """Weight of a yarn's own state at signed offset ``off`` from its centre: 1 at the centre,
    0.5 half-way to the neighbour (``gap`` away), with a continuous slope there (cosine ramp)."""
    t = np.minimum(np.abs(off) / gap, 1.0)
    return (0.5 + 0.5 * np.cos(np.pi * t)).astype(F32)


def _slub_factor(fab: Fabric, along: np.ndarray, lanes: np.ndarray, key: int) -> np.ndarray:
    """Thickness multiplier >= 1 along each yarn (rows: ``along``, columns: yarn ``lanes``)."""
    n = noise_1d(along[:, None], fab.slub_length_mm, key, lanes[None, :])
    # Slubs are occasional thick spots, not a uniform wobble: only the top ~third of the
    # noise range thickens the yarn, quadratically.
    t = np.clip((n - 0.3) / 0.7, 0.0, 1.0)
    return (1.0 + fab.slub * t * t).astype(F32)


# --------------------------------------------------------------------------- woven

def weave_up(fab: Fabric, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """True where warp ``c`` passes over weft ``r`` (broadcast integer arrays)."""
    fam = fab.family
    if fam in ("plain", "ripstop"):
        return (r + c) % 2 == 0
    if fam == "twill":
        n = fab.twill_over + fab.twill_under
        return (c - r) % n < fab.twill_over
    if fam == "herringbone":
        n = fab.twill_over + fab.twill_under
        k = fab.herringbone_warps
        forward = (c // k) % 2 == 0
        # Mirror the diagonal at each stripe boundary so that the stripes meet in a V.
        cm = np.where(forward, c, 2 * k * (c // k) + k - 1 - (c - k * (c // k)))
        return (cm - r) % n < fab.twill_over
    if fam == "satin":
        h = fab.satin_harness
        return (r - c * fab.satin_step) % h != 0
    if fam == "basket":
        g = fab.basket_group
        return (r // g + c // g) % 2 == 0
    raise AssertionError(fam)


def woven(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    jit = fab.spacing_jitter
    c, cu_off, cu_gap = jittered_index(u, fab.warp_pitch_mm, jit, make_key(key, "warp"))
    r, rv_off, rv_gap = jittered_index(v, fab.weft_pitch_mm, jit, make_key(key, "weft"))
    cn = c + np.where(cu_off >= 0, 1, -1)
    rn = r + np.where(rv_off >= 0, 1, -1)
    c0, r0 = int(c.min()) - 1, int(r.min()) - 1
    cc = np.arange(c0, int(c.max()) + 2)
    rr = np.arange(r0, int(r.max()) + 2)
    pat = np.where(weave_up(fab, rr[:, None], cc[None, :]), F32(1.0), F32(-1.0))
    wr = _blend_weight(rv_off, rv_gap)[:, None]
    wc = _blend_weight(cu_off, cu_gap)
    p_r = pat[r - r0]                                   # (H, nc): states along each row's weft
    # Warp centreline: own weft's state blended with the neighbouring weft's (small array first).
    zwarp_small = p_r * wr + pat[rn - r0] * (1.0 - wr)
    zwarp = np.take(zwarp_small, c - c0, axis=1)
    # Weft centreline: up where the warp is down, blended across neighbouring warps.
    zweft = np.take(p_r, c - c0, axis=1)
    zweft *= -wc
    zn = np.take(p_r, cn - c0, axis=1)
    zn *= -(1.0 - wc)
    zweft += zn

    # Per-yarn size multipliers (ripstop reinforcement yarns).
    mu = np.ones(len(u), F32)
    mv = np.ones(len(v), F32)
    if fab.family == "ripstop":
        # Reinforcement yarns are about 1.6x the ground yarns (visible grid of ripstop nylon).
        mu[c % fab.ripstop_every == 0] = 1.6
        mv[r % fab.ripstop_every == 0] = 1.6
    crimp = F32(fab.crimp)
    tops = []
    for z, off, half, mult, lanes, along, tag in (
            (zwarp, cu_off, fab.warp_width_mm / 2, mu, c, v, "slub-warp"),
            (zweft, rv_off, fab.weft_width_mm / 2, mv, r, u, "slub-weft")):
        horizontal = tag == "slub-weft"
        x2 = ((off / half) ** 2).astype(F32) / (mult * mult)
        if fab.slub > 0:
            s = _slub_factor(fab, along, np.unique(lanes), make_key(key, tag))
            lane_idx = np.searchsorted(np.unique(lanes), lanes)
            s = np.take(s, lane_idx, axis=1)            # (len(along), len(lanes_axis))
            if horizontal:
                s = s.T
            x2 = (x2[:, None] if horizontal else x2[None, :]) / (s * s)
            prof = _profile(x2) * s
        else:
            prof = _profile(x2)
            prof = prof[:, None] if horizontal else prof[None, :]
        prof = prof * (mult[:, None] if horizontal else mult[None, :])
        top = z + F32(1.0)
        top *= crimp
        top += prof
        top *= prof > 0
        tops.append(top)
    s = np.maximum(tops[0], tops[1])
    # Normalise by the highest possible top: crimp above the centreline plus the thickest yarn
    # (a reinforcement yarn, thickened further at a slub).
    s *= F32(1.0 / (2.0 * fab.crimp + (1.6 if fab.family == "ripstop" else 1.0) * (1.0 + fab.slub)))
    return s


# --------------------------------------------------------------------------- knitted

def _knit_legs(a_abs: np.ndarray, b: np.ndarray, half: float) -> np.ndarray:
    """Face of a jersey stitch: two slanted legs forming a V, ``a_abs`` = |offset across the
    wale| and ``b`` in [0, 1) up the course, both in stitch units; broadcast arrays."""
    # Legs converge towards the bottom of the stitch (centres 0.12 wale apart at b=0, 0.34 at
    # b=1), as the loop's sinker arc sits under the next course.
    centre = 0.12 + 0.22 * b
    x = (a_abs - centre) / half
    prof = _profile((x * x).astype(F32))
    # Legs dip where they pass under the neighbouring course's loop head.
    prof *= (0.55 + 0.45 * np.sin(np.pi * b)).astype(F32)
    return prof


def _stitch_coords(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int):
    c, u_off, _ = jittered_index(u, fab.warp_pitch_mm, fab.spacing_jitter, make_key(key, "wale"))
    r, v_off, _ = jittered_index(v, fab.weft_pitch_mm, fab.spacing_jitter, make_key(key, "course"))
    a = u_off / fab.warp_pitch_mm                       # across the wale, about -0.5..0.5
    b = np.clip(v_off / fab.weft_pitch_mm + 0.5, 0.0, 1.0)   # up the course, 0..1
    return c, a, r, b


def knit(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    c, a, r, b = _stitch_coords(fab, u, v, key)
    half = fab.warp_width_mm / fab.warp_pitch_mm / 2
    fam = fab.family
    if fam == "jersey":
        s = _knit_legs(np.abs(a)[None, :], b[:, None], half)
    elif fam == "interlock":
        # Two interlocked rib sets: every other wale is shifted by half a course.
        odd = (c % 2 == 1)[None, :]
        b2 = np.where(odd, (b[:, None] + 0.5) % 1.0, b[:, None])
        s = _knit_legs(np.abs(a)[None, :], b2, half * 1.1)
    elif fam == "purl":
        # Loop heads (the back of jersey) as rounded bumps, every other course shifted half a wale.
        odd = (r % 2 == 1)[:, None]
        a2 = np.where(odd, ((a[None, :] + 1.0) % 1.0) - 0.5, a[None, :])
        ex = (a2 / 0.45) ** 2
        ey = ((b[:, None] - 0.5) / max(half * 1.6, 0.2)) ** 2
        s = _profile((ex + ey).astype(F32))
    elif fam == "rib":
        k, m = fab.rib_face_wales, fab.rib_back_wales
        face = (c % (k + m) < k)
        legs = _knit_legs(np.abs(a)[None, :], b[:, None], half)
        # Back wales show loop heads, recessed between the face ribs (the rib's relief).
        head_x = _profile(((a / 0.45) ** 2).astype(F32))
        head_y = _profile((((b - 0.5) / 0.4) ** 2).astype(F32))
        back = (0.45 * head_y)[:, None] * head_x[None, :]
        s = np.where(face[None, :], legs, back).astype(F32)
    else:
        raise AssertionError(fam)
    if fab.slub > 0:
        lanes = np.unique(c)
        sf = _slub_factor(fab, v, lanes, make_key(key, "slub"))
        s = s * np.take(sf, np.searchsorted(lanes, c), axis=1)
        s *= F32(1.0 / (1.0 + fab.slub))
    return s


# --------------------------------------------------------------------------- pile

def corduroy(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    c, off, _ = jittered_index(u, fab.warp_pitch_mm, fab.spacing_jitter, make_key(key, "wale"))
    x = off / (fab.warp_width_mm / 2)
    ridge = np.maximum(0.0, 1.0 - x * x) ** 0.6         # rounded, slightly flat-topped wale
    # The cut pile stands in tuft rows along the wale, one per weft pick of the ground.
    rows = 1.0 - 0.12 * (0.5 + 0.5 * np.cos(2 * np.pi * v / fab.weft_pitch_mm))
    # The ground weave between the wales sits at 8% of the relief.
    ground = 0.08
    s = np.maximum(ridge[None, :] * rows[:, None], ground).astype(F32)
    if fab.slub > 0:
        lanes = np.unique(c)
        sf = _slub_factor(fab, v, lanes, make_key(key, "slub"))
        s = s * np.take(sf, np.searchsorted(lanes, c), axis=1) / F32(1.0 + fab.slub)
    return s


def velvet(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    # A dense cut pile: the top is even, with tuft-scale variation only.
    n = fbm(u, v, fab.feature_mm, fab.feature_mm, make_key(key, "tufts"), 3)
    n *= F32(0.5)
    n += F32(0.5)
    return n


def _bump_lattice(u, v, pu, pv, radius_mm, jitter, key, shift, size_spread=0.0):
    """Round bumps, one per cell of a (pu, pv) lattice shifted by ``shift`` cells, at jittered
    positions inside the cell, random height 0.6-1 and radius ``radius_mm`` x (1 - size_spread * U);
    float32 (len(v), len(u))."""
    gu = u / pu + shift
    gv = v / pv + shift
    cu = np.floor(gu).astype(np.int64)
    cv = np.floor(gv).astype(np.int64)
    a = (gu - cu - 0.5) * pu
    b = (gv - cv - 0.5) * pv
    cu0, cv0 = int(cu.min()), int(cv.min())
    ucells = np.arange(cu0, int(cu.max()) + 1)[None, :]
    vcells = np.arange(cv0, int(cv.max()) + 1)[:, None]
    rad = radius_mm * (1.0 - size_spread * hash_unit(ucells, vcells, make_key(key, "r")))
    # Keep each bump inside its cell, so that no bump is cut by a neighbouring cell.
    scale = min(1.0, jitter / 0.45)
    ou = ((hash_unit(ucells, vcells, make_key(key, "ou")) * 2 - 1) * np.maximum(0.0, pu / 2 - rad) * scale)
    ov = ((hash_unit(ucells, vcells, make_key(key, "ov")) * 2 - 1) * np.maximum(0.0, pv / 2 - rad) * scale)
    hh = (0.6 + 0.4 * hash_unit(ucells, vcells, make_key(key, "h"))).astype(F32)
    inv_r2 = (1.0 / (rad * rad)).astype(F32)
    ri = cv - cv0
    ci = cu - cu0
    du = np.take(ou.astype(F32)[ri], ci, axis=1)
    np.subtract(a.astype(F32)[None, :], du, out=du)
    dv = np.take(ov.astype(F32)[ri], ci, axis=1)
    np.subtract(b.astype(F32)[:, None], dv, out=dv)
    du *= du
    dv *= dv
    du += dv
    du *= np.take(inv_r2[ri], ci, axis=1)
    prof = _profile(du)
    prof *= np.take(hh[ri], ci, axis=1)
    return prof


def terry(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    # Loops stand densely in no visible order: three jittered lattices of slightly different
    # pitch (ratios 1, 1.17, 0.89, chosen incommensurate) overlap into a quasi-random pile.
    r = fab.warp_width_mm / 2
    pu, pv, jit = fab.warp_pitch_mm, fab.weft_pitch_mm, fab.spacing_jitter
    s = _bump_lattice(u, v, pu, pv, r, jit, make_key(key, 1), 0.0, 0.3)
    for k, (fu, fv, sh) in enumerate(((1.17, 0.89, 0.5), (0.89, 1.17, 0.25)), start=2):
        s2 = _bump_lattice(u, v, pu * fu, pv * fv, r, jit, make_key(key, k), sh, 0.3)
        np.maximum(s, s2, out=s)
    return s


# --------------------------------------------------------------------------- non-woven, leather

def felt(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    n = fbm(u, v, fab.feature_mm, fab.feature_mm * fab.anisotropy, make_key(key, "mat"), 4, gain=0.6)
    if fab.family == "fleece":
        # Brushed fleece gathers into soft clumps: emphasise the highs, flatten the lows.
        n = np.clip(n * F32(1.8) + F32(0.2), -1.0, 1.0)
        n = (n + F32(1.0)) * F32(0.5)
        return n * n
    n *= F32(0.5)
    n += F32(0.5)
    return n


def leather(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    f = fab.feature_mm
    # Grain wrinkles: a network of creases along the zero set of a noise field.
    n = fbm(u, v, f, f, make_key(key, "crease"), 3)
    crease = np.abs(n)
    crease *= F32(1.0 / 0.18)     # crease half-width: 18% of the noise range
    np.minimum(crease, 1.0, out=crease)
    crease = F32(1.0) - crease
    crease *= crease
    base = value_noise(u, v, f * 0.5, f * 0.5, make_key(key, "grain"))
    base *= F32(0.2)
    base += F32(0.75)
    depth = 0.6 if fab.family == "leather" else 0.25   # suede's nap hides most creases
    crease *= F32(depth)
    base -= crease
    if fab.pore_diameter_mm > 0:
        pores = _bump_lattice(u, v, fab.pore_spacing_mm, fab.pore_spacing_mm, fab.pore_diameter_mm / 2,
                              0.45, make_key(key, "pores"), 0.0)
        pores *= F32(0.5)
        base -= pores
    np.clip(base, 0.0, 1.0, out=base)
    return base


# --------------------------------------------------------------------------- open

def _net(fab: Fabric, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    p = fab.warp_pitch_mm
    half = fab.warp_width_mm / 2
    ang = math.radians(fab.mesh_angle_deg)
    dirs = [ang, -ang] + ([0.0] if fab.mesh_third_set else [])
    profs = []
    for k, phi in enumerate(dirs):
        # Distance across the yarn set whose yarns run at angle phi to u.
        nu, nv = -math.sin(phi), math.cos(phi)
        s = (u * (nu / p))[None, :].astype(np.float64) + (v * (nv / p))[:, None] + 0.25 * k
        s -= np.floor(s)
        s -= 0.5
        s *= p / half
        profs.append(_profile((s * s).astype(F32)))
    net = profs[0]
    knots = profs[0] * profs[1]
    for pr in profs[1:]:
        np.maximum(net, pr, out=net)
    # Yarns cross over each other at the knots, which stand higher.
    net *= F32(0.8)
    knots *= F32(0.2)
    net += knots
    return net


_LACE_THRESHOLDS: dict[tuple, float] = {}


def _lace_threshold(fab: Fabric, key: int) -> float:
    """Noise level above which the lace is motif, from a fixed reference sample (not the patch),
    so that the threshold is the same for every patch."""
    k = (fab.motif_mm, fab.motif_fill, key)
    if k not in _LACE_THRESHOLDS:
        ref = np.arange(256) * (fab.motif_mm / 16)
        n = fbm(ref, ref, fab.motif_mm, fab.motif_mm, make_key(key, "motif"), 3)
        _LACE_THRESHOLDS[k] = float(np.quantile(n, 1.0 - fab.motif_fill))
    return _LACE_THRESHOLDS[k]


def mesh(fab: Fabric, u: np.ndarray, v: np.ndarray, key: int) -> np.ndarray:
    net = _net(fab, u, v)
    if fab.family == "mesh":
        return net
    thr = _lace_threshold(fab, key)
    n = fbm(u, v, fab.motif_mm, fab.motif_mm, make_key(key, "motif"), 3)
    n -= F32(thr)
    # Cordonnet: a raised cord outlines every motif.
    cord = np.abs(n) * F32(1.0 / 0.06)
    cord = _profile(cord * cord)
    # Inside the motif: a dense cloth-stitch work with a fine regular texture (yarn scale).
    q = 2 * np.pi / (fab.warp_width_mm * 2.5)
    tex = (0.55 + 0.08 * np.cos(q * u))[None, :] + (0.08 * np.cos(q * v))[:, None]
    fill = np.where(n > 0, tex.astype(F32), F32(0.0))
    net *= F32(0.45)
    np.maximum(net, fill, out=net)
    np.maximum(net, cord, out=net)
    return net


RENDERERS = {
    **{f: woven for f in ("plain", "twill", "satin", "basket", "herringbone", "ripstop")},
    **{f: knit for f in ("jersey", "interlock", "purl", "rib")},
    "corduroy": corduroy, "velvet": velvet, "terry": terry,
    "felt": felt, "fleece": felt,
    "leather": leather, "suede": leather,
    "mesh": mesh, "lace": mesh,
}
