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
import torch

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
    return _shipped_critic()


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
        first, second = (_predict(critic, [d, r], motion, smooth, seed=s) for s in (7, 7 + 2**31))
        assert first[1] > first[0] and second[1] > second[0]
        assert out.after[i] == pytest.approx(first[1], rel=1e-4, abs=1e-3)


def test_log_prediction_scores_the_same_samples_with_the_smooth_stand_in(critic, motion, monkeypatch):
    import tt.guidance.predicted as predicted

    designs = get_space("viperx").sample(2, seed=8)
    motions = (motion, for_space([get_motion("wipe")], "viperx")[0])
    cfg = get_reward("tracking", "viperx")
    seen = []
    plain_metrics = predicted.predicted_metrics
    monkeypatch.setattr(
        predicted, "predicted_metrics", lambda scorer, x0: seen.append((scorer, x0)) or plain_metrics(scorer, x0)
    )
    both = predict_designs(critic, designs, motions, cfg, samples=2, num_steps=STEPS, seed=3, log=True)
    plain = predict_designs(critic, designs, motions, cfg, samples=2, num_steps=STEPS, seed=3)
    assert plain.log_reward is None and both.log_reward.shape == (2, 2)
    np.testing.assert_array_equal(both.reward, plain.reward)  # the same samples, scored twice
    assert len(seen) == 4  # one scoring per motion and call
    for j, (scorer, x0) in enumerate(seen[:2]):  # motion j's rows: design 0's two samples, then design 1's
        with torch.no_grad():
            smooth = scorer(x0, log=True).double().numpy()
        np.testing.assert_allclose(both.log_reward[:, j], [smooth[:2].mean(), smooth[2:].mean()], rtol=1e-6)
    assert np.all(both.log_reward < 0) and both.log_reward[0, 0] != both.log_reward[0, 1]


def test_zeroth_order_returns_the_refined_design(critic, motion):
    space = get_space("viperx")
    design = _middle(space.sample(1, seed=11)[0], seed=2)
    problem = Problem("viperx", (motion,), "tracking", 1, seed=4, device="cpu")
    opt = ZerothOrder(SamplerConfig(num_steps=STEPS, refine=1), model=critic)
    given = Result("zeroth", design, 1.0, [design], np.array([1.0]), 0.1, 0, [1.0], {"samples": 1})
    out = opt.refined(problem, given)
    expected = refine_designs(
        critic, [design], (motion,), get_reward("tracking", "viperx"), RefineConfig(iterations=1), seed=4
    )
    assert out.best == expected.designs[0] != design
    assert out.designs == [out.best, design] and out.info["refine"]["ranked_objective"] == 1.0
    # Both re-predicted in one call with common noise: the same as each alone.
    before, after = (
        predict_designs(
            critic, [d], (motion,), get_reward("tracking", "viperx"), num_steps=STEPS, seed=4, common_noise=True
        ).reward.mean()
        for d in (design, out.best)
    )
    assert out.best_reward == pytest.approx(after, rel=1e-4, abs=1e-3)
    assert out.info["refine"]["objective_before"] == pytest.approx(before, rel=1e-4, abs=1e-3)


def test_zeroth_order_keeps_its_result_when_no_step_is_taken(critic, motion, monkeypatch):
    import tt.guidance.zeroth as zeroth
    from tt.guidance.refine import Refined

    design = get_space("viperx").sample(1, seed=11)[0]
    monkeypatch.setattr(
        zeroth,
        "refine_designs",
        lambda critic, designs, *a, **k: Refined(
            list(designs), np.array([5.0]), np.array([5.0]), np.array([0]), [[5.0]], 3, 0.1
        ),
    )
    problem = Problem("viperx", (motion,), "tracking", 1, seed=4, device="cpu")
    given = Result("zeroth", design, 1.0, [design], np.array([1.0]), 0.1, 0, [1.0], {"samples": 1})
    out = ZerothOrder(SamplerConfig(num_steps=STEPS, refine=2), model=critic).refined(problem, given)
    assert out.best == design and out.best_reward == 1.0 and out.designs == [design] and out.history == [1.0]
    assert out.info["refine"]["steps"] == [0] and out.info["refine"]["ranked_objective"] == 1.0


def test_init_noise_of_a_type_the_task_does_not_diffuse_is_refused(critic, motion):
    from tt.dit.sampling import sample
    from tt.dit.tasks import TaskSpec
    from tt.guidance.predicted import build_query

    q = build_query(critic.layout, critic.normalizer, motion, 2)
    task = TaskSpec("dynamics", critic.robot_diffusion_steps, "start")
    with pytest.raises(ValueError, match="does not diffuse"):
        sample(
            critic.model, q.tokens, task, num_steps=1, init_noise={"link": torch.zeros_like(q.tokens.values["link"])}
        )
    name = next(n for n in q.tokens.values if n == "track_link_obs")
    with pytest.raises(ValueError, match="shape"):
        sample(critic.model, q.tokens, task, num_steps=1, init_noise={name: torch.zeros(1, 2, 3)})


def test_bad_refine_settings_are_refused(critic, motion):
    for bad in (
        dict(iterations=0),
        dict(rel_step=0.5),
        dict(step_sizes=()),
        dict(step_sizes=(0.1, 1.5)),
        dict(samples=0),
        dict(num_steps=0),
    ):
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


def test_tt_optimize_refine_reports_the_climb(tmp_path):
    """The CLI end to end with the shipped checkpoints: the refined design is the one validated and saved."""
    import json

    from typer.testing import CliRunner

    from tt.cli import app

    out = tmp_path / "result.json"
    result = CliRunner().invoke(
        app,
        [
            "optimize",
            "--method",
            "zeroth",
            "--motion",
            "reach_place",
            "--budget",
            "1",
            "--num-steps",
            "10",
            "--refine",
            "2",
            "--json",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "refined by the dynamics critic" in result.output
    saved = json.loads(out.read_text())
    refine = saved["info"]["refine"]
    assert refine["iterations"] == 2 and len(refine["trace"][0]) == refine["steps"][0] + 1
    # The saved objective is the saved design's prediction: re-predicted with common noise
    # after a step, the ranking's own figure (one candidate, row 0) without one.
    expected = predict_designs(
        _shipped_critic(),
        [get_space("viperx").from_dict(saved["design"])],
        for_space([get_motion("reach_place")], "viperx"),
        get_reward("tracking", "viperx"),
        num_steps=10,
        seed=0,
        common_noise=refine["steps"][0] > 0,
    ).reward.mean()
    assert saved["objective"] == pytest.approx(expected, rel=1e-4, abs=1e-3)


def _shipped_critic():
    from tt.dit.checkpoint import load_model

    return load_model("checkpoints/viperx_mini_dynamics.pt", device="cpu")
