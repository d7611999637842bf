"""Fit a sensor profile to real ball presses (a data pack, see :mod:`gelsim.realism`).

What is fitted, from the selected frames only:

* background: the no-contact frame ``f0``, smoothed and stored at half resolution
  as a PNG beside the profile (``[background] image``);
* shading: the lookup table of :mod:`gelsim.optics.lut` (colour change over the
  surface normal with a first-order spatial term, plus a shadow colour per LED, the
  depth term and the halo term), by regularised, weighted linear least squares on the
  pixels near each contact: pixels outside the contact weigh less (``OUTSIDE_WEIGHT``),
  since there the imprint model's normals are approximate;
* gel response: the gel thickness (sets the pyramid spread of the imprint around the
  ball) and the membrane smoothing, and the shadows' grazing elevation, chosen by
  two-fold cross-validation among the selected frames (the table is refitted for
  each candidate);
* noise: read noise and shot gain from the frame-to-frame differences away from
  the contacts.

Each press is simulated as in :func:`gelsim.realism.ball_depth`: the ball pressed to
the depth that gives the annotated contact radius.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import cv2
import numpy as np
from scipy import sparse
from scipy.sparse.linalg import LinearOperator, cg, splu, spsolve

from .atomic import atomic_write_npz, atomic_write_text, not_a_folder, write_png
from .centres import detect_centres
from .errors import GelsimError
from .optics.lut import normal_xy
from .optics.ops.coarse import coarse_features
from .optics.ops.shadows import shadow_factors
from .params import dump_toml, to_dict, toml_comments
from .realism import DISK_RADII, DataPack, ball_cap, ball_depth, ball_indentation_mm, check_geometry, disk_mask

# Fitting constants (why each has its value):
N_BINS = 41             # normal bins over -1..1: 0.05 per bin, finer than the ball's normal changes per px
FIT_RADII = 1.75        # fit inside 1.75 contact radii: the scored disk (1.5) plus the rim's outer edge
FIT_STRIDE = 2          # every 2nd pixel each way: neighbours are nearly the same sample (the image is smooth)
SMOOTH_WEIGHT = 3.0     # second-difference penalty between bins, per unit of sample weight: the first guess;
                        # the fit then picks the weight from DEFAULT_GRID["smooth_weight"] by cross-validation
RIDGE_WEIGHT = 1e-3     # keeps bins without samples near zero
# The spatial terms (the change over the field, T1 xn + T2 yn, and the depth term's D1 xn + D2 yn) are
# only as good as the spread of the presses over the field. The GelSight Mini's 24 presses all lie
# within 0.1 of the field's centre (xn, yn in -1..1): there the fit made them 300-400 DN per unit of
# field, extrapolated into visible seams between the renderer's tiles and colour casts across the
# field. Each spatial coefficient is held towards zero by SPATIAL_RIDGE times the data's weight on its
# constant counterpart: as if the presses' positions had a spread of 0.1 (RMS, field units) more
# than they have. The R1.5's presses span -0.8..0.8, a spread of about 0.5: its terms hardly change.
SPATIAL_RIDGE = 0.01
# Pixels outside the contact weigh 0.3 in the table's fit. There the normals come from the imprint
# model's spread, which ends at about 1.8 contact radii while real presses change the image out to
# 2.5 (docs/realism.md): the real gel is still sloped where the model's is flat. At near-flat normals
# these pixels outnumber the ball's own flat top (exact normals) about 100:1, and taught the table
# a step at flat: on the R1.5's held-out frames the response to slopes below 0.1 was 2.1-3.1x the
# real one. Two-fold cross-validation on the R1.5's even frames, skill / RMS error at slopes < 0.2:
# before (no depth or halo term, weight 1) 0.927 / 7.2 DN; with both terms, outside weight
# 1 / 0.3 / 0.1: 0.931 / 5.6, 0.930 / 4.9, 0.926 / 4.5 DN. 0.3 keeps the skill and removes most
# of the step; lower weights start to cost skill and leave blue with a dead zone near flat.
OUTSIDE_WEIGHT = 0.3
# The halo term (gelsim.optics.lut): widths chosen by the same cross-validation (1 and 2 mm, and the
# outside weight, were compared): 1 mm reaches about 3 mm around a press, the real halo's extent; the
# base blur of 0.25 mm removes relief finer than about 1 mm (a fabric's weave), so that the halo
# follows the press's shape and not its texture; the gate, 0.02 mm of spill, is a fiftieth of the
# R1.5's presses (about 1 mm deep), so the halo switches on within a few pixels of the spill's edge.
HALO_SIGMA_MM = 1.0
HALO_BASE_MM = 0.25
HALO_GATE_MM = 0.02
SHADOW_SAT_MM = 0.1     # occlusion at which a shadow is half dark: a tenth of the ball's 1 mm presses, so a
                        # shadow deepens over its first third and fades out over its last tenth
BG_SCALE = 2            # background stored at 1/2 resolution: keeps 2 px detail, is not the raw frame
BG_SIGMA_PX = 1.0       # smoothing before downsampling (full-resolution px): removes the frame's own noise
DEFAULT_GRID = {
    "thickness_mm": (1.0, 2.0, 3.0),
    "membrane_smoothing_mm": (0.02, 0.06, 0.12),
    # slope of each LED's grazing ray (tan of its elevation; 0 = no shadow terms): a shadow is at most
    # depth / tan long, so slopes from 0.5 (27 deg) up keep a 1 mm press's shadows within 2 mm of the ball
    "shadow_tan": (0.0, 0.5, 0.7, 1.0),
    # penumbra (Gaussian sigma, mm): the LEDs' extent seen from the gel and the membrane's scatter
    "shadow_soft_mm": (0.1, 0.2),
    # the table's smoothness penalty: a sensor whose colour turns within a few hundredths of slope
    # (the GelSight Mini) needs less than one with a gentle response (the R1.5); chosen last
    "smooth_weight": (0.1, 0.3, 1.0, 3.0),
}


# --------------------------------------------------------------------------------------
# Background and noise
# --------------------------------------------------------------------------------------
def fit_background(f0: np.ndarray) -> np.ndarray:
    """The smoothed, half-resolution background: uint8 ``(H/2, W/2, 3)`` RGB."""
    h, w = f0.shape[:2]
    k = 2 * int(math.ceil(3 * BG_SIGMA_PX)) + 1
    b = cv2.GaussianBlur(f0.astype(np.float32), (k, k), BG_SIGMA_PX, borderType=cv2.BORDER_REPLICATE)
    small = cv2.resize(b, (w // BG_SCALE, h // BG_SCALE), interpolation=cv2.INTER_AREA)
    return np.clip(np.rint(small), 0, 255).astype(np.uint8)


def upsample_background(small: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The stored background at ``shape`` (H, W) as the renderer sees it: float32 RGB."""
    from .optics.field import resize_background
    return resize_background(small.astype(np.float32), shape, "linear")


def fit_noise(pack: DataPack, idx: list[int]) -> tuple[float, float]:
    """``(read_sigma_dn, shot_gain)`` from ``frame - f0`` away from the contacts.

    The difference of two frames has twice one frame's noise variance; slow drift is
    removed by subtracting a blur (sigma 5 px) of the difference. The variance is
    regressed on the signal level: ``var = read^2 + shot_gain * level``.
    """
    f0 = pack.f0.astype(np.float32)
    levels, variances = [], []
    for i in idx:
        diff = pack.imgs[i].astype(np.float32) - f0
        hp = diff - cv2.GaussianBlur(diff, (0, 0), 5.0)
        away = ~disk_mask(pack.centers_px[i], 3.0 * pack.radii_px[i], pack.shape)
        lv = f0[away].ravel()
        v = (hp[away].ravel() ** 2) / 2.0
        levels.append(lv)
        variances.append(v)
    lv = np.concatenate(levels)
    v = np.concatenate(variances)
    edges = np.percentile(lv, np.linspace(0, 100, 11))
    xs, ys = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (lv >= a) & (lv <= b)
        if m.sum() > 100:
            xs.append(lv[m].mean())
            ys.append(v[m].mean())
    # Shot noise is told from read noise only by its growth with the level; over less
    # than a 2:1 range of levels the slope is not determined, so all goes to read noise.
    if len(xs) >= 2 and xs[-1] >= 2.0 * max(xs[0], 1.0):
        slope, icpt = np.polyfit(xs, ys, 1)
        slope, icpt = max(float(slope), 0.0), max(float(icpt), 0.0)
    else:
        slope, icpt = 0.0, float(v.mean())
    # a blur of sigma 5 px leaves about 98% of white noise's variance in the high-pass part
    return math.sqrt(icpt), slope


# --------------------------------------------------------------------------------------
# Shading table
# --------------------------------------------------------------------------------------
def _frame_samples(profile, pack: DataPack, i: int, bg: np.ndarray, ball_mm: float, shadow: dict | None):
    """Features and targets of frame ``i``: dict of nx, ny, xn, yn, ``extra`` (K + 6, n: the K shadow
    factors, the depth term's basis, the halo's features), ``n_shadow`` (K), target (n, 3) and the
    samples' fit ``weight`` (n,) (1 inside the annotated contact, OUTSIDE_WEIGHT outside).

    ``shadow``: None, or the shadow terms' ``shadow_dirs_deg``, ``shadow_tan``, ``shadow_sat_mm``
    and ``shadow_soft_mm`` (the keys of the table file)."""
    h, w = pack.shape
    depth = ball_depth(profile, pack.centers_px[i], pack.radii_px[i], ball_mm)
    c, r = pack.centers_px[i], pack.radii_px[i]
    rr = FIT_RADII * r
    y0, y1 = max(0, int(c[1] - rr) - 1), min(h, int(c[1] + rr) + 2)
    x0, x1 = max(0, int(c[0] - rr) - 1), min(w, int(c[0] + rr) + 2)
    roi = (slice(y0, y1), slice(x0, x1))
    mm = profile.image.mm_per_px
    nx, ny = normal_xy(depth, mm)
    yy, xx = np.mgrid[y0:y1:FIT_STRIDE, x0:x1:FIT_STRIDE]
    keep = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= rr * rr
    yy, xx = yy[keep], xx[keep]
    inside = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= r * r
    xn, yn = field_position(xx, yy, pack.shape)
    out = {
        "nx": nx[yy, xx], "ny": ny[yy, xx], "xn": xn, "yn": yn,
        "target": pack.imgs[i][yy, xx].astype(np.float32) - bg[yy, xx],
        "weight": np.where(inside, 1.0, OUTSIDE_WEIGHT).astype(np.float32),
    }
    extra = []
    if shadow is not None:
        f, to_full = shadow_factors(depth, mm, shadow["shadow_dirs_deg"], shadow["shadow_tan"],
                                    shadow["shadow_sat_mm"], shadow["shadow_soft_mm"])
        # the renderer brings the factors to full resolution the same way (bilinear)
        full = np.stack([cv2.warpAffine(np.ascontiguousarray(f[..., k]), to_full, (w, h),
                                        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                        borderMode=cv2.BORDER_REPLICATE) for k in range(f.shape[-1])], axis=-1)
        extra.append(full[yy, xx].T)
    out["n_shadow"] = len(extra[0]) if extra else 0
    halo = {k: float(v) for k, v in halo_spec().items()}
    extra.append(coarse_features(depth, mm, profile.field_mm, True, halo)[yy, xx].T)
    out["extra"] = np.concatenate(extra).astype(np.float32)
    del roi
    return out


def field_position(xx: np.ndarray, yy: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel columns and rows ``xx, yy`` (any shape) of an image of ``shape`` (H, W) as the table's
    positions ``xn, yn``: float32, -1..1 from edge to edge of the field (pixel centres, as the renderer)."""
    h, w = shape
    return (((xx - (w - 1) / 2.0) / (w / 2.0)).astype(np.float32),
            ((yy - (h - 1) / 2.0) / (h / 2.0)).astype(np.float32))


def halo_spec() -> dict:
    """The halo term's widths (table-file keys)."""
    return {"halo_sigma_mm": np.float32(HALO_SIGMA_MM), "halo_base_mm": np.float32(HALO_BASE_MM),
            "halo_gate_mm": np.float32(HALO_GATE_MM)}


def _design(samples: list[dict], nb: int) -> tuple[sparse.csr_matrix, np.ndarray]:
    """Sparse design matrix (n, 3 nb^2 + K + 6) and targets (n, 3) of the table model (unweighted)."""
    nx = np.concatenate([s["nx"] for s in samples])
    ny = np.concatenate([s["ny"] for s in samples])
    xn = np.concatenate([s["xn"] for s in samples])
    yn = np.concatenate([s["yn"] for s in samples])
    y = np.concatenate([s["target"] for s in samples]).astype(np.float64)
    n = nx.size
    half = (nb - 1) / 2.0
    mx = np.clip(nx * half + half, 0, nb - 1 - 1e-6)
    my = np.clip(ny * half + half, 0, nb - 1 - 1e-6)
    ix, iy = np.floor(mx).astype(np.int64), np.floor(my).astype(np.int64)
    fx, fy = mx - ix, my - iy
    rows, cols, vals = [], [], []
    basis = (np.ones(n), xn, yn)
    ar = np.arange(n)
    for dy, dx, wgt in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        b = (iy + dy) * nb + (ix + dx)
        for k, bv in enumerate(basis):
            rows.append(ar)
            cols.append(b * 3 + k)
            vals.append(wgt * bv)
    ncol = 3 * nb * nb
    if "extra" in samples[0]:
        ex = np.concatenate([s["extra"] for s in samples], axis=1)
        for k in range(ex.shape[0]):
            rows.append(ar)
            cols.append(np.full(n, ncol + k))
            vals.append(ex[k])
        ncol += ex.shape[0]
    a = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, ncol))
    return a, y


def _regulariser(nb: int, ncol: int) -> sparse.csr_matrix:
    """Second differences between neighbouring bins (both axes, each basis) and a small ridge."""
    rows, cols, vals = [], [], []
    r = 0
    for k in range(3):
        for j in range(nb):
            for i in range(1, nb - 1):
                for (a, b) in (((j, i - 1), (j, i + 1)), ((i - 1, j), (i + 1, j))):
                    mid = (j, i) if a[0] == j else (i, j)
                    for (bj, bi), v in ((a, 1.0), (mid, -2.0), (b, 1.0)):
                        rows.append(r)
                        cols.append((bj * nb + bi) * 3 + k)
                        vals.append(v)
                    r += 1
    return sparse.csr_matrix((vals, (rows, cols)), shape=(r, ncol))


def normal_equations(samples: list[dict], nb: int = N_BINS) -> dict:
    """The weighted least-squares problem of the table model for ``samples``: ``ata`` (sparse, ncol x
    ncol), ``aty`` (ncol, 3), the sample count ``n`` and ``n_shadow``. Problems of disjoint samples
    add (and subtract) term by term, which :func:`register_presses` uses to leave one frame out."""
    a, y = _design(samples, nb)
    if "weight" in samples[0]:
        # each sample's squared error counts weight times
        w = np.sqrt(np.concatenate([s["weight"] for s in samples]).astype(np.float64))
        a = sparse.diags(w) @ a
        y = y * w[:, None]
    return {"ata": (a.T @ a).tocsc(), "aty": a.T @ y, "n": a.shape[0], "n_shadow": samples[0].get("n_shadow", 0)}


def _system(eq: dict, nb: int, smooth: float) -> sparse.csc_matrix:
    """The regularised matrix of :func:`normal_equations` ``eq`` (its right-hand side is ``eq["aty"]``)."""
    ncol = eq["ata"].shape[0]
    reg = _regulariser(nb, ncol)
    lam = smooth * eq["n"] / (nb * nb)
    # the spatial terms (T1, T2 of each bin; the depth term's D1, D2) are held towards zero by
    # SPATIAL_RIDGE times the data's weight on their constant counterparts (T0 of the bin; D0)
    diag = eq["ata"].diagonal()
    spatial = np.zeros(ncol)
    ntab = 3 * nb * nb
    const = np.arange(0, ntab, 3)
    spatial[const + 1] = spatial[const + 2] = SPATIAL_RIDGE * diag[const]
    if ncol > ntab:
        d0 = ntab + eq["n_shadow"]
        spatial[d0 + 1] = spatial[d0 + 2] = SPATIAL_RIDGE * diag[d0]
    m = (eq["ata"] + lam * (reg.T @ reg) + RIDGE_WEIGHT * lam * sparse.identity(ncol)
         + sparse.diags(spatial)).tocsc()
    # T(0, 0) = 0: a flat gel shows the background, so pin the centre bin's three terms
    c = ((nb // 2) * nb + nb // 2) * 3
    pin = sparse.lil_matrix((ncol, ncol))
    for k in range(3):
        pin[c + k, c + k] = 1e6 * lam
    return (m + pin.tocsc()).tocsc()


def _unpack(sol: np.ndarray, nb: int, n_shadow: int) -> dict:
    """The LUT file's arrays from the solution ``(ncol, 3)`` of the table's system."""
    ncol = sol.shape[0]
    table = sol[:3 * nb * nb].reshape(nb, nb, 3, 3)       # (row=ny, col=nx, basis, colour)
    out = {"table": np.ascontiguousarray(table.reshape(nb, nb, 9), dtype=np.float32)}
    if ncol > 3 * nb * nb:
        ex = sol[3 * nb * nb:].astype(np.float32)
        k = n_shadow
        if k:
            out["shadow_rgb"] = ex[:k]
        out["depth_rgb"], out["halo_rgb"] = ex[k:k + 3], ex[k + 3:k + 6]
    return out


def solve_table(eq: dict, nb: int = N_BINS, smooth: float = SMOOTH_WEIGHT) -> dict:
    """The table, shadow colours, depth and halo terms solving :func:`normal_equations` ``eq`` with the
    smoothness penalty; the LUT file's arrays (without the shadows' and the halo's geometry)."""
    sol = spsolve(_system(eq, nb, smooth), eq["aty"])
    return _unpack(np.asarray(sol).reshape(eq["ata"].shape[0], 3), nb, eq["n_shadow"])


def fit_table(samples: list[dict], nb: int = N_BINS, smooth: float = SMOOTH_WEIGHT) -> dict:
    """Weighted least-squares table, shadow colours, depth and halo terms from samples; returns the
    LUT file's arrays (without the shadows' and the halo's geometry, which the caller adds)."""
    return solve_table(normal_equations(samples, nb), nb, smooth)


def predict(table: dict, s: dict, nb: int = N_BINS) -> np.ndarray:
    """The table's colour change (n, 3) for one frame's samples (for cross-validation)."""
    a, _ = _design([s], nb)
    none = np.zeros((0, 3), np.float32)
    coef = np.concatenate([table["table"].reshape(nb * nb * 3, 3), table.get("shadow_rgb", none),
                           table.get("depth_rgb", none), table.get("halo_rgb", none)])
    return a @ coef.astype(np.float64)


# --------------------------------------------------------------------------------------
# Registration: where each ball was pressed
# --------------------------------------------------------------------------------------
# A pack's contact centres are annotated by hand (taxim's tool moves a circle in 2 px steps). Where
# the contact's rim shows (the R1.5) they are right to a few pixels; where it does not (the GelSight
# Mini, whose image fades towards the rim and turns through its whole colour wheel within 10-25 px of
# the ball's lowest point) they are off by 5.5 / 8.5 px RMS in x / y, up to 21 px (docs/realism.md).
# Inside the contact the gel takes the ball's shape, so a press's colours there follow from its centre alone
# (the ball's normals and depth; no gel model): each centre is moved to where its press agrees best
# with a shading table fitted on the other presses. Constants:
REGISTER_REACH = 0.75   # search within 0.75 contact radii of the annotated centre (the Mini's worst: 0.49)
REGISTER_GRID = 9       # coarse search: 9 x 9 centres over the reach (0.19 radii apart, 8.6 px on the Mini:
                        # inside the 10-25 px over which its colours turn), then a pattern search
REGISTER_TOL_PX = 0.25  # the pattern search stops at this step, px
REGISTER_SAMPLES = 20   # sample every n-th pixel each way, n = median contact radius / 20 (at least 1): every
                        # 2nd on the Mini (radii 34-57 px), 3rd on the R1.5 (59-67); centres found at
                        # twice as many samples each way differ by under 0.3 / 0.8 px. On a synthetic pack
                        # with 11-15 px contacts and exact centres, every 2nd pixel moves them by 1.0 px
                        # RMS, every pixel by 0.6
REGISTER_SMOOTH = 0.3   # the reference table's smoothness, between the Mini's fitted 0.1 (its colour wheel)
                        # and the R1.5's 1.0-3.0; on the Mini, 0.3 and 3.0 move the centres by 9.56 and
                        # 9.58 px RMS
REGISTER_CG_RTOL = 1e-4 # relative residual of each left-out table's solve (its colours to about 0.01 DN)
REGISTER_ROUNDS = 4     # rounds over the fitted presses (each against the others' table); stops earlier
                        # once no centre moves by more than a pixel
# Registration is applied only where the annotation is demonstrably off: when it removes at least half
# of the misfit inside the contacts that the annotated centres leave (mean over the fitted frames, each
# against a table of the others). Where a sensor's response is nearly linear in the slope, a shift of
# the centre looks much like a uniform colour change, and the search chases the table's own errors
# instead. Measured on the even frames: the R1.5 (rims visible) 26%, its centres moved 4.1 px RMS in
# step with their place in the field (the table's spatial error, not the annotation's); a synthetic
# phong pack with known centres -4% (0.6 px); the GelSight Mini 91% (9.5 px). A synthetic pack rendered
# with the Mini's table, its annotations shifted by 2-5 px: 77-80%, centres recovered to 0.3-0.7 px RMS
# (tests/gelsim/test_calibrate.py).
REGISTER_MIN_EXPLAINED = 0.5


def _cap_samples(pack: DataPack, i: int, center, bg: np.ndarray, mm_per_px: float, ball_mm: float,
                 stride: int) -> dict:
    """Frame ``i``'s samples inside its contact (:func:`gelsim.realism.ball_cap`) for a ball centred
    on ``center`` (x, y) px: the ball's exact normals (nx, ny), positions (xn, yn), the depth term's
    basis ``extra`` (3, n) (the depth is the annotated press's, ``ball_indentation_mm`` of its radius,
    less the sphere's rise) and the target colour change (n, 3) over ``bg``; every ``stride``-th pixel."""
    yy, xx, gx, gy, sag = ball_cap(center, pack.radii_px[i], pack.shape, mm_per_px, ball_mm, stride)
    inv = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    xn, yn = field_position(xx, yy, pack.shape)
    d = (ball_indentation_mm(pack.radii_px[i] * mm_per_px, ball_mm) - sag).astype(np.float32)
    return {"nx": (-gx * inv).astype(np.float32), "ny": (-gy * inv).astype(np.float32), "xn": xn, "yn": yn,
            "extra": np.stack([d, d * xn, d * yn]), "n_shadow": 0,
            "target": pack.imgs[i][yy, xx].astype(np.float32) - bg[yy, xx]}


def _misfit(pack: DataPack, i: int, center, table: dict, bg: np.ndarray, mm_per_px: float, ball_mm: float,
            stride: int) -> float:
    """Mean squared difference (DN^2 per sample and channel) between frame ``i``'s colour change inside
    its contact, the ball centred on ``center``, and ``table``'s; inf when no pixel is inside."""
    s = _cap_samples(pack, i, center, bg, mm_per_px, ball_mm, stride)
    if s["nx"].size == 0:
        return math.inf
    return float(((predict(table, s) - s["target"]) ** 2).mean())


def _place(pack: DataPack, i: int, table: dict, bg: np.ndarray, mm_per_px: float, ball_mm: float,
           stride: int) -> tuple[np.ndarray, float, float]:
    """The centre (x, y) px within REGISTER_REACH contact radii of frame ``i``'s annotated one where its
    press agrees best (:func:`_misfit`) with ``table``: a coarse grid, then a pattern search (one step
    each way, halved when no neighbour is better). Returns the centre, its misfit and the misfit at
    the annotated centre (the grid's middle)."""
    c0 = pack.centers_px[i]
    reach = REGISTER_REACH * pack.radii_px[i]
    h, w = pack.shape

    def cost(c):
        if (c[0] - c0[0]) ** 2 + (c[1] - c0[1]) ** 2 > reach * reach:
            return math.inf
        if not (0 <= c[0] <= w - 1 and 0 <= c[1] <= h - 1):
            return math.inf
        return _misfit(pack, i, c, table, bg, mm_per_px, ball_mm, stride)

    offs = np.linspace(-reach, reach, REGISTER_GRID)      # an odd count: the middle is the annotation
    grid = [(cost(c0 + (dx, dy)), tuple(c0 + (dx, dy))) for dy in offs for dx in offs]
    at_annotation = grid[len(grid) // 2][0]
    best_e, best = min(grid)
    best = np.asarray(best)
    step = offs[1] - offs[0]
    while step > REGISTER_TOL_PX:
        moves = [(cost(best + (dx, dy)), (dx, dy)) for dy in (-step, 0.0, step) for dx in (-step, 0.0, step)
                 if dx or dy]
        e, mv = min(moves)
        if e < best_e:
            best_e, best = e, best + mv
        else:
            step /= 2.0
    return best, best_e, at_annotation


def _leave_out(m: sparse.csc_matrix, lu, aty: np.ndarray, eq: dict) -> dict:
    """The table of all frames but one: the system ``m`` (all frames, factorised as ``lu``) less that
    frame's normal equations ``eq``, solved by conjugate gradients preconditioned with ``lu`` (a few
    iterations: one frame changes the system little). The smoothness stays that of all frames."""
    mi = (m - eq["ata"]).tocsr()
    rhs = aty - eq["aty"]
    pre = LinearOperator(m.shape, matvec=lu.solve, dtype=np.float64)
    sol = np.empty_like(rhs)
    for c in range(rhs.shape[1]):
        sol[:, c], _ = cg(mi, rhs[:, c], x0=lu.solve(rhs[:, c]), M=pre, rtol=REGISTER_CG_RTOL, maxiter=200)
    return _unpack(sol, N_BINS, 0)


def register_presses(pack: DataPack, frames: str, mm_per_px: float, ball_diameter_mm: float,
                     log=None) -> tuple[DataPack, dict]:
    """``pack`` with its contact centres registered from the images, if the annotation is off (see the
    constants above).

    The ``frames`` ("even", "odd" or "all") are registered among themselves: in rounds, each against a
    table fitted on all the others (:func:`fit_table` with the depth term, on the exact normals inside
    the contacts; one frame left out of the summed normal equations), their mean offset from the
    annotation removed after each round (the presses fix one another's positions only up to a common
    shift; on a synthetic pack with known centres the whole set drifted by 3.5 px without this, while
    the centres relative to each other came out within 0.7 px). The registration is *applied*
    only if it removes at least REGISTER_MIN_EXPLAINED of the left-out misfit (:func:`_misfit`, mean
    over ``frames``) that the annotated centres leave; otherwise every centre stays as annotated. The
    other frames keep their annotated centres (:func:`register_heldout` places them against a table
    of ``frames``). Radii are kept.

    Returns the pack (new centres for ``frames``, or ``pack`` itself) and a report: ``applied``;
    ``explained`` (the fraction of the misfit removed); ``misfit_dn2`` (annotated, registered);
    ``found_offsets_px`` (N, 2) (registered minus annotated; zero for the other frames);
    ``offsets_px`` (those applied: zero when not); ``rms_offset_px`` (of the found offsets over
    ``frames``); ``rounds``; ``stride`` (px between samples)."""
    log = log or (lambda msg: None)
    idx = pack.select(frames)
    bg = upsample_background(fit_background(pack.f0), pack.shape)
    annotated = pack.centers_px.astype(np.float64)
    stride = max(1, int(np.median(pack.radii_px) / REGISTER_SAMPLES))

    def left_out_tables(cents):
        """(frame, table of the other frames of ``idx`` at ``cents``) for each frame of ``idx``."""
        eqs = {j: normal_equations([_cap_samples(pack, j, cents[j], bg, mm_per_px, ball_diameter_mm, stride)])
               for j in idx}
        total = {"ata": sum(e["ata"] for e in eqs.values()), "aty": sum(e["aty"] for e in eqs.values()),
                 "n": sum(e["n"] for e in eqs.values()), "n_shadow": 0}
        m = _system(total, N_BINS, REGISTER_SMOOTH)
        lu = splu(m)
        for i in idx:
            yield i, _leave_out(m, lu, total["aty"], eqs[i])

    cents = annotated.copy()
    rounds, before = 0, 0.0
    for rounds in range(1, REGISTER_ROUNDS + 1):
        new = cents.copy()
        at_annotation = []
        for i, t in left_out_tables(cents):
            new[i], _, at = _place(pack, i, t, bg, mm_per_px, ball_diameter_mm, stride)
            at_annotation.append(at)
        if rounds == 1:     # every table of this round is at the annotated centres
            before = float(np.mean(at_annotation))
        # the presses place each other only relative to one another: moving all of them together (with
        # the table) fits as well, so the annotation is taken as right on average
        new[idx] -= (new[idx] - annotated[idx]).mean(axis=0)
        moved = float(np.abs(new - cents).max())
        cents = new
        if moved <= 1.0:
            break
    # the registered centres' misfit against tables at the registered centres (the search's own best
    # misfits, against the tables it moved with, flatter it: on a synthetic pack with shifted centres
    # that it could not recover, 77% less instead of 6% more)
    after = float(np.mean([_misfit(pack, i, cents[i], t, bg, mm_per_px, ball_diameter_mm, stride)
                           for i, t in left_out_tables(cents)]))
    # a press with no sampled pixel inside its contact (a contact under a pixel wide) scores inf: no verdict
    explained = 1.0 - after / before if math.isfinite(before) and math.isfinite(after) and before > 0 else 0.0
    applied = explained >= REGISTER_MIN_EXPLAINED
    found = cents - annotated
    rms = float(np.sqrt((found[idx] ** 2).sum(axis=1).mean()))
    verdict = (f"moved by {rms:.1f} px RMS" if applied else f"kept as annotated (moving them {rms:.1f} px RMS "
               f"would remove only {100 * explained:.0f}% < {100 * REGISTER_MIN_EXPLAINED:.0f}%)")
    log(f"press centres: the annotated ones leave a misfit of {before:.1f} DN^2 inside the contacts, registered "
        f"ones {after:.1f} ({100 * explained:.0f}% less): {verdict}")
    report = {"applied": applied, "explained": explained, "misfit_dn2": [before, after],
              "found_offsets_px": found.tolist(), "offsets_px": (found if applied else 0.0 * found).tolist(),
              "rms_offset_px": rms, "rounds": rounds, "stride": stride}
    return (dataclasses.replace(pack, centers_px=cents) if applied else pack), report


def register_heldout(pack: DataPack, fit_idx: list[int], fit_centres: np.ndarray, targets: list[int],
                     mm_per_px: float, ball_diameter_mm: float) -> np.ndarray:
    """The centres (N, 2) px of ``pack`` with each of ``targets`` moved to where its press agrees best
    (:func:`_place`, searched around its centre in ``pack``) with the table fitted on the ``fit_idx``
    frames placed at ``fit_centres`` (N, 2) (the depth term on the exact normals inside the contacts,
    as :func:`register_presses`). The other rows are ``pack``'s. The pose of each target is fitted to
    that table: scores at these centres are an upper bound of what the table's model can reach."""
    bg = upsample_background(fit_background(pack.f0), pack.shape)
    stride = max(1, int(np.median(pack.radii_px) / REGISTER_SAMPLES))
    t = fit_table([_cap_samples(pack, j, fit_centres[j], bg, mm_per_px, ball_diameter_mm, stride) for j in fit_idx],
                  smooth=REGISTER_SMOOTH)
    cents = pack.centers_px.astype(np.float64).copy()
    for i in targets:
        cents[i] = _place(pack, i, t, bg, mm_per_px, ball_diameter_mm, stride)[0]
    return cents


# --------------------------------------------------------------------------------------
# Centres: where the fitted and the scored presses are placed
# --------------------------------------------------------------------------------------
# A held-out score must not place its presses with the model it scores (issue #44): registering a
# scored press against the fitted frames' table fits two numbers per frame to that model. The scored
# presses are placed from a source independent of it: the pack's annotation where it holds (the
# registration among the fitted frames cannot remove half the misfit it leaves), else the flat-point
# detector (gelsim.centres) where it agrees with that registration on the fitted frames: within
# DETECT_AGREE_PX RMS once their common shift is removed (the registration fixes the presses only
# relative to each other). On the GelSight Mini pack the detector agrees to 0.37 px (even frames);
# on the R1.5 it would not (8 px: its annotation holds). 1 px is a fifth of the Mini's 5-10 px
# over which its colour wheel turns.
DETECT_AGREE_PX = 1.0
CENTRE_SOURCES = ("annotated", "detected", "registered")
# what a calibrated profile's header says of the centres its fitted frames were placed at
CENTRES_NOTE = {
    "annotated": "Press centres as annotated (registration would not remove half their misfit).",
    "detected": "Press centres detected in each frame (gelsim.centres: the flat point, where the colour change\n"
                "vanishes), as the pack's annotation is off and the detector agrees with the registration.",
    "registered": "Press centres registered from the images (gelsim.calibrate.register_presses), as the pack's\n"
                  "annotation is off; the flat-point detector did not agree with them.",
}


def choose_centres(pack: DataPack, frames: str, mm_per_px: float, ball_diameter_mm: float, log=None) -> dict:
    """Where ``pack``'s presses are placed: ``frames`` ("even", "odd", "all") are the fitted ones (the
    only frames the choice looks at besides each frame's own detection), the others are scored.

    Returns ``{"headline": "annotated" | "detected"`` (the independent source the scored frames are
    placed by), ``"fit"``: the source the fitted frames are placed by (the headline's, or "registered"
    where the annotation is off and the detector disagrees), ``"centres_px"`` (N, 2) (the fitted frames
    at the fit source, the others at the headline's), ``"fit_idx"``, ``"registration"`` (the report of
    :func:`register_presses` on ``frames``) and ``"detection"``: ``available`` (every frame has a flat
    point), ``reason`` (why not, or why not used), ``agreement_px`` (RMS against the registration on
    ``frames`` after the common shift), ``common_shift_px`` (detected minus registered, mean) and
    ``centres_px`` (N, 2; NaN where none)}."""
    log = log or (lambda msg: None)
    idx = pack.select(frames)
    moved, registration = register_presses(pack, frames, mm_per_px, ball_diameter_mm, log)
    det = {"available": False, "reason": None, "agreement_px": None, "common_shift_px": None, "centres_px": None}
    try:
        found = detect_centres(pack, mm_per_px, ball_diameter_mm)
    except GelsimError as e:
        det["reason"] = str(e)
    else:
        det["centres_px"] = [[float(v) if np.isfinite(v) else None for v in c] for c in found["centres_px"]]
        det["points"] = [None if q is None else dataclasses.asdict(q) for q in found["points"]]
        if found["failures"]:
            i, why = next(iter(found["failures"].items()))
            det["reason"] = f"{len(found['failures'])} frames have no flat point (frame {i}: {why})"
        else:
            det["available"] = True
            diff = found["centres_px"][idx] - moved.centers_px[idx]
            shift = diff.mean(axis=0)
            det["common_shift_px"] = shift.tolist()
            det["agreement_px"] = float(np.sqrt(((diff - shift) ** 2).sum(axis=1).mean()))
    annotated = pack.centers_px.astype(np.float64)
    if not registration["applied"]:
        head, fit, cents = "annotated", "annotated", annotated.copy()
        if det["available"] and det["reason"] is None:
            det["reason"] = "not needed: the annotation holds"
    elif det["available"] and det["agreement_px"] <= DETECT_AGREE_PX:
        head, fit, cents = "detected", "detected", np.asarray(det["centres_px"], np.float64)
    else:
        if det["available"]:
            det["reason"] = (f"its centres are {det['agreement_px']:.1f} px RMS from the registration's on the fitted "
                             f"frames (more than {DETECT_AGREE_PX:g})")
        head, fit, cents = "annotated", "registered", annotated.copy()
        cents[idx] = moved.centers_px[idx]
    log(f"press centres: fitted frames {fit}, scored frames {head}"
        + (f" (flat points {det['agreement_px']:.2f} px RMS from the registration)" if head == "detected" else "")
        + (f"; flat-point detector not used: {det['reason']}" if head != "detected" and det["reason"] else ""))
    return {"headline": head, "fit": fit, "centres_px": cents, "fit_idx": idx,
            "registration": registration, "detection": det}


# --------------------------------------------------------------------------------------
# Whole calibration
# --------------------------------------------------------------------------------------
def fit_lights(table: dict, template, gain_dn: float | None = None, elevation_deg: float | None = None) -> tuple:
    """One light per colour channel, for backends that shade from lights (pyrender) and for the
    shadows' directions: each channel's azimuth from the slope of its table response near the
    flat normal (for small tilts the change is ~ nx lx + ny ly, so its gradient over (nx, ny)
    points to where the light comes from); colour the pure channel.

    ``elevation_deg`` (default: the template's; a lookup over normals does not pin it down)
    sets the elevation; with ``gain_dn`` (the profile's ``[shading] gain_dn``) each light's
    intensity is set so that Lambert shading changes by the table's DN per unit tilt near flat:
    ``|gradient| = gain_dn x intensity x cos(elevation)``."""
    nb = table["table"].shape[0]
    t0 = table["table"][..., 0:3]                       # constant spatial term, (ny, nx, colour)
    u = np.linspace(-1, 1, nb)
    ny, nx = np.meshgrid(u, u, indexing="ij")
    near = nx ** 2 + ny ** 2 <= 0.3 ** 2                # |n_xy| <= 0.3: the linear regime
    a = np.stack([nx[near], ny[near]], axis=1)
    elev = template.elevation_deg if elevation_deg is None else float(elevation_deg)
    lights = []
    names = ("red", "green", "blue")
    for c in range(3):
        g, *_ = np.linalg.lstsq(a, t0[..., c][near], rcond=None)
        az = math.degrees(math.atan2(g[1], g[0]))
        col = [0.0, 0.0, 0.0]
        col[c] = 1.0
        inten = 1.0 if gain_dn is None else float(np.hypot(*g)) / (gain_dn * math.cos(math.radians(elev)))
        lights.append(dataclasses.replace(template, name=names[c], color_rgb=tuple(col), azimuth_deg=round(az, 1),
                                          elevation_deg=round(elev, 1), intensity=round(inten, 3),
                                          falloff_per_mm=0.0, distance_mm=0.0))
    return tuple(lights)


def _with_gel(profile, **gel):
    return dataclasses.replace(profile, gel=dataclasses.replace(profile.gel, **gel))


def shadow_spec(dirs_deg, tan_e: float, soft_mm: float) -> dict | None:
    """The shadow terms' parameters (table-file keys) for lights at ``dirs_deg``; None for ``tan_e <= 0``."""
    if tan_e <= 0:
        return None
    k = len(dirs_deg)
    return {"shadow_dirs_deg": np.asarray(dirs_deg, np.float32), "shadow_tan": np.full(k, tan_e, np.float32),
            "shadow_sat_mm": np.float32(SHADOW_SAT_MM), "shadow_soft_mm": np.float32(soft_mm)}


def _cv_mse(profile, pack, idx, bg, ball_mm, shadow: dict | None, smooth: float = SMOOTH_WEIGHT) -> float:
    """Two-fold cross-validated MSE of the table model inside the scored disks of ``idx``."""
    return _cv_errors(profile, pack, idx, bg, ball_mm, shadow, smooth)[0]


def _cv_errors(profile, pack, idx, bg, ball_mm, shadow: dict | None,
               smooth: float = SMOOTH_WEIGHT) -> tuple[float, float]:
    """Two-fold cross-validated MSEs of the table model: inside the scored disks of ``idx``, and on
    the balls' flat tops (true slope below gelsim.realism.SMALL_SLOPE, where fabric texture lives)."""
    from .realism import SMALL_SLOPE

    samples = [_frame_samples(profile, pack, i, bg, ball_mm, shadow) for i in idx]
    # score only inside DISK_RADII (the metric's disk) although the fit reaches FIT_RADII
    for s, i in zip(samples, idx):
        c, r = pack.centers_px[i], pack.radii_px[i]
        w, h = profile.field_mm
        px = (s["xn"] * (w / 2.0) / profile.image.mm_per_px + (pack.shape[1] - 1) / 2.0)
        py = (s["yn"] * (h / 2.0) / profile.image.mm_per_px + (pack.shape[0] - 1) / 2.0)
        rho2 = (px - c[0]) ** 2 + (py - c[1]) ** 2
        s["scored"] = rho2 <= (DISK_RADII * r) ** 2
        # the ball's slope rho / sqrt(R^2 - rho^2) < SMALL_SLOPE inside the contact
        big_r = ball_mm / 2.0 / profile.image.mm_per_px
        s["flat"] = (rho2 <= r * r) & (rho2 < (SMALL_SLOPE ** 2 / (1.0 + SMALL_SLOPE ** 2)) * big_r * big_r)
    folds = (samples[0::2], samples[1::2])
    err, cnt, err_f, cnt_f = 0.0, 0, 0.0, 0
    for fit_on, test_on in ((folds[0], folds[1]), (folds[1], folds[0])):
        t = fit_table(fit_on, smooth=smooth)
        for s in test_on:
            e = predict(t, s) - s["target"]
            err += float((e[s["scored"]] ** 2).sum())
            cnt += int(s["scored"].sum()) * 3
            err_f += float((e[s["flat"]] ** 2).sum())
            cnt_f += int(s["flat"].sum()) * 3
    return err / max(cnt, 1), err_f / max(cnt_f, 1)


# A calibration needs this many ball presses to fit (the two cross-validation folds need two each)
# and, to report a held-out score, this many left over.
MIN_FIT_FRAMES = 4
MIN_HELDOUT_FRAMES = 2
# A press changes the image inside its contact by 17-38 DN RMS in the packs at hand, 6-27 times the RMS
# noise of a frame difference (sqrt(2) x read noise): R1.5 16x at least, Mini 27x, the synthetic test
# pack (2 DN noise) 6x. Below 3x a frame is taken to hold no press (a blank frame or a wrong annotation).
MIN_PRESS_SNR = 3.0
MIN_NOISE_DN = 0.5      # noise assumed at least (DN) for that check: 8-bit rounding alone is 0.29 DN RMS, and a
                        # noiseless synthetic pack still needs a press of a few DN
HELDOUT = {"even": "odd", "odd": "even", "all": None}


def check_pack(pack: DataPack, frames: str, mm_per_px: float, ball_diameter_mm: float) -> tuple[list, list]:
    """The fit and held-out frame indices of ``pack`` for ``frames``, after checking that the pack is
    large and consistent enough (see :func:`gelsim.realism.check_geometry`)."""
    check_geometry(pack, mm_per_px, ball_diameter_mm, Path(pack.source).name or "data pack")
    idx = pack.select(frames)
    if len(idx) < MIN_FIT_FRAMES:
        raise GelsimError(f"only {len(idx)} {frames} frames in the pack; calibration needs at least {MIN_FIT_FRAMES} "
                          f"ball presses to fit (and {MIN_HELDOUT_FRAMES} more to score), so give a larger pack")
    held = pack.select(HELDOUT[frames]) if HELDOUT[frames] else []
    if HELDOUT[frames] and len(held) < MIN_HELDOUT_FRAMES:
        raise GelsimError(f"only {len(held)} {HELDOUT[frames]} frames are left to score the fit; give a pack with at "
                          f"least {MIN_FIT_FRAMES + MIN_HELDOUT_FRAMES} presses, or --frames all (no held-out score)")
    # every press must show: its contact differs from f0 by clearly more than two frames' noise
    read, _ = fit_noise(pack, list(range(len(pack.imgs))))
    floor = MIN_PRESS_SNR * math.sqrt(2.0) * max(read, MIN_NOISE_DN)
    f0 = pack.f0.astype(np.float32)
    for i in idx + held:
        m = disk_mask(pack.centers_px[i], pack.radii_px[i], pack.shape)
        change = float(np.sqrt(((pack.imgs[i][m].astype(np.float32) - f0[m]) ** 2).mean()))
        if change < floor:
            raise GelsimError(f"frame {i} differs from f0 inside its annotated contact by only {change:.1f} DN RMS, "
                              f"within {MIN_PRESS_SNR:g}x the frames' noise ({read:.1f} DN): no press there; check "
                              f"that imgs hold the presses and touch_center/touch_radius mark them, or drop the frame")
    return idx, held


def centre_scores(profile, pack: DataPack, scored: str, choice: dict, ball_diameter_mm: float,
                  sources=CENTRE_SOURCES, keep: int | None = None) -> dict:
    """``profile`` scored on ``pack``'s ``scored`` frames (:func:`gelsim.realism.evaluate`) with the
    presses placed by each of ``sources``: ``"annotated"`` (the pack's centres), ``"detected"`` (each
    frame's flat point; GelsimError where a frame has none), ``"registered"`` (each scored press
    registered against the table of ``choice``'s fitted frames at their centres, starting from the
    headline's centre: the pose fitted, an upper bound; its dict holds ``"offsets_px"`` from there).
    ``choice`` is :func:`choose_centres`' result. Returns ``{source: evaluate's dict}``; ``keep`` (a
    frame index) adds the example frame to the headline's."""
    from .realism import evaluate

    idx = pack.select(scored)
    head = choice["headline"]
    det = choice["detection"]
    out = {}
    for src in sources:
        if src == "annotated":
            cents = pack.centers_px
        elif src == "detected":
            if not det["available"]:
                raise GelsimError(f"the flat-point detector found no centres here ({det['reason']}); use "
                                  f"--centres annotated or auto")
            cents = np.asarray(det["centres_px"], np.float64)
        elif src == "registered":
            start = dataclasses.replace(pack, centers_px=np.asarray(choice["centres_px"], np.float64))
            cents = register_heldout(start, choice["fit_idx"], start.centers_px, idx, profile.image.mm_per_px,
                                     ball_diameter_mm)
        else:
            raise GelsimError(f"unknown centres {src!r}; choose one of {', '.join(CENTRE_SOURCES)}")
        res = evaluate(profile, dataclasses.replace(pack, centers_px=np.asarray(cents, np.float64)), scored,
                       ball_diameter_mm=ball_diameter_mm, keep=keep if src == head else None)
        if src == "registered":
            res["offsets_px"] = (cents - np.asarray(choice["centres_px"], np.float64))[idx].tolist()
        out[src] = res
    return out


def headline_report(scores: dict, chosen: str) -> dict:
    """The ``chosen`` score of :func:`centre_scores`' ``scores`` with ``"centres"`` (its source) and the
    others beside it under ``"compare"`` (without example frames)."""
    rep = dict(scores[chosen], centres=chosen)
    rep["compare"] = {k: {kk: vv for kk, vv in v.items() if kk != "example"} for k, v in scores.items() if k != chosen}
    return rep


def heldout_score(profile_path: str | Path, pack: DataPack, frames: str, ball_diameter_mm: float,
                  choice: dict) -> dict | None:
    """The written profile scored on the frames it was not fitted on, the presses placed by ``choice``
    (:func:`choose_centres` on ``frames``): :func:`headline_report` of the headline's centres, with the
    annotated ones (where they are not the headline) and the registered ones (an upper bound) beside
    it; None for ``frames == "all"``."""
    from .sensor import load_profile

    other = HELDOUT[frames]
    if other is None:
        return None
    sources = [choice["headline"]] + [s for s in ("annotated", "registered") if s != choice["headline"]]
    scores = centre_scores(load_profile(profile_path), pack, other, choice, ball_diameter_mm, sources)
    return dict(headline_report(scores, choice["headline"]), frame_set=other)


def _carried_comments(base_profile, data: dict) -> dict[str, str]:
    """The base profile file's comments (its sources and reasons) for the values the calibrated profile
    carries over unchanged (by dotted key, :func:`gelsim.params.toml_comments`)."""
    if not base_profile.source or not Path(base_profile.source).is_file():
        return {}
    base = to_dict(base_profile)
    keep = {}
    for key, note in toml_comments(base_profile.source).items():
        section, _, name = key.rpartition(".")
        ours = data.get(section, {}) if section else data
        theirs = base.get(section) or {} if section else base
        if isinstance(ours, dict) and isinstance(theirs, dict) and name in ours and ours[name] == theirs.get(name):
            keep[key] = note
    return keep


def calibrate(pack: DataPack, base_profile, out_path: str | Path, *, frames: str = "even",
              mm_per_px: float = 0.0295, ball_diameter_mm: float = 4.0, grid: dict | None = None,
              name: str | None = None, description: str | None = None, note: str = "", log=None) -> dict:
    """Fit a profile to ``pack``'s selected frames and write it to ``out_path`` (TOML), with its
    background PNG and shading table ``.npz`` beside it (same stem).

    ``base_profile`` provides the sections that are not fitted (gel stiffness, markers,
    camera); ``note`` goes into the profile's header (e.g. the data's licence). Returns a report: the chosen parameters, the cross-validation MSE of every
    candidate, the noise fit and the file paths.
    """
    grid = {**DEFAULT_GRID, **(grid or {})}
    out_path = Path(out_path)
    if out_path.suffix != ".toml":
        raise GelsimError(f"--out {out_path} must end in .toml; the table and background go beside it")
    problem = not_a_folder(out_path.parent)
    if problem:
        raise GelsimError(f"{problem}; create the folder or choose another --out")
    idx, _ = check_pack(pack, frames, mm_per_px, ball_diameter_mm)
    h, w = pack.shape
    log = log or (lambda msg: None)
    placed = choose_centres(pack, frames, mm_per_px, ball_diameter_mm, log)
    pack = dataclasses.replace(pack, centers_px=placed["centres_px"])
    desc = description or (f"{name or out_path.stem}: {w}x{h} at {mm_per_px:g} mm/px, fitted by `gelsim calibrate` "
                           f"on {Path(pack.source).name or 'a data pack'}")
    prof = dataclasses.replace(
        base_profile, name=name or out_path.stem, description=desc,
        image=dataclasses.replace(base_profile.image, width_px=w, height_px=h, mm_per_px=mm_per_px),
        markers=dataclasses.replace(base_profile.markers, enabled=False),
        camera=dataclasses.replace(base_profile.camera, blur_sigma_px=0.0, vignetting=0.0))
    # the ball goes as deep as its radius; the pad must not bottom out before
    max_ind = max(prof.gel.max_indentation_mm, ball_diameter_mm / 2.0)
    prof = _with_gel(prof, max_indentation_mm=max_ind)
    small = fit_background(pack.f0)
    bg = upsample_background(small, (h, w))
    read, shot = fit_noise(pack, idx)
    log(f"noise: read {read:.2f} DN, shot gain {shot:.4f}")

    trials = []
    best = None
    for th, sm in itertools.product(grid["thickness_mm"], grid["membrane_smoothing_mm"]):
        p = _with_gel(prof, thickness_mm=float(th), membrane_smoothing_mm=float(sm))
        mse = _cv_mse(p, pack, idx, bg, ball_diameter_mm, None)
        trials.append({"thickness_mm": th, "membrane_smoothing_mm": sm, "shadow_tan": 0.0, "shadow_soft_mm": 0.0,
                       "cv_mse": mse})
        log(f"thickness {th} mm, smoothing {sm} mm: cv mse {mse:.2f}")
        if best is None or mse < best["cv_mse"]:
            best = trials[-1]
    p_best = _with_gel(prof, thickness_mm=float(best["thickness_mm"]),
                       membrane_smoothing_mm=float(best["membrane_smoothing_mm"]))
    # One shadow term per LED, cast away from it: the LEDs' azimuths come from the table fitted
    # without shadows (the shading's slope near flat points to each channel's LED).
    plain_samples = [_frame_samples(p_best, pack, i, bg, ball_diameter_mm, None) for i in idx]
    plain = fit_table(plain_samples)
    lights = fit_lights(plain, p_best.lights[0])
    led_az = [lt.azimuth_deg for lt in lights]
    log("LED azimuths (deg): " + ", ".join(f"{a:.1f}" for a in led_az))
    for tan_e, soft in itertools.product(grid["shadow_tan"], grid["shadow_soft_mm"]):
        if tan_e <= 0:
            continue
        mse = _cv_mse(p_best, pack, idx, bg, ball_diameter_mm, shadow_spec(led_az, float(tan_e), float(soft)))
        trials.append({"thickness_mm": best["thickness_mm"], "membrane_smoothing_mm": best["membrane_smoothing_mm"],
                       "shadow_tan": tan_e, "shadow_soft_mm": soft, "cv_mse": mse})
        log(f"shadow slope {tan_e}, penumbra {soft} mm: cv mse {mse:.2f}")
        if mse < best["cv_mse"]:
            best = trials[-1]
    shadow = shadow_spec(led_az, float(best["shadow_tan"]), float(best["shadow_soft_mm"]))
    # The smoothness trades the disk's error against the flat tops' (the response to small slopes,
    # issue #11): chosen by their sum, both DN^2 per pixel and channel.
    best = dict(best, smooth_weight=None, cv_flat_mse=None)
    choice = None
    for sw in grid["smooth_weight"]:
        mse, flat = _cv_errors(p_best, pack, idx, bg, ball_diameter_mm, shadow, smooth=float(sw))
        trials.append(dict(best, smooth_weight=sw, cv_mse=mse, cv_flat_mse=flat))
        log(f"table smoothness {sw}: cv mse {mse:.2f}, on the flat tops {flat:.2f}")
        if choice is None or mse + flat < choice["cv_mse"] + choice["cv_flat_mse"]:
            choice = trials[-1]
    best = choice
    smooth = float(best["smooth_weight"])
    # the LEDs' elevation is the shadows' grazing slope (the template's when there are no shadows),
    # and their intensity the table's response near flat, so pyrender shades as the table does
    elev = math.degrees(math.atan(float(best["shadow_tan"]))) if shadow is not None else None
    if smooth != SMOOTH_WEIGHT:
        plain = fit_table(plain_samples, smooth=smooth)
    lights = fit_lights(plain, p_best.lights[0], gain_dn=p_best.shading.gain_dn, elevation_deg=elev)
    samples = [_frame_samples(p_best, pack, i, bg, ball_diameter_mm, shadow) for i in idx]
    table = fit_table(samples, smooth=smooth)
    # the spatial and depth terms hold where the presses were: the renderer clamps positions into this box
    xs, ys = np.concatenate([s["xn"] for s in samples]), np.concatenate([s["yn"] for s in samples])
    table["position_box"] = np.array([xs.min(), xs.max(), ys.min(), ys.max()], np.float32)
    if shadow is not None:
        table.update(shadow)
    table.update(halo_spec())
    table["gain_dn"] = np.float32(p_best.shading.gain_dn)   # the DN scale the table was fitted at

    stem = out_path.stem
    bg_file = out_path.with_name(f"{stem}-background.png")
    lut_file = out_path.with_name(f"{stem}-shading.npz")
    write_png(bg_file, small)
    atomic_write_npz(lut_file, **table)
    fitted = dataclasses.replace(
        p_best, lights=lights,                  # the shadows' directions, for pyrender
        shading=dataclasses.replace(p_best.shading, model="lut", table=lut_file.name),
        background=dataclasses.replace(p_best.background, image=bg_file.name, image_resample="linear",
                                       rgb_dn=tuple(float(v) for v in pack.f0.reshape(-1, 3).mean(0))),
        noise=dataclasses.replace(p_best.noise, read_sigma_dn=round(read, 3), shot_gain=round(shot, 5)),
        source="")
    data = {k: v for k, v in to_dict(fitted).items() if v is not None}
    data.pop("source", None)
    header = (f"Fitted by `gelsim calibrate` on {len(idx)} {frames} frames of {Path(pack.source).name}\n"
              f"(mm_per_px {mm_per_px}, ball {ball_diameter_mm} mm). Fitted: background image, shading table,\n"
              f"gel thickness_mm and membrane_smoothing_mm, noise, shadows (one per LED: slope, penumbra, colour);\n"
              f"lights: azimuths from the table (for pyrender and the shadows).\n"
              + CENTRES_NOTE[placed["fit"]] + "\n"
              + 
              f"Other values come from the base profile, with their comments." + (f"\n{note}" if note else ""))
    atomic_write_text(out_path, dump_toml(data, header, _carried_comments(base_profile, data)))
    return {"profile": str(out_path), "background": str(bg_file), "table": str(lut_file),
            "frames": idx, "best": best, "trials": trials, "centres": placed,
            "noise": {"read_sigma_dn": read, "shot_gain": shot}}

