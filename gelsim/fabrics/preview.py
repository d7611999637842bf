"""Preview images of fabrics: hillshade with a scale bar and label, and the contact sheet."""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..errors import GelsimError
from .catalog import Catalog, Fabric
from .render import heightfield

# Hillshade light: from the top-left (the cartographic convention, so relief reads as raised)
# at 45 degrees elevation.
_LIGHT_AZIMUTH_DEG = 315.0
_LIGHT_ELEVATION_DEG = 45.0
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def hillshade(height_mm: np.ndarray, mm_per_px: float, exaggeration: float | None = None) -> np.ndarray:
    """uint8 (H, W) shaded relief of a height map in mm.

    ``exaggeration`` scales the slopes; by default it is chosen so that the 95th percentile
    slope shades at about 60 degrees, whatever the fabric's relief (a fine silk and a
    corduroy both read clearly).
    """
    gy, gx = np.gradient(height_mm.astype(np.float32), mm_per_px)
    if exaggeration is None:
        slope = np.hypot(gx, gy)
        p95 = float(np.percentile(slope, 95)) if slope.size else 0.0
        exaggeration = math.tan(math.radians(60.0)) / p95 if p95 > 0 else 1.0
    gx *= exaggeration
    gy *= exaggeration
    az = math.radians(_LIGHT_AZIMUTH_DEG)
    el = math.radians(_LIGHT_ELEVATION_DEG)
    # Light direction in image coordinates (x right, y down, z up out of the fabric).
    lx, ly, lz = math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    shade = (-gx * lx - gy * ly + lz) / norm
    return np.clip(shade * 255.0, 0, 255).astype(np.uint8)


def _scale_bar_mm(width_mm: float) -> float:
    """A round bar length (1, 2 or 5 x 10^k mm) of about a fifth of the image width."""
    target = width_mm / 5
    k = math.floor(math.log10(target))
    for m in (5, 2, 1):
        if m * 10 ** k <= target:
            return m * 10 ** k
    return 10 ** k


def _draw_scale_bar(img: np.ndarray, mm_per_px: float, scale: float = 0.5) -> None:
    h, w = img.shape[:2]
    bar_mm = _scale_bar_mm(w * mm_per_px)
    bar_px = max(1, int(round(bar_mm / mm_per_px)))
    x1, y1 = w - 12 - bar_px, h - 14
    thick = max(2, h // 120)
    cv2.rectangle(img, (x1 - 4, y1 - 22 - thick), (x1 + bar_px + 4, y1 + thick + 4), (255, 255, 255), -1)
    cv2.rectangle(img, (x1, y1), (x1 + bar_px, y1 + thick), (0, 0, 0), -1)
    label = f"{bar_mm:g} mm"
    cv2.putText(img, label, (x1, y1 - 6), _FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def preview(fabric: Fabric, *, size_mm: float = 10.0, mm_per_px: float = 0.01, seed: int = 0,
            rotation_deg: float = 0.0) -> np.ndarray:
    """uint8 (H, W, 3) BGR hillshade of a ``size_mm`` square of ``fabric``, with a title and a mm scale bar."""
    if not (math.isfinite(size_mm) and size_mm > 0):
        raise GelsimError(f"--size-mm {size_mm} must be positive; e.g. 10")
    if not (math.isfinite(mm_per_px) and mm_per_px > 0):
        raise GelsimError(f"--mm-per-px {mm_per_px} must be positive; e.g. 0.01")
    n = int(round(size_mm / mm_per_px))
    if n < 16:
        raise GelsimError(f"{size_mm} mm at {mm_per_px} mm/px is only {n} px; use at least 16 px "
                          "(a larger --size-mm or a smaller --mm-per-px)")
    if n > 8192:
        raise GelsimError(f"{size_mm} mm at {mm_per_px} mm/px is {n} px; use at most 8192 px per side")
    h = heightfield(fabric, x0_mm=0.0, y0_mm=0.0, width_px=n, height_px=n, mm_per_px=mm_per_px, seed=seed,
                    rotation_deg=rotation_deg)
    img = cv2.cvtColor(hillshade(h, mm_per_px), cv2.COLOR_GRAY2BGR)
    band = max(28, n // 20)
    title = np.full((band, n, 3), 255, np.uint8)
    fscale = band / 48
    text = f"{fabric.id}: {fabric.name} ({fabric.family}, {fabric.material}), relief {fabric.relief_mm:g} mm"
    cv2.putText(title, text, (6, int(band * 0.7)), _FONT, fscale, (0, 0, 0), 1, cv2.LINE_AA)
    _draw_scale_bar(img, mm_per_px, scale=fscale)
    return np.vstack([title, img])


def put_fitted_label(img: np.ndarray, text: str, origin_xy: tuple[int, int], width_px: int, scale: float) -> None:
    """Write ``text`` in black on the uint8 image ``img`` (in place), its baseline starting at ``origin_xy``
    (x, y px), at font ``scale`` or, if it is wider than ``width_px``, smaller in steps of 0.02 down to 0.2."""
    while scale > 0.2 and cv2.getTextSize(text, _FONT, scale, 1)[0][0] > width_px:
        scale -= 0.02
    cv2.putText(img, text, origin_xy, _FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def contact_sheet(catalog: Catalog, *, tile_mm: float = 5.0, mm_per_px: float = 0.025, columns: int = 10,
                  seed: int = 0) -> np.ndarray:
    """uint8 BGR sheet of every fabric in ``catalog``, one labelled hillshade tile each, with a scale bar."""
    if not (math.isfinite(tile_mm) and tile_mm > 0) or not (math.isfinite(mm_per_px) and mm_per_px > 0):
        raise GelsimError("tile size and mm per pixel must be positive; e.g. --tile-mm 6 --mm-per-px 0.03")
    if columns < 1:
        raise GelsimError(f"--columns {columns} must be at least 1")
    n = int(round(tile_mm / mm_per_px))
    if not 16 <= n <= 2048:
        raise GelsimError(f"tiles of {n} px are out of range; choose --tile-mm and --mm-per-px for 16-2048 px")
    label_h = 18
    fabrics = list(catalog)
    rows = math.ceil(len(fabrics) / columns)
    pad = 4
    sheet = np.full((rows * (n + label_h + pad) + pad, columns * (n + pad) + pad, 3), 255, np.uint8)
    for k, fab in enumerate(fabrics):
        r, c = divmod(k, columns)
        y, x = pad + r * (n + label_h + pad), pad + c * (n + pad)
        h = heightfield(fab, x0_mm=0.0, y0_mm=0.0, width_px=n, height_px=n, mm_per_px=mm_per_px, seed=seed)
        sheet[y + label_h:y + label_h + n, x:x + n] = hillshade(h, mm_per_px)[:, :, None]
        put_fitted_label(sheet, f"{fab.id} {fab.name}", (x, y + label_h - 5), n, 0.38)
    _draw_scale_bar(sheet[pad + label_h:pad + label_h + n, pad:pad + n], mm_per_px, scale=0.4)
    return sheet
