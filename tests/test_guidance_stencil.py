"""`tt.guidance.stencil.central_points` and `tt.guidance.simgrad.design_stencil` against
the points written out by hand: c +- h e_j, cut at the bounds."""

from __future__ import annotations

import numpy as np

from tt.guidance.simgrad import design_stencil
from tt.guidance.stencil import central_points
from tt.sim.designs import get_space


def test_central_points_cut_at_the_bounds():
    x = np.array([0.5, 0.0, 0.99])
    points, width = central_points(x, 0.02, 0.0, 1.0)
    expected = np.array(
        [
            [0.52, 0.0, 0.99],
            [0.48, 0.0, 0.99],
            [0.5, 0.02, 0.99],
            [0.5, 0.0, 0.99],  # at the lower bound: one-sided
            [0.5, 0.0, 1.0],
            [0.5, 0.0, 0.97],
        ]
    )  # 0.01 from the upper bound
    np.testing.assert_allclose(points, expected, atol=1e-15)
    np.testing.assert_allclose(width, [0.04, 0.02, 0.03], atol=1e-15)
    assert x.tolist() == [0.5, 0.0, 0.99]  # not written to


def test_central_points_take_per_choice_steps_and_bounds():
    x = np.array([1.0, -3.0])
    points, width = central_points(x, np.array([0.1, 2.0]), np.array([0.0, -4.0]), np.array([2.0, 10.0]))
    np.testing.assert_allclose(points, [[1.1, -3.0], [0.9, -3.0], [1.0, -1.0], [1.0, -4.0]])
    np.testing.assert_allclose(width, [0.2, 3.0])


def test_design_stencil_moves_one_choice_in_physical_units():
    space = get_space("viperx")
    design = space.sample(1, seed=2)[0]
    params = space.continuous_params(design.discrete)
    designs, width = design_stencil(space, design, 0.01)
    assert len(designs) == 2 * len(params) == 2 * len(width)
    c0 = np.asarray(design.continuous)
    for j, p in enumerate(params):
        plus, minus = np.asarray(designs[2 * j].continuous), np.asarray(designs[2 * j + 1].continuous)
        assert designs[2 * j].discrete == design.discrete
        others = np.arange(len(params)) != j
        assert np.array_equal(plus[others], c0[others]) and np.array_equal(minus[others], c0[others])
        h = 0.01 * (p.high - p.low)
        assert plus[j] == min(c0[j] + h, p.high) and minus[j] == max(c0[j] - h, p.low)
        assert width[j] == plus[j] - minus[j] > 0
