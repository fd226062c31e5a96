"""CMA-ES over the continuous choices, for sampled discrete choices (the paper's baseline).

Each restart draws one discrete choice (mount, DoF, axes, ...) and runs pycma on that
choice's continuous parameters, normalised to [0, 1] with pycma's bound handling. In the
batched mode all restarts advance in lock step and every generation's populations x all
motions are one batched rollout. The sequential mode is the paper's: one candidate at a
time, each motion rolled out on the MuJoCo + mink oracle.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cma
import numpy as np

from tt.baselines.evaluate import evaluate_designs
from tt.baselines.problem import Optimizer, Problem, Result, best_of
from tt.sim.designs import Design, DesignSpace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CMAESConfig:
    """popsize: candidates per generation (paper: 5). generations: generations per restart
    (paper's data biasing: 3). sigma0: initial step size in normalised units. sequential:
    evaluate one candidate at a time on the oracle, as the paper did."""

    popsize: int = 5
    generations: int = 3
    sigma0: float = 0.25
    sequential: bool = False

    def __post_init__(self) -> None:
        if self.popsize < 2:
            raise ValueError(f"CMAESConfig.popsize = {self.popsize}; CMA-ES needs at least 2")
        if self.generations < 1:
            raise ValueError(f"CMAESConfig.generations = {self.generations}; must be >= 1")
        if not 0 < self.sigma0 <= 1:
            raise ValueError(f"CMAESConfig.sigma0 = {self.sigma0}; must be in (0, 1]")


def _decode(space: DesignSpace, discrete: tuple[int, ...], x: np.ndarray) -> Design:
    params = space.continuous_params(discrete)
    lo = np.array([p.low for p in params])
    hi = np.array([p.high for p in params])
    values = lo + np.clip(x, 0.0, 1.0) * (hi - lo)
    return Design(space.name, discrete, tuple(float(v) for v in values))


def _encode(space: DesignSpace, design: Design) -> np.ndarray:
    params = space.continuous_params(design.discrete)
    lo = np.array([p.low for p in params])
    hi = np.array([p.high for p in params])
    return (np.asarray(design.continuous) - lo) / (hi - lo)


class CMAES(Optimizer):
    """CMA-ES with restarts over sampled discrete choices; see the module docstring."""

    name = "cmaes"

    def __init__(self, config: CMAESConfig = CMAESConfig()):
        self.config = config

    def plan(self, problem: Problem) -> tuple[int, int]:
        """(restarts, generations) that fit the budget; raises if the budget is below one population."""
        c = self.config
        if problem.budget < c.popsize:
            raise ValueError(
                f"budget {problem.budget} is below the CMA-ES population size {c.popsize}; "
                f"give --budget >= {c.popsize} or a smaller population"
            )
        generations = min(c.generations, problem.budget // c.popsize)
        restarts = max(1, problem.budget // (c.popsize * generations))
        return restarts, generations

    def optimize(self, problem: Problem) -> Result:
        c = self.config
        restarts, generations = self.plan(problem)
        space = problem.design_space
        start = time.perf_counter()
        # Each restart's discrete choice and initial mean come from one seeded draw.
        seeds = space.sample(restarts, seed=problem.seed)
        strategies = []
        for k, d in enumerate(seeds):
            x0 = _encode(space, d)
            opts = {"bounds": [0.0, 1.0], "popsize": c.popsize, "seed": problem.seed * 1000 + k + 1, "verbose": -9}
            strategies.append((d.discrete, cma.CMAEvolutionStrategy(x0, c.sigma0, opts)))

        all_designs: list[Design] = []
        all_rewards: list[float] = []
        history: list[float] = []
        for g in range(generations):
            asked = [(discrete, es, es.ask()) for discrete, es in strategies]
            batch = [_decode(space, discrete, x) for discrete, _, xs in asked for x in xs]
            if c.sequential:
                objective = np.array([self._evaluate_one(problem, d) for d in batch])
            else:
                ev = evaluate_designs(batch, problem.motions, problem.reward, backend=problem.backend, device=problem.device)
                objective = ev.objective
            k = 0
            for _, es, xs in asked:
                f = objective[k : k + len(xs)]
                # pycma minimises; a diverged candidate (NaN) gets the worst finite value.
                loss = np.where(np.isfinite(f), -f, np.inf)
                finite_max = np.max(loss[np.isfinite(loss)]) if np.isfinite(loss).any() else 0.0
                es.tell(xs, list(np.where(np.isfinite(loss), loss, finite_max + 1.0)))
                k += len(xs)
            all_designs += batch
            all_rewards += list(objective)
            history.append(float(np.nanmax(all_rewards)))
            log.info("cmaes generation %d/%d: best %.3f", g + 1, generations, history[-1])

        rewards = np.array(all_rewards)
        best, best_reward = best_of(all_designs, rewards)
        return Result(
            method=self.name + ("-sequential" if c.sequential else ""),
            best=best,
            best_reward=best_reward,
            designs=all_designs,
            rewards=rewards,
            seconds=time.perf_counter() - start,
            rollouts=len(all_designs) * len(problem.motions),
            history=history,
            info={"restarts": restarts, "generations": generations, "popsize": c.popsize},
        )

    @staticmethod
    def _evaluate_one(problem: Problem, design: Design) -> float:
        """The paper's way: one candidate, one motion at a time, on the oracle."""
        rewards = [evaluate_designs([design], [m], problem.reward, backend="mujoco").objective[0] for m in problem.motions]
        return float(np.mean(rewards)) if all(math.isfinite(r) for r in rewards) else float("nan")
