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
``sum_k S_k`` times it, on a grid as coarse as the penumbra allows (:mod:`gelsim.optics.ops.shadows`).

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

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import GelsimError
from .ops.box import MARGIN_PX, grow_extent, imprint_extent
from .ops.coarse import CoarseSpec, CoarseTerm, clamp_positions
from .ops.filters import slopes
from .ops.resample import upsample, upsample_rows
from .ops.shadows import ShadowSpec, ShadowTerm, shadow_grid
from .ops.table import TableLookup, basis_weights, lookup_rows
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
    ``(-gx, -gy, 1) / sqrt(1 + gx^2 + gy^2)`` with ``g`` the depth's slope
    (:func:`~gelsim.optics.ops.filters.slopes`)."""
    gx, gy = slopes(depth, mm_per_px)
    inv = cv2.sqrt(1.0 + gx * gx + gy * gy)
    cv2.divide(-1.0, inv, inv)
    return gx * inv, gy * inv


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


def table_lookup(profile, table: np.ndarray, box, spatial_dn: tuple[float, float]) -> TableLookup:
    """The lookup of ``table`` (float32 ``(nb, nb, 9)`` DN) at ``profile``'s resolution: the mosaic of per-tile
    tables (:data:`MOSAIC_TILES`) or, where the tiles' error bound from the table's largest spatial terms
    ``spatial_dn`` (DN per unit of field, as fitted) exceeds :data:`MOSAIC_MAX_ERR_DN`, the exact form;
    positions clamped into ``box`` (the table's ``position_box``, or None)."""
    nb = table.shape[0]
    h, w = profile.shape
    tw, th = -(-w // min(MOSAIC_TILES[0], w)), -(-h // min(MOSAIC_TILES[1], h))
    ntx, nty = -(-w // tw), -(-h // th)
    half = (nb - 1) / 2.0
    # the exact form's channels colour-major (3 colour + basis), so that per pixel and colour the three
    # basis values are adjacent and one multiply by [1, xn, yn] and one 3-to-1 transform give the change
    t9 = np.ascontiguousarray(table.reshape(nb, nb, 3, 3).transpose(0, 1, 3, 2).reshape(nb, nb, 9))
    # the tiles' error bound, DN: a pixel is at most half a tile (in field units) from its tile's centre
    if spatial_dn[0] * tw / w + spatial_dn[1] * th / h > MOSAIC_MAX_ERR_DN:
        xn, yn = clamp_positions(((np.arange(w, dtype=np.float32) - (w - 1) / 2.0) / (w / 2.0)).astype(np.float32),
                                 ((np.arange(h, dtype=np.float32) - (h - 1) / 2.0) / (h / 2.0)).astype(np.float32),
                                 box)
        wts = basis_weights(np.broadcast_to(xn[None, :], (h, w)), np.broadcast_to(yn[:, None], (h, w)))
        full = np.full((h, w), half, np.float32)
        return TableLookup(half, True, full, full.copy(), t9=t9, xn=xn, yn=yn, wts=wts)
    mm = profile.image.mm_per_px
    fw, fh = profile.field_mm
    # tile centres in pixels (the last tile may be narrower), then in -1..1 of the field
    cx = np.minimum(np.arange(ntx) * tw + (tw - 1) / 2.0, (np.arange(ntx) * tw + w - 1) / 2.0)
    cy = np.minimum(np.arange(nty) * th + (th - 1) / 2.0, (np.arange(nty) * th + h - 1) / 2.0)
    xn = ((cx - (w - 1) / 2.0) * mm / (fw / 2.0)).astype(np.float32)
    yn = ((cy - (h - 1) / 2.0) * mm / (fh / 2.0)).astype(np.float32)
    xn, yn = clamp_positions(xn, yn, box)
    t = table.reshape(nb, nb, 3, 3)                               # (ny bin, nx bin, basis, colour)
    tiles = (t[None, None, :, :, 0] + xn[None, :, None, None, None] * t[None, None, :, :, 1]
             + yn[:, None, None, None, None] * t[None, None, :, :, 2])   # (ty, tx, ny, nx, 3)
    # one replicated bin after each tile's last, so a bilinear tap never reads the next tile
    stride = nb + 1
    tiles = np.concatenate([tiles, tiles[:, :, -1:]], axis=2)
    tiles = np.concatenate([tiles, tiles[:, :, :, -1:]], axis=3)
    mosaic = tiles.transpose(0, 2, 1, 3, 4).reshape(nty * stride, ntx * stride, 3)
    mosaic4 = np.zeros(mosaic.shape[:2] + (4,), np.float32)
    mosaic4[..., :3] = mosaic
    offx = np.ascontiguousarray(np.broadcast_to(
        ((np.arange(w) // tw) * stride + half).astype(np.float32)[None, :], (h, w)))
    offy = np.ascontiguousarray(np.broadcast_to(
        ((np.arange(h) // th) * stride + half).astype(np.float32)[:, None], (h, w)))
    return TableLookup(half, False, offx, offy, mosaic4=mosaic4, t9=t9)


@dataclass(frozen=True)
class TableModel:
    """A calibrated table ready for every backend at a profile's resolution (:func:`table_model`):
    ``table`` float32 ``(nb, nb, 9)`` DN at the profile's gain (channel ``3 * basis + colour``, the unit's
    channel gains and rotations applied); ``lookup`` its lookup at the normal; ``shadows`` and ``coarse``
    its optional terms' parameters; ``box``: the table's ``position_box`` (or None); ``terms``: those terms in the order their changes are added to the
    camera-blurred lookup's (the shadows, then the depth and halo terms), each with a numpy ``part`` and
    a torch ``part_torch`` (:class:`~gelsim.optics.ops.shadows.ShadowTerm`,
    :class:`~gelsim.optics.ops.coarse.CoarseTerm`)."""
    table: np.ndarray
    lookup: TableLookup
    shadows: ShadowSpec | None
    coarse: CoarseSpec | None
    box: np.ndarray | None
    terms: tuple


def table_model(profile, table: dict | None = None) -> TableModel:
    """The :class:`TableModel` of ``profile`` (at the resolution being shaded): its ``shading.table`` file, or
    ``table`` (:func:`load_table`'s dict)."""
    t = table if table is not None else load_table(table_path(profile))
    # [shading] gain_dn is the photometric scale of both backends: the table's DN were fitted
    # at the profile's gain_dn of the time (stored with it), so another gain scales them
    gain = np.float32(profile.shading.gain_dn / t["gain_dn"] if "gain_dn" in t else 1.0)
    # tiles or the exact lookup (MOSAIC_MAX_ERR_DN): decided on the table as fitted, so that a unit's
    # gains (gelsim.units) or another gain_dn never switch between them
    spatial_dn = (float(np.abs(t["table"][..., 3:6]).max()), float(np.abs(t["table"][..., 6:9]).max()))
    # the shadows' grid likewise (ShadowSpec.grid_factor): from their colours as fitted
    shadow_dn = float(np.abs(t["shadow_rgb"]).max()) if "shadow_rgb" in t else 0.0
    t = adjust_channels(t, profile.shading.channel_gain, profile.shading.channel_rotation_deg)
    tab = t["table"] * gain
    box = t.get("position_box")
    shadows = None
    if "shadow_rgb" in t:
        shadows = ShadowSpec(t["shadow_dirs_deg"], t["shadow_tan"], np.ascontiguousarray((t["shadow_rgb"] * gain).T),
                             float(t["shadow_sat_mm"]), float(t["shadow_soft_mm"]), shadow_dn)
    # the depth and halo terms: their colours, stacked in coarse_grid's feature order
    halo = {k: t[k] for k in ("halo_sigma_mm", "halo_base_mm", "halo_gate_mm")} if "halo_rgb" in t else None
    mix = ([t["depth_rgb"]] if "depth_rgb" in t else []) + ([t["halo_rgb"]] if halo is not None else [])
    coarse = CoarseSpec("depth_rgb" in t, halo, np.concatenate(mix).astype(np.float32) * gain, box) if mix else None
    mm = profile.image.mm_per_px
    terms = (([ShadowTerm(shadows, mm)] if shadows is not None else [])
             + ([CoarseTerm(coarse, mm, profile.field_mm, profile.shape)] if coarse is not None else []))
    return TableModel(tab, table_lookup(profile, tab, box, spatial_dn), shadows, coarse, box, tuple(terms))


def _box_shape(box) -> tuple[int, int]:
    return box[0].stop - box[0].start, box[1].stop - box[1].start


class LutShader(Shader):
    """Colour change of the membrane from a calibrated table (see the module docstring).

    ``profile``: sensor profile at the resolution being rendered (its ``shading.table``
    is read, or ``table``, :func:`load_table`'s dict); ``maps`` is accepted for the shader
    interface and unused. Its inputs, public: ``model`` (:class:`TableModel`), and from it
    ``table``, ``nb`` (bins), ``lookup``, ``exact`` (the exact lookup rather than tiles),
    ``shadow`` (:class:`~gelsim.optics.ops.shadows.ShadowSpec` or None) and ``terms``.
    """

    name = "lut"
    # rows per band of the table lookup: its work arrays (slopes, maps) stay in the cache. Each band
    # recomputes the blur's and the gradient's extra rows (6 at a 0.6 px blur); at 960x720, 80-96 rows
    # took 0.15 ms per frame less than 48 and than 120-240 (replay of dataset frames, 2-core machine)
    BAND_ROWS = 96

    @classmethod
    def reads_light_maps(cls, profile) -> bool:
        return False

    def __init__(self, profile, maps=None, table: dict | None = None):
        self.profile = profile
        self.model = table_model(profile, table)
        self.table = self.model.table
        self.nb = self.table.shape[0]
        self.lookup = self.model.lookup
        self.exact = self.lookup.exact
        self.shadow = self.model.shadows
        self.terms = self.model.terms
        self.margin_px = MARGIN_PX
        self._bufs: dict[str, np.ndarray] = {}

    def term_parts(self, depth_mm: np.ndarray, margin_px: int, blur_sigma_px: float, extent=None):
        """``(roi, parts)``: the table's box (None for a flat gel) and the terms' ``(box, grid, factor)``
        (:attr:`terms`' ``part``, in their order; ``grid`` None where a term adds nothing in its box).
        ``extent``: :func:`imprint_extent` of ``depth_mm`` where the caller has it (None: found here)."""
        margin = self.margin_px + margin_px
        if extent is None:
            extent = imprint_extent(depth_mm)
        roi = grow_extent(extent, margin, depth_mm.shape)
        if roi is None:
            return None, []
        return roi, [p for t in self.terms if (p := t.part(depth_mm, extent, margin, blur_sigma_px)) is not None]

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, delta)``: slices of the shaded box and float32 ``(h, w, 3)`` DN change there; None if flat.

        The table is looked up only over the imprint's box; the shadows reach further,
        up to the deepest point's height over the flattest grazing slope."""
        roi, parts = self.term_parts(depth_mm, margin_px, 0.0)
        if roi is None:
            return None
        lut = self._shade_mosaic(depth_mm, roi).copy()
        if not parts:
            return roi, lut
        changes = [(roi, lut)] + [(box, np.zeros(_box_shape(box) + (3,), np.float32) if grid is None
                                   else upsample(grid, f, _box_shape(box))) for box, grid, f in parts]
        big = (slice(min(b[0].start for b, _ in changes), max(b[0].stop for b, _ in changes)),
               slice(min(b[1].start for b, _ in changes), max(b[1].stop for b, _ in changes)))
        out = np.zeros(_box_shape(big) + (3,), np.float32)
        for box, change in changes:
            out[box[0].start - big[0].start:box[0].stop - big[0].start,
                box[1].start - big[1].start:box[1].stop - big[1].start] += change
        return big, out

    def parts(self, depth_mm: np.ndarray, margin_px: int, blur_sigma_px: float):
        """The renderer's form of :meth:`delta`: a list of ``(roi, change, blurred)``, or None if flat.

        The table's change is sharp (the renderer applies the camera blur to it); the shadows
        come already blurred by the camera too, folded into their own penumbra blur on the coarse
        grid (``sqrt(soft^2 + camera^2)``: the blurs of a Gaussian compose), and the depth and halo
        terms are smooth at its scale. The returned arrays are work buffers reused by the next call."""
        roi, parts = self.term_parts(depth_mm, margin_px, blur_sigma_px)
        if roi is None:
            return None
        return [(roi, self._shade_mosaic(depth_mm, roi), False)] + \
            [(box, upsample(grid, f, _box_shape(box)), True) for box, grid, f in parts if grid is not None]

    def compose(self, frame: np.ndarray, bg: np.ndarray, depth_mm: np.ndarray, margin_px: int,
                blur_sigma_px: float, blur, finish=None, extent=None) -> bool:
        """The renderer's fused pass: ``frame = bg + blur(table change) + terms`` (float32 ``(H, W, 3)``
        DN, written in place); False (``frame`` untouched) for a flat gel.

        ``blur(img, sigma, dst)`` is the camera blur. The table's change is computed, blurred and
        added in bands of rows, each with the blur's radius of extra rows on both sides, so that its
        work arrays stay in the cache: the frame's passes are memory-bound at 960x720. The terms (the
        shadows, blurred by the camera already, see :meth:`parts`, and the depth and halo terms) are
        computed first, over their boxes on their grids, and each band's rows of them are interpolated
        and added right after the table's change: the same sums, in the same order, as adding them to
        the whole frame afterwards. The rows above and below the table's box, and the columns beside
        it, are the background copied band by band (with the terms added). ``finish(rows, y0, y1)``
        (optional) is called on each band of frame rows ``y0:y1`` once its values are final, in row
        order, while the band is in the cache: the renderer applies its stages there (markers, noise,
        quantisation; see :meth:`Shader.compose`). With ``finish`` and ``frame`` None the bands are
        composed in one band-sized work buffer: the frame's 8 MB float32 copy is never written to memory."""
        roi, parts = self.term_parts(depth_mm, margin_px, blur_sigma_px, extent)
        if roi is None:
            return False
        # (box, grid, factor) of the changes added after the table's: each band interpolates its own rows
        parts = [p for p in parts if p[1] is not None]
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
        offx, offy = self.lookup.offx[roi], self.lookup.offy[roi]
        bgr = bg[roi]
        mm = self.profile.image.mm_per_px
        r = int(math.ceil(3.0 * blur_sigma_px)) if blur_sigma_px > 0 else 0
        for y0 in range(0, h, band):
            y1 = min(h, y0 + band)
            l0, l1 = max(0, y0 - r), min(h, y1 + r)          # table rows the blur reads
            a, b = max(0, l0 - 1), min(h, l1 + 1)            # depth rows the gradient reads
            lut = self._buffer("band_lut", (l1 - l0, w, 3))
            lookup_rows(d[a:b], l0 - a, l1 - l0, offx[l0:l1], offy[l0:l1], lut, self.lookup, mm, self._buffer,
                        self.lookup.band_weights(roi, l0, l1))
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

    def shade_shadows(self, d: np.ndarray) -> np.ndarray:
        """The shadow terms alone: float32 ``(h, w, 3)`` DN (computed on their grid, :meth:`ShadowSpec.grid_factor`)."""
        g = shadow_grid(d, self.shadow, self.profile.image.mm_per_px, 0.0)
        return np.zeros(d.shape + (3,), np.float32) if g is None else upsample(g[0], g[1], d.shape).copy()

    def _shade_mosaic(self, depth_mm: np.ndarray, roi) -> np.ndarray:
        """The table's colour change over ``roi``: float32 ``(h, w, 3)`` DN work buffer.

        Computed in bands of rows, each with one row of depth above and below for the gradient
        stencil (the box's own edges replicate, as one pass over the box would)."""
        d = depth_mm[roi]
        h, w = d.shape
        out = self._buffer("lut", (h, w, 3))
        offx, offy = self.lookup.offx[roi], self.lookup.offy[roi]
        mm = self.profile.image.mm_per_px
        band = self.BAND_ROWS
        for y0 in range(0, h, band):
            y1 = min(h, y0 + band)
            a, b = max(0, y0 - 1), min(h, y1 + 1)
            lookup_rows(d[a:b], y0 - a, y1 - y0, offx[y0:y1], offy[y0:y1], out[y0:y1], self.lookup, mm,
                        self._buffer, self.lookup.band_weights(roi, y0, y1))
        return out

    def shade_table(self, d: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """The table's exact colour change: float32 ``(h, w, 3)`` DN of imprint ``d`` (mm) at positions
        ``xn, yn`` (-1..1, ``(h, w)``), without the depth term."""
        wts = basis_weights(*clamp_positions(xn, yn, self.model.box))
        mm = self.profile.image.mm_per_px
        nx, ny = normal_xy(d, mm)
        half = float((self.nb - 1) / 2.0)
        cv2.multiply(nx, half, nx)
        cv2.add(nx, half, nx)
        cv2.multiply(ny, half, ny)
        cv2.add(ny, half, ny)
        m1, m2 = cv2.convertMaps(nx, ny, cv2.CV_16SC2)   # fixed-point maps
        h, w = d.shape
        r = cv2.remap(self.lookup.t9, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        r = r.reshape(h, 3 * w, 3)                       # per (pixel, colour): the three basis values
        cv2.multiply(r, wts, r)
        return cv2.transform(r, np.ones((1, 3), np.float32)).reshape(h, w, 3)


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
        cv2.add(region, upsample_rows(grid, factor, a - top, b - top, region.shape[1]), region)
