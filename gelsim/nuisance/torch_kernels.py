"""Torch twins of the nuisance stages' image kernels, on ``(B, 3, H, W)`` float32 tensors.

Each gives the same bits as its numpy kernel frame by frame (an element-wise IEEE multiply, correctly
rounded on every device), whatever the batch size.
"""
from __future__ import annotations

import numpy as np

from ..errors import GelsimError


def apply_gains_torch(frames, gains):
    """``frames`` (float32 ``(B, 3, H, W)`` DN tensor) times per-frame, per-channel ``gains`` ((B, 3) array or
    tensor, rounded to float32 as :func:`gelsim.nuisance.camera.apply_gains` does): a new tensor, same shape."""
    import torch

    if not isinstance(frames, torch.Tensor) or frames.dtype != torch.float32 or frames.ndim != 4 \
            or frames.shape[1] != 3:
        raise GelsimError(f"frames must be a float32 (B, 3, H, W) tensor, got "
                          f"{getattr(frames, 'dtype', type(frames).__name__)} {tuple(getattr(frames, 'shape', ()))}")
    g = gains.detach().cpu().double().numpy() if isinstance(gains, torch.Tensor) else np.asarray(gains, np.float64)
    if g.shape != (frames.shape[0], 3) or not np.all(np.isfinite(g)) or np.any(g < 0):
        raise GelsimError(f"gains of shape {g.shape} must be (B, 3) = ({frames.shape[0]}, 3) finite numbers >= 0")
    gt = torch.from_numpy(g.astype(np.float32)).to(frames.device)
    return frames * gt[:, :, None, None]
