"""gelsim.labels: the contact mask's centroid and bounding box, numpy and torch kernels side by side: the same
boxes, the same centroids to float64 rounding; a mask with one pixel more moves them beyond that."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.labels import contact_location, contact_location_torch  # noqa: E402


def test_contact_location_numpy_and_torch_kernels_agree():
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
