"""CMA-ES over the continuous choices, for sampled discrete choices (the paper's baseline).

Each restart fixes one discrete choice (mount, DoF, joint axes, ...) and runs pycma on that
choice's continuous parameters, normalised to [0, 1] with pycma's bound handling, starting
from the continuous values of the design it was drawn with. The restarts' starting designs
are either drawn at random (``screen=0``, the paper's way) or are the best designs, one per
discrete choice, of a random batch that takes a share ``screen`` of the budget.

Modes. Batched (default): all restarts advance in lock step and every generation's
populations x all motions are one batched rollout on the problem's backend. Sequential
(the paper's way, for comparison): one candidate at a time, its motions one after another
on the MuJoCo + mink oracle. Every restart samples from its own random stream, so the order
of evaluation does not change the candidates: both modes propose the same designs wherever
the backends agree on the rewards.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import cma
import numpy as np

from tt.baselines.evaluate import evaluate_designs, warm_up_problem
from tt.baselines.problem import Optimizer, Problem, Result, best_of
from tt.kernels.errors import TTError
from tt.sim.designs import Design, DesignSpace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CMAESConfig:
    """popsize: candidates per generation (paper: 5). generations: generations per restart
    (paper's data biasing: 3); the budget sets the number of restarts. sigma0: initial step
    size in normalised units (the box is [0, 1] per parameter). screen: share of the budget,
    in [0, 1), spent first on random designs evaluated as one batch; the restarts start from
    the best of them (one per discrete choice). sequential: evaluate one candidate at a time
    on the oracle, as the paper did."""

    popsize: int = 5
    generations: int = 3
    sigma0: float = 0.25
    screen: float = 0.5
    sequential: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.popsize, int) or self.popsize < 2:
            raise TTError(f"CMAESConfig.popsize = {self.popsize!r}; CMA-ES needs an integer >= 2")
        if not isinstance(self.generations, int) or self.generations < 1:
            raise TTError(f"CMAESConfig.generations = {self.generations!r}; must be an integer >= 1")
        if not 0 < self.sigma0 <= 1:
            raise TTError(f"CMAESConfig.sigma0 = {self.sigma0}; must be in (0, 1]")
        if not 0 <= self.screen < 1:
            raise TTError(f"CMAESConfig.screen = {self.screen}; must be in [0, 1)")


class CMAESPlan(NamedTuple):
    """How a budget is spent: `screen` random designs, then `restarts` x `generations` x popsize."""

    restarts: int
    generations: int
    screen: int


def _bounds(space: DesignSpace, discrete: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    params = space.continuous_params(discrete)
    return np.array([p.low for p in params]), np.array([p.high for p in params])


def _decode(space: DesignSpace, discrete: tuple[int, ...], x: np.ndarray) -> Design:
    lo, hi = _bounds(space, discrete)
    values = lo + np.clip(x, 0.0, 1.0) * (hi - lo)
    return Design(space.name, discrete, tuple(float(v) for v in values))


def _encode(space: DesignSpace, design: Design) -> np.ndarray:
    lo, hi = _bounds(space, design.discrete)
    return np.clip((np.asarray(design.continuous) - lo) / (hi - lo), 0.0, 1.0)


def _strategy(x0: np.ndarray, sigma0: float, popsize: int, rng: np.random.Generator) -> cma.CMAEvolutionStrategy:
    # pycma's own seeding reseeds numpy's global generator; a private `randn` keeps each
    # restart on its own stream and leaves the caller's global state alone.
    opts = {
        "bounds": [0.0, 1.0],
        "popsize": popsize,
        "randn": lambda *shape: rng.standard_normal(shape),
        "seed": float("nan"),
        "verbose": -9,
    }
    return cma.CMAEvolutionStrategy(list(x0), sigma0, opts)


def _starts(
    designs: Sequence[Design], objective: np.ndarray, fallback: Sequence[Design], restarts: int
) -> list[Design]:
    """The best design of each discrete choice among `designs`, best first, `restarts` of them
    (topped up from `fallback` when the batch holds fewer discrete choices)."""
    order = np.argsort(-np.where(np.isfinite(objective), objective, -np.inf), kind="stable")
    starts: list[Design] = []
    seen: set[tuple[int, ...]] = set()
    for i in order:
        if designs[i].discrete not in seen and len(starts) < restarts:
            seen.add(designs[i].discrete)
            starts.append(designs[i])
    for d in fallback:
        if len(starts) == restarts:
            break
        if d.discrete not in seen:
            seen.add(d.discrete)
            starts.append(d)
    starts += list(fallback[: restarts - len(starts)])
    return starts


#: Smallest step size [normalised units] a proposal spread may set: below it, a restart
#: cannot move off a prior that is confidently wrong.
MIN_SIGMA = 0.05


def _spread(space: DesignSpace, proposals: Sequence[Design], start: Design, sigma0: float) -> float:
    """Step size of a restart from the proposals of its discrete choice (see `CMAES.optimize`)."""
    same = [_encode(space, d) for d in proposals if d.discrete == start.discrete]
    if len(same) < 2 or not same[0].size:
        return sigma0
    return float(np.clip(np.std(np.stack(same), axis=0).mean(), MIN_SIGMA, sigma0))


class CMAES(Optimizer):
    """CMA-ES with restarts over sampled discrete choices; see the module docstring."""

    name = "cmaes"

    def __init__(self, config: CMAESConfig = CMAESConfig()):
        self.config = config

    def plan(self, problem: Problem) -> CMAESPlan:
        """How the budget is spent; raises ValueError if it is below one population."""
        c = self.config
        if problem.budget < c.popsize:
            raise TTError(
                f"budget {problem.budget} is below the CMA-ES population size {c.popsize}; "
                f"give --budget >= {c.popsize} or a smaller population"
            )
        generations = min(c.generations, problem.budget // c.popsize)
        per_restart = c.popsize * generations
        restarts = max(1, int((1.0 - c.screen) * problem.budget) // per_restart)
        screen = problem.budget - restarts * per_restart if c.screen > 0 else 0
        return CMAESPlan(restarts, generations, screen)

    def evaluate(self, problem: Problem, designs: Sequence[Design]) -> np.ndarray:
        """Objective (mean reward over the problem's motions) of each design, (D,): one batched
        rollout, or in the sequential mode one oracle rollout after another."""
        if not self.config.sequential:
            ev = evaluate_designs(
                designs,
                problem.motions,
                problem.reward,
                backend=problem.backend,
                device=problem.device,
                threads=problem.threads,
            )
            return ev.objective
        out = []
        for d in designs:
            # The oracle runs one world at a time: this is one candidate, motion after motion.
            r = evaluate_designs([d], problem.motions, problem.reward, backend="mujoco").reward[0]
            out.append(float(np.mean(r)) if all(math.isfinite(v) for v in r) else float("nan"))
        return np.array(out)

    def optimize(self, problem: Problem, *, proposals: Sequence[Design] | None = None) -> Result:
        """Run CMA-ES on `problem`.

        proposals: designs of the problem's space from a learned prior, best first. They
        take the first half (rounded up) of the screening batch, random draws the rest, so
        that a prior that knows nothing costs at most half the screen. Each restart starts
        from the best screened design of its discrete choice; a restart that starts from a
        proposal takes the spread of the proposals of its choice as its step size (mean
        standard deviation of the normalised continuous values, clipped to [MIN_SIGMA,
        sigma0]; sigma0 where the choice has one proposal).
        """
        c = self.config
        plan = self.plan(problem)
        if plan.generations < c.generations:
            log.warning(
                "budget %d is below one CMA-ES restart (%d generations of %d): this run makes %d generation(s), "
                "close to a random search; give a budget of at least %d",
                problem.budget,
                c.generations,
                c.popsize,
                plan.generations,
                c.generations * c.popsize,
            )
        space = problem.design_space
        backend = "mujoco" if c.sequential else problem.backend
        # Every candidate keeps the discrete choice of a design drawn here (a topology), so
        # every kernel the search needs is compiled before the clock starts.
        drawn = space.sample(plan.screen + plan.restarts, seed=problem.seed)
        screened, fallback = drawn[: plan.screen], drawn[plan.screen :]
        if proposals is not None:
            proposals = list(proposals)
            if any(d.space != space.name for d in proposals):
                raise TTError(f"CMA-ES proposals must be designs of space {space.name!r}")
            take = min(len(proposals), -(-plan.screen // 2))
            screened = (proposals[:take] + screened)[: plan.screen]
        warmup_seconds = warm_up_problem(problem, list(screened) + list(fallback), backend=backend)

        start = time.perf_counter()
        all_designs: list[Design] = list(screened)
        all_rewards: list[float] = []
        history: list[float] = []
        if screened:
            objective = self.evaluate(problem, screened)
            all_rewards += list(objective)
            history.append(float(np.nanmax(objective)) if np.isfinite(objective).any() else float("nan"))
            starts = _starts(screened, objective, fallback, plan.restarts)
        else:
            starts = list(fallback)
        streams = np.random.SeedSequence([problem.seed, 0x434D41]).spawn(plan.restarts)
        proposed = {id(d) for d in proposals or ()}  # identity: a start is one of these very objects
        sigmas = [_spread(space, proposals, d, c.sigma0) if id(d) in proposed else c.sigma0 for d in starts]
        strategies = [
            (d.discrete, _strategy(_encode(space, d), sigma, c.popsize, np.random.default_rng(s)))
            for d, sigma, s in zip(starts, sigmas, streams)
        ]

        for g in range(plan.generations):
            asked = [(discrete, es, es.ask()) for discrete, es in strategies]
            batch = [_decode(space, discrete, x) for discrete, _, xs in asked for x in xs]
            objective = self.evaluate(problem, batch)
            k = 0
            for _, es, xs in asked:
                f = objective[k : k + len(xs)]
                # pycma minimises; a diverged candidate (NaN) gets a value worse than any finite one.
                loss = -f
                finite = np.isfinite(loss)
                worst = float(np.max(loss[finite])) + 1.0 if finite.any() else 0.0
                es.tell(xs, [float(v) for v in np.where(finite, loss, worst)])
                k += len(xs)
            all_designs += batch
            all_rewards += list(objective)
            history.append(float(np.nanmax(all_rewards)) if np.isfinite(all_rewards).any() else float("nan"))
            log.info("cmaes generation %d/%d: best %.3f", g + 1, plan.generations, history[-1])

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
            info={
                "restarts": plan.restarts,
                "generations": plan.generations,
                "popsize": c.popsize,
                "screen": plan.screen,
                "sigma0": c.sigma0,
                "backend": backend,
                "warmup_seconds": warmup_seconds,
                "sigmas": [float(v) for v in sigmas],
                "proposals": None if proposals is None else len(proposals),
            },
        )
