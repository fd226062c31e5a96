"""Does the model know what a design does? Predicted against simulated reward, rung by rung.

The learnability ladder (issue "The model learns what designs do"):

* R0, memorize: a small model overfits the 64 episodes of one online refresh (16 designs
  of ``viperx-nominal`` x 4 training motions) and `tt predict` on those same designs x
  motions must correlate with their simulated rewards at r >= 0.95 (`tests/test_ladder.py`).
  A failure there is a bug in the predict -> reward path, not a lack of compute.
* R1, one structure (``viperx-nominal``) and R2, the full ``viperx`` space: held-out
  designs x validation motions (`benchmarks/dit_ladder.py`).

`score_designs` runs `tt predict`'s code path (`tt.guidance.predicted.predict_designs`) and
the simulator (`tt.baselines.evaluate.evaluate_designs`) on the same designs x motions and
reports both kinds of correlation: pooled over every pair (motion difficulty feeds it, as in
the paper's figure) and within each motion (what ranking candidates for one motion needs),
beside the ceiling of the 8-step reward estimate itself (the same estimator on the simulated
poses at the query's steps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from tt.guidance.predicted import CRITIC_DDIM_STEPS
from tt.kernels.errors import TTError

#: Seed offset of held-out designs: far from every seed a training run or `tt generate` draws
#: designs with (`tt.tokens.draws` and `tt.dit.online` hash (seed, index, stream)).
HELDOUT_SEED = 90_001


#: R0's training choices shared by every row of `benchmarks/dit_recipe.py`.
R0_TRAINING = dict(size="tiny", batch_size=32, lr=5e-3, warmup_steps=50, type_weights={"track_link_obs": 4.0})
#: R0's recipe (`tests/test_ladder.py`; the ``x0`` row of `benchmarks/results/dit_recipe.md`):
#: the dynamics task, x0 prediction, the default sinusoidal time-step IDs, 2,000 steps. The
#: damped start posture (2026-12-03) made more of R0's 16 designs survive, so the rewards to
#: tell apart are closer together: 1,000 steps then gave r 0.92, 2,000 give 0.997.
R0_RECIPE = dict(R0_TRAINING, steps=2000, task="dynamics", prediction="x0")


def r0_online():
    """R0's data: the 64 episodes of one online refresh, 16 ``viperx-nominal`` designs x 4
    augmented training motions, no control perturbation, terminated episodes kept to the
    motion's end (`tt.dit.online.OnlineConfig`; refresh 0 only)."""
    from tt.dit.online import OnlineConfig

    return OnlineConfig(
        space="viperx-nominal",
        designs=16,
        motions=4,
        refresh_every=10**9,
        buffer=1,
        action_noise=0.0,
        min_steps=8,
        seed=0,
        absorbing=True,
    )


def validation_motions(space: str, count: int | None = None) -> list:
    """`count` validation motions of the space's end-effector count, spread over the skills
    (every one for None), placed for the space."""
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, motion_set

    val = motion_set("val", arms=get_space(space).ee_count)
    if count is not None:
        if count < 1:
            raise TTError(f"count must be >= 1, got {count}")
        stride = max(1, len(val) // count)
        val = val[::stride][:count]
    return for_space(val, space)


def heldout_designs(space: str, count: int, seed: int = 0) -> list:
    """`count` designs of the space that no training draw holds (plain `DesignSpace.sample`
    with seed ``HELDOUT_SEED + seed``)."""
    from tt.sim.designs import get_space

    return get_space(space).sample(count, seed=HELDOUT_SEED + seed)


def pearson(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson r of two 1-D arrays over their finite pairs (NaN for fewer than 3 or no spread)."""
    x, y = np.asarray(x, np.float64).ravel(), np.asarray(y, np.float64).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def within_motion(predicted: np.ndarray, simulated: np.ndarray) -> list[float]:
    """Pearson r over designs, per motion: columns of (D, M) arrays."""
    return [pearson(predicted[:, j], simulated[:, j]) for j in range(predicted.shape[1])]


@dataclass
class LadderScore:
    """Predicted vs simulated reward of D designs x M motions.

    predicted, simulated, estimator: (D, M) rewards: the model's, the simulator's, and the
    8-step estimate on the simulated poses (the estimator's ceiling); predicted_error,
    simulated_error: (D, M) mean position error [cm] at the query's steps, counted or not,
    of the predicted and the simulated end effector; motions: names;
    pooled: r over all pairs; within: r per motion; estimator_pooled / estimator_within: the
    same for the estimator; seconds: predict and simulate wall times; term: the reward's
    effort metric (``torque`` or ``velocity``: mean actuator force or speed norm over the
    counted steps, `tt.sim.rewards.metrics`) or None, with its predicted and simulated
    values and its 8-step estimate on the simulated poses (the ceiling), (D, M): whether the
    model knows the effort, apart from the tracking that dominates the reward.
    """

    predicted: np.ndarray
    simulated: np.ndarray
    estimator: np.ndarray
    motions: list[str]
    pooled: float
    within: list[float]
    estimator_pooled: float
    estimator_within: list[float]
    predicted_error: np.ndarray
    simulated_error: np.ndarray
    seconds: dict[str, float] = field(default_factory=dict)
    term: str | None = None
    predicted_term: np.ndarray | None = None
    simulated_term: np.ndarray | None = None
    estimator_term: np.ndarray | None = None

    @property
    def term_pooled(self) -> float:
        """Pooled r of the predicted against the simulated effort term (nan without one)."""
        return float("nan") if self.term is None else pearson(self.predicted_term, self.simulated_term)

    @property
    def term_within(self) -> list[float]:
        """Within-motion r of the effort term (empty without one)."""
        return [] if self.term is None else within_motion(self.predicted_term, self.simulated_term)

    @property
    def estimator_term_within(self) -> list[float]:
        """Within-motion r of the effort term's 8-step estimate on the simulated episode
        against the whole episode's: the ceiling of `term_within` (empty without a term)."""
        return [] if self.term is None else within_motion(self.estimator_term, self.simulated_term)

    @property
    def within_mean(self) -> float:
        """Mean within-motion r (over motions where it is defined)."""
        v = [r for r in self.within if np.isfinite(r)]
        return float(np.mean(v)) if v else float("nan")

    def to_dict(self) -> dict:
        return {
            "motions": self.motions,
            "pooled_r": self.pooled,
            "within_r": self.within,
            "within_r_mean": self.within_mean,
            "estimator_pooled_r": self.estimator_pooled,
            "estimator_within_r": self.estimator_within,
            "predicted": self.predicted.tolist(),
            "simulated": self.simulated.tolist(),
            "estimator": self.estimator.tolist(),
            "predicted_error_cm": self.predicted_error.tolist(),
            "simulated_error_cm": self.simulated_error.tolist(),
            "seconds": self.seconds,
        } | (
            {}
            if self.term is None
            else {
                "term": self.term,
                "term_pooled_r": self.term_pooled,
                "term_within_r": self.term_within,
                "predicted_term": self.predicted_term.tolist(),
                "simulated_term": self.simulated_term.tolist(),
                "estimator_term": self.estimator_term.tolist(),
                "estimator_term_pooled_r": pearson(self.estimator_term, self.simulated_term),
                "estimator_term_within_r": self.estimator_term_within,
            }
        )


def score_designs(
    trained,
    designs: Sequence,
    motions: Sequence,
    reward: str = "tracking",
    *,
    samples: int = 1,
    num_steps: int | None = CRITIC_DDIM_STEPS,
    seed: int = 0,
    chunk: int | None = None,
    backend: str | None = None,
    device: str | None = None,
    via: str | None = None,
) -> LadderScore:
    """`tt predict` and the simulator on `designs` x `motions` (see the module docstring).

    trained: `tt.dit.checkpoint.TrainedModel`; designs: of the checkpoint's space; motions:
    placed for it; samples, num_steps, seed, chunk, via: `tt.guidance.predicted.predict_designs`;
    backend, device: the simulator's (`tt.baselines.evaluate.evaluate_designs`; backend None: the space's).
    """
    import time

    import torch

    from tt.baselines.evaluate import evaluate_designs
    from tt.guidance.predicted import predict_designs, query_position_error, query_steps, scored_steps
    from tt.report import REWARD_METRIC
    from tt.sim.rewards import RewardInputs, get_reward, metrics

    designs, motions = list(designs), list(motions)
    cfg = get_reward(reward, designs[0].space)
    t0 = time.perf_counter()
    pred = predict_designs(
        trained, designs, motions, cfg, samples=samples, num_steps=num_steps, seed=seed, chunk=chunk, via=via
    )
    t1 = time.perf_counter()
    ev = evaluate_designs(designs, motions, reward, backend=backend, device=device)
    t2 = time.perf_counter()
    ep, D = ev.episode, len(designs)
    estimator = np.zeros((D, len(motions)))
    metric = REWARD_METRIC.get(cfg.name)
    term = metric[0] if metric and metric[0] in ("torque", "velocity") else None  # what the model predicts
    estimator_term = np.zeros((D, len(motions)))
    simulated_error = np.zeros((D, len(motions)))
    S = trained.layout.steps
    world = torch.full((D, len(motions)), -1, dtype=torch.long)
    world[ep.design_index.cpu(), ep.motion_index.cpu()] = torch.arange(len(ep.design_index))
    for j, m in enumerate(motions):
        n = scored_steps(m.steps, S)  # a motion shorter than the window: its own steps only
        st = query_steps(m.steps, S, 1)[0][:n].to(ep.ee_pos.device)
        w = world[:, j].to(ep.ee_pos.device)
        # The effort and size terms read the same steps and designs as the poses.
        steps_of = {k: getattr(ep, k)[w][:, st].double() for k in ("act_force", "act_vel") if k in cfg.needs}
        design_of = {
            k: torch.as_tensor(ev.metrics[k][:, j], dtype=torch.float64, device=ep.ee_pos.device)
            for k in ("size", "mass")
            if k in cfg.needs
        }
        inputs = RewardInputs(
            ep.ee_pos[w][:, st].double(),
            ep.ee_quat[w][:, st].double(),
            ep.target_pos[w][:, st].double(),
            ep.target_quat[w][:, st].double(),
            **steps_of,
            **design_of,
        )
        estimate = metrics(inputs, cfg)  # the reward and its effort term from one evaluation
        estimator[:, j] = (m.steps / n) * estimate["reward"].cpu().numpy()
        if term is not None:
            estimator_term[:, j] = estimate[term].cpu().numpy()
        simulated_error[:, j] = query_position_error(inputs.ee_pos, inputs.target_pos).cpu().numpy()
    return LadderScore(
        pred.reward,
        ev.reward,
        estimator,
        [m.name for m in motions],
        pearson(pred.reward, ev.reward),
        within_motion(pred.reward, ev.reward),
        pearson(estimator, ev.reward),
        within_motion(estimator, ev.reward),
        pred.metrics["query_pos_err"],
        simulated_error,
        {"predict": t1 - t0, "simulate": t2 - t1},
        term,
        None if term is None else pred.metrics[term],
        None if term is None else ev.metrics[term],
        None if term is None else estimator_term,
    )


__all__ = [
    "HELDOUT_SEED",
    "R0_RECIPE",
    "R0_TRAINING",
    "r0_online",
    "LadderScore",
    "heldout_designs",
    "pearson",
    "score_designs",
    "validation_motions",
    "within_motion",
]
