"""gelsim.labels: the contact mask's centroid and bounding box, numpy and torch kernels side by side: the same
boxes, the same centroids to float64 rounding; a mask with one pixel more moves them beyond that."""
from __future__ import annotations

import numpy as np
import pytest

from gelsim.labels import contact_location


def test_contact_location_of_a_known_mask():
    mask = np.zeros((20, 30), bool)
    mask[4:7, 10:20] = True   # rows 4-6, columns 10-19
    c, b = contact_location(mask)
    np.testing.assert_allclose(c, [14.5, 5.0])
    np.testing.assert_allclose(b, [9.5, 3.5, 19.5, 6.5])
    # the box's area (px^2) is the mask's pixel count for a rectangle
    assert (b[2] - b[0]) * (b[3] - b[1]) == pytest.approx(mask.sum())


def test_contact_location_single_pixel_and_empty():
    mask = np.zeros((5, 5), bool)
    mask[2, 3] = True
    c, b = contact_location(mask)
    np.testing.assert_allclose(c, [3.0, 2.0])
    np.testing.assert_allclose(b, [2.5, 1.5, 3.5, 2.5])
    c, b = contact_location(np.zeros((5, 5), bool))
    assert np.isnan(c).all() and np.isnan(b).all()


def test_contact_location_of_a_strided_mask():
    big = np.zeros((10, 10), bool)
    big[2, 4] = True
    c, _ = contact_location(big[::2, ::2])  # not contiguous
    np.testing.assert_allclose(c, [2.0, 1.0])


def test_contact_location_numpy_and_torch_kernels_agree():
    torch = pytest.importorskip("torch")
    from gelsim.labels import contact_location_torch

    rng = np.random.default_rng(0)
    masks = rng.random((3, 20, 30)) > 0.7
    masks[1] = False
    masks[0, :2] = False
    masks[0, :, :2] = False
    cen, bb = contact_location_torch(torch.as_tensor(masks))
    for m, c, b in zip(masks, cen, bb):
        c2, b2 = contact_location(m)
        np.testing.assert_allclose(c, c2, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(b, b2)
    # one pixel more moves the centroid beyond the tolerance (and the box when it lies outside it)
    grown = masks[0].copy()
    grown[0, 0] = True
    c3, b3 = contact_location(grown)
    assert np.abs(c3 - cen[0]).max() > 1e-12 and not np.array_equal(b3, bb[0])
