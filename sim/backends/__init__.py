"""Rollout backends by name: one interface (`RolloutBackend`), one resolver, five simulators.

``rollout(designs, motions, backend=name)`` (`tt.sim.rollout`) resolves the designs with
the backend's `resolve` (`tt.sim.backends.base.resolve_designs`, the only design -> model
resolver) and hands the `Robots` to its `run`. The implementations:

| name | simulator | implementation |
|---|---|---|
| ``warp`` | tt's fused Warp kernels, contact-free trees (default) | `tt.sim.rollout` over `tt.kernels.rollout` |
| ``mjwarp`` | MuJoCo-Warp, contacts too; the batched reference | `tt.sim.mjwarp_backend` |
| ``newton`` | Newton's Featherstone solver, contact-free arms | `tt.sim.newton_backend` |
| ``mjbatch`` | MuJoCo C on a thread pool, legged floating bases (the quadruped) | `tt.sim.mjbatch_backend` |
| ``mujoco`` | the oracle: MuJoCo C + mink, one world at a time | `tt.sim.validate` |

The simulators import lazily (MuJoCo-Warp and Newton take seconds to import).
"""

from __future__ import annotations

from typing import Sequence

import mujoco

from tt.kernels.errors import TTError
from tt.sim.backends.base import Robots, RolloutBackend, check_designs, check_motions, resolve_designs
from tt.sim.controller import IKConfig
from tt.sim.designs import Design, get_space
from tt.sim.designs.trees import DesignTrees
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion


class WarpBackend:
    """tt's fused Warp kernels (FK + DLS IK at 50 Hz, CRBA/RNEA dynamics at 500 Hz), one
    batched launch per topology group; contact-free fixed-base trees."""

    name = "warp"
    perturbs = True

    def resolve(self, designs: Sequence[Design | mujoco.MjModel]) -> "Robots | DesignTrees":
        """Designs of a space that compiles its designs to tree fields directly
        (`DesignSpace.trees`) become `DesignTrees`, no MJCF or MuJoCo compile per design;
        the rest are compiled by `resolve_designs`."""
        who, hint = "the 'warp' backend", "use backend='mjwarp' or 'mujoco'"
        if len(designs) and all(isinstance(d, Design) for d in designs):
            check_designs(designs, who=who, contacts=False, hint=hint)
            trees = get_space(designs[0].space).trees(designs)
            if trees is not None:
                return trees
        return resolve_designs(designs, who=who, contacts=False, hint=hint)

    def run(
        self,
        robots: "Robots | DesignTrees",
        motions: Sequence[Motion],
        *,
        config: IKConfig,
        device: str,
        chunk: int | None,
        progress: bool,
        action_noise: float,
        noise_seed: int,
        threads: int | None = None,
        graph: bool | None = None,
    ) -> Episode:
        from tt.sim.rollout import _rollout_warp

        sites = robots.ee_sites
        check_motions(motions, config.control_dt, len(sites))
        models = robots if isinstance(robots, DesignTrees) else list(robots.models)
        return _rollout_warp(
            models,
            sites,
            motions,
            config=config,
            device=device,
            chunk=chunk,
            progress=progress,
            action_noise=action_noise,
            noise_seed=noise_seed,
            threads=threads,
            graph=graph,
        )


class MjWarpBackend:
    """MuJoCo-Warp: MuJoCo's own physics (contacts, floating bases) batched on Warp."""

    name = "mjwarp"
    perturbs = False

    def resolve(self, designs: Sequence[Design | mujoco.MjModel]) -> Robots:
        return resolve_designs(designs, who="the 'mjwarp' backend", one_space=False)

    def run(
        self,
        robots: Robots,
        motions: Sequence[Motion],
        *,
        config: IKConfig,
        device: str,
        chunk: int | None,
        progress: bool,
        action_noise: float,
        noise_seed: int,
        threads: int | None = None,
        graph: bool | None = None,
    ) -> Episode:
        from tt.sim.mjwarp_backend import mjwarp_rollout

        return mjwarp_rollout(robots, motions, config=config, device=device, progress=progress, graph=graph)


class NewtonBackend:
    """Newton's Featherstone solver on the designs' MJCF; contact-free fixed-base arms."""

    name = "newton"
    perturbs = False

    def resolve(self, designs: Sequence[Design | mujoco.MjModel]) -> Robots:
        return resolve_designs(designs, who="the 'newton' backend", contacts=False, hint="use backend='mjwarp'")

    def run(
        self,
        robots: Robots,
        motions: Sequence[Motion],
        *,
        config: IKConfig,
        device: str,
        chunk: int | None,
        progress: bool,
        action_noise: float,
        noise_seed: int,
        threads: int | None = None,
        graph: bool | None = None,
    ) -> Episode:
        from tt.sim.newton_backend import newton_rollout

        return newton_rollout(robots, motions, config=config, device=device, progress=progress)


class MjBatchBackend:
    """MuJoCo C's own physics (the oracle's, float64) stepped by ``mujoco.batch`` on every
    thread, with tt's batched whole-body controller kernel: floating-base legged robots
    (the quadruped), any mix of structures in one call."""

    name = "mjbatch"
    perturbs = True

    def resolve(self, designs: Sequence[Design | mujoco.MjModel]) -> Robots:
        return resolve_designs(designs, who="the 'mjbatch' backend")

    def run(
        self,
        robots: Robots,
        motions: Sequence[Motion],
        *,
        config: IKConfig,
        device: str,
        chunk: int | None,
        progress: bool,
        action_noise: float,
        noise_seed: int,
        threads: int | None = None,
        graph: bool | None = None,
    ) -> Episode:
        from tt.sim.mjbatch_backend import mjbatch_rollout

        return mjbatch_rollout(
            robots,
            motions,
            config=config,
            threads=threads,
            progress=progress,
            action_noise=action_noise,
            noise_seed=noise_seed,
        )


class OracleBackend:
    """The oracle (MuJoCo C + mink, world by world), the reference of every other backend."""

    name = "mujoco"
    perturbs = False

    def resolve(self, designs: Sequence[Design | mujoco.MjModel]) -> Robots:
        return resolve_designs(designs, who="the 'mujoco' backend")

    def run(
        self,
        robots: Robots,
        motions: Sequence[Motion],
        *,
        config: IKConfig,
        device: str,
        chunk: int | None,
        progress: bool,
        action_noise: float,
        noise_seed: int,
        threads: int | None = None,
        graph: bool | None = None,
    ) -> Episode:
        from tt.sim.validate import oracle_rollout

        check_motions(motions, config.control_dt, len(robots.ee_sites))
        return oracle_rollout(robots, motions, config=config, progress=progress)


_REGISTRY: dict[str, RolloutBackend] = {
    b.name: b for b in (WarpBackend(), MjWarpBackend(), NewtonBackend(), MjBatchBackend(), OracleBackend())
}

#: Rollout backends by name.
BACKENDS: tuple[str, ...] = tuple(_REGISTRY)


def get_backend(name: str) -> RolloutBackend:
    """The backend called `name`; raises ValueError listing the valid names."""
    if name not in _REGISTRY:
        raise TTError(f"unknown rollout backend {name!r}; valid: {list(BACKENDS)}")
    return _REGISTRY[name]


def default_backend(space: str) -> str:
    """The backend a space's designs roll out on when a caller names none (optimizers, `tt
    generate`, online training): ``"warp"`` (tt's kernels) for contact-free spaces, ``"mjbatch"``
    for spaces with contacts (the quadruped), which ``"warp"`` cannot simulate: the oracle's own
    MuJoCo C physics on every thread with tt's batched whole-body controller, whose episodes
    agree with the oracle's (tests/test_mjbatch.py) at several times its speed
    (benchmarks/results/quadruped_batched.md). ``"mujoco"`` is the oracle itself; ``"mjwarp"``
    simulates contacts too but on a CPU ran random quadruped designs at 0.03x the oracle
    (benchmarks/results/quadruped.md): name it to use it, e.g. on a GPU."""
    return "mjbatch" if get_space(space).has_contacts else "warp"


__all__ = [
    "BACKENDS",
    "MjBatchBackend",
    "MjWarpBackend",
    "NewtonBackend",
    "OracleBackend",
    "Robots",
    "RolloutBackend",
    "WarpBackend",
    "check_motions",
    "default_backend",
    "get_backend",
    "resolve_designs",
]
