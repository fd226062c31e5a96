"""The learnability ladder (`tt.ladder`): correlations, and R0, a small model memorizing 64
episodes well enough that `tt predict` ranks them as the simulator does."""

from __future__ import annotations

import numpy as np
import pytest

from tt.ladder import pearson, within_motion


def test_pearson_and_within_motion_against_numpy():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(12, 3))
    y = x + rng.normal(scale=0.5, size=(12, 3)) + np.array([0.0, 10.0, -5.0])
    assert np.isclose(pearson(x, y), np.corrcoef(x.ravel(), y.ravel())[0, 1])
    assert np.allclose(within_motion(x, y), [np.corrcoef(x[:, j], y[:, j])[0, 1] for j in range(3)])
    # Motion offsets inflate the pooled r of noise: within-motion r sees through it.
    z = rng.normal(size=(12, 3)) + np.array([0.0, 10.0, -5.0])
    assert pearson(z, y) > 0.9 and max(abs(r) for r in within_motion(z, y)) < 0.7
    assert np.isnan(pearson(np.ones(5), np.arange(5.0)))  # no spread
    assert np.isnan(pearson(np.array([1.0, np.nan, 2.0]), np.array([1.0, 2.0, np.nan])))  # < 3 finite pairs


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_r0_a_small_model_memorizes_64_episodes(tmp_path):
    """R0: the 64 episodes of one online refresh (16 viperx-nominal designs x 4 augmented
    training motions, no control perturbation, terminated episodes kept to the motion's end:
    `OnlineConfig.absorbing`; `tt.ladder.r0_online`) trained on alone with `tt.ladder.R0_RECIPE`;
    `tt predict` on those same designs x motions correlates with their simulated rewards at
    r >= 0.95 (pooled). Measured on the 2-core box (2026-12-02, benchmarks/results/dit_recipe.md,
    row `x0`): 0.97 at step 1,000 (within-motion 0.95-0.99) after 4 min of training; the
    paper's recipe (robot task, design inpainted, eps, a learned time-ID table) gave 0.14.
    With the damped start posture (2026-12-03) 1,000 steps gave 0.92 and the recipe's 2,000
    give 0.997 (within-motion 0.99-1.00; 10 min on one core of the Intel Xeon)."""
    from tt.dit.checkpoint import load_model
    from tt.dit.online import OnlineTokenSource
    from tt.dit.train import TrainConfig, train
    from tt.ladder import R0_RECIPE, r0_online, score_designs

    online = r0_online()
    train(
        TrainConfig(
            out=str(tmp_path / "r0"), device="cpu", checkpoint_every=R0_RECIPE["steps"], online=online, **R0_RECIPE
        )
    )
    # Scored with 20 DDIM steps, eta 0, one sample per pair (`tt predict --num-steps 20`; the
    # design given to the dynamics task, the default for a model trained on it).
    trained = load_model(tmp_path / "r0")
    designs, motions = OnlineTokenSource(online, device="cpu").draw(0)
    score = score_designs(trained, designs, motions, num_steps=20)
    assert score.estimator_pooled > 0.99  # the 8-step estimate itself is not what limits r
    assert score.pooled >= 0.95, f"R0: pooled r {score.pooled:.3f}, within-motion {np.round(score.within, 2)}"


@pytest.mark.parametrize("reward", ["tracking_velocity", "tracking_torque", "tracking_size"])
def test_estimator_of_an_effort_or_size_reward_is_the_simulated_one_on_a_window_long_motion(reward):
    """The 8-step estimator reads the effort and size terms of the same steps and designs as
    the poses (`score_designs`): on a motion no longer than the critic's window every step is
    a query step, so the estimate is the simulated reward itself (float32 rollouts scored in
    float64 against float32: 1e-4 relative)."""
    from tt.dit.checkpoint import default_checkpoint, load_model
    from tt.ladder import heldout_designs, score_designs, validation_motions
    from tt.sim.motions.base import Motion

    trained = load_model(default_checkpoint("viperx", task="dynamics"), device="cpu")
    S = trained.layout.steps
    m = validation_motions("viperx", 1)[0]
    short = Motion(m.name + f"[:{S}]", m.pos[:S], m.quat[:S], m.dt)
    score = score_designs(trained, heldout_designs("viperx", 4), [short], reward, num_steps=2)
    assert np.all(np.isfinite(score.predicted))
    np.testing.assert_allclose(score.estimator, score.simulated, rtol=1e-4, atol=1e-4)
    term = {"tracking_velocity": "velocity", "tracking_torque": "torque"}.get(reward)
    assert score.term == term
    if term is not None:  # the simulated term is the metric of the same episodes
        from tt.baselines.evaluate import evaluate_designs

        ev = evaluate_designs(heldout_designs("viperx", 4), [short], reward)
        np.testing.assert_allclose(score.simulated_term, ev.metrics[term], rtol=1e-6)
        assert np.all(np.isfinite(score.predicted_term)) and np.all(score.predicted_term >= 0)
        # Every step is a query step: the 8-step estimate of the term is the whole episode's.
        np.testing.assert_allclose(score.estimator_term, score.simulated_term, rtol=1e-4)
