"""Batched evaluation of candidate designs: one rollout over designs x motions, one reward."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.sim.backends import default_backend
from tt.sim.designs import Design, get_space
from tt.sim.designs.trees import DesignTrees
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardInputs, get_reward, metrics, robot_mass, robot_size

logger = logging.getLogger(__name__)


@dataclass
class Evaluation:
    """Scores of D designs on M motions.

    objective: mean reward over motions per design, (D,).
    reward: reward per design and motion, (D, M).
    metrics: per-metric arrays of shape (D, M) (units in `tt.sim.rewards.METRIC_UNITS`).
    episode: the rollout the scores came from (worlds design-major: w = d * M + m).
    """

    objective: np.ndarray
    reward: np.ndarray
    metrics: dict[str, np.ndarray]
    episode: Episode


def run_rollout(
    designs: "Sequence[Design | mujoco.MjModel] | DesignTrees",
    motions: Sequence[Motion],
    *,
    backend: str,
    device: str | None,
    progress: bool = False,
    threads: int | None = None,
    graph: bool | None = None,
) -> Episode:
    """Rollout of every design (or its built model) on every motion with `backend` (design-major
    worlds; threads: CPU threads of the "warp" backend, None for every core)."""
    from tt.sim.rollout import rollout

    return rollout(
        designs if isinstance(designs, DesignTrees) else list(designs),
        list(motions),
        backend=backend,
        device=device,
        progress=progress,
        threads=threads,
        graph=graph,
    )


def score_episode(
    ep: Episode,
    designs: Sequence[Design],
    motions: Sequence[Motion],
    reward: str,
    *,
    models: "Sequence[mujoco.MjModel] | DesignTrees | None" = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Reward and metrics of each world of `ep`, reshaped to (D, M).

    models: the designs' built models or tree fields (`DesignTrees`) when the caller has
    them (size and mass are read from them); None builds them.
    """
    space = designs[0].space
    cfg = get_reward(reward, space)
    if models is None:
        sp = get_space(space)
        models = [sp.model(d) for d in designs]
    device = ep.ee_pos.device
    if isinstance(models, DesignTrees):
        size_d, mass_d = (
            torch.as_tensor(models.size, dtype=torch.float32),
            torch.as_tensor(models.mass, dtype=torch.float32),
        )
    else:
        size_d, mass_d = robot_size(models), robot_mass(models)
    size = size_d.to(device)[ep.design_index.to(device)]
    mass = mass_d.to(device)[ep.design_index.to(device)]
    steps = torch.tensor([m.steps for m in motions], device=device)[ep.motion_index.to(device)]
    inputs = RewardInputs.from_episode(ep, size.to(ep.ee_pos.dtype), mass.to(ep.ee_pos.dtype), motion_steps=steps)
    per_world = metrics(inputs, cfg)
    D, M = len(designs), len(motions)
    out = {k: v.detach().double().cpu().numpy().reshape(D, M) for k, v in per_world.items()}
    return out["reward"], out


def _load_counted(sp, models: Sequence[mujoco.MjModel], device) -> None:
    """Load the rollout kernels of `models`' topologies, a note and a bar counting those
    that compile (`tt.sim.rollout.load_rollout_kernels`)."""
    from tt.kernels.model import topology_of
    from tt.kernels.rollout import rollout_kernels
    from tt.sim.rollout import load_rollout_kernels

    modules = [rollout_kernels(topology_of(m, sp.ee_sites())).module for m in models]
    load_rollout_kernels(modules, device, progress=True)


def _models(
    sp, designs: Sequence[Design], *, backend: str, device: str | None, threads: int | None, progress: bool = False
) -> list[mujoco.MjModel]:
    """`sp.models(designs)`, one worker process per rollout thread for large batches; on
    "warp", this process meanwhile loads the rollout kernels of the batch's structures
    (progress: with the bar of `tt.sim.rollout.load_rollout_kernels` where some compile).

    A cached module loads in milliseconds, but one missing from Warp's kernel cache takes
    seconds to build (about 12 s per fused rollout module here), and the workers leave this
    process idle, so the build comes off the rollout's critical path. One model per distinct
    discrete structure names the topologies; one that the batch turns out not to use costs
    only its load.
    """
    import threading

    from tt.kernels.device import resolve_device
    from tt.kernels.rollout import cpu_threads, preload_rollout_kernels
    from tt.sim.designs.base import builds_in_workers

    processes = cpu_threads(threads)
    if backend != "warp" or not builds_in_workers(len(designs), processes):
        return sp.models(designs, processes=processes)
    firsts: dict[tuple[int, ...], Design] = {}
    for d in designs:
        firsts.setdefault(tuple(int(i) for i in d.discrete), d)
    device = resolve_device(device)

    def preload() -> None:
        try:
            models = [sp.model(d) for d in firsts.values()]
            if progress:  # the same loads, their compiles counted on a bar
                _load_counted(sp, models, device)
            else:
                preload_rollout_kernels(models, sp.ee_sites(), device)
        except Exception:  # the rollout loads the same modules next and reports the error there
            logger.debug("preloading the rollout kernels failed", exc_info=True)

    loader = threading.Thread(target=preload, name="tt-preload-kernels", daemon=True)
    loader.start()
    try:
        return sp.models(designs, processes=processes)
    finally:
        loader.join()


def evaluate_designs(
    designs: Sequence[Design],
    motions: Sequence[Motion],
    reward: str,
    *,
    backend: str | None = None,
    device: str | None = None,
    progress: bool = False,
    threads: int | None = None,
    graph: bool | None = None,
) -> Evaluation:
    """Roll out every design on every motion in one batch and score it with `reward`
    (backend: None for the space's, `tt.sim.backends.default_backend`: "warp", or "mjbatch"
    for a space with contacts; progress: a tqdm bar over the rollout; threads: CPU threads of
    the "warp" backend, None for every core; graph: CUDA graphs, see `tt.sim.rollout.rollout`)."""
    if not designs:
        raise TTError("evaluate_designs needs at least one design")
    spaces = {d.space for d in designs}
    if len(spaces) > 1:
        raise TTError(f"designs from several spaces in one evaluation: {sorted(spaces)}")
    sp = get_space(designs[0].space)
    get_reward(reward, sp.name)  # an unknown reward fails before the rollout
    if backend is None:
        backend = default_backend(sp.name)
    if backend == "warp" and sp.has_contacts:
        raise TTError(
            f"design space {sp.name!r} has contacts; backend 'warp' simulates contact-free trees only, "
            "use backend='mujoco' or 'mjwarp'"
        )
    # Each design's model is built once, for the size and mass terms and, on "warp" and
    # "mjbatch" (where a second build is a visible share of the time), for the rollout too: as tree
    # fields where the space builds them directly, else as MuJoCo models, large batches in
    # worker processes, one per rollout thread.
    models = sp.trees(designs) if backend == "warp" else None
    if models is None:
        models = _models(sp, designs, backend=backend, device=device, threads=threads, progress=progress)
    ep = run_rollout(
        # "warp" and "mjbatch" run the models built here; the others import MJCF or build their own.
        models if backend in ("warp", "mjbatch") else designs,
        motions,
        backend=backend,
        device=device,
        progress=progress,
        threads=threads,
        graph=graph,
    )
    r, m = score_episode(ep, designs, motions, reward, models=models)
    return Evaluation(objective=r.mean(axis=1), reward=r, metrics=m, episode=ep)


def warm_up(
    designs: Sequence[Design],
    motions: Sequence[Motion],
    *,
    reward: str = "tracking",
    backend: str = "warp",
    device: str | None = None,
    progress: bool = False,
) -> float:
    """Compile (or load from Warp's kernel cache) what evaluating `designs` needs; seconds taken.

    Warp builds one kernel module per tree topology on its first launch (about a minute per
    topology on a CPU when not cached on disk). This evaluates one design per topology among
    `designs` on the first two steps of the first motion, so an optimizer can start its
    clock after every compile and first-call cost (imports, torch's first ops in the
    reward); in a warm process it costs the models' build (milliseconds per design).
    Candidates that keep a design's discrete choices share its topology. The "mujoco" oracle
    compiles nothing; one short episode takes its first-call costs out of the timings.
    progress: on "warp", a note and a tqdm bar on stderr counting the topologies whose kernels
    compile (none when all are in the kernel cache; `tt.sim.rollout.load_rollout_kernels`).
    """
    start = time.perf_counter()
    if not designs or not motions:
        return 0.0
    m = motions[0]
    short = Motion(m.name, m.pos[:2], m.quat[:2], m.dt)
    chosen = [designs[0]]
    if backend != "mujoco":
        from tt.kernels.model import topology_key

        sp = get_space(designs[0].space)
        by_discrete: dict[tuple[int, ...], Design] = {}
        for d in designs:
            by_discrete.setdefault(d.discrete, d)
        by_topology: dict[tuple, tuple[Design, mujoco.MjModel]] = {}
        for d in by_discrete.values():
            m = sp.model(d)
            by_topology.setdefault(topology_key(m, sp.ee_sites()), (d, m))
        chosen = [d for d, _ in by_topology.values()]
        if progress and backend == "warp":
            from tt.kernels.device import resolve_device

            _load_counted(sp, [m for _, m in by_topology.values()], resolve_device(device))
    evaluate_designs(chosen, [short], reward, backend=backend, device=device)
    return time.perf_counter() - start


def warm_up_problem(problem, designs: Sequence[Design], *, backend: str | None = None) -> float:
    """`warm_up` of `designs` for a `tt.baselines.Problem`: its motions, reward, device and
    progress, and its backend unless `backend` is given; seconds taken."""
    return warm_up(
        designs,
        problem.motions,
        reward=problem.reward,
        backend=backend or problem.backend,
        device=problem.device,
        progress=problem.progress,
    )


__all__ = ["Evaluation", "evaluate_designs", "run_rollout", "score_episode", "warm_up", "warm_up_problem"]
