"""No library motion is physically impossible: for every single-arm validation motion, placed at
the base as the paper places demonstrations and paced at human speed, some ViperX design
tracks it to the end. The design is the best that batched CMA-ES finds for the motion; the
reference that checks it is the MuJoCo C + mink oracle, not the kernels CMA-ES searched with.
"""

from __future__ import annotations

import pytest

from tt.baselines import CMAES, CMAESConfig, Problem, evaluate_designs
from tt.sim.motions import for_space, motion_set


@pytest.mark.slow
def test_every_validation_motion_is_tracked_to_the_end_by_cmaes_best_design():
    motions = for_space(motion_set("val", arms=1), "viperx")
    winners = [
        CMAES(CMAESConfig()).optimize(Problem("viperx", (m,), "tracking", budget=64, seed=0)).best for m in motions
    ]
    for m, design in zip(motions, winners):
        ev = evaluate_designs([design], [m], "tracking", backend="mujoco")
        survival = float(ev.metrics["survival"][0, 0])
        assert survival == 1.0, f"{m.name}: the best CMA-ES design ({design}) survives {100 * survival:.0f} %"
