"""Critic refinement: the decoded design climbs the dynamics critic's predicted reward.

Critic guidance in token space (`tt.guidance.critic_grad`) steers x0_hat, which decodes to a
design only by projection onto another structure at almost every step, and a critic told
the episode's start sees a change of the design only through its tokens, not through the
start it moves (`benchmarks/results/critic_start.md`: the critic's differences follow the
simulator's at r = 0.82 with the start re-simulated, 0.28 with it held fixed). Once sampling
has ended the candidate is a real design, and both problems go away: its continuous choices
c (link lengths, masses, gains, mount offsets, in units of each choice's range) climb

    J(c) = the critic's predicted reward of the design, mean over the problem's motions

(`tt.guidance.predicted.predict_designs`, each design's first control step re-simulated,
as `tt predict` asks), with its gradient by central differences over c (half step
``rel_step``, `tt.guidance.stencil`: a step that would leave the range is cut at the bound), and a line search
along g / max|g| over ``step_sizes`` (the largest move of one choice). A step is taken only
when it raises J, and, with ``check`` (the default), also J under a second, independent
draw of the critic's noise: a climb that only exploits the one draw it was searched with
is not taken. The design stops at the first iteration no step is taken. The discrete
choices (structure, axes, mount) stay as sampled.

Every prediction of one call is sampled from the same starting noise per motion and
sample (``common_noise``), so J is a deterministic function of the design and its central
differences measure the design, not the sampling noise. The simulator only runs each
design's first control step (the critic's start); the reward itself is never simulated.
All designs of a call go through one prediction per stage: (1 + 2 p) per design for the
gradient, ``len(step_sizes)`` for the line search and, with ``check``, 2 per design whose
line search found a step.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from tt.dit.checkpoint import TrainedModel
from tt.guidance.critic_grad import NO_TERMINATION
from tt.guidance.predicted import CRITIC_DDIM_STEPS, predict_designs
from tt.guidance.stencil import central_points, choice_bounds
from tt.kernels.errors import TTError
from tt.sim.designs import Design, get_space
from tt.sim.motions import Motion
from tt.sim.rewards import RewardConfig


@dataclass(frozen=True)
class RefineConfig:
    """iterations: gradient steps at most per design; rel_step: half step of the central
    differences, a share of each choice's range; step_sizes: line-search steps, the move of
    the choice with the largest gradient entry as a share of its range (the others move in
    proportion); samples: critic predictions averaged per design and motion; num_steps: the
    critic's DDIM steps; terminate: keep the reward's termination in J (False: every query
    step counts, as critic guidance's gradient does, `tt.guidance.critic_grad.NO_TERMINATION`;
    a design predicted to stop at its first step then still has a slope); check: a step must
    also raise J under a second noise draw (module docstring). (Climbing the reward's smooth
    log stand-in instead lost to the reward: docs/experiments.md.)
    """

    iterations: int = 5
    rel_step: float = 0.02
    step_sizes: tuple[float, ...] = (0.02, 0.05, 0.1, 0.2)
    samples: int = 1
    num_steps: int = CRITIC_DDIM_STEPS
    terminate: bool = False
    check: bool = True

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise TTError(f"iterations = {self.iterations}; must be >= 1")
        if not 0 < self.rel_step < 0.5:
            raise TTError(f"rel_step = {self.rel_step}; must be in (0, 0.5)")
        if not self.step_sizes or not all(0 < s <= 1 for s in self.step_sizes):
            raise TTError(f"step_sizes = {self.step_sizes}; give at least one, each in (0, 1]")
        if self.samples < 1:
            raise TTError(f"samples = {self.samples}; must be >= 1")
        if self.num_steps < 1:
            raise TTError(f"num_steps = {self.num_steps}; must be >= 1")


@dataclass
class Refined:
    """What `refine_designs` did to N designs.

    designs: the refined designs, in input order; before / after: J of the given and the
    refined designs, (N,); steps: accepted steps per design, (N,); trace: per design, J after
    each accepted step (starting with J before); predictions: design x motion predictions
    asked in all; seconds: wall time.
    """

    designs: list[Design]
    before: np.ndarray
    after: np.ndarray
    steps: np.ndarray
    trace: list[list[float]] = field(default_factory=list)
    predictions: int = 0
    seconds: float = 0.0

    def summary(self) -> dict:
        return {
            "before": self.before.tolist(),
            "after": self.after.tolist(),
            "steps": self.steps.tolist(),
            "trace": self.trace,
            "predictions": self.predictions,
            "seconds": self.seconds,
        }


def _unit(space, design: Design) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, low, span): the design's continuous choices in units of their ranges, and the ranges."""
    low, high = choice_bounds(space, design)
    span = high - low
    u = (np.asarray(design.continuous, dtype=np.float64) - low) / np.where(span > 0, span, 1.0)
    return np.clip(u, 0.0, 1.0), low, span


def refine_designs(
    critic: TrainedModel,
    designs: Sequence[Design],
    motions: Sequence[Motion],
    cfg: RewardConfig,
    config: RefineConfig = RefineConfig(),
    *,
    seed: int = 0,
    device=None,
) -> Refined:
    """Refine N designs of one space along the critic's central-difference gradient (module docstring).

    critic: a model trained on the dynamics task of the designs' space (`predict_designs`
    checks the space); designs: N designs; motions: M motions placed for the space; cfg: the
    reward; seed: of the critic's (common) sampling noise; device: torch device (None: the
    critic's). Raises ValueError for no designs or designs of several spaces.
    """
    start = time.perf_counter()
    designs, motions = list(designs), list(motions)
    if not designs:
        raise TTError("refine needs at least one design")
    spaces = sorted({d.space for d in designs})
    if len(spaces) > 1:
        raise TTError(f"designs from several spaces in one call: {spaces}")
    space = get_space(spaces[0])
    if not config.terminate:
        cfg = dataclasses.replace(cfg, threshold=NO_TERMINATION)
    units = [_unit(space, d) for d in designs]
    u = [x[0] for x in units]

    def make(i: int, x: np.ndarray) -> Design:
        _, low, span = units[i]
        return Design(designs[i].space, designs[i].discrete, tuple(float(v) for v in low + np.clip(x, 0.0, 1.0) * span))

    asked = 0

    def judge(batch: list[Design], draw: int = seed) -> np.ndarray:
        nonlocal asked
        asked += len(batch) * len(motions)
        pred = predict_designs(
            critic,
            batch,
            motions,
            cfg,
            samples=config.samples,
            num_steps=config.num_steps,
            seed=draw,
            device=device,
            via="dynamics",
            common_noise=True,
        )
        value = pred.reward.mean(axis=1)
        return np.where(np.isfinite(value), value, -np.inf)

    n = len(designs)
    h = config.rel_step
    active = list(range(n))
    before = np.full(n, np.nan)
    current = np.full(n, np.nan)
    steps = np.zeros(n, dtype=np.int64)
    trace: list[list[float]] = [[] for _ in range(n)]
    for _ in range(config.iterations):
        if not active:
            break
        # Gradient: the centre and a +/- pair per choice, cut at the bounds.
        batch, pairs = [], []
        for i in active:
            points, width = central_points(u[i], h, 0.0, 1.0)
            batch += [make(i, u[i])] + [make(i, x) for x in points]
            pairs.append(width)
        values = judge(batch)
        directions, at = {}, 0
        for i, width in zip(active, pairs):
            p = len(u[i])
            centre, plus, minus = values[at], values[at + 1 : at + 1 + 2 * p : 2], values[at + 2 : at + 1 + 2 * p : 2]
            at += 1 + 2 * p
            if np.isnan(before[i]):
                before[i] = centre
                trace[i].append(float(centre))
            current[i] = centre
            with np.errstate(invalid="ignore", divide="ignore"):
                g = np.where((width > 0) & np.isfinite(plus) & np.isfinite(minus), (plus - minus) / width, 0.0)
            if np.isfinite(centre) and np.any(g != 0):
                directions[i] = g / np.abs(g).max()
        # Line search along each direction, in one prediction.
        moving = [i for i in active if i in directions]
        if not moving:
            break
        trial = [np.clip(u[i] + a * directions[i], 0.0, 1.0) for i in moving for a in config.step_sizes]
        values = judge([make(i, x) for i, x in zip([i for i in moving for _ in config.step_sizes], trial)])
        k = len(config.step_sizes)
        picks = {}
        for r, i in enumerate(moving):
            best = int(np.argmax(values[r * k : (r + 1) * k]))
            if values[r * k + best] > current[i]:
                picks[i] = r * k + best
        if config.check and picks:
            # The same comparison under another draw of the noise (seeds 2^31 apart do not meet).
            again = judge([make(i, x) for i, t in picks.items() for x in (u[i], trial[t])], draw=seed + 2**31)
            picks = {i: t for r, (i, t) in enumerate(picks.items()) if again[2 * r + 1] > again[2 * r]}
        for i, t in picks.items():
            u[i] = trial[t]
            current[i] = values[t]
            steps[i] += 1
            trace[i].append(float(current[i]))
        active = list(picks)
    return Refined([make(i, u[i]) for i in range(n)], before, current, steps, trace, asked, time.perf_counter() - start)


__all__ = ["RefineConfig", "Refined", "refine_designs"]
