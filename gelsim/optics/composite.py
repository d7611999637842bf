"""Compositing shared by the backends: markers, camera blur, camera noise, quantisation.

Both backends produce only a shading change over the background; everything
here is the same for both, so they differ in shading alone.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..errors import GelsimError

# cv2 drawing takes fixed-point coordinates with this many fractional bits:
# 4 bits = 1/16 px placement, far below the blur and noise of the image.
SHIFT_BITS = 4


def blur_radius_px(sigma_px: float) -> int:
    """Half-size of the Gaussian kernel used for ``sigma_px`` (3 sigma holds 99.7% of its weight)."""
    return int(math.ceil(3.0 * sigma_px)) if sigma_px > 0 else 0


def gaussian_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Camera blur; identity for ``sigma_px == 0``. Borders replicate (the gel continues past the image)."""
    if sigma_px <= 0:
        return img
    k = 2 * blur_radius_px(sigma_px) + 1
    return cv2.GaussianBlur(img, (k, k), sigma_px, borderType=cv2.BORDER_REPLICATE)


def marker_corners(markers) -> np.ndarray | None:
    """Marker corners as float32 ``(N, 4, 2)`` px from a Markers-like object, an array, or None."""
    if markers is None:
        return None
    corners = getattr(markers, "corners_px", markers)
    corners = np.asarray(corners, dtype=np.float32)
    if corners.size == 0:
        return None
    if corners.ndim != 3 or corners.shape[1:] != (4, 2):
        raise GelsimError(f"marker corners have shape {corners.shape}; give (N, 4, 2) pixel coordinates (x, y)")
    if not np.all(np.isfinite(corners)):
        raise GelsimError("marker corners contain NaN or infinity; check the marker displacement")
    return corners


def darken_markers(frame: np.ndarray, corners: np.ndarray, darkness: float, blur_sigma_px: float) -> None:
    """Multiply ``frame`` (float32 ``(H, W, 3)``, in place) by ``1 - darkness * coverage`` of the markers.

    Coverage is drawn anti-aliased with sub-pixel corners (``cv2.fillPoly``,
    ``LINE_AA``, :data:`SHIFT_BITS`), blurred like the rest of the image, and
    applied per marker box so that the cost grows with the markers, not the frame.
    """
    h, w = frame.shape[:2]
    pad = blur_radius_px(blur_sigma_px) + 2
    lo = np.floor(corners.min(axis=1)).astype(np.int64) - pad      # (N, 2) x, y
    hi = np.ceil(corners.max(axis=1)).astype(np.int64) + pad + 1
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [w, h])
    keep = np.all(hi > lo, axis=1)
    if not keep.any():
        return
    corners, lo, hi = corners[keep], lo[keep], hi[keep]
    x0, y0 = lo.min(axis=0)
    x1, y1 = hi.max(axis=0)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    pts = np.round((corners - np.array([x0, y0], np.float32)) * (1 << SHIFT_BITS)).astype(np.int32)
    cv2.fillPoly(mask, list(pts), 255, lineType=cv2.LINE_AA, shift=SHIFT_BITS)
    mask = gaussian_blur(mask, blur_sigma_px)
    scale = -darkness / 255.0
    for (ax, ay), (bx, by) in zip(lo.tolist(), hi.tolist()):
        m = mask[ay - y0:by - y0, ax - x0:bx - x0].astype(np.float32)
        m *= scale
        m += 1.0
        frame[ay:by, ax:bx] *= m[..., None]


def to_uint8(frame: np.ndarray) -> np.ndarray:
    """Round and saturate float32 DN to uint8 (no wrap-around)."""
    return cv2.add(frame, np.zeros_like(frame), dtype=cv2.CV_8U) if frame.ndim == 3 else \
        np.clip(np.rint(frame), 0, 255).astype(np.uint8)


class NoiseBank:
    """Camera noise from a bank of pre-drawn standard-normal frames.

    Drawing 960x720x3 normals costs about 6 ms per frame; instead ``frames``
    frames are drawn once from the renderer's seed, each ``pad_px`` larger than
    the image, and a frame's noise is one of them at an offset chosen by the
    frame's seed (``frames * (pad_px + 1)^2`` distinct patterns). The standard
    normal is scaled per pixel by ``sqrt(read_sigma^2 + shot_gain * signal)``.
    """

    def __init__(self, shape: tuple[int, int], read_sigma_dn: float, shot_gain: float, seed: int,
                 frames: int = 4, pad_px: int = 48):
        h, w = shape
        self.shape = shape
        self.read_var = float(read_sigma_dn) ** 2
        self.shot_gain = float(shot_gain)
        self.pad = pad_px
        rng = np.random.default_rng([seed, 0x401])
        self.bank = [rng.standard_normal((h + pad_px, w + pad_px, 3), dtype=np.float32) for _ in range(frames)]

    @property
    def active(self) -> bool:
        return self.read_var > 0 or self.shot_gain > 0

    def pick(self, seed: int | np.random.Generator) -> np.ndarray:
        """The standard-normal field for ``seed``: float32 ``(H, W, 3)`` view."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        k = int(rng.integers(len(self.bank)))
        oy, ox = (int(v) for v in rng.integers(self.pad + 1, size=2))
        h, w = self.shape
        return self.bank[k][oy:oy + h, ox:ox + w]

    def apply(self, frame: np.ndarray, seed: int | np.random.Generator) -> np.ndarray:
        """``frame`` (float32 ``(H, W, 3)`` DN, overwritten) plus noise, as uint8."""
        z = self.pick(seed)
        var = cv2.addWeighted(frame, self.shot_gain, frame, 0.0, self.read_var)
        cv2.max(var, 0.0, var)   # a dark pixel below 0 DN has no shot noise
        cv2.sqrt(var, var)
        cv2.multiply(var, z, var)
        return cv2.add(frame, var, dtype=cv2.CV_8U)
