"""Critic refinement (`tt.guidance.refine`) and the common noise it relies on, with the shipped critic.

The references: a design's prediction under common noise does not depend on what else is in
the batch (the same design twice gives the same number, and alone the same as beside
others); one refinement step moves the design along central differences computed here
design by design, one prediction per call; the refined design's J re-predicted on its own
is what the refinement reports, and with ``check`` it is higher under the second noise draw
too. (A random network's predictions hardly move with the design, so these use the shipped
dynamics critic, with few DDIM steps.)
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tt.baselines.problem import Problem, Result
from tt.guidance.critic_grad import NO_TERMINATION
from tt.guidance.predicted import predict_designs
from tt.guidance.refine import RefineConfig, refine_designs
from tt.guidance.zeroth import SamplerConfig, ZerothOrder
from tt.sim.designs import Design, get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import get_reward

STEPS = 3

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def critic():
    from tt.dit.checkpoint import load_model

    return load_model("checkpoints/viperx_mini_dynamics.pt", device="cpu")


@pytest.fixture(scope="module")
def motion():
    return for_space([get_motion("reach_place")], "viperx")[0]


def _middle(design: Design, seed: int) -> Design:
    """`design` with every continuous choice drawn from the middle half of its range (no step reaches a bound)."""
    space = get_space(design.space)
    params = space.continuous_params(design.discrete)
    u = 0.25 + 0.5 * np.random.default_rng(seed).random(len(params))
    return Design(design.space, design.discrete, tuple(p.low + x * (p.high - p.low) for p, x in zip(params, u)))


def _predict(critic, designs, motion, cfg, seed):
    return predict_designs(critic, designs, (motion,), cfg, num_steps=STEPS, seed=seed, common_noise=True).reward[:, 0]


def test_common_noise_makes_a_prediction_independent_of_the_batch(critic, motion):
    a, b = get_space("viperx").sample(2, seed=3)
    cfg = get_reward("tracking", "viperx")
    together = _predict(critic, [a, b, a], motion, cfg, seed=1)
    alone = _predict(critic, [a], motion, cfg, seed=1)
    assert together[0] == together[2]
    np.testing.assert_allclose(alone[0], together[0], rtol=1e-4, atol=1e-3)
    drawn = predict_designs(critic, [a, b, a], (motion,), cfg, num_steps=STEPS, seed=1).reward[:, 0]
    assert drawn[0] != drawn[2]  # without it each row has its own noise


def test_one_step_follows_central_differences_taken_design_by_design(critic, motion):
    space = get_space("viperx")
    design = _middle(space.sample(1, seed=11)[0], seed=2)
    cfg = dataclasses.replace(get_reward("tracking", "viperx"), threshold=NO_TERMINATION)
    config = RefineConfig(iterations=1, num_steps=STEPS, check=False)
    out = refine_designs(critic, [design], (motion,), get_reward("tracking", "viperx"), config, seed=4)
    params = space.continuous_params(design.discrete)
    low = np.array([p.low for p in params])
    span = np.array([p.high for p in params]) - low
    u0 = (np.array(design.continuous) - low) / span
    slope = []
    for j in range(len(params)):
        moved = []
        for s in (1, -1):
            u = u0.copy()
            u[j] += s * config.rel_step
            moved.append(Design("viperx", design.discrete, tuple(low + u * span)))
        plus, minus = (_predict(critic, [d], motion, cfg, seed=4)[0] for d in moved)
        slope.append((plus - minus) / (2 * config.rel_step))
    slope = np.array(slope)
    assert np.abs(slope).max() > 0
    assert out.before[0] == pytest.approx(_predict(critic, [design], motion, cfg, seed=4)[0], rel=1e-4, abs=1e-3)
    assert out.steps[0] == 1, out.trace  # this design does climb
    refined = out.designs[0]
    assert refined.discrete == design.discrete
    step = (np.array(refined.continuous) - low) / span - u0
    size = np.abs(step).max()
    assert min(abs(size - a) for a in config.step_sizes) < 1e-9
    # The step is the slope scaled to size; batch composition moves the slope by float32 rounding.
    np.testing.assert_allclose(step, size * slope / np.abs(slope).max(), atol=2e-2 * size)
    assert out.after[0] > out.before[0]
    assert out.after[0] == pytest.approx(_predict(critic, [refined], motion, cfg, seed=4)[0], rel=1e-4, abs=1e-3)


def test_refined_designs_score_higher_under_both_draws(critic, motion):
    space = get_space("viperx")
    designs = [_middle(d, seed=i) for i, d in enumerate(space.sample(3, seed=21))]
    cfg = get_reward("tracking", "viperx")
    out = refine_designs(critic, designs, (motion,), cfg, RefineConfig(iterations=3, num_steps=STEPS), seed=7)
    smooth = dataclasses.replace(cfg, threshold=NO_TERMINATION)
    assert out.steps.sum() > 0
    for i, (d, r) in enumerate(zip(designs, out.designs)):
        assert r.discrete == d.discrete
        get_space("viperx").validate(r)
        assert len(out.trace[i]) == out.steps[i] + 1 and np.all(np.diff(out.trace[i]) > 0)
        if out.steps[i] == 0:
            assert r == d
            continue
        first, second = (_predict(critic, [d, r], motion, smooth, seed=s) for s in (7, 7 + 2 ** 31))
        assert first[1] > first[0] and second[1] > second[0]
        assert out.after[i] == pytest.approx(first[1], rel=1e-4, abs=1e-3)


def test_zeroth_order_returns_the_refined_design(critic, motion):
    space = get_space("viperx")
    design = _middle(space.sample(1, seed=11)[0], seed=2)
    problem = Problem("viperx", (motion,), "tracking", 1, seed=4, device="cpu")
    opt = ZerothOrder(SamplerConfig(num_steps=STEPS, refine=1), model=critic)
    given = Result("zeroth", design, 1.0, [design], np.array([1.0]), 0.1, 0, [1.0], {"samples": 1})
    out = opt.refined(problem, given)
    expected = refine_designs(critic, [design], (motion,), get_reward("tracking", "viperx"),
                              RefineConfig(iterations=1), seed=4)
    assert out.best == expected.designs[0] != design
    assert out.designs == [out.best, design] and out.info["refine"]["objective_before"] == 1.0
    assert out.best_reward == pytest.approx(predict_designs(critic, [out.best], (motion,), get_reward("tracking", "viperx"),
                                                            num_steps=STEPS, seed=4).reward.mean())


def test_bad_refine_settings_are_refused(critic, motion):
    for bad in (dict(iterations=0), dict(rel_step=0.5), dict(step_sizes=()), dict(step_sizes=(0.1, 1.5)),
                dict(samples=0), dict(num_steps=0)):
        with pytest.raises(ValueError):
            RefineConfig(**bad)
    with pytest.raises(ValueError, match="refine"):
        SamplerConfig(refine=-1)
    cfg = get_reward("tracking", "viperx")
    with pytest.raises(ValueError, match="at least one design"):
        refine_designs(critic, [], (motion,), cfg)
    mixed = [get_space("viperx").sample(1, seed=0)[0], get_space("viperx-nominal").sample(1, seed=0)[0]]
    with pytest.raises(ValueError, match="several spaces"):
        refine_designs(critic, mixed, (motion,), cfg)
