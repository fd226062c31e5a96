"""Random search: sample the budget's worth of designs, evaluate them in one batch, keep the best."""

from __future__ import annotations

import time

from tt.baselines.evaluate import evaluate_designs, warm_up_problem
from tt.baselines.problem import Optimizer, Problem, Result, best_of


class RandomSearch(Optimizer):
    """The paper's Random baseline, evaluated as one batched rollout."""

    name = "random"

    def optimize(self, problem: Problem) -> Result:
        designs = problem.design_space.sample(problem.budget, seed=problem.seed)
        warmup_seconds = warm_up_problem(problem, designs)
        start = time.perf_counter()
        ev = evaluate_designs(
            designs,
            problem.motions,
            problem.reward,
            backend=problem.backend,
            device=problem.device,
            threads=problem.threads,
        )
        best, best_reward = best_of(designs, ev.objective)
        return Result(
            method=self.name,
            best=best,
            best_reward=best_reward,
            designs=designs,
            rewards=ev.objective,
            seconds=time.perf_counter() - start,
            rollouts=len(designs) * len(problem.motions),
            history=[best_reward],
            info={"backend": problem.backend, "warmup_seconds": warmup_seconds},
        )
