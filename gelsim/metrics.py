"""Image similarity: the one SSIM and PSNR of gelsim (realism scores, fidelity bench).

Images are 8-bit scale, 0-255 DN (uint8 or float), ``(H, W)`` or ``(H, W, C)``.

* :func:`ssim`: Wang et al. (2004), "Image quality assessment: from error visibility to structural
  similarity", with their constants: an 11 x 11 circular-symmetric Gaussian window of sigma 1.5 px,
  ``K1 = 0.01``, ``K2 = 0.03``, ``L = 255``. Colour channels are scored separately and averaged.
  **Edges**: the mean runs over the pixels whose whole 11 x 11 window lies inside the image (the
  "valid" region of Wang's reference code: window centres at least 5 px from every edge), so no
  padded pixel enters the score; images narrower or shorter than 11 px are an error. (The local
  statistics are computed over the whole image with reflected borders and then cropped, which gives
  the same valid-region values.)
  :func:`ssim_map` is the per-pixel map before that crop (the fidelity bench's score is its mean over
  every pixel, border included, as its reports have always been).
* :func:`psnr`: ``10 log10(255^2 / MSE)`` dB; ``+inf`` for identical images (MSE 0). Writers of JSON
  turn the infinity into what their format wants (e.g. ``null``).
* :func:`mse`: the mean squared error, DN^2, over all pixels and channels.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .errors import GelsimError

PEAK_DN = 255.0             # L: the dynamic range of 8-bit images
SSIM_WINDOW_PX = 11         # Wang et al. 2004: 11 x 11 Gaussian window ...
SSIM_SIGMA_PX = 1.5         # ... of standard deviation 1.5 px
SSIM_K = (0.01, 0.03)       # K1, K2 of Wang et al. 2004


def _same_shape(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise GelsimError(f"images have shapes {a.shape} and {b.shape}; compare images of one shape")


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two images (``(H, W)`` or ``(H, W, C)``, 0-255 DN), 1 for identical images,
    averaged over channels and over the pixels whose 11 x 11 window lies inside the image
    (H, W >= 11; see the module docstring)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    _same_shape(a, b)
    if min(a.shape[:2]) < SSIM_WINDOW_PX:
        raise GelsimError(f"images of {a.shape[:2]} px are smaller than SSIM's {SSIM_WINDOW_PX} px window; "
                          f"compare images at least {SSIM_WINDOW_PX} px on a side")
    p = SSIM_WINDOW_PX // 2     # the valid region: drop the pixels whose window reaches past an edge
    return float(ssim_map(a, b)[p:-p, p:-p].mean())


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM at every pixel (and channel) of two images of one shape, float64 shaped like them: the
    local statistics of :func:`ssim` with reflected borders, so pixels within 5 px of an edge see
    padded values (:func:`ssim` leaves them out; the fidelity bench averages the whole map)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    _same_shape(a, b)
    c1, c2 = (SSIM_K[0] * PEAK_DN) ** 2, (SSIM_K[1] * PEAK_DN) ** 2

    def local_mean(x):
        return cv2.GaussianBlur(x, (SSIM_WINDOW_PX, SSIM_WINDOW_PX), SSIM_SIGMA_PX, borderType=cv2.BORDER_REFLECT)

    mu_a, mu_b = local_mean(a), local_mean(b)
    saa = local_mean(a * a) - mu_a * mu_a
    sbb = local_mean(b * b) - mu_b * mu_b
    sab = local_mean(a * b) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (saa + sbb + c2))


def mse(a: np.ndarray, b: np.ndarray) -> float:
    """Mean squared difference of two images of one shape, DN^2."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    _same_shape(a, b)
    return float(np.mean((a - b) ** 2))


def psnr(mse_dn2: float) -> float:
    """PSNR in dB of a mean squared error ``mse_dn2`` (DN^2) on 0-255 images; +inf for 0."""
    return float("inf") if mse_dn2 <= 0 else float(10.0 * math.log10(PEAK_DN ** 2 / mse_dn2))
