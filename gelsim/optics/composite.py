"""Compositing shared by the backends: markers, camera blur, camera noise, quantisation.

Both backends produce only a shading change over the background; everything
here is the same for both, so they differ in shading alone.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..errors import GelsimError
from .kernels import add_noise_u8, add_shot_noise_u8, multiply_patches_rows, quad_coverage_strip

def blur_radius_px(sigma_px: float) -> int:
    """Half-size of the Gaussian kernel used for ``sigma_px`` (3 sigma holds 99.7% of its weight)."""
    return int(math.ceil(3.0 * sigma_px)) if sigma_px > 0 else 0


def gaussian_blur(img: np.ndarray, sigma_px: float, dst: np.ndarray | None = None) -> np.ndarray:
    """Camera blur; identity for ``sigma_px == 0``. Borders replicate (the gel continues past the image).
    ``dst``: an array of ``img``'s shape and type to write into (reused buffers avoid page faults)."""
    if sigma_px <= 0:
        return img
    k = 2 * blur_radius_px(sigma_px) + 1
    return cv2.GaussianBlur(img, (k, k), sigma_px, dst, borderType=cv2.BORDER_REPLICATE)


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


def coverage_strip(corners: np.ndarray, pad_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Anti-aliased coverage of convex quadrilateral markers, one patch per marker, side by side.

    ``corners``: float32 ``(N, 4, 2)`` (x, y) px, pixel centres at integers. Returns
    ``(origin, strip)``: int64 ``(N, 2)`` (x, y) of each patch's top-left pixel and float32
    ``(P, N P)`` coverage in 0-1, patch ``i`` in columns ``i P:(i + 1) P`` (the layout
    :func:`marker_factors` blurs in one call), each patch ``pad_px`` wider than its marker on every
    side. Coverage is the product over the 4 edges of ``clip(0.5 + signed distance inside, 0, 1)``:
    the exact pixel-box coverage of an axis-aligned rectangle at least 1 px wide, and within a few
    percent of it at the corners of a sheared one. (cv2.fillPoly with LINE_AA was tried first: its
    squares came out 1.2 px too wide and moved in whole pixels.)
    """
    n = corners.shape[0]
    lo = np.floor(corners.min(axis=1)).astype(np.int64) - pad_px
    size = int(np.ceil(corners.max(axis=1) - corners.min(axis=1)).max()) + 2 * pad_px + 2
    v0 = corners
    v1 = np.roll(corners, -1, axis=1)
    e = v1 - v0                                                           # (N, 4, 2)
    # orientation of each quad (shoelace sign) so that the normals point inwards
    area2 = (v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]).sum(axis=1)
    sign = np.where(area2 >= 0, 1.0, -1.0).astype(np.float32)[:, None]
    length = np.maximum(np.linalg.norm(e, axis=-1), 1e-6)
    nx, ny = -e[..., 1] * sign / length, e[..., 0] * sign / length       # (N, 4)
    c = -(nx * v0[..., 0] + ny * v0[..., 1])
    strip = np.empty((size, n * size), np.float32)
    # per pixel: the product over the edges of clip(nx x + ny y + c + 0.5, 0, 1), in one pass
    quad_coverage_strip(lo, np.ascontiguousarray(nx, np.float32), np.ascontiguousarray(ny, np.float32),
                        np.ascontiguousarray(c + np.float32(0.5), np.float32), strip)
    return lo, strip


def darken_markers(frame: np.ndarray, corners: np.ndarray, darkness: float, blur_sigma_px: float) -> None:
    """Multiply ``frame`` (float32 ``(H, W, 3)``, in place) by ``1 - darkness * coverage`` of the markers.

    Coverage (:func:`coverage_strip`) is blurred like the rest of the image and
    applied per marker patch, so the cost grows with the markers, not the frame.
    """
    apply_marker_factors(frame, marker_factors(corners, darkness, blur_sigma_px, frame.shape))


def marker_factors(corners: np.ndarray, darkness: float, blur_sigma_px: float,
                   shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """The factors :func:`darken_markers` multiplies a frame of ``shape`` (H, W, C) by: ``(origin, factor)``
    with int64 ``(N, 2)`` (x, y) of each marker's patch's top-left pixel and float32 ``(P, N P)``
    ``1 - darkness * blur(coverage)``, the ``P x P`` patches side by side, the same for every channel;
    None if no marker's blurred patch reaches the frame. Depends on nothing else, so a frame whose
    markers did not move can reuse it."""
    h, w = shape[:2]
    radius = blur_radius_px(blur_sigma_px)
    inside = ((corners.max(axis=1) >= -radius - 1) & (corners.min(axis=1) <= np.array([w, h]) + radius)).all(axis=1)
    corners = corners[inside]
    if corners.shape[0] == 0:
        return None
    # side by side in one strip: each patch has >= radius zero columns at both ends,
    # so the blur does not mix neighbouring patches
    lo, strip = coverage_strip(corners, radius + 1)
    if radius:
        strip = gaussian_blur(strip, blur_sigma_px)
    strip = cv2.addWeighted(strip, -darkness, strip, 0.0, 1.0)        # 1 - darkness * coverage
    return lo, strip


def apply_marker_factors(frame: np.ndarray, factors: tuple[np.ndarray, np.ndarray] | None, y0: int = 0) -> None:
    """Multiply ``frame`` (float32 C-contiguous ``(H, W, C)``, in place) by :func:`marker_factors`' patches,
    in marker order (one pass of :func:`~gelsim.optics.kernels.multiply_patches_rows`: a Python loop of
    OpenCV multiplies over about 100 patches took 0.4 ms per frame). ``y0``: the frame row (px) that
    ``frame``'s first row is, for a band of a frame (the same values there as the whole frame's pass)."""
    if factors is None:
        return
    lo, factor = factors
    multiply_patches_rows(frame, lo, factor, y0)


def to_uint8_rows(rows: np.ndarray, out: np.ndarray, y0: int) -> None:
    """:func:`to_uint8` of a band of a frame: ``rows`` float32 ``(n, W, 3)`` DN, the frame's rows ``y0:y0 + n``,
    into the same rows of ``out`` (uint8 ``(H, W, 3)``)."""
    cv2.add(rows, (0.0, 0.0, 0.0, 0.0), out[y0:y0 + rows.shape[0]], dtype=cv2.CV_8U)


def to_uint8(frame: np.ndarray) -> np.ndarray:
    """Round and saturate float32 DN to uint8 (no wrap-around)."""
    if frame.ndim == 3 and frame.shape[2] <= 4:
        # cv2 rounds to nearest and saturates when converting to 8 bits
        return cv2.add(frame, (0.0, 0.0, 0.0, 0.0), dtype=cv2.CV_8U)
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


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

    def offsets(self, seed: int | np.random.Generator) -> tuple[int, int, int]:
        """The draw for ``seed``: (bank frame, row offset, column offset) of its noise field (a Generator
        advances by this draw, as a frame of a sequence does)."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        k = int(rng.integers(len(self.bank)))
        oy, ox = (int(v) for v in rng.integers(self.pad + 1, size=2))
        return k, oy, ox

    def pick(self, seed: int | np.random.Generator) -> np.ndarray:
        """The standard-normal field for ``seed``: float32 ``(H, W, 3)`` view."""
        k, oy, ox = self.offsets(seed)
        h, w = self.shape
        return self.bank[k][oy:oy + h, ox:ox + w]

    def apply(self, frame: np.ndarray, seed: int | np.random.Generator) -> np.ndarray:
        """``frame`` (float32 ``(H, W, 3)`` DN, not modified) plus noise, as a new uint8 array.

        One fused pass (:mod:`gelsim.optics.kernels`) reads the frame and the noise once: the same
        values as OpenCV's ``addWeighted`` into 8 bits (constant sigma) or its five passes (shot
        noise), in a third (constant sigma) to a fifth (shot noise) of their time."""
        h, w = self.shape
        frame = np.ascontiguousarray(frame, dtype=np.float32)
        if frame.shape != (h, w, 3):
            raise GelsimError(f"frame has shape {frame.shape}; the noise bank is for {(h, w, 3)}")
        out = np.empty((h, w, 3), np.uint8)
        self.apply_rows(frame, self.offsets(seed), out, 0)
        return out

    def apply_rows(self, rows: np.ndarray, offsets: tuple[int, int, int], out: np.ndarray, y0: int) -> None:
        """:meth:`apply` on a band of a frame with the draw ``offsets`` (:meth:`offsets`): ``rows`` float32
        C-contiguous ``(n, W, 3)`` DN, the frame's rows ``y0:y0 + n``; ``out`` uint8 C-contiguous
        ``(H, W, 3)``, those rows written. Each pixel's value depends on that pixel alone, so a frame
        finished band by band, while its rows are in the cache, equals the whole frame's :meth:`apply`."""
        k, oy, ox = offsets
        h, w = self.shape
        n = rows.shape[0]
        bank = self.bank[k]
        flat, bank2 = rows.reshape(n, w * 3), bank.reshape(bank.shape[0], -1)
        dst = out.reshape(h, w * 3)[y0:y0 + n]
        if self.shot_gain == 0:
            # the scalars are float32, as OpenCV's vector code uses them
            add_noise_u8(flat, bank2, oy + y0, 3 * ox, np.float32(math.sqrt(self.read_var)), dst)
        else:
            add_shot_noise_u8(flat, bank2, oy + y0, 3 * ox, np.float32(self.shot_gain), np.float32(self.read_var), dst)
