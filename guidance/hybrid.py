"""Learned prior + batched simulator: optimizers that use both the model and tt's rollouts.

The paper ranks the model's candidates with the model alone, because its simulator is
slow. tt's batched rollouts check a hundred candidates in about a second on a CPU, so the
hybrids here let the simulator have the last word:

* `SimVerified` (``zeroth-sim``, ``dgs-sim``): the model samples n candidates (plain, or
  with Dynamics Self-Guidance) and ranks them by predicted reward; the top k that decode
  (``verify``; all n by default) are rolled out in one batch, and the best *simulated* one
  wins. The result's info holds both rewards of every verified candidate.
* `ModelInitCMAES` (``cmaes --init model``): the model's samples, best predicted first,
  replace CMA-ES's random screening batch: they are simulated, each restart starts from
  the best of its discrete choice, with a step size from the spread of the model's samples
  of that choice (`tt.baselines.CMAES.optimize`'s ``proposals``); then the usual batched
  CMA-ES runs, at the same rollout budget as plain CMA-ES.

Both degrade gracefully: with a model that knows nothing, the decoded samples are designs
scattered over the space, so `SimVerified` is best-of-k random search and `ModelInitCMAES`
is CMA-ES with a random screen. Several motions make one multi-trajectory problem, as for
every optimizer: the model composes them, the simulator averages the reward over them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from tt.baselines.cmaes import CMAES, CMAESConfig
from tt.baselines.evaluate import evaluate_designs, warm_up_problem
from tt.baselines.problem import Optimizer, Problem, Result, best_of
from tt.guidance.zeroth import ZerothOrder, learned_result
from tt.kernels.errors import TTError


@dataclass(frozen=True)
class VerifyConfig:
    """verify: candidates (best predicted first) the simulator checks; None: all sampled."""

    verify: int | None = None

    def __post_init__(self) -> None:
        if self.verify is not None and (not isinstance(self.verify, (int, np.integer)) or self.verify < 1):
            raise TTError(f"verify = {self.verify!r}; must be an integer >= 1")


class SimVerified(Optimizer):
    """A learned sampler whose top candidates the batched simulator verifies (see the module).

    sampler: the `ZerothOrder` (or `DynamicsSelfGuidance`) that proposes; config: `VerifyConfig`.
    """

    def __init__(self, sampler: ZerothOrder, config: VerifyConfig = VerifyConfig()):
        self.sampler = sampler
        self.config = config
        self.name = f"{sampler.name}-sim"

    def optimize(self, problem: Problem) -> Result:
        n = self.sampler.config.samples or problem.budget
        k = self.config.verify or n
        if k > n:
            raise TTError(f"verify = {k} is larger than samples = {n}: the simulator can only check sampled candidates")
        start = time.perf_counter()
        gen, decoder, info = self.sampler.generate(problem)
        ranking = self.sampler.rank(gen, decoder, limit=k)
        order = [i for i in ranking.order if i in ranking.decoded and ranking.decoded[i].design is not None][:k]
        if not order:
            # No candidate decoded: learned_result raises with the decoder's reasons.
            return learned_result(self.name, problem, gen, ranking, time.perf_counter() - start)
        designs = [ranking.decoded[i].design for i in order]
        sample_seconds = time.perf_counter() - start
        # Compiling the verified designs' kernels is a one-off cost of the process, as for
        # CMA-ES and Random; it is reported, not counted in the optimize time.
        compile_seconds = warm_up_problem(problem, designs)
        verify_start = time.perf_counter()
        ev = evaluate_designs(designs, problem.motions, problem.reward, backend=problem.backend, device=problem.device)
        seconds = sample_seconds + time.perf_counter() - verify_start
        best, best_reward = best_of(designs, ev.objective)
        predicted = gen.objective[order]
        finite = np.isfinite(ev.objective) & np.isfinite(predicted)
        p_, s_ = predicted[finite], ev.objective[finite]
        # Pearson r needs two spreads; a model that predicts one value for all has none.
        r = float(np.corrcoef(p_, s_)[0, 1]) if p_.size > 2 and p_.std() > 0 and s_.std() > 0 else float("nan")
        result = learned_result(
            self.name, problem, gen, ranking, seconds, rollouts=len(designs) * len(problem.motions), info=info
        )
        result.info.update(
            {
                "verified": len(designs),
                "verified_candidates": order,
                "verified_predicted": [float(v) for v in predicted],
                "verified_simulated": [float(v) for v in ev.objective],
                "predicted_vs_simulated_r": r,
                "verify_seconds": seconds - sample_seconds,
                "compile_seconds": compile_seconds,
                # Where the simulator's pick stood in the model's ranking (0: the model's own pick).
                "best_predicted_rank": int(np.argmax(np.where(np.isfinite(ev.objective), ev.objective, -np.inf))),
            }
        )
        return Result(
            method=self.name,
            best=best,
            best_reward=best_reward,
            designs=designs,
            rewards=np.asarray(ev.objective, dtype=np.float64),
            seconds=seconds,
            rollouts=result.rollouts,
            history=[float(ev.objective[0]), best_reward],
            info=result.info,
        )


class ModelInitCMAES(Optimizer):
    """CMA-ES whose screening batch and step sizes come from the model's samples (see the module).

    sampler: the `ZerothOrder` that proposes (its ``samples``: how many it draws, default the
    CMA-ES screen size); cmaes: the CMA-ES settings (``screen`` > 0: the share of the budget
    that verifies the model's samples).
    """

    name = "cmaes-init-model"

    def __init__(self, sampler: ZerothOrder, cmaes: CMAESConfig = CMAESConfig()):
        if cmaes.sequential:
            raise TTError("cmaes --init model runs the batched CMA-ES; drop --sequential")
        if cmaes.screen <= 0:
            raise TTError(
                "cmaes --init model needs a screening share (CMAESConfig.screen > 0) to verify the model's samples"
            )
        self.sampler = sampler
        self.cmaes = CMAES(cmaes)

    def optimize(self, problem: Problem) -> Result:
        plan = self.cmaes.plan(problem)
        n = self.sampler.config.samples or plan.screen
        start = time.perf_counter()
        # The sampler reads its sample count from the problem's budget when it has none.
        gen, decoder, info = self.sampler.generate(replace(problem, budget=n))
        ranking = self.sampler.rank(gen, decoder, limit=n)
        proposals = [
            ranking.decoded[i].design
            for i in ranking.order
            if i in ranking.decoded and ranking.decoded[i].design is not None
        ]
        sample_seconds = time.perf_counter() - start
        result = self.cmaes.optimize(problem, proposals=proposals)
        result.method = self.name
        result.seconds += sample_seconds
        result.info.update(
            {
                "model_samples": n,
                "model_decoded": len(proposals),
                "sample_seconds": sample_seconds,
                "model_structures": len({d.discrete for d in proposals}),
                **{f"sampler_{k}": v for k, v in info.items()},
            }
        )
        return result


__all__ = ["ModelInitCMAES", "SimVerified", "VerifyConfig"]
