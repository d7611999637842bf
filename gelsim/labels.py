"""The contact labels of a frame's imprint: where its contact mask lies (centroid and bounding box, px), with the
numpy kernel (OpenCV, one frame) and the torch kernel (a batch of masks on any device) side by side, as
:mod:`gelsim.optics.ops` holds the optics' primitives. Parity: ``tests/gelsim/test_labels.py`` (the same
centroids to float64 rounding, the same boxes exactly).
"""
from __future__ import annotations

import cv2
import numpy as np

from .batch_ops import bbox, torch_module


def contact_location(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a bool (H, W) contact mask lies, in px (x = column, y = row, pixel centres at integers).

    Returns the centroid float (2,) (x, y) and the bounding box float (4,) (x0, y0, x1, y1) of its
    pixels' edges, so a single pixel at column 5 spans x 4.5-5.5; both NaN when the mask is empty.
    """
    m = np.ascontiguousarray(mask).view(np.uint8)
    # Column and row counts by cv2.reduce: 0.16 ms in all at 960x720, against 1.4 ms for cv2.moments. The box
    # is read off the counts (their first and last nonzero), not found by a third pass over the mask.
    cols = cv2.reduce(m, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel().astype(np.float64)
    n = cols.sum()
    if n == 0:
        return np.full(2, np.nan), np.full(4, np.nan)
    rows = cv2.reduce(m, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel().astype(np.float64)
    xs, ys = np.flatnonzero(cols), np.flatnonzero(rows)
    return (np.array([cols @ np.arange(cols.size) / n, rows @ np.arange(rows.size) / n]),
            np.array([xs[0] - 0.5, ys[0] - 0.5, xs[-1] + 0.5, ys[-1] + 0.5]))


def contact_location_torch(mask):
    """:func:`contact_location` per frame of a bool ``(B, H, W)`` tensor: centroid float ``(B, 2)`` (x, y)
    px and bounding box float ``(B, 4)`` (x0, y0, x1, y1) of the pixels' edges, NaN for an empty mask (numpy)."""
    torch = torch_module()
    cols = mask.sum(dim=1, dtype=torch.float64)            # (B, W)
    rows = mask.sum(dim=2, dtype=torch.float64)            # (B, H)
    n = cols.sum(dim=1)
    cx = (cols * torch.arange(cols.shape[1], device=mask.device, dtype=torch.float64)).sum(dim=1)
    cy = (rows * torch.arange(rows.shape[1], device=mask.device, dtype=torch.float64)).sum(dim=1)
    box = bbox(mask)
    n, cx, cy, box = n.cpu().numpy(), cx.cpu().numpy(), cy.cpu().numpy(), box.cpu().numpy()
    empty = n == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = np.stack([cx / n, cy / n], axis=1)
    bb = np.stack([box[:, 2] - 0.5, box[:, 0] - 0.5, box[:, 3] - 0.5, box[:, 1] - 0.5], axis=1).astype(np.float64)
    cen[empty] = np.nan
    bb[empty] = np.nan
    return cen, bb
