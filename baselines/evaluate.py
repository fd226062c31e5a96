"""Batched evaluation of candidate designs: one rollout over designs x motions, one reward."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from tt.guidance.rewards import RewardInputs, get_reward, metrics, robot_mass, robot_size
from tt.sim.designs import Design, get_space
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion


@dataclass
class Evaluation:
    """Scores of D designs on M motions.

    objective: mean reward over motions per design, (D,).
    reward: reward per design and motion, (D, M).
    metrics: per-metric arrays of shape (D, M) (units in `tt.guidance.rewards.METRIC_UNITS`).
    episode: the rollout the scores came from (worlds design-major: w = d * M + m).
    """

    objective: np.ndarray
    reward: np.ndarray
    metrics: dict[str, np.ndarray]
    episode: Episode


def run_rollout(designs: Sequence[Design], motions: Sequence[Motion], *, backend: str, device: str | None) -> Episode:
    """Rollout of every design on every motion with `backend` (design-major worlds)."""
    if backend == "mujoco":
        from tt.sim.validate import oracle_rollout

        return oracle_rollout(list(designs), list(motions))
    from tt.sim.rollout import rollout

    return rollout(list(designs), list(motions), backend=backend, device=device)


def score_episode(ep: Episode, designs: Sequence[Design], motions: Sequence[Motion], reward: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Reward and metrics of each world of `ep`, reshaped to (D, M)."""
    space = designs[0].space
    cfg = get_reward(reward, space)
    sp = get_space(space)
    models = [sp.model(d) for d in designs]
    device = ep.ee_pos.device
    size = robot_size(models).to(device)[ep.design_index.to(device)]
    mass = robot_mass(models).to(device)[ep.design_index.to(device)]
    steps = torch.tensor([m.steps for m in motions], device=device)[ep.motion_index.to(device)]
    inputs = RewardInputs.from_episode(ep, size.to(ep.ee_pos.dtype), mass.to(ep.ee_pos.dtype), motion_steps=steps)
    per_world = metrics(inputs, cfg)
    D, M = len(designs), len(motions)
    out = {k: v.detach().double().cpu().numpy().reshape(D, M) for k, v in per_world.items()}
    return out["reward"], out


def evaluate_designs(
    designs: Sequence[Design],
    motions: Sequence[Motion],
    reward: str,
    *,
    backend: str = "warp",
    device: str | None = None,
) -> Evaluation:
    """Roll out every design on every motion in one batch and score it with `reward`."""
    if not designs:
        raise ValueError("evaluate_designs needs at least one design")
    spaces = {d.space for d in designs}
    if len(spaces) > 1:
        raise ValueError(f"designs from several spaces in one evaluation: {sorted(spaces)}")
    ep = run_rollout(designs, motions, backend=backend, device=device)
    r, m = score_episode(ep, designs, motions, reward)
    return Evaluation(objective=r.mean(axis=1), reward=r, metrics=m, episode=ep)


__all__ = ["Evaluation", "evaluate_designs", "run_rollout", "score_episode"]
