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

Table file keys: ``table`` float32 ``(nb, nb, 9)`` (bin row = ny, column = nx;
channel ``3 * basis + colour``), and optionally ``shadow_dirs_deg`` ``(K,)``,
``shadow_tan`` ``(K,)``, ``shadow_rgb`` ``(K, 3)`` DN, ``shadow_sat_mm`` and ``shadow_soft_mm``
scalars (mm), and ``gain_dn``: the profile's ``[shading] gain_dn`` when fitted; a profile with
another gain scales the table's DN by the ratio (as it scales the lights of the other models).
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..errors import GelsimError
from .fast import imprint_roi
from .field import pixel_grid_mm


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


def _to_rotated(shape: tuple[int, int], dir_deg: float, scale: float) -> tuple[np.ndarray, int]:
    """Affine map (2x3) from full-resolution pixels to the rotated, scaled square of side ``n``
    in which direction ``dir_deg`` points along -y (up the columns)."""
    h, w = shape
    n = int(math.ceil(math.hypot(h, w) * scale)) + 2
    c = ((w - 1) / 2.0, (h - 1) / 2.0)
    # cv2's angle turns counter-clockwise on screen: dir_deg + 90 takes the direction to -y
    m = cv2.getRotationMatrix2D(c, dir_deg + 90.0, scale)
    m[:, 2] += ((n - 1) / 2.0 - c[0], (n - 1) / 2.0 - c[1])
    return m, n


def _occlusion_rotated(depth: np.ndarray, m: np.ndarray, n: int, step_mm: float) -> np.ndarray:
    """Occlusion in the rotated square: running max up the columns of ``h(s) - s tan_e``."""
    rot = cv2.warpAffine(depth, m, (n, n), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    # g = h(s) - s tan_e with s growing up the rows (towards the light)
    g = rot - (np.arange(n, dtype=np.float32)[::-1] * np.float32(step_mm))[:, None]
    run = np.maximum.accumulate(g, axis=0)        # run[i] = max of g over rows <= i
    occ = np.zeros_like(g)
    np.subtract(run[:-1], g[1:], out=occ[1:])     # strictly ahead of each row
    np.maximum(occ, 0.0, out=occ)
    return occ


def occlusion(depth: np.ndarray, mm_per_px: float, dir_deg: float, tan_e: float,
              scale: float = SHADOW_SCALE) -> np.ndarray:
    """Height of the surface towards the light above the grazing ray, mm: float32 like ``depth``.

    ``o(p) = max(0, max_{s > 0} h(p + s u) - h(p) - s tan_e)`` with ``u`` the unit
    in-plane vector at ``dir_deg`` (0 = +x, 90 = +y). Computed at ``scale`` times the
    resolution as a running max down the columns of the image rotated so that ``u``
    points along -y (one bilinear warp in, one out)."""
    m, n = _to_rotated(depth.shape, dir_deg, scale)
    occ = _occlusion_rotated(depth, m, n, tan_e * mm_per_px / scale)
    h, w = depth.shape
    return cv2.warpAffine(occ, cv2.invertAffineTransform(m), (w, h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT)


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
    h, w = depth.shape
    hs, ws = max(1, math.ceil(h * scale)), max(1, math.ceil(w * scale))
    # grid pixel (x', y') sits at full-resolution ((x' + 1/2) / scale - 1/2, ...)
    from_grid = np.array([[1 / scale, 0, 0.5 / scale - 0.5], [0, 1 / scale, 0.5 / scale - 0.5]])
    f = np.empty((hs, ws, len(dirs_deg)), np.float32)
    sat = np.float32(sat_mm)
    for k, (phi, tan_e) in enumerate(zip(dirs_deg, tans)):
        m, n = _to_rotated(depth.shape, float(phi), scale)
        occ = _occlusion_rotated(depth, m, n, float(tan_e) * mm_per_px / scale)
        # the saturation is applied in the rotated square, before the warp back (same result, one pass)
        occ /= occ + sat
        # grid -> rotated square: m applied after from_grid
        g2r = m[:, :2] @ from_grid[:, :2]
        g2r = np.hstack([g2r, (m[:, :2] @ from_grid[:, 2] + m[:, 2])[:, None]])
        f[..., k] = cv2.warpAffine(occ, g2r, (ws, hs), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_CONSTANT)
    sigma = soft_mm / mm_per_px * scale
    if sigma > 0.3:     # below a third of a grid pixel a blur changes nothing visible
        f = cv2.GaussianBlur(f, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT).reshape(hs, ws, -1)
    to_full = np.array([[scale, 0, 0.5 * scale - 0.5], [0, scale, 0.5 * scale - 0.5]])
    return f, to_full


class LutShader:
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
        self.table = t["table"] * np.float32(gain)
        self.nb = self.table.shape[0]
        # One 9-channel remap per frame (about half the time of three 3-channel ones), with the
        # channels reordered colour-major (3 colour + basis), so that per pixel and colour the
        # three basis values are adjacent and one multiply by [1, xn, yn] and one 3-to-1
        # transform give the colour change.
        nb = self.nb
        self._t9 = np.ascontiguousarray(self.table.reshape(nb, nb, 3, 3).transpose(0, 1, 3, 2).reshape(nb, nb, 9))
        self.shadow = dict(t, shadow_rgb=t["shadow_rgb"] * np.float32(gain)) if "shadow_rgb" in t else None
        x, y = pixel_grid_mm(profile)
        fw, fh = profile.field_mm
        h, w = profile.shape
        xn = np.broadcast_to(x / (fw / 2.0), (h, w))
        yn = np.broadcast_to(y / (fh / 2.0), (h, w))
        self._w = basis_weights(xn, yn)
        # 1 px for the 3x3 gradient stencil, 1 more so the box's border is flat for sure
        self.margin_px = 2

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, delta)``: slices of the shaded box and float32 ``(h, w, 3)`` DN change there; None if flat.

        The table is looked up only over the imprint's box; the shadows reach further,
        up to the deepest point's height over the flattest grazing slope."""
        margin = self.margin_px + margin_px
        roi = imprint_roi(depth_mm, margin)
        if roi is None:
            return None
        mm = self.profile.image.mm_per_px
        wroi = (roi[0], slice(3 * roi[1].start, 3 * roi[1].stop))
        lut = self._shade_table(depth_mm[roi], self._w[wroi])
        if self.shadow is None:
            return roi, lut
        s = self.shadow
        # a shadow ends depth / tan(elevation) beyond its occluder; its blur reaches 3 sigma further
        reach = int(math.ceil((float(depth_mm[roi].max()) / max(float(np.min(s["shadow_tan"])), 1e-3)
                               + 3.0 * s["shadow_soft_mm"]) / mm))
        big = imprint_roi(depth_mm, margin + reach)
        d = depth_mm[big]
        out = self.shade_shadows(d)
        out[roi[0].start - big[0].start:roi[0].stop - big[0].start,
            roi[1].start - big[1].start:roi[1].stop - big[1].start] += lut
        return big, out

    def shade(self, d: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """Colour change float32 ``(h, w, 3)`` DN of imprint ``d`` (mm) at positions ``xn, yn`` (-1..1, ``(h, w)``)."""
        out = self.shade_table(d, xn, yn)
        if self.shadow is not None:
            out += self.shade_shadows(d)
        return out

    def shade_shadows(self, d: np.ndarray) -> np.ndarray:
        """The shadow terms alone: float32 ``(h, w, 3)`` DN (computed at half resolution)."""
        s = self.shadow
        mm = self.profile.image.mm_per_px
        f, to_full = shadow_factors(d, mm, s["shadow_dirs_deg"], s["shadow_tan"], s["shadow_sat_mm"],
                                    s["shadow_soft_mm"])
        hs, ws, k = f.shape
        if k <= 4:      # cv2.transform mixes up to 4 channels per pixel, several times faster than a matmul
            small = cv2.transform(f, np.ascontiguousarray(s["shadow_rgb"].T)).reshape(hs, ws, 3)
        else:
            small = (f.reshape(-1, k) @ s["shadow_rgb"]).reshape(hs, ws, 3)
        h, w = d.shape
        return cv2.warpAffine(small, to_full, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)

    def shade_table(self, d: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """The table's colour change alone: float32 ``(h, w, 3)`` DN (``xn, yn`` as in :meth:`shade`)."""
        return self._shade_table(d, basis_weights(xn, yn))

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


_SUM3 = np.ones((1, 3), np.float32)     # cv2.transform matrix: the sum of three channels


def basis_weights(xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    """Per pixel and colour the table's basis ``[1, xn, yn]``: float32 ``(h, 3 w, 3)`` from ``(h, w)`` positions."""
    h, w = xn.shape
    b = np.empty((h, w, 3, 3), np.float32)
    b[..., 0] = 1.0
    b[..., 1] = np.asarray(xn, np.float32)[..., None]
    b[..., 2] = np.asarray(yn, np.float32)[..., None]
    return b.reshape(h, 3 * w, 3)
