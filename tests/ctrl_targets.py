"""Joint targets for the open-loop agreement tests (tests/test_backends.py, tests/test_kernels_dynamics.py)."""

from __future__ import annotations

import numpy as np


def some_at_the_ends(targets, lo, hi, rng, share=0.3):
    """`targets` (steps, nu) with about `share` of the joints sent to an end of their ctrl range
    (= the joint range) for the last two thirds of the run. The servos turn at most ~3 rad/s
    and their back-EMF damps every overshoot, so targets that change every 0.1 s inside the
    range rarely reach a limit; one held at the end does, once gravity or the approach
    carries the joint past it."""
    chosen = rng.uniform(size=targets.shape[1]) < share
    end = np.where(rng.uniform(size=targets.shape[1]) < 0.5, lo, hi)
    out = targets.copy()
    out[targets.shape[0] // 3 :, chosen] = end[chosen]
    return out
