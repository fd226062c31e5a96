"""The optimizer interface every design method in tt shares.

A `Problem` is a design space, one or more target motions, a reward, a budget and a seed.
An `Optimizer` turns a problem into a `Result` with ``optimize(problem)``; the learned
methods (Zeroth-Order, Dynamics Self-Guidance) implement the same interface, so
`tt optimize` and the benchmarks treat every method alike.

Budget: the number of candidate designs whose rollouts the method may run, per motion.
A method that needs no rollouts (a learned sampler) reads it as its sample count.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from tt.kernels.errors import TTError
from tt.sim.backends import BACKENDS as _ROLLOUT_BACKENDS
from tt.sim.backends import default_backend
from tt.sim.designs import Design, get_space
from tt.sim.motions.base import Motion

#: Rollout backends an optimizer may evaluate candidates with (those `tt.sim.rollout` has).
BACKENDS: tuple[str, ...] = tuple(_ROLLOUT_BACKENDS)


@dataclass(frozen=True)
class Problem:
    """One design optimization problem.

    space: design space name. motions: target motions (all with one dt and the space's
    end-effector count). reward: reward name (`tt.sim.rewards.REWARDS`, or a paper's name of
    `REWARD_ALIASES`, stored as tt's). budget: candidate designs per motion. seed: random
    seed. backend: rollout backend used to evaluate candidates in batches. device:
    Warp/torch device, None for the default.
    threads: CPU threads of the "warp" and "mjbatch" backends' batched rollouts, None for every core.
    progress: say so, with a bar on stderr, when the candidates' kernels must compile before
    the search (`tt.baselines.warm_up`), and show the learned methods' sampling steps; the
    CLI's searches do.
    """

    space: str
    motions: tuple[Motion, ...]
    reward: str
    budget: int
    seed: int = 0
    backend: str | None = None
    device: str | None = None
    threads: int | None = None
    progress: bool = False

    def __post_init__(self) -> None:
        from tt.sim.rewards import get_reward, reward_name

        sp = get_space(self.space)  # raises on an unknown space, listing valid ones
        object.__setattr__(self, "reward", reward_name(self.reward))  # the paper's names become tt's; raises on unknown
        get_reward(self.reward, self.space)
        object.__setattr__(self, "motions", tuple(self.motions))
        if not self.motions:
            raise TTError("Problem.motions is empty; give at least one target motion")
        for m in self.motions:
            if not isinstance(m, Motion):
                raise TTError(f"Problem.motions holds a {type(m).__name__}; expected tt Motion objects")
            if m.arms != sp.ee_count:
                raise TTError(f"motion {m.name!r} has {m.arms} end effector(s); space {self.space!r} has {sp.ee_count}")
        dts = {round(m.dt, 9) for m in self.motions}
        if len(dts) > 1:
            raise TTError(f"motions have different rates (dt {sorted(dts)} s); resample them to one rate")
        if not isinstance(self.budget, (int, np.integer)) or isinstance(self.budget, bool) or self.budget < 1:
            raise TTError(f"Problem.budget = {self.budget!r}; must be an integer >= 1")
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool) or self.seed < 0:
            raise TTError(f"Problem.seed = {self.seed!r}; must be an integer >= 0")
        if self.backend is None:
            object.__setattr__(self, "backend", default_backend(self.space))
        if self.backend not in BACKENDS:
            raise TTError(f"unknown backend {self.backend!r}; valid: {list(BACKENDS)}")
        if self.backend == "warp" and sp.has_contacts:
            raise TTError(
                f"Problem.backend = 'warp' cannot evaluate design space {self.space!r}: it has contacts, which "
                "tt's kernels do not simulate; use 'mujoco' (the oracle), 'mjwarp', or None for the default"
            )
        if self.device is not None:
            from tt.kernels.device import resolve_device

            resolve_device(self.device)  # raises on a device that does not exist, listing valid ones
        if self.threads is not None and (
            not isinstance(self.threads, (int, np.integer)) or isinstance(self.threads, bool) or self.threads < 1
        ):
            raise TTError(f"Problem.threads = {self.threads!r}; must be an integer >= 1, or None for every core")

    @property
    def design_space(self):
        return get_space(self.space)


@dataclass
class Result:
    """What an optimizer returns.

    best: the chosen design. best_reward: its objective (mean reward over the motions, as
    the optimizer measured it). designs / rewards: every candidate evaluated and its
    objective, (n,). seconds: wall time of `optimize`. rollouts: rollouts run (candidates
    x motions). history: best objective after each generation / batch.
    """

    method: str
    best: Design
    best_reward: float
    designs: list[Design]
    rewards: np.ndarray
    seconds: float
    rollouts: int
    history: list[float] = field(default_factory=list)
    info: dict = field(default_factory=dict)


class Optimizer(ABC):
    """A design optimizer: ``result = optimizer.optimize(problem)``."""

    name: str = ""

    @abstractmethod
    def optimize(self, problem: Problem) -> Result:
        """Search the problem's design space within its budget."""


def best_of(designs: Sequence[Design], rewards: np.ndarray) -> tuple[Design, float]:
    """The design with the highest objective (first on ties) and that objective."""
    rewards = np.asarray(rewards, dtype=np.float64)
    finite = np.where(np.isfinite(rewards), rewards, -np.inf)
    i = int(np.argmax(finite))
    return designs[i], float(rewards[i])
