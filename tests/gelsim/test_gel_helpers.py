"""The gel's helpers that both engines read (issue 49: public and tested where they are defined): the contact
window's least width, the coarse pressure's cell averages, the layer's influence pieces and the markers' corners
and screened-Poisson multiplier."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gelsim.gel.layer import love_influence, layer_correction_table, wrapped_offsets
from gelsim.gel.twoscale import MIN_WINDOW_PX, axis_cell_matrix, widen_window
from gelsim.markers import screen_multiplier, square_corners
from gelsim.sensor import load_profile


@pytest.mark.parametrize("a, b, n, want", [
    (10, 11, 100, (7, 15)),          # grown about its middle to the least width
    (0, 1, 100, (0, MIN_WINDOW_PX)),  # kept inside the frame at its start...
    (99, 100, 100, (92, 100)),        # ...and at its end
    (3, 40, 100, (3, 40)),            # wide enough: unchanged
    (0, 5, 5, (0, 5)),                # the frame itself is narrower: unchanged
])
def test_widen_window(a, b, n, want):
    assert widen_window(a, b, n) == want


def test_axis_cell_matrix_is_the_bilinear_read_then_the_cells_means():
    """One axis of the coarse pressure read at fine pixels (edges held where the grid's edge is the frame's) and
    averaged over cells tiling them: against np.interp (which holds the ends) and block means."""
    rng = np.random.default_rng(3)
    n, f, cells = 6, 4, 6
    p = rng.random(n).astype(np.float32)
    m = axis_cell_matrix(0, n * f, 0, f, n, cells, n * f)
    assert m.shape == (cells, n) and not m.flags.writeable
    fine = np.interp((np.arange(n * f) + 0.5) / f - 0.5, np.arange(n), p)
    np.testing.assert_allclose(m @ p, fine.reshape(cells, f).mean(axis=1), atol=1e-6)
    # inside the frame, beyond the grid's edge the field is zero: the last pixels read less than the edge's value
    inside = axis_cell_matrix(0, n * f, 0, f, n, cells, n * f + 40)
    assert (inside @ p)[-1] < (m @ p)[-1] and np.allclose((inside @ p)[:-1], (m @ p)[:-1])


def test_wrapped_offsets_make_a_circular_convolution_linear():
    np.testing.assert_array_equal(wrapped_offsets(3, 6, 0.5), [0.0, 0.5, 1.0, -1.5, -1.0, -0.5])


def test_love_influence_mixed_derivative_is_one_over_r():
    x, y, h = 0.7, -1.3, 1e-3
    mixed = (love_influence(np.array(x + h), np.array(y + h)) - love_influence(np.array(x + h), np.array(y - h))
             - love_influence(np.array(x - h), np.array(y + h)) + love_influence(np.array(x - h), np.array(y - h)))
    assert mixed / (4 * h * h) == pytest.approx(1.0 / math.hypot(x, y), rel=1e-5)
    assert np.all(np.isfinite(love_influence(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))))


def test_layer_correction_table_cancels_the_half_space_far_away():
    """The layer's kernel is 1/r + G(r/h)/h: bonded to a rigid base, it carries nothing a few thicknesses away
    (G(rho) -> -1/rho), and near the load it is the half-space's (G finite)."""
    rho, g = layer_correction_table(0.49, 8.0)
    assert rho[0] == 0.0 and rho[-1] == 8.0 and np.all(np.isfinite(g))
    assert abs(1.0 / rho[-1] + g[-1]) < 0.02 / rho[-1]


def test_square_corners_are_drawn_tl_tr_br_bl():
    prof = load_profile("vitac")
    half = prof.markers.size_mm / prof.image.mm_per_px / 2
    c = square_corners(np.array([[10.0, 20.0]], np.float32), prof)
    np.testing.assert_allclose(c[0], [[10 - half, 20 - half], [10 + half, 20 - half], [10 + half, 20 + half],
                                      [10 - half, 20 + half]])


def test_screen_multiplier_is_minus_one_over_q2_plus_screening():
    m = screen_multiplier(8, 10, 2.0)
    assert m.shape == (8, 6) and not m.flags.writeable
    assert m[0, 0] == pytest.approx(-4.0)                       # q = 0: -l^2
    assert m[0, 1] == pytest.approx(-1.0 / ((2 * np.pi / 10) ** 2 + 0.25))
