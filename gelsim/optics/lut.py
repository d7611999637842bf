"""Calibrated shading: a lookup table of the colour change over the membrane's normal.

``[shading] model = "lut"`` in a profile selects this shader for the fast backend;
``shading.table`` names an ``.npz`` beside the profile, written by
:func:`gelsim.calibrate.calibrate` from real ball presses. The colour change of a
pixel with respect to the flat gel is

    delta_c(n, x, y) = T_c0(nx, ny) + T_c1(nx, ny) * xn + T_c2(nx, ny) * yn

with ``(nx, ny)`` the in-plane components of the unit surface normal (bilinear
interpolation between the table's bins, which span -1..1), ``xn, yn`` the pixel's
position scaled to -1..1 across the field of view (so a table is independent of
the resolution), ``T(0, 0) = 0`` (a flat gel shows the background). The spatial
terms carry what a lookup over normals alone cannot: the LEDs' light falls off
across the gel, so the same slope is brighter near its LED. This is the idea of
Taxim's per-pixel polynomial table (Si and Yuan 2022) with a first-order
polynomial in position, fitted here by regularised least squares.

Optionally soft shadows, one per LED (``K`` in-plane directions ``phi_k``, the LEDs'
azimuths). Seen from the camera a press is a bump of the membrane into the gel, lit
through the gel at grazing angles, so each LED's shadow falls on the side away from
it, at most ``depth / tan(e_k)`` long. The *occlusion* ``o_k = max(0, max_{s>0}(h(p +
s u_k) - h(p) - s tan(e_k)))`` (mm, ``h`` the imprint height, ``u_k`` the direction
towards the light) is how far the surface towards the light rises above the grazing
ray; the darkness ``o_k / (o_k + o_sat)`` is blurred by a Gaussian penumbra of
``soft`` mm (extended LEDs, a scattering membrane) and the colour change adds
``sum_k S_k`` times it. The running max is computed on the image rotated so that
``u_k`` runs along columns, at half resolution, over the touched box only.

Two optional terms beyond the normal (both fitted with the table, both zero on a flat gel):

* the *depth term* ``d (D_0 + D_1 xn + D_2 yn)`` (DN per mm of imprint depth ``d``): the LEDs'
  light changes with the membrane's height in the gel, so a pressed region changes colour even
  where it is flat (the R1.5's ball tops: red +16 DN near its LED, -17 DN across the field);
* the *halo term*: real presses change the image out to about 2.5 contact radii, beyond the
  imprint model's spread. From the depth alone: ``b`` = the depth blurred by ``halo_sigma_mm``,
  ``b0`` by ``halo_base_mm`` (which removes fabric texture), the spill ``s = max(b - b0, 0)`` mm
  (positive around a bump, zero on its top and on a uniform press), its gate
  ``g = min(s / halo_gate_mm, 1)``, and the change ``g (H_x db/dx + H_y db/dy) + H_s s``.

Both are computed on a coarse grid (``COARSE_GRID_MM``) and interpolated back bilinearly. Without it the table learns the
  halo at near-flat normals (where the ring outside a contact outnumbers the ball's own flat
  top) as a step at flat, which over-states the response to small slopes (docs/realism.md).

Table file keys: ``table`` float32 ``(nb, nb, 9)`` (bin row = ny, column = nx;
channel ``3 * basis + colour``), and optionally ``shadow_dirs_deg`` ``(K,)``,
``shadow_tan`` ``(K,)``, ``shadow_rgb`` ``(K, 3)`` DN, ``shadow_sat_mm`` and ``shadow_soft_mm``
scalars (mm); ``depth_rgb`` ``(3, 3)`` (rows: the basis ``[1, xn, yn]``, DN per mm);
``halo_rgb`` ``(3, 3)`` (rows: ``db/dx``, ``db/dy`` in DN per unit slope, ``s`` in DN per mm)
with scalars ``halo_sigma_mm``, ``halo_base_mm``, ``halo_gate_mm``; ``position_box`` ``(4,)``: the
range ``[xn_min, xn_max, yn_min, yn_max]`` of the positions the table was fitted at (outside it the
spatial and depth terms take the value at the box's nearest edge: a linear term fitted where the
presses were is not extrapolated across the field); and ``gain_dn``: the profile's ``[shading]
gain_dn`` when fitted; a profile with another gain scales the table's DN by the ratio (as it scales
the lights of the other models).
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..errors import GelsimError
from .fast import grow_extent, imprint_extent
from .field import pixel_grid_mm
from .shader import Shader


def table_path(profile) -> Path:
    """The profile's LUT file: ``shading.table`` relative to the profile file or, if it is not
    there, a table shipped in ``assets/sensors/`` (so a copy of a shipped profile, e.g. ``vitac``
    written elsewhere, still finds the R1.5 table it borrows)."""
    from ..sensor import SENSORS_DIR

    spec = profile.shading.table
    if not spec:
        raise GelsimError(f"profile {profile.name}: shading.model is 'lut' but shading.table is empty; "
                          "name the .npz written by `gelsim calibrate`")
    p = Path(spec)
    if not p.is_absolute():
        p = (Path(profile.source).parent if profile.source else Path.cwd()) / p
        shipped = SENSORS_DIR / spec
        if not p.is_file() and shipped.is_file():
            return shipped
    return p


def load_table(path: str | Path) -> dict:
    """Read and check a LUT file (see the module docstring); arrays come back float32."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise GelsimError(f"shading table {path} cannot be read ({e}); rerun `gelsim calibrate`") from None
    t = data.get("table")
    if t is None or t.ndim != 3 or t.shape[0] != t.shape[1] or t.shape[2] != 9 or t.shape[0] < 3:
        raise GelsimError(f"shading table {path}: 'table' must be (nb, nb, 9) with nb >= 3; rerun `gelsim calibrate`")
    out = {"table": np.ascontiguousarray(t, np.float32)}
    if "gain_dn" in data:
        g = float(data["gain_dn"])
        if not (math.isfinite(g) and g > 0):
            raise GelsimError(f"shading table {path}: gain_dn {g} is not positive; rerun `gelsim calibrate`")
        out["gain_dn"] = g
    if "shadow_rgb" in data:
        k = len(data["shadow_dirs_deg"])
        if data["shadow_rgb"].shape != (k, 3) or data["shadow_tan"].shape != (k,):
            raise GelsimError(f"shading table {path}: shadow arrays disagree in length; rerun `gelsim calibrate`")
        for key in ("shadow_dirs_deg", "shadow_tan", "shadow_rgb"):
            out[key] = np.asarray(data[key], np.float32)
        out["shadow_sat_mm"] = float(data["shadow_sat_mm"])
        # tables written before soft shadows have hard-edged ones
        out["shadow_soft_mm"] = float(data.get("shadow_soft_mm", 0.0))
    if "position_box" in data:
        box = np.asarray(data["position_box"], np.float32)
        if box.shape != (4,) or not np.all(np.isfinite(box)) or box[0] > box[1] or box[2] > box[3]:
            raise GelsimError(f"shading table {path}: position_box must be [xn_min, xn_max, yn_min, yn_max]; "
                              "rerun `gelsim calibrate`")
        out["position_box"] = box
    if "depth_rgb" in data:
        if data["depth_rgb"].shape != (3, 3):
            raise GelsimError(f"shading table {path}: depth_rgb must be (3, 3); rerun `gelsim calibrate`")
        out["depth_rgb"] = np.asarray(data["depth_rgb"], np.float32)
    if "halo_rgb" in data:
        keys = ("halo_sigma_mm", "halo_base_mm", "halo_gate_mm")
        if data["halo_rgb"].shape != (3, 3) or any(k not in data for k in keys):
            raise GelsimError(f"shading table {path}: halo_rgb must be (3, 3) with {', '.join(keys)}; "
                              "rerun `gelsim calibrate`")
        vals = [float(data[k]) for k in keys]
        if not all(math.isfinite(v) and v > 0 for v in vals) or vals[0] <= vals[1]:
            raise GelsimError(f"shading table {path}: halo widths {vals} must be positive with "
                              "halo_sigma_mm > halo_base_mm; rerun `gelsim calibrate`")
        out["halo_rgb"] = np.asarray(data["halo_rgb"], np.float32)
        out.update(zip(keys, vals))
    return out


def normal_xy(depth: np.ndarray, mm_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """In-plane components ``(nx, ny)`` of the unit normal of the imprint surface: float32, same shape.

    The surface rises towards the camera by the depth, so its normal is
    ``(-gx, -gy, 1) / sqrt(1 + gx^2 + gy^2)`` with ``g`` the depth's slope (Sobel 3x3,
    which responds 8 per unit step: scaled to mm/mm)."""
    gx = cv2.Sobel(depth, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / (8.0 * mm_per_px), borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(depth, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / (8.0 * mm_per_px), borderType=cv2.BORDER_REPLICATE)
    inv = cv2.sqrt(1.0 + gx * gx + gy * gy)
    cv2.divide(-1.0, inv, inv)
    return gx * inv, gy * inv
# Shadows vary over several pixels (the ball's rim is blurred by the gel), so they are
# computed at half resolution: 4x fewer pixels, no visible change (checked in the tests).
SHADOW_SCALE = 0.5

# The renderer looks the table up in a mosaic of per-tile 3-colour tables, each with the
# spatial terms evaluated at its tile's centre: one 3-channel bilinear remap per frame instead
# of a 9-channel one plus a per-pixel weighting (3x less time). 30 x 24 tiles put every pixel
# within 1/60 of the field width and 1/48 of its height of its tile's centre, so the error is at
# most |T1| / 60 + |T2| / 48: under 1 DN at the steepest normals of the R1.5 table (mean 0.17 DN
# on a steep weave), far less at fabric slopes. More tiles cost cache misses on steep textures:
# at 60 x 45, a steep full-frame weave took 13.9 ms at 640x480 and 22.6 ms at 960x720; at
# 30 x 24, 9.5 and 18.2 ms (one core).
MOSAIC_TILES = (30, 24)
# Where the tiles' error bound (the table's largest |T1| and |T2|, DN per unit of field, times half a
# tile in field units: tile width / image width) exceeds 2 DN, the lookup is exact instead: the
# 9-channel table looked up per pixel and weighted by the pixel's own [1, xn, yn] (about 3x the
# lookup's time). The R1.5 table's bound is 1.6 DN (largest difference measured 1.1 DN: tiles); the
# GelSight Mini's, whose spatial terms are 5-8x larger, 10 DN (tiles showed as seams of up to 20 DN).
MOSAIC_MAX_ERR_DN = 2.0


def _bilinear_shift(src: np.ndarray, pad: int, shape: tuple[int, int], vx: float, vy: float,
                    minus: float) -> np.ndarray:
    """``src(p + v) - minus`` for the ``shape`` interior of ``src`` padded by ``pad`` on every side
    (bilinear; ``|v| <= pad - 1``): float32 ``shape``. Four shifted views mixed by cv2, no warp."""
    h, w = shape
    ix, iy = math.floor(vx), math.floor(vy)
    fx, fy = vx - ix, vy - iy
    y0, x0 = pad + iy, pad + ix

    def view(dy, dx):
        return src[y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w]

    a = cv2.addWeighted(view(0, 0), (1 - fx) * (1 - fy), view(0, 1), fx * (1 - fy), -minus)
    if fy > 0:
        b = cv2.addWeighted(view(1, 0), (1 - fx) * fy, view(1, 1), fx * fy, 0.0)
        cv2.add(a, b, a)
    return a


def occlusion_grid(hg: np.ndarray, dir_deg: float, rise: float, slopes: tuple[float, float] | None = None) -> np.ndarray:
    """Occlusion ``max(0, max_{s = 1, 2, ...} h(p + s u) - h(p) - s rise)`` on ``hg``'s own grid, mm.

    ``hg``: float32 ``(h, w)`` heights (mm, 0 outside); ``u``: unit vector at ``dir_deg`` (0 = +x,
    90 = +y), ``s`` in grid pixels; ``rise``: mm the grazing ray climbs per grid pixel. Only
    ``s <= L = (max h - min h) / rise`` can occlude, so the running max is taken over windows
    doubling up to ``L`` (``M_2w(p) = max(M_w(p), M_w(p + w u) - w rise)``, bilinear shifts): about
    ``log2 L + 1`` passes over the grid instead of a rotation there and back. ``slopes``: the
    largest ``|h(x + 1, y) - h(x, y)|`` and ``|h(x, y + 1) - h(x, y)|`` (mm, :func:`grid_slopes`), if
    known: the bilinear surface climbs at most ``|ux| sx + |uy| sy`` per grid pixel along ``u``."""
    h, w = hg.shape
    lo, hi, _, _ = cv2.minMaxLoc(hg)
    reach = (hi - min(lo, 0.0)) / rise if rise > 0 else math.hypot(h, w)
    reach = min(reach, math.hypot(h, w))
    ux, uy = math.cos(math.radians(dir_deg)), math.sin(math.radians(dir_deg))
    if reach < 1.0 or (slopes is not None and abs(ux) * slopes[0] + abs(uy) * slopes[1] < rise):
        # no occluder rises above a one-step ray, or the surface nowhere climbs as steeply as the
        # ray along u (so h(p + s u) - h(p) < s rise for every s): no shadow at all
        return np.zeros((h, w), np.float32)
    pad = int(math.ceil(reach)) + 2
    buf = cv2.copyMakeBorder(hg, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
    inner = buf[pad:pad + h, pad:pad + w]
    m = _bilinear_shift(buf, pad, (h, w), ux, uy, rise)      # window s = 1
    cover = 1
    while cover < reach:
        inner[...] = m                                       # the border stays 0: outside the box
        s = _bilinear_shift(buf, pad, (h, w), cover * ux, cover * uy, cover * rise)
        cv2.max(m, s, m)
        cover *= 2
    cv2.subtract(m, hg, m)
    cv2.max(m, 0.0, m)
    return m


def grid_slopes(hg: np.ndarray) -> tuple[float, float]:
    """Largest absolute height step between neighbours along x and along y inside ``hg`` (mm).

    The step down to the 0 outside the box need not count: outside is never higher than the
    (non-negative) heights inside, and a ray leaving the (convex) box never comes back."""
    out = []
    for a, b in ((hg[:, 1:], hg[:, :-1]), (hg[1:], hg[:-1])):
        out.append(float(cv2.absdiff(a, b).max()) if a.size else 0.0)
    return out[0], out[1]


def _grid_heights(depth: np.ndarray, factor: int) -> np.ndarray:
    """``depth`` averaged over ``factor`` x ``factor`` blocks (zero-padded to a multiple): grid pixel
    ``x'`` is centred on full-resolution ``factor (x' + 1/2) - 1/2``."""
    if factor == 1:
        return np.ascontiguousarray(depth, dtype=np.float32)
    h, w = depth.shape
    hs, ws = -(-h // factor), -(-w // factor)
    if (hs * factor, ws * factor) != (h, w):
        depth = cv2.copyMakeBorder(depth, 0, hs * factor - h, 0, ws * factor - w, cv2.BORDER_CONSTANT, value=0.0)
    return cv2.resize(depth, (ws, hs), interpolation=cv2.INTER_AREA)


def _grid_factor(scale: float) -> int:
    f = round(1.0 / scale)
    if f < 1 or abs(f * scale - 1.0) > 1e-6:
        raise GelsimError(f"shadow scale {scale} is not 1/n for an integer n; use 0.5 or 0.25")
    return f


def occlusion(depth: np.ndarray, mm_per_px: float, dir_deg: float, tan_e: float,
              scale: float = SHADOW_SCALE) -> np.ndarray:
    """Height of the surface towards the light above the grazing ray, mm: float32 like ``depth``.

    ``o(p) = max(0, max_{s > 0} h(p + s u) - h(p) - s tan_e)`` with ``u`` the unit
    in-plane vector at ``dir_deg`` (0 = +x, 90 = +y). Computed on a grid ``scale`` times the
    resolution (:func:`occlusion_grid`) and interpolated back bilinearly."""
    f = _grid_factor(scale)
    occ = occlusion_grid(_grid_heights(depth, f), dir_deg, tan_e * mm_per_px * f)
    h, w = depth.shape
    return _upsample(occ, f, (h, w))


def _upsample(small: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear from a grid of ``factor``-pixel blocks back to ``shape`` (edges replicated)."""
    if factor == 1:
        return small
    hs, ws = small.shape[:2]
    up = cv2.resize(small, (ws * factor, hs * factor), interpolation=cv2.INTER_LINEAR)
    h, w = shape
    return up if (hs * factor, ws * factor) == (h, w) else up[:h, :w]


def _occlusion_factors(depth: np.ndarray, mm_per_px: float, dirs_deg, tans, sat_mm: float,
                       factor: int) -> np.ndarray:
    """Unblurred shadow darkness ``o_k / (o_k + sat_mm)`` per direction on the grid: float32 ``(h', w', K)``;
    None when no direction casts any shadow."""
    hg = _grid_heights(depth, factor)
    slopes = grid_slopes(hg)
    sat = float(sat_mm)
    chans, lit = [], False
    for phi, tan_e in zip(dirs_deg, tans):
        rise = float(tan_e) * mm_per_px * factor
        if abs(math.cos(math.radians(phi))) * slopes[0] + abs(math.sin(math.radians(phi))) * slopes[1] < rise:
            chans.append(None)                  # no shadow this way (see occlusion_grid)
            continue
        occ = occlusion_grid(hg, float(phi), rise, slopes)
        den = cv2.add(occ, sat)
        chans.append(cv2.divide(occ, den))
        lit = True
    if not lit:
        return None
    chans = [np.zeros(hg.shape, np.float32) if c is None else c for c in chans]
    return chans[0][..., None] if len(chans) == 1 else cv2.merge(chans)


def shadow_factors(depth: np.ndarray, mm_per_px: float, dirs_deg, tans, sat_mm: float,
                   soft_mm: float = 0.0, scale: float = SHADOW_SCALE) -> tuple[np.ndarray, np.ndarray]:
    """Soft shadow darkness per light direction on a ``scale`` grid.

    For each direction ``k`` the hard occlusion ``o_k`` (:func:`occlusion`) becomes
    ``o_k / (o_k + sat_mm)`` (the shadow deepens with the height of the occluder above the
    grazing ray, and fades out towards its tip, where ``o_k`` falls to 0 over
    ``depth / tan_k``); then a Gaussian blur of ``soft_mm`` (sigma, mm) softens its edges:
    the LEDs are extended sources and the membrane scatters, so no real shadow edge is sharp.

    Returns ``(f, to_full)``: float32 ``(h', w', K)`` with ``h' = ceil(scale h)`` and the 2x3
    map from full-resolution pixels to that grid (for ``cv2.warpAffine(..., WARP_INVERSE_MAP)``).
    Pixel centres: full-resolution ``x`` is grid ``x' = scale (x + 1/2) - 1/2``.
    """
    factor = _grid_factor(scale)
    f = _occlusion_factors(depth, mm_per_px, dirs_deg, tans, sat_mm, factor)
    if f is None:
        h, w = depth.shape
        f = np.zeros((-(-h // factor), -(-w // factor), len(dirs_deg)), np.float32)
    hs, ws = f.shape[:2]
    sigma = soft_mm / mm_per_px * scale
    if sigma > 0.3:     # below a third of a grid pixel a blur changes nothing visible
        f = cv2.GaussianBlur(f, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT).reshape(hs, ws, -1)
    to_full = np.array([[scale, 0, 0.5 * scale - 0.5], [0, scale, 0.5 * scale - 0.5]])
    return f, to_full


# The depth and halo terms are smooth (the depth term follows the press's shape: a fabric's texture
# changes it by about 0.1 DN), so they are computed on a coarse grid of about 0.125 mm, which the
# halo's narrower blur (0.25 mm) spans at 2 grid pixels (a Gaussian of sigma >= 2 px is well
# sampled), and interpolated back bilinearly.
COARSE_GRID_MM = 0.125
# Where the two terms change no pixel by one 8-bit step (1 DN, about the R1.5's 0.92 DN read noise),
# they are skipped: a whole-pad fabric press 0.04-0.05 mm deep changes pixels by at most 0.4-0.8 DN
# (vitac, catalog fabrics 1, 12, 30, 45, 80 at 3-4 N; a broad change, not the texture), and bringing
# the terms back to full resolution would cost about 2 ms of a 960x720 frame's 10.
COARSE_SKIP_DN = 1.0


def coarse_factor(mm_per_px: float) -> int:
    """Full-resolution pixels per coarse-grid pixel (an integer >= 1)."""
    return max(1, int(COARSE_GRID_MM / mm_per_px))


def clamp_positions(xn: np.ndarray, yn: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """Field positions ``xn, yn`` (float32 arrays) clamped into a table's ``position_box`` (None: as given)."""
    if box is None:
        return xn, yn
    return (np.clip(xn, box[0], box[1]).astype(np.float32), np.clip(yn, box[2], box[3]).astype(np.float32))


def coarse_grid(depth: np.ndarray, mm_per_px: float, field_mm: tuple[float, float], depth_term: bool,
                halo: dict | None, box=None) -> tuple[np.ndarray, int]:
    """The depth and halo terms' features on the coarse grid: float32 ``(h', w', k)``, ``k`` = 3 for the
    depth term's ``[d, d xn, d yn]`` if ``depth_term`` and 3 for the halo's ``[g db/dx, g db/dy, s]``
    if ``halo`` (a dict of ``halo_sigma_mm``, ``halo_base_mm``, ``halo_gate_mm``); and the grid's
    factor (:func:`coarse_factor`). ``depth``: the whole frame's imprint, mm; the gel continues past
    the image (replicated borders), as for the camera blur; ``box``: the table's ``position_box``
    (:func:`clamp_positions`). See the module docstring."""
    f = coarse_factor(mm_per_px)
    hg = _grid_heights(depth, f)
    gmm = mm_per_px * f
    feats = []
    if depth_term:
        hs, ws = hg.shape
        # grid pixel x' is centred on full-resolution f (x' + 1/2) - 1/2
        h, w = depth.shape
        xn = ((f * (np.arange(ws) + 0.5) - 0.5 - (w - 1) / 2.0) * mm_per_px / (field_mm[0] / 2.0)).astype(np.float32)
        yn = ((f * (np.arange(hs) + 0.5) - 0.5 - (h - 1) / 2.0) * mm_per_px / (field_mm[1] / 2.0)).astype(np.float32)
        xn, yn = clamp_positions(xn, yn, box)
        feats += [hg, hg * xn[None, :], hg * yn[:, None]]
    if halo is not None:
        b = cv2.GaussianBlur(hg, (0, 0), halo["halo_sigma_mm"] / gmm, borderType=cv2.BORDER_REPLICATE)
        b0 = cv2.GaussianBlur(hg, (0, 0), halo["halo_base_mm"] / gmm, borderType=cv2.BORDER_REPLICATE)
        sp = cv2.subtract(b, b0)
        cv2.max(sp, 0.0, sp)
        gate = cv2.min(cv2.multiply(sp, 1.0 / halo["halo_gate_mm"]), 1.0)
        gx = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / (8.0 * gmm), borderType=cv2.BORDER_REPLICATE)
        gy = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / (8.0 * gmm), borderType=cv2.BORDER_REPLICATE)
        feats += [cv2.multiply(gx, gate), cv2.multiply(gy, gate), sp]
    return np.ascontiguousarray(np.stack(feats, axis=-1), dtype=np.float32), f


def coarse_features(depth: np.ndarray, mm_per_px: float, field_mm: tuple[float, float], depth_term: bool,
                    halo: dict | None) -> np.ndarray:
    """:func:`coarse_grid`'s features at full resolution, interpolated as the renderer does:
    float32 ``(H, W, k)`` (for the calibration's design matrix)."""
    g, f = coarse_grid(depth, mm_per_px, field_mm, depth_term, halo)
    k = g.shape[-1]
    chans = [_upsample(np.ascontiguousarray(g[..., i]), f, depth.shape) for i in range(k)]
    return np.stack(chans, axis=-1)


class LutShader(Shader):
    """Colour change of the membrane from a calibrated table (see the module docstring).

    ``profile``: sensor profile at the resolution being rendered (its ``shading.table``
    is read); ``maps`` is accepted for the shader interface and unused.
    """

    name = "lut"

    def __init__(self, profile, maps=None, table: dict | None = None):
        self.profile = profile
        t = table if table is not None else load_table(table_path(profile))
        # [shading] gain_dn is the photometric scale of both backends: the table's DN were fitted
        # at the profile's gain_dn of the time (stored with it), so another gain scales them
        gain = profile.shading.gain_dn / t["gain_dn"] if "gain_dn" in t else 1.0
        # tiles or the exact lookup (MOSAIC_MAX_ERR_DN): decided on the table as fitted, so that a unit's
        # gains (gelsim.units) or another gain_dn never switch between them
        self._spatial_dn = (float(np.abs(t["table"][..., 3:6]).max()), float(np.abs(t["table"][..., 6:9]).max()))
        t = adjust_channels(t, profile.shading.channel_gain, profile.shading.channel_rotation_deg)
        self.table = t["table"] * np.float32(gain)
        self.nb = self.table.shape[0]
        # the exact lookup (shade_table): one 9-channel remap, channels colour-major (3 colour +
        # basis), so that per pixel and colour the three basis values are adjacent and one multiply
        # by [1, xn, yn] and one 3-to-1 transform give the colour change
        nb = self.nb
        self._t9 = np.ascontiguousarray(self.table.reshape(nb, nb, 3, 3).transpose(0, 1, 3, 2).reshape(nb, nb, 9))
        self.shadow = dict(t, shadow_rgb=t["shadow_rgb"] * np.float32(gain)) if "shadow_rgb" in t else None
        if self.shadow is not None:
            self._shadow_mix = np.ascontiguousarray(self.shadow["shadow_rgb"].T)
        # the depth and halo terms: their colours, stacked in coarse_grid's feature order
        self.depth_term = "depth_rgb" in t
        self.halo = {k: t[k] for k in ("halo_sigma_mm", "halo_base_mm", "halo_gate_mm")} if "halo_rgb" in t else None
        mix = ([t["depth_rgb"]] if self.depth_term else []) + ([t["halo_rgb"]] if self.halo is not None else [])
        self._coarse_mix = np.concatenate(mix).astype(np.float32) * np.float32(gain) if mix else None
        self.box = t.get("position_box")
        self._build_mosaic()
        # 1 px for the 3x3 gradient stencil, 1 more so the box's border is flat for sure
        self.margin_px = 2

    def _build_mosaic(self) -> None:
        """Per-tile 3-colour tables (see MOSAIC_TILES) and the per-pixel map offsets into them."""
        profile, nb = self.profile, self.nb
        h, w = profile.shape
        tw, th = -(-w // min(MOSAIC_TILES[0], w)), -(-h // min(MOSAIC_TILES[1], h))
        ntx, nty = -(-w // tw), -(-h // th)
        mm = profile.image.mm_per_px
        fw, fh = profile.field_mm
        # tile centres in pixels (the last tile may be narrower), then in -1..1 of the field
        cx = np.minimum(np.arange(ntx) * tw + (tw - 1) / 2.0, (np.arange(ntx) * tw + w - 1) / 2.0)
        cy = np.minimum(np.arange(nty) * th + (th - 1) / 2.0, (np.arange(nty) * th + h - 1) / 2.0)
        xn = ((cx - (w - 1) / 2.0) * mm / (fw / 2.0)).astype(np.float32)
        yn = ((cy - (h - 1) / 2.0) * mm / (fh / 2.0)).astype(np.float32)
        xn, yn = clamp_positions(xn, yn, self.box)
        t = self.table.reshape(nb, nb, 3, 3)                          # (ny bin, nx bin, basis, colour)
        half = (nb - 1) / 2.0
        self._bufs: dict[str, np.ndarray] = {}
        # the tiles' error bound, DN: a pixel is at most half a tile (in field units) from its tile's centre
        bound = self._spatial_dn[0] * tw / w + self._spatial_dn[1] * th / h
        self.exact = bound > MOSAIC_MAX_ERR_DN
        if self.exact:
            px, py = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
            self._wts = basis_weights(*clamp_positions(((px - (w - 1) / 2.0) / (w / 2.0)).astype(np.float32),
                                                       ((py - (h - 1) / 2.0) / (h / 2.0)).astype(np.float32),
                                                       self.box))
            self._offx = np.full((h, w), half, np.float32)
            self._offy = np.full((h, w), half, np.float32)
            return
        tiles = (t[None, None, :, :, 0] + xn[None, :, None, None, None] * t[None, None, :, :, 1]
                 + yn[:, None, None, None, None] * t[None, None, :, :, 2])   # (ty, tx, ny, nx, 3)
        # one replicated bin after each tile's last, so a bilinear tap never reads the next tile
        stride = nb + 1
        tiles = np.concatenate([tiles, tiles[:, :, -1:]], axis=2)
        tiles = np.concatenate([tiles, tiles[:, :, :, -1:]], axis=3)
        mosaic = tiles.transpose(0, 2, 1, 3, 4).reshape(nty * stride, ntx * stride, 3)
        # kept with a fourth, zero channel: OpenCV's remap interpolates 1- and 4-channel float images with
        # vector instructions and 3-channel ones without (a 960-pixel band: 240 us as 3 channels, 90 as 4,
        # plus 17 to drop the fourth; same values). _mosaic is the 3-colour view (the torch backend's).
        self._mosaic4 = np.zeros(mosaic.shape[:2] + (4,), np.float32)
        self._mosaic4[..., :3] = mosaic
        self._mosaic = self._mosaic4[..., :3]
        self._offx = np.ascontiguousarray(np.broadcast_to(
            ((np.arange(w) // tw) * stride + half).astype(np.float32)[None, :], (h, w)))
        self._offy = np.ascontiguousarray(np.broadcast_to(
            ((np.arange(h) // th) * stride + half).astype(np.float32)[:, None], (h, w)))

    def _boxes(self, depth_mm: np.ndarray, margin_px: int, blur_px: float = 0.0):
        """The table's box and the (larger) shadows' box, or None for a flat gel."""
        margin = self.margin_px + margin_px
        extent = imprint_extent(depth_mm)
        roi = grow_extent(extent, margin, depth_mm.shape)
        if roi is None or self.shadow is None:
            return roi, roi
        s = self.shadow
        mm = self.profile.image.mm_per_px
        _, dmax, _, _ = cv2.minMaxLoc(depth_mm[roi])
        # a shadow ends depth / tan(elevation) beyond its occluder; its blur reaches 3 sigma further
        soft_px = math.hypot(s["shadow_soft_mm"] / mm, blur_px)
        reach = int(math.ceil(dmax / max(float(np.min(s["shadow_tan"])), 1e-3) / mm + 3.0 * soft_px))
        return roi, grow_extent(extent, margin + reach, depth_mm.shape)

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, delta)``: slices of the shaded box and float32 ``(h, w, 3)`` DN change there; None if flat.

        The table is looked up only over the imprint's box; the shadows reach further,
        up to the deepest point's height over the flattest grazing slope."""
        roi, big = self._boxes(depth_mm, margin_px)
        if roi is None:
            return None
        lut = self._shade_mosaic(depth_mm, roi).copy()
        halo = self._coarse(depth_mm)
        if self.shadow is None and halo is None:
            return roi, lut
        parts = [(roi, lut)] + ([(big, self.shade_shadows(depth_mm[big]))] if self.shadow is not None else [])
        if halo is not None:
            parts.append(halo)
            big = _union(big, halo[0])
        out = np.zeros((big[0].stop - big[0].start, big[1].stop - big[1].start, 3), np.float32)
        for box, change in parts:
            out[box[0].start - big[0].start:box[0].stop - big[0].start,
                box[1].start - big[1].start:box[1].stop - big[1].start] += change
        return big, out

    def parts(self, depth_mm: np.ndarray, margin_px: int, blur_sigma_px: float):
        """The renderer's form of :meth:`delta`: a list of ``(roi, change, blurred)``, or None if flat.

        The table's change is sharp (the renderer applies the camera blur to it); the shadows
        come already blurred by the camera too, folded into their own penumbra blur on the coarse
        grid (``sqrt(soft^2 + camera^2)``: the blurs of a Gaussian compose). The returned arrays
        are work buffers reused by the next call."""
        roi, big = self._boxes(depth_mm, margin_px, blur_sigma_px)
        if roi is None:
            return None
        out = [(roi, self._shade_mosaic(depth_mm, roi), False)]
        if self.shadow is not None:
            sh = self._shadows(depth_mm[big], blur_sigma_px)
            if sh is not None:
                out.append((big, sh, True))
        halo = self._coarse(depth_mm)
        if halo is not None:
            out.append((halo[0], halo[1], True))
        return out

    def compose(self, frame: np.ndarray, bg: np.ndarray, depth_mm: np.ndarray, margin_px: int,
                blur_sigma_px: float, blur, finish=None) -> bool:
        """The renderer's fused pass: ``frame = bg + blur(table change) + shadows`` (float32 ``(H, W, 3)``
        DN, written in place); False (``frame`` untouched) for a flat gel.

        ``blur(img, sigma, dst)`` is the camera blur. The table's change is computed, blurred and
        added in bands of rows, each with the blur's radius of extra rows on both sides, so that its
        work arrays stay in the cache: the frame's passes are memory-bound at 960x720. The shadows
        (blurred by the camera already, see :meth:`parts`) and the depth and halo terms are computed
        first, over their boxes, and added to each band's rows right after the table's change: the
        same sums, in the same order, as adding them to the whole frame afterwards. The rows above
        and below the table's box, and the columns beside it, are the background copied band by
        band (with those terms added). ``finish(rows, y0, y1)`` (optional) is called on each band of
        frame rows ``y0:y1`` once its values are final, in row order, while the band is in the cache:
        the renderer darkens its markers and adds the noise there (see :meth:`Shader.compose`). With
        ``finish`` and ``frame`` None the bands are composed in one band-sized work buffer: the
        frame's 8 MB float32 copy is never written to memory."""
        roi, big = self._boxes(depth_mm, margin_px, blur_sigma_px)
        if roi is None:
            return False
        # (box, grid, factor) of the changes added after the table's: each band interpolates its own rows
        parts = []
        if self.shadow is not None:
            sh = self._shadow_grid(depth_mm[big], blur_sigma_px)
            if sh is not None:
                parts.append((big, *sh))
        halo = self._coarse_crop(depth_mm)
        if halo is not None:
            parts.append(halo)
        band = self.BAND_ROWS
        width = bg.shape[1]

        def rows(a: int, b: int) -> np.ndarray:
            """Where the frame's rows a:b are composed: the frame's own, or the band work buffer."""
            return frame[a:b] if frame is not None else self._buffer("band_frame", (band, width, 3))[:b - a]

        def outside(r0: int, r1: int) -> None:
            """Frame rows r0:r1 outside the box's rows: the background plus the parts, band by band."""
            for a in range(r0, r1, band):
                b = min(r1, a + band)
                dst = rows(a, b)
                np.copyto(dst, bg[a:b])
                for part in parts:
                    _add_rows(dst, *part, a, b, a)
                if finish is not None:
                    finish(dst, a, b)

        top, bottom = roi[0].start, roi[0].stop
        c0, c1 = roi[1].start, roi[1].stop
        outside(0, top)
        d = depth_mm[roi]
        h, w = d.shape
        offx, offy = self._offx[roi], self._offy[roi]
        bgr = bg[roi]
        r = int(math.ceil(3.0 * blur_sigma_px)) if blur_sigma_px > 0 else 0
        for y0 in range(0, h, band):
            y1 = min(h, y0 + band)
            l0, l1 = max(0, y0 - r), min(h, y1 + r)          # table rows the blur reads
            a, b = max(0, l0 - 1), min(h, l1 + 1)            # depth rows the gradient reads
            lut = self._buffer("band_lut", (l1 - l0, w, 3))
            self._shade_band(d[a:b], l0 - a, l1 - l0, offx[l0:l1], offy[l0:l1], lut, self._band_wts(roi, l0, l1))
            sm = blur(lut, blur_sigma_px, self._buffer("band_blur", lut.shape))
            dst = rows(top + y0, top + y1)
            for cols in (slice(0, c0), slice(c1, width)):               # the background beside the box
                if cols.start < cols.stop:
                    np.copyto(dst[:, cols], bg[top + y0:top + y1, cols])
            cv2.add(bgr[y0:y1], sm[y0 - l0:y1 - l0], dst[:, c0:c1])
            for part in parts:                               # while the band's rows are in the cache
                _add_rows(dst, *part, top + y0, top + y1, top + y0)
            if finish is not None:
                finish(dst, top + y0, top + y1)
        outside(bottom, bg.shape[0])
        return True

    def shade(self, d: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """Colour change float32 ``(h, w, 3)`` DN of imprint ``d`` (mm) at positions ``xn, yn`` (-1..1, ``(h, w)``)."""
        out = self.shade_table(d, xn, yn)
        if self.shadow is not None:
            out += self.shade_shadows(d)
        halo = self._coarse(d)
        if halo is not None:
            out[halo[0]] += halo[1]
        return out

    def _coarse(self, depth_mm: np.ndarray):
        """The depth and halo terms over the box where they are not zero: ``(roi, change)`` with float32
        ``(h, w, 3)`` DN (a fresh array), or None (no such terms, or none reaching COARSE_SKIP_DN).
        Computed over the whole frame on the coarse grid (cheap), then interpolated back only over
        the box of grid pixels where they are not zero, grown by one zero pixel, so that the crop's
        bilinear values equal those of the whole grid. Added unblurred: they are smooth at the
        camera blur's scale."""
        part = self._coarse_crop(depth_mm)
        if part is None:
            return None
        (ys, xs), crop, f = part
        rows, cols = crop.shape[:2]
        up = crop if f == 1 else cv2.resize(crop, (cols * f, rows * f), interpolation=cv2.INTER_LINEAR)
        return (ys, xs), np.ascontiguousarray(up[:ys.stop - ys.start, :xs.stop - xs.start])

    def _coarse_crop(self, depth_mm: np.ndarray):
        """:meth:`_coarse` before its interpolation: ``(roi, crop, f)``, the change on the coarse grid's
        crop (float32 ``(h', w', 3)`` DN) whose bilinear upsampling by ``f`` gives the change over
        ``roi`` (cut to its size); None as for :meth:`_coarse`."""
        if self._coarse_mix is None:
            return None
        g, f = coarse_grid(depth_mm, self.profile.image.mm_per_px, self.profile.field_mm, self.depth_term,
                           self.halo, self.box)
        hs, ws, k = g.shape
        small = (g.reshape(-1, k) @ self._coarse_mix).reshape(hs, ws, 3)
        # |change| with a grid row's colours side by side: numpy's max along an axis of 3 took 0.75 ms
        # here (a loop per pixel), along rows of 3 ws values and down columns 0.04 ms
        mag = np.abs(small).reshape(hs, ws * 3)
        row_max = mag.max(axis=1)
        if row_max.max() < COARSE_SKIP_DN:
            return None
        rows = np.flatnonzero(row_max > 0)
        cols = np.flatnonzero(mag.max(axis=0).reshape(ws, 3).max(axis=1) > 0)
        r0, r1 = max(0, rows[0] - 1), min(hs, rows[-1] + 2)
        c0, c1 = max(0, cols[0] - 1), min(ws, cols[-1] + 2)
        crop = np.ascontiguousarray(small[r0:r1, c0:c1])
        h, w = depth_mm.shape
        y0, x0 = r0 * f, c0 * f
        y1, x1 = min(h, r1 * f), min(w, c1 * f)
        return (slice(y0, y1), slice(x0, x1)), crop, f

    def shade_shadows(self, d: np.ndarray) -> np.ndarray:
        """The shadow terms alone: float32 ``(h, w, 3)`` DN (computed at half resolution)."""
        out = self._shadows(d, 0.0)
        return np.zeros(d.shape + (3,), np.float32) if out is None else out.copy()

    def _shadows(self, d: np.ndarray, extra_blur_px: float) -> np.ndarray | None:
        """Shadow colour change of ``d`` at full resolution, blurred by its penumbra and by
        ``extra_blur_px`` (sigma, full-resolution px): float32 ``(h, w, 3)`` work buffer; None if none."""
        g = self._shadow_grid(d, extra_blur_px)
        return None if g is None else _upsample(g[0], g[1], d.shape)

    def _shadow_grid(self, d: np.ndarray, extra_blur_px: float):
        """:meth:`_shadows` before its interpolation: ``(small, factor)``, the change on the grid
        (float32 ``(h', w', 3)`` DN) and the grid's factor (:func:`_upsample`); None if none."""
        s = self.shadow
        mm = self.profile.image.mm_per_px
        factor = _grid_factor(SHADOW_SCALE)
        f = _occlusion_factors(d, mm, s["shadow_dirs_deg"], s["shadow_tan"], s["shadow_sat_mm"], factor)
        if f is None or not f.any():
            return None
        hs, ws, k = f.shape
        if k <= 4:      # cv2.transform mixes up to 4 channels per pixel, several times faster than a matmul
            small = cv2.transform(f, self._shadow_mix).reshape(hs, ws, 3)
        else:
            small = (f.reshape(-1, k) @ s["shadow_rgb"]).reshape(hs, ws, 3)
        sigma = math.hypot(s["shadow_soft_mm"] / mm, extra_blur_px) / factor
        if sigma > 0.3:     # below a third of a grid pixel a blur changes nothing visible
            small = cv2.GaussianBlur(small, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        return small, factor

    # rows per band of the table lookup: its work arrays (slopes, maps) stay in the cache. Each band
    # recomputes the blur's and the gradient's extra rows (6 at a 0.6 px blur); at 960x720, 80-96 rows
    # took 0.15 ms per frame less than 48 and than 120-240 (replay of dataset frames, 2-core machine)
    BAND_ROWS = 96

    def _shade_mosaic(self, depth_mm: np.ndarray, roi) -> np.ndarray:
        """The table's colour change over ``roi`` from the tile mosaic: float32 ``(h, w, 3)`` DN work buffer.

        Computed in bands of rows, each with one row of depth above and below for the gradient
        stencil (the box's own edges replicate, as one pass over the box would)."""
        d = depth_mm[roi]
        h, w = d.shape
        out = self._buffer("lut", (h, w, 3))
        offx, offy = self._offx[roi], self._offy[roi]
        band = self.BAND_ROWS
        for y0 in range(0, h, band):
            y1 = min(h, y0 + band)
            a, b = max(0, y0 - 1), min(h, y1 + 1)
            self._shade_band(d[a:b], y0 - a, y1 - y0, offx[y0:y1], offy[y0:y1], out[y0:y1],
                             self._band_wts(roi, y0, y1))
        return out

    def _band_wts(self, roi, r0: int, r1: int):
        """The exact lookup's basis weights for rows ``r0:r1`` of box ``roi`` (None for the mosaic)."""
        if not self.exact:
            return None
        y0, x0 = roi[0].start or 0, roi[1].start or 0
        x1 = roi[1].stop if roi[1].stop is not None else self.profile.shape[1]
        return self._wts[y0 + r0:y0 + r1, 3 * x0:3 * x1]

    def _shade_band(self, d, top, rows, offx, offy, out, wts=None) -> None:
        """Rows ``top:top + rows`` of ``d`` (which carries the gradient stencil's extra rows) into ``out``;
        ``wts``: the exact lookup's basis weights for those rows (:meth:`_band_wts`), None for the mosaic."""
        shape = d.shape
        mm = self.profile.image.mm_per_px
        gx, gy, k = (self._buffer(n, shape) for n in ("gx", "gy", "k"))
        # Sobel 3x3 responds 8 per unit step per pixel: scaled to a slope in mm/mm
        cv2.Sobel(d, cv2.CV_32F, 1, 0, gx, ksize=3, scale=1.0 / (8.0 * mm), borderType=cv2.BORDER_REPLICATE)
        cv2.Sobel(d, cv2.CV_32F, 0, 1, gy, ksize=3, scale=1.0 / (8.0 * mm), borderType=cv2.BORDER_REPLICATE)
        gx, gy, k = gx[top:top + rows], gy[top:top + rows], k[top:top + rows]
        # map = offset + half - half * g / sqrt(1 + |g|^2): the bin of the normal's (nx, ny) in
        # the pixel's tile; cv2 calls into reused buffers (numpy temporaries were 3x slower)
        cv2.multiply(gx, gx, k)
        cv2.accumulateSquare(gy, k)
        cv2.add(k, 1.0, k)
        cv2.pow(k, -0.5, k)                 # one pass; sqrt then divide took 8x longer
        half = (self.nb - 1) / 2.0
        cv2.multiply(gx, k, gx, scale=-half)
        cv2.add(gx, offx, gx)
        cv2.multiply(gy, k, gy, scale=-half)
        cv2.add(gy, offy, gy)
        if wts is None:
            r4 = self._buffer("r4", (rows, shape[1], 4))
            cv2.remap(self._mosaic4, gx, gy, cv2.INTER_LINEAR, r4, borderMode=cv2.BORDER_REPLICATE)
            cv2.cvtColor(r4, cv2.COLOR_RGBA2RGB, out)       # drop the zero fourth channel
            return
        r9 = self._buffer("r9", (rows, shape[1], 9))
        cv2.remap(self._t9, gx, gy, cv2.INTER_LINEAR, r9, borderMode=cv2.BORDER_REPLICATE)
        r = r9.reshape(rows, 3 * shape[1], 3)
        cv2.multiply(r, wts, r)
        np.copyto(out, cv2.transform(r, _SUM3).reshape(rows, shape[1], 3))

    def shade_table(self, d: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """The table's exact colour change: float32 ``(h, w, 3)`` DN (``xn, yn`` as in :meth:`shade`),
        without the depth term."""
        return self._shade_table(d, basis_weights(*clamp_positions(xn, yn, self.box)))

    def _shade_table(self, d: np.ndarray, wts: np.ndarray) -> np.ndarray:
        """The table's colour change with :func:`basis_weights` ``wts`` ``(h, 3 w, 3)``."""
        mm = self.profile.image.mm_per_px
        nx, ny = normal_xy(d, mm)
        half = float((self.nb - 1) / 2.0)
        cv2.multiply(nx, half, nx)
        cv2.add(nx, half, nx)
        cv2.multiply(ny, half, ny)
        cv2.add(ny, half, ny)
        m1, m2 = cv2.convertMaps(nx, ny, cv2.CV_16SC2)   # fixed-point maps
        h, w = d.shape
        r = cv2.remap(self._t9, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        r = r.reshape(h, 3 * w, 3)                       # per (pixel, colour): the three basis values
        cv2.multiply(r, wts, r)
        return cv2.transform(r, _SUM3).reshape(h, w, 3)


def _rotate_pair(a: np.ndarray, b: np.ndarray, deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The 2-vector ``(a, b)`` (element-wise arrays) rotated by ``deg`` (counter-clockwise in x, y)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return c * a - s * b, s * a + c * b


def adjust_channels(t: dict, channel_gain, rotation_deg) -> dict:
    """A table file's arrays for a unit whose LEDs differ from the calibrated one's: colour channel
    ``c`` scaled by ``channel_gain[c]`` and its LED turned by ``rotation_deg[c]`` about the gel normal.

    Turning an LED by ``delta`` turns its response over the normal: ``T'_c(n) = T_c(R(-delta) n)``
    (the table resampled bilinearly; ``T(0) = 0`` stays), and with it the direction of its
    spatial, depth and halo terms and of the shadow it casts (the shadow whose colour darkens
    channel ``c`` most). Returns ``t`` itself when nothing changes."""
    gains = np.asarray(channel_gain, np.float32)
    rots = [float(r) for r in rotation_deg]
    if np.all(gains == 1.0) and not any(rots):
        return t
    t = dict(t)
    table = t["table"].copy()
    nb = table.shape[0]
    half = (nb - 1) / 2.0
    jj, ii = np.meshgrid(np.arange(nb, dtype=np.float32), np.arange(nb, dtype=np.float32))
    nx, ny = (jj - half) / half, (ii - half) / half
    for c in range(3):
        if rots[c]:
            sx, sy = _rotate_pair(nx, ny, -rots[c])
            mx, my = (half + half * sx).astype(np.float32), (half + half * sy).astype(np.float32)
            for b in range(3):
                table[..., 3 * b + c] = cv2.remap(np.ascontiguousarray(table[..., 3 * b + c]), mx, my,
                                                  cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            table[..., 3 + c], table[..., 6 + c] = _rotate_pair(table[..., 3 + c], table[..., 6 + c], rots[c])
        table[..., c::3] *= gains[c]
    t["table"] = table
    if "shadow_rgb" in t:
        own = np.argmin(t["shadow_rgb"], axis=1)                # the channel each shadow darkens most
        t["shadow_dirs_deg"] = (t["shadow_dirs_deg"] + np.asarray([rots[c] for c in own], np.float32)).astype(np.float32)
        t["shadow_rgb"] = t["shadow_rgb"] * gains[None, :]
    for key, pair in (("depth_rgb", (1, 2)), ("halo_rgb", (0, 1))):
        if key in t:
            m = t[key].copy()
            for c in range(3):
                m[pair[0], c], m[pair[1], c] = _rotate_pair(m[pair[0], c], m[pair[1], c], rots[c])
            t[key] = m * gains[None, :]
    return t


def _add_rows(frame: np.ndarray, box, grid: np.ndarray, factor: int, y0: int, y1: int, origin: int = 0) -> None:
    """Add the rows ``y0:y1`` (of the frame) of a change over ``box`` of ``frame``, given on a grid: float32
    ``grid`` ``(h', w', 3)`` upsampled ``factor`` times bilinearly (cv2.resize) and cut to the box.
    ``origin``: the frame row that ``frame``'s first row is (a band of the frame: 0 for the whole)."""
    a, b = max(y0, box[0].start), min(y1, box[0].stop)
    if a < b:
        region = frame[a - origin:b - origin, box[1]]
        top = box[0].start
        cv2.add(region, _upsample_rows(grid, factor, a - top, b - top, region.shape[1]), region)


def _upsample_rows(grid: np.ndarray, factor: int, a: int, b: int, width: int) -> np.ndarray:
    """Rows ``a:b`` and columns ``:width`` of ``cv2.resize(grid, (factor w', factor h'), INTER_LINEAR)``
    (``grid`` float32 ``(h', w', C)``), computed from the grid rows they read only: output row ``y``
    reads grid rows ``floor((y + 1/2) / factor - 1/2)`` and the next, and OpenCV gives a pixel of an
    integer upsampling the same value from a crop of the grid as from the whole (its weights depend on
    the pixel's position modulo the factor: tested), so a band of a frame needs no upsampled copy of
    the whole grid (an 8 MB array written and read back at 960x720)."""
    if factor == 1:
        return grid[a:b, :width]
    ga, gb = max(0, a // factor - 1), min(grid.shape[0], (b - 1) // factor + 2)
    up = cv2.resize(grid[ga:gb], (grid.shape[1] * factor, (gb - ga) * factor), interpolation=cv2.INTER_LINEAR)
    return up[a - ga * factor:b - ga * factor, :width]


def _union(a, b):
    """The smallest box (row and column slices) holding boxes ``a`` and ``b``."""
    return (slice(min(a[0].start, b[0].start), max(a[0].stop, b[0].stop)),
            slice(min(a[1].start, b[1].start), max(a[1].stop, b[1].stop)))


_SUM3 = np.ones((1, 3), np.float32)     # cv2.transform matrix: the sum of three channels


def basis_weights(xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    """Per pixel and colour the table's basis ``[1, xn, yn]``: float32 ``(h, 3 w, 3)`` from ``(h, w)`` positions."""
    h, w = xn.shape
    b = np.empty((h, w, 3, 3), np.float32)
    b[..., 0] = 1.0
    b[..., 1] = np.asarray(xn, np.float32)[..., None]
    b[..., 2] = np.asarray(yn, np.float32)[..., None]
    return b.reshape(h, 3 * w, 3)
