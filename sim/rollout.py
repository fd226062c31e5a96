"""Batched closed-loop rollouts: every design on every motion, one Episode; and the warp
backend's launch code.

`rollout(designs, motions)` runs W = D * M worlds, design-major (world ``d * M + m`` is
design d on motion m), with the controller of `tt.sim.controller` (mink DiffIK with its
look-ahead, 40 ms, at 50 Hz) driving the design's position actuators, on one of the backends of
`tt.sim.backends` (``warp``, ``mjwarp``, ``newton``, ``mujoco``; the table there says
where each lives). This module holds the ``"warp"`` one (the default): tt's fused Warp
kernels (`tt.kernels.rollout`), contact-free trees of hinge/slide joints. Designs are
grouped by topology; each group is one batched launch (per chunk of control steps; on
several CPU threads the groups run at once, their slices sharing one pool). With a
single group the Episode's tensors are zero-copy torch views of the kernel's Warp arrays;
with several groups (designs of different DoF) the groups' records are copied into one
zero-padded Episode.

The Episode's conventions (padding of joint fields to the widest design, repeated records
after termination or past a motion's end) are the oracle's; see `tt.sim.validate`.

Control perturbation (``action_noise`` > 0, "warp" and "mjbatch"): the paper's data generation adds
noise to the expert's commands and logs the unperturbed ones for supervision. Each step the
actuators execute ``Episode.ctrl`` = clip(action + sigma n, ctrlrange), n ~ N(0, 1) per
actuator, a function of (noise_seed, world, step) only; ``Episode.action`` holds the clean
command the controller computed at the (perturbed) state. With sigma = 0 the rollout is the
unperturbed one, bit for bit, and ``action`` is ``ctrl``.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Sequence

import mujoco
import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.sim.backends import get_backend
from tt.sim.controller import IKConfig, check_fixed_base
from tt.sim.designs import Design
from tt.sim.designs.trees import DesignTrees
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion

if TYPE_CHECKING:
    from tt.kernels.rollout import RolloutArrays

logger = logging.getLogger(__name__)

#: Run a multi-threaded CPU rollout's topology groups at once on one shared pool (True) or one
#: after another (False); `benchmarks/ab_groups.py` measures the two.
GROUPS_AT_ONCE = True

#: Default control steps per kernel launch (1 s at 50 Hz): long enough that launch
#: overhead is negligible, short enough for a live progress bar.
DEFAULT_CHUNK = 50


def rollout(
    designs: "Sequence[Design | mujoco.MjModel] | DesignTrees",
    motions: Sequence[Motion],
    *,
    backend: str = "warp",
    device: str | None = None,
    chunk: int | None = DEFAULT_CHUNK,
    progress: bool = False,
    config: IKConfig = IKConfig(),
    action_noise: float = 0.0,
    noise_seed: int = 0,
    threads: int | None = None,
    graph: bool | None = None,
) -> Episode:
    """Run every design on every motion; returns an Episode of W = D * M worlds (design-major).

    designs: D designs of one design space (or MjModels with sites ee_0, ...); the "warp"
        backend also takes them already compiled to tree fields (`DesignSpace.trees`).
    motions: M motions sampled at ``config.control_dt`` with one arm per end effector.
    backend: ``"warp"`` (tt's kernels), ``"mjwarp"`` (MuJoCo-Warp, contacts too, see
        `tt.sim.mjwarp_backend`), ``"newton"`` (Newton Featherstone, see
        `tt.sim.newton_backend`) or ``"mujoco"`` (the oracle).
    device: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or None for `tt.kernels.device.default_device()`;
        tensors of the Episode live there ("mujoco" always returns CPU tensors).
    chunk: control steps per kernel launch (None: the whole episode in one launch).
    progress: show a tqdm bar (control steps for "warp", worlds for "mujoco").
    action_noise: control perturbation, standard deviation [rad or m] of the Gaussian noise
        on every executed command (``Episode.ctrl``; ``Episode.action`` stays the clean
        command); 0 for none. The "warp" and "mjbatch" backends perturb.
    noise_seed: seed of that noise, 0..2**31-1; world w's noise depends on (noise_seed, w,
        control step) only, so equal arguments give identical episodes.
    threads: CPU threads the "warp" backend spreads each topology group's worlds over
        (None: every core); the Episode is the same bit for bit for every count. Other
        backends ignore it.
    graph: replay the kernel launches as captured graphs ("warp": each topology group's
        whole rollout; "mjwarp": each control step's physics); None: on a CUDA device yes,
        on the CPU no; False: plain launches (see `tt.kernels.rollout.rollout_tree`).
    Raises ValueError for mixed design spaces, motions of different dt, an unknown device
    or backend, designs with contacts on "warp", and action_noise > 0 on another backend.
    """
    from tt.kernels.device import resolve_device

    impl = get_backend(backend)
    device = resolve_device(device)
    if threads is not None:
        from tt.kernels.rollout import cpu_threads

        cpu_threads(threads)  # a bad count fails on every backend
    if action_noise != 0.0 and not impl.perturbs:
        raise TTError(
            f"action_noise = {action_noise!r} needs backend 'warp' or 'mjbatch'; backend {backend!r} executes "
            "the clean commands (use action_noise=0)"
        )
    if isinstance(designs, DesignTrees) and backend != "warp":
        raise TTError(
            f"designs compiled to tree fields (DesignTrees) run on backend 'warp' only; "
            f"pass backend {backend!r} the Designs themselves"
        )
    robots = designs if isinstance(designs, DesignTrees) else impl.resolve(designs)
    return impl.run(
        robots,
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


#: Episode fields the Warp rollout kernel records in every rollout.
_RECORDED = ("qpos", "qvel", "ctrl", "act_force", "act_vel", "ee_pos", "ee_quat", "target_pos", "target_quat", "alive")


def rollout_records(
    models: "Sequence[mujoco.MjModel] | DesignTrees",
    sites: tuple[str, ...],
    motions: Sequence[Motion],
    *,
    config: IKConfig = IKConfig(),
    device: str,
    chunk: int | None = DEFAULT_CHUNK,
    progress: bool = False,
    action_noise: float = 0.0,
    noise_seed: int = 0,
    threads: int | None = None,
    graph: bool | None = None,
    steps: int | None = None,
) -> list[tuple[list[int], "RolloutArrays"]]:
    """The Warp rollouts of `rollout` ("warp" backend), one per topology group, as Warp arrays.

    models: D compiled contact-free trees with end-effector `sites`, or D designs already
        compiled to tree fields (`tt.sim.designs.trees.DesignTrees`); motions: M motions.
    Returns [(members, records)]: the design indices of each topology group (ascending) and
    the kernel's records of its ``len(members) * M`` worlds, design-major over members.
    progress: show a tqdm bar over the control steps of every group.
    threads: CPU threads the worlds are spread over (None: every core); with several groups
        and threads, the groups run at the same time on one shared pool of that many workers
        (a group too small to slice launches from its own driver thread).
    graph: one captured graph per group (None: on CUDA devices; see `rollout_tree`).
    steps: control steps to run (None: the longest motion's); fewer give the first steps of
        the full rollout, bit for bit (the controller still looks ahead along the motions).
    Inputs are not validated here; `rollout` does that.
    """
    from tt.kernels.model import tree_model
    from tt.kernels.rollout import cpu_threads, motion_arrays, rollout_kernels, rollout_tree

    groups = _tree_groups(models, sites)
    M = len(motions)
    T = max(motion.steps for motion in motions)
    run_steps = T if steps is None else int(steps)
    if not 1 <= run_steps <= T:
        raise TTError(f"steps = {steps}; must be 1 .. {T}, the longest motion's")
    A = len(sites)
    pos = np.zeros((M, T, A, 3))
    quat = np.zeros((M, T, A, 4))
    for j, motion in enumerate(motions):
        idx = np.minimum(np.arange(T), motion.steps - 1)
        pos[j], quat[j] = motion.pos[idx], motion.quat[idx]
    marrays = motion_arrays(pos, quat, [motion.steps for motion in motions], device=device)
    logger.debug("warp rollout: %d designs in %d topology group(s), %d motions, T=%d", len(models), len(groups), M, T)
    import warp as wp

    workers = cpu_threads(threads)
    at_once = GROUPS_AT_ONCE and len(groups) > 1 and workers > 1 and not graph and not wp.get_device(device).is_cuda
    modules = [rollout_kernels(fields.topology).module for _, fields in groups]
    compiling = None
    if progress and at_once:  # counted as each group's driver loads its module, below
        compiling = _compile_bar(modules, device)
    elif progress:
        # One group after another: every compile first, so that its bar ends before stepping.
        load_rollout_kernels(modules, device, progress=True)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=run_steps * len(groups), desc="rollout", unit="step")

    def run(group, pool=None):
        members, fields = group
        # One model entry per design; world k * M + j (member k on motion j) reads entry k.
        tree = tree_model(fields, world_entry=np.repeat(np.arange(len(members)), M), device=device)
        # Noise keyed by the world's index in the whole rollout, not in its topology group.
        world_ids = np.array([d * M + j for d in members for j in range(M)])
        arrays = rollout_tree(
            tree, marrays, len(members) * M, run_steps,
            **config.rollout_args(), chunk=chunk, progress=bar.update if bar else None,
            action_noise=action_noise, noise_seed=noise_seed, world_ids=world_ids, device=device, threads=threads,
            graph=graph, pool=pool,
        )  # fmt: skip
        return list(members), arrays

    if at_once:
        # Several topologies on several CPU threads: every group runs at once from its own
        # driver thread, its slices queued on one shared pool of `workers` threads, so that one
        # group's Python work (model upload, allocation) and its chunk barriers overlap the
        # others' stepping instead of leaving cores idle. A world's arithmetic is unchanged.
        # Each group starts as soon as its kernels are built and loaded (here, one thread:
        # Warp's code generation and module loading are not for concurrent callers), so the
        # next groups' code generation overlaps the first groups' stepping.
        with (
            ThreadPoolExecutor(workers, thread_name_prefix="tt-rollout") as pool,
            ThreadPoolExecutor(len(groups), thread_name_prefix="tt-group") as drivers,
        ):
            started = []
            for group, module in zip(groups, modules):
                _load(module, device, compiling)
                started.append(drivers.submit(run, group, pool))
            _close(compiling)
            results = [future.result() for future in started]
    else:
        results = [run(group) for group in groups]
    if bar is not None:
        bar.close()
    return results


#: The line above the compile bar: what is compiled and that it happens once.
COMPILE_NOTE = (
    "compiling Warp kernels for {pending} of {total} robot structure(s) on {device}: once per structure "
    "(topology), then loaded from Warp's kernel cache ({cache})"
)


def load_rollout_kernels(modules: Sequence[str], device: str, *, progress: bool = False) -> None:
    """Build (or load from Warp's kernel cache) the fused rollout modules `modules`
    (`tt.kernels.rollout.rollout_kernels(topology).module`) on `device`, as a first launch would.

    progress: where some are neither loaded nor cached (`tt.kernels.rollout.module_built`),
    `COMPILE_NOTE` and a tqdm bar counting their compiles on stderr (a compile takes 9-12 s on
    an idle 2-core CPU, more under load; loading a cached module milliseconds). Checking costs each
    module's hash, which its load computes anyway.
    """
    compiling = _compile_bar(modules, device) if progress else None
    try:
        for module in dict.fromkeys(modules):
            _load(module, device, compiling)
    finally:
        _close(compiling)


def _compile_bar(modules: Sequence[str], device: str):
    """None where every module in `modules` is built (`module_built`); else `COMPILE_NOTE` and
    a tqdm bar (stderr) over those that are not, their names in its ``pending`` attribute."""
    import sys

    import warp as wp
    from tqdm import tqdm

    from tt.kernels.rollout import module_built

    names = set(modules)
    pending = {name for name in names if not module_built(name, device)}
    if not pending:
        return None
    note = COMPILE_NOTE.format(pending=len(pending), total=len(names), device=device, cache=wp.config.kernel_cache_dir)
    tqdm.write(note, file=sys.stderr)
    bar = tqdm(total=len(pending), desc="compiling kernels", unit="topology", file=sys.stderr)
    bar.pending = pending
    return bar


def _load(module: str, device: str, compiling) -> None:
    """Build or load `module` on `device`, counting a pending build on the compile bar."""
    import warp as wp

    wp.load_module(module, device=device)
    if compiling is not None and module in compiling.pending:
        compiling.pending.discard(module)
        compiling.update(1)


def _close(compiling) -> None:
    if compiling is not None:
        compiling.close()


def _tree_groups(models: "Sequence[mujoco.MjModel] | DesignTrees", sites: tuple[str, ...]) -> list:
    """[(members, TreeFields)] per topology: `DesignTrees`' own groups, or compiled models
    read by `tt.kernels.model.tree_fields` (each distinct model object once)."""
    from tt.kernels.model import check_supported, topology_key, tree_fields

    if isinstance(models, DesignTrees):
        if tuple(sites) != tuple(models.ee_sites):
            raise TTError(f"sites {list(sites)} differ from the designs' end effectors {list(models.ee_sites)}")
        return [(list(int(i) for i in members), fields) for members, fields in models.groups]
    for i, m in enumerate(models):
        check_fixed_base(m)
        check_supported(m, i)
    groups: dict[tuple, list[int]] = {}
    for d, m in enumerate(models):
        groups.setdefault(topology_key(m, sites), []).append(d)
    out = []
    for members in groups.values():
        first: dict[int, int] = {}  # model object -> its entry
        entry = [first.setdefault(id(models[d]), len(first)) for d in members]
        distinct = list({id(models[d]): models[d] for d in members}.values())
        out.append((members, tree_fields(distinct, sites).take(entry)))
    return out


def _recorded(perturbed: bool) -> tuple[str, ...]:
    """Episode fields the Warp rollout records (``action`` only with control perturbation)."""
    return _RECORDED + (("action",) if perturbed else ())


def group_episode(members: Sequence[int], records, motions: int, nu: int, *, perturbed: bool, dt: float) -> Episode:
    """The Episode of one topology group's records, as zero-copy torch views of its Warp arrays.

    members: the group's design indices (its worlds are design-major over them: world
    k * motions + m is design members[k] on motion m; ``design_index`` holds members[k]);
    records: its `RolloutArrays`; nu: the group's actuator count (a model without actuators
    records one padding column, cut off by the view); perturbed: the rollout had action noise.
    """
    import warp as wp

    fields = {name: wp.to_torch(getattr(records, name)) for name in _recorded(perturbed)}
    if fields["ctrl"].shape[-1] != nu:
        for name in ("ctrl", "action", "act_force", "act_vel"):
            if name in fields:
                fields[name] = fields[name][..., :nu]
    tdev = fields["qpos"].device
    W, T = fields["qpos"].shape[:2]
    return Episode(
        **{k: fields[k] for k in _RECORDED},
        action=fields["action"] if perturbed else fields["ctrl"],
        fallen=torch.zeros((W, T), dtype=torch.bool, device=tdev),
        design_index=torch.as_tensor(list(members), dtype=torch.long, device=tdev).repeat_interleave(motions),
        motion_index=torch.arange(motions, device=tdev).repeat(len(members)),
        dt=dt,
    )


def _rollout_warp(
    models: "list[mujoco.MjModel] | DesignTrees",
    sites: tuple[str, ...],
    motions: Sequence[Motion],
    *,
    config: IKConfig,
    device: str,
    chunk: int | None,
    progress: bool,
    action_noise: float = 0.0,
    noise_seed: int = 0,
    threads: int | None = None,
    graph: bool | None = None,
) -> Episode:
    import warp as wp

    D, M = len(models), len(motions)
    T = max(motion.steps for motion in motions)
    results = rollout_records(
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
    perturbed = action_noise > 0.0
    if isinstance(models, DesignTrees):
        nq, nu = models.max_dofs(), models.max_actuators()
    else:
        nq, nu = max(m.nq for m in models), max(m.nu for m in models)
    if len(results) == 1:
        ((members, arrays),) = results
        return group_episode(members, arrays, M, nu, perturbed=perturbed, dt=config.control_dt)
    # Several topologies: copy each group's records into one zero-padded Episode.
    names = _recorded(perturbed)
    actuator_fields = ("ctrl", "action", "act_force", "act_vel") if perturbed else ("ctrl", "act_force", "act_vel")
    sizes = {"qpos": nq, "qvel": nq}  # hinge/slide trees: nv == nq (`check_supported`)
    sizes.update({name: nu for name in actuator_fields})
    tdev = wp.device_to_torch(device)
    fields = {}
    for name in names:
        first = wp.to_torch(getattr(results[0][1], name))
        shape = (D * M, T) + (tuple(first.shape[2:]) if name not in sizes else (sizes[name],))
        fields[name] = torch.zeros(shape, dtype=first.dtype, device=tdev)
    for members, arrays in results:
        worlds = torch.tensor([d * M + j for d in members for j in range(M)], device=tdev)
        for name in names:
            src = wp.to_torch(getattr(arrays, name))
            if name in sizes:
                width = min(src.shape[-1], sizes[name])
                fields[name][worlds, :, :width] = src[..., :width]
            else:
                fields[name][worlds] = src
    return Episode(
        **{k: fields[k] for k in _RECORDED},
        action=fields["action"] if perturbed else fields["ctrl"],
        fallen=torch.zeros((D * M, T), dtype=torch.bool, device=tdev),
        design_index=torch.arange(D, device=tdev).repeat_interleave(M),
        motion_index=torch.arange(M, device=tdev).repeat(D),
        dt=config.control_dt,
    )


__all__ = ["COMPILE_NOTE", "DEFAULT_CHUNK", "group_episode", "load_rollout_kernels", "rollout", "rollout_records"]
