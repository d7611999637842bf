"""Filters: the camera blur and other Gaussian blurs, Sobel slopes, per-pixel channel mixes.

numpy kernels: OpenCV on float32 ``(H, W)`` or ``(H, W, C)`` images. torch kernels: ``(..., H, W)``
tensors (channels and frames leading), separable filters written as sums of shifted slices, one
multiply and one add per tap in tap order (no fused multiply-add, no convolution whose algorithm a
library would pick by shape), with OpenCV's float32 taps: the same values to float32 rounding.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from . import pad_hw, torch_module

_BORDERS = {"replicate": cv2.BORDER_REPLICATE, "constant": cv2.BORDER_CONSTANT}


def blur_radius_px(sigma_px: float) -> int:
    """Half-size of the camera blur's kernel for ``sigma_px`` (3 sigma holds 99.7% of its weight)."""
    return int(math.ceil(3.0 * sigma_px)) if sigma_px > 0 else 0


def gaussian_blur(img: np.ndarray, sigma_px: float, dst: np.ndarray | None = None) -> np.ndarray:
    """The camera blur, ``2 r + 1`` taps (:func:`blur_radius_px`); identity for ``sigma_px == 0``. Borders
    replicate (the gel continues past the image). ``dst``: an array of ``img``'s shape and type to write
    into (reused buffers avoid page faults)."""
    if sigma_px <= 0:
        return img
    k = 2 * blur_radius_px(sigma_px) + 1
    return cv2.GaussianBlur(img, (k, k), sigma_px, dst, borderType=cv2.BORDER_REPLICATE)


def smooth(img: np.ndarray, sigma_px: float, border: str = "replicate") -> np.ndarray:
    """A Gaussian blur with OpenCV's own kernel size for ``sigma_px`` (``round(8 sigma + 1) | 1`` taps on
    float images), borders ``"replicate"`` or ``"constant"`` (zero): the shadows' penumbra, the halo."""
    return cv2.GaussianBlur(img, (0, 0), sigma_px, borderType=_BORDERS[border])


def slopes(d: np.ndarray, mm_per_px: float, gx: np.ndarray | None = None,
           gy: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Slopes ``(dd/dx, dd/dy)`` (mm/mm) of heights ``d`` (float32 ``(H, W)`` mm on a ``mm_per_px`` grid):
    3x3 Sobel, which responds 8 per unit step per pixel, scaled; borders replicate. ``gx, gy``: float32
    arrays of ``d``'s shape to write into."""
    scale = 1.0 / (8.0 * mm_per_px)
    gx = cv2.Sobel(d, cv2.CV_32F, 1, 0, gx, ksize=3, scale=scale, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(d, cv2.CV_32F, 0, 1, gy, ksize=3, scale=scale, borderType=cv2.BORDER_REPLICATE)
    return gx, gy


def mix_channels(stack: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Per-pixel mix ``out[..., c] = sum_k matrix[c, k] stack[..., k]``: float32 ``(h, w, C)`` from ``(h, w, K)``
    (or ``(h, w)`` for ``K = 1``) and a float32 C-contiguous ``(C, K)`` matrix (cv2.transform, several times
    faster than a matmul, for ``K <= 4``; a matmul beyond)."""
    if stack.ndim == 2 or stack.shape[2] <= 4:
        return cv2.transform(stack, matrix)
    h, w, k = stack.shape
    return (stack.reshape(-1, k) @ matrix.T).reshape(h, w, -1)


# ---------------------------------------------------------------- torch

def cv_gaussian_taps(sigma_px: float, ksize: int | None = None) -> list[float]:
    """The float32 taps OpenCV's GaussianBlur uses for ``sigma_px`` on float images (``ksize`` None: its
    own choice for a zero size, ``round(8 sigma + 1) | 1``)."""
    if ksize is None:
        ksize = int(round(sigma_px * 8 + 1)) | 1
    return [float(v) for v in cv2.getGaussianKernel(ksize, sigma_px, cv2.CV_32F).ravel()]


def shifted_sum_torch(x, taps: list[float], dim: int, border: str):
    """``sum_i taps[i] x[.. j + i - r ..]`` along ``dim`` (-2: down the rows, -1: along them, of an
    ``(..., H, W)`` tensor), the border ``"replicate"`` or ``"constant"`` (zero). A multiply and an add
    per tap, in tap order, as separate operations (no fused multiply-add)."""
    torch = torch_module()
    r = (len(taps) - 1) // 2
    if r == 0:
        return x * taps[0]
    n = x.shape[dim]
    xp = pad_hw(x, (r, r, 0, 0) if dim in (-1, x.dim() - 1) else (0, 0, r, r), border)
    out = xp.narrow(dim, 0, n) * taps[0]
    tmp = torch.empty_like(out)
    for i in range(1, len(taps)):
        if taps[i] == 0.0:
            continue                      # (a Sobel's middle tap: adding 0 x would change nothing)
        out += torch.mul(xp.narrow(dim, i, n), taps[i], out=tmp)
    return out


def smooth_torch(x, sigma_px: float, border: str = "replicate", ksize: int | None = None):
    """:func:`smooth` of an ``(..., H, W)`` tensor (``ksize``: the taps, default OpenCV's choice), separable,
    along the rows first (OpenCV's order); identity for ``sigma_px <= 0``."""
    if sigma_px <= 0:
        return x
    taps = cv_gaussian_taps(sigma_px, ksize)
    return shifted_sum_torch(shifted_sum_torch(x, taps, -1, border), taps, -2, border)


def gaussian_blur_torch(x, sigma_px: float):
    """:func:`gaussian_blur` (the camera blur: ``2 r + 1`` taps, replicated borders) of an ``(..., H, W)`` tensor."""
    return smooth_torch(x, sigma_px, "replicate", 2 * blur_radius_px(sigma_px) + 1)


def slopes_torch(d, mm_per_px: float):
    """:func:`slopes` of ``(..., H, W)`` heights ``d``."""
    scale = 1.0 / (8.0 * mm_per_px)
    dx = shifted_sum_torch(shifted_sum_torch(d, [-1.0, 0.0, 1.0], -1, "replicate"), [1.0, 2.0, 1.0], -2, "replicate")
    dy = shifted_sum_torch(shifted_sum_torch(d, [1.0, 2.0, 1.0], -1, "replicate"), [-1.0, 0.0, 1.0], -2, "replicate")
    return dx * scale, dy * scale


def mix_channels_torch(maps: list, matrix: np.ndarray):
    """:func:`mix_channels` of ``K`` maps ``(B, h, w)``: ``(B, C, h, w)``, summed in ``k`` order."""
    torch = torch_module()
    out = []
    for c in range(matrix.shape[0]):
        acc = maps[0] * float(matrix[c, 0])
        for k in range(1, len(maps)):
            acc = acc + maps[k] * float(matrix[c, k])
        out.append(acc)
    return torch.stack(out, dim=1)
