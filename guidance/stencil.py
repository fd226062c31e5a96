"""Central-difference stencils over a design's continuous choices.

Several guidance paths take slopes over a design's continuous choices c by central
differences: the model fields' and tokens' Jacobians of the simulator's gradient
(`tt.guidance.simgrad`) and the start's term of the critic's gradient
(`tt.guidance.critic_grad`), both through `simgrad.design_stencil` in physical units with the
step a share of each range, and the critic refinement (`tt.guidance.refine`, in units of each
range). All use these points: c + h_j e_j and c - h_j e_j for every choice j, each cut at its
bound, so a choice at a bound gets a one-sided difference over the width that is left.
"""

from __future__ import annotations

import numpy as np

from tt.sim.designs import Design, DesignSpace


def choice_bounds(space: DesignSpace, design: Design) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (p,) float64: the ranges of the design's continuous choices."""
    params = space.continuous_params(design.discrete)
    return np.array([p.low for p in params], dtype=np.float64), np.array([p.high for p in params], dtype=np.float64)


def central_points(x: np.ndarray, h, low, high) -> tuple[np.ndarray, np.ndarray]:
    """The stencil around x, (p,): rows x + h_j e_j and x - h_j e_j, cut at [low, high], in
    the order (+, -) per choice j, (2 p, p) float64; and each pair's width, (p,).

    h, low, high: scalars or (p,) arrays.
    """
    x = np.asarray(x, dtype=np.float64)
    plus, minus = np.minimum(x + h, high), np.maximum(x - h, low)
    points = np.repeat(x[None], 2 * len(x), axis=0)
    j = np.arange(len(x))
    points[2 * j, j], points[2 * j + 1, j] = plus, minus
    return points, plus - minus


__all__ = ["central_points", "choice_bounds"]
