"""The closed loop of a batched policy: every design on every motion, one control step at a time.

`closed_loop_rollout(designs, motions, policy)` runs W = D * M worlds (design-major, world
``d * M + m`` is design d on motion m) like `tt.sim.rollout.rollout`, but every control
step asks a `Policy` (`tt.dit.policies`: the DiT, or the DiffIK as its reference) for the
joint position targets instead of running the DiffIK in the kernel. Physics is tt's Warp
kernels (`tt.kernels.control_step`: the "warp" backend's contact-free trees, one launch
per topology group and control step, `substeps` physics steps with the command held).
The result is an `Episode` with the oracle's conventions (`tt.sim.validate`): start at
rest at the oracle's start posture, record the state after each step, end a world at the
first step whose summed position error exceeds the threshold (that record kept with
alive False, later ones repeated), targets at index ``min(k, T_m - 1)``; so
`tt.sim.rewards` scores it like any other rollout.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol, Sequence

import mujoco
import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.sim.controller import IKConfig, check_fixed_base
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ state
@dataclass
class StepState:
    """Measured state of W worlds at the start of a control step: the record of the
    previous step (at step 0 the start posture at rest with the command that holds it).

    qpos, qvel: (W, NQ) [rad or m], (W, NV) [rad/s or m/s], zero-padded to the widest
    design; ctrl: the command that led to it, (W, NU); act_force [N m or N], act_vel
    [rad/s or m/s]: (W, NU); ee_pos (W, A, 3) [m]; ee_quat (W, A, 4) (w, x, y, z).
    """

    qpos: torch.Tensor
    qvel: torch.Tensor
    ctrl: torch.Tensor
    act_force: torch.Tensor
    act_vel: torch.Tensor
    ee_pos: torch.Tensor
    ee_quat: torch.Tensor


@dataclass
class LoopContext:
    """What a policy may read about a closed-loop run (fixed for the whole run).

    models: the D compiled designs; motions: the M motions; design_index, motion_index:
    (W,) long, design-major; target_pos (W, T, A, 3) [m] and target_quat (W, T, A, 4): the
    motion pose at index min(t, T_m - 1) of each world's motion; motion_steps: (W,) long,
    T_m; config: the controller timing (control period, look-ahead, termination);
    worlds: the simulation (its topology groups hold the kernels' model arrays).
    """

    models: list[mujoco.MjModel]
    motions: tuple[Motion, ...]
    design_index: torch.Tensor
    motion_index: torch.Tensor
    target_pos: torch.Tensor
    target_quat: torch.Tensor
    motion_steps: torch.Tensor
    config: IKConfig
    worlds: "ArmWorlds"

    @property
    def world_count(self) -> int:
        return int(self.design_index.shape[0])


class Policy(Protocol):
    """A batched controller: joint position targets for the worlds still running."""

    def reset(self, ctx: LoopContext) -> None:
        """Called once before step 0."""

    def __call__(self, step: int, worlds: torch.Tensor, state: StepState) -> torch.Tensor:
        """Commands (n, NU) for worlds `worlds` (n,) long at control step `step`; `state`
        holds every world (index it with `worlds`). Columns past a design's nu are ignored."""


@dataclass
class _Group:
    """Worlds of one topology: their global indices (Wg,) and Warp arrays, with torch views."""

    worlds: torch.Tensor
    tree: object
    nv: int
    nu: int
    arrays: dict = field(default_factory=dict)
    views: dict = field(default_factory=dict)


class ArmWorlds:
    """W contact-free fixed-base arm worlds stepped one control step at a time.

    models: D compiled designs (hinge/slide trees, `tt.kernels.model.check_supported`);
    sites: end-effector site names; motions: M motions (their first poses set the start
    postures); worlds are design-major. config: control period, look-ahead, start-posture
    iterations and termination threshold (`IKConfig`); device: Warp/torch device.
    After `reset`, `state` holds the start posture at rest; `step(ctrl)` advances every
    world by one control period and updates `state` to the new record.
    """

    def __init__(
        self,
        models: Sequence[mujoco.MjModel],
        sites: Sequence[str],
        motions: Sequence[Motion],
        *,
        config: IKConfig = IKConfig(),
        device: str | None = None,
    ):
        import warp as wp

        from tt.kernels.device import resolve_device
        from tt.kernels.model import build_tree_model, check_supported, topology_key

        self.device = resolve_device(device)
        self.torch_device = wp.device_to_torch(self.device)
        self.models = list(models)
        self.sites = tuple(sites)
        self.motions = tuple(motions)
        self.config = config
        D, M = len(self.models), len(self.motions)
        if D == 0 or M == 0:
            raise TTError(f"need at least one design and one motion, got {D} and {M}")
        for i, m in enumerate(self.models):
            check_fixed_base(m)
            check_supported(m, i)
        subs = {config.substeps(m) for m in self.models}
        if len(subs) != 1:
            raise TTError(
                f"designs need different physics steps per control step {sorted(subs)}; give designs of one timestep"
            )
        self.substeps = subs.pop()
        self.world_count = D * M
        self.nq = max(m.nq for m in self.models)
        self.nu = max(m.nu for m in self.models)
        self.design_index = torch.arange(D).repeat_interleave(M).to(self.torch_device)
        self.motion_index = torch.arange(M).repeat(D).to(self.torch_device)
        dev = self.torch_device
        lo = torch.zeros(D, self.nu, dtype=torch.float32)
        hi = torch.zeros(D, self.nu, dtype=torch.float32)
        for d, m in enumerate(self.models):
            clamp = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
            limited = m.actuator_ctrllimited.astype(bool) & clamp
            lo[d, : m.nu] = torch.as_tensor(np.where(limited, m.actuator_ctrlrange[:, 0], -np.inf), dtype=torch.float32)
            hi[d, : m.nu] = torch.as_tensor(np.where(limited, m.actuator_ctrlrange[:, 1], np.inf), dtype=torch.float32)
        self.ctrl_low = lo.to(dev)[self.design_index]  # (W, NU)
        self.ctrl_high = hi.to(dev)[self.design_index]

        groups: dict[tuple, list[int]] = {}
        for d, m in enumerate(self.models):
            groups.setdefault(topology_key(m, self.sites), []).append(d)
        self.groups: list[_Group] = []
        for members in groups.values():
            worlds = torch.tensor([d * M + j for d in members for j in range(M)], device=dev)
            # One model entry per world (design-major), so local world i reads entry i and
            # runs motion i % M, as the rollout kernels expect.
            tree = build_tree_model([self.models[d] for d in members for _ in range(M)], self.sites, device=self.device)
            g = _Group(worlds, tree, tree.topology.dof_count, tree.topology.actuator_count)
            wg, ne = len(worlds), tree.topology.ee_count
            nv, nu = g.nv, max(g.nu, 1)
            g.arrays = {
                "qpos": wp.zeros((wg, nv), dtype=float, device=self.device),
                "qvel": wp.zeros((wg, nv), dtype=float, device=self.device),
                "ctrl": wp.zeros((wg, nu), dtype=float, device=self.device),
                "act_force": wp.zeros((wg, nu), dtype=float, device=self.device),
                "act_vel": wp.zeros((wg, nu), dtype=float, device=self.device),
                "ee_pos": wp.zeros((wg, ne), dtype=wp.vec3, device=self.device),
                "ee_quat": wp.zeros((wg, ne), dtype=wp.vec4, device=self.device),
            }
            g.views = {k: wp.to_torch(v) for k, v in g.arrays.items()}
            self.groups.append(g)
        A = len(self.sites)
        W = self.world_count
        self.state = StepState(
            qpos=torch.zeros(W, self.nq, device=dev), qvel=torch.zeros(W, self.nq, device=dev),
            ctrl=torch.zeros(W, self.nu, device=dev), act_force=torch.zeros(W, self.nu, device=dev),
            act_vel=torch.zeros(W, self.nu, device=dev), ee_pos=torch.zeros(W, A, 3, device=dev),
            ee_quat=torch.zeros(W, A, 4, device=dev),
        )  # fmt: skip

    def reset(self) -> StepState:
        """Every world at the oracle's start posture (`IKConfig.init_iterations` IK steps from
        qpos0 toward its motion's first pose), at rest, commanded to hold it."""
        import warp as wp

        from tt.kernels.rollout import motion_arrays, start_postures

        M = len(self.motions)
        first_pos = np.stack([m.pos[:1] for m in self.motions])  # (M, 1, A, 3)
        first_quat = np.stack([m.quat[:1] for m in self.motions])
        marrays = motion_arrays(first_pos, first_quat, [1] * M, device=self.device)
        hold = torch.zeros(self.world_count, self.nu, device=self.torch_device)
        for g in self.groups:
            start = start_postures(
                g.tree, marrays, self.config.init_ik_weights(), self.config.init_iterations, device=self.device
            )
            g.views["qpos"].copy_(wp.to_torch(start))
            g.views["qvel"].zero_()
            act = torch.as_tensor(g.tree.topology.actuator_dof, dtype=torch.long, device=self.torch_device)
            hold[g.worlds, : g.nu] = g.views["qpos"][:, act]
        self._advance(hold, 0)
        return self.state

    def step(self, ctrl: torch.Tensor) -> StepState:
        """One control period of every world with joint position targets `ctrl` (W, NU)
        (clipped to each actuator's ctrlrange, as MuJoCo executes them); returns the new state."""
        if tuple(ctrl.shape) != (self.world_count, self.nu):
            raise TTError(f"ctrl has shape {tuple(ctrl.shape)}; expected (W={self.world_count}, NU={self.nu})")
        return self._advance(ctrl, self.substeps)

    def _advance(self, ctrl: torch.Tensor, substeps: int) -> StepState:
        from tt.kernels.control_step import control_step

        ctrl = torch.minimum(torch.maximum(ctrl.to(self.torch_device, torch.float32), self.ctrl_low), self.ctrl_high)
        s = self.state
        for g in self.groups:
            a, v = g.arrays, g.views
            v["ctrl"][:, : g.nu].copy_(ctrl[g.worlds, : g.nu])
            control_step(
                g.tree, a["ctrl"], a["qpos"], a["qvel"], a["act_force"], a["act_vel"], a["ee_pos"], a["ee_quat"],
                substeps=substeps, device=self.device,
            )  # fmt: skip
            s.qpos[g.worlds, : g.nv] = v["qpos"]
            s.qvel[g.worlds, : g.nv] = v["qvel"]
            s.ctrl[g.worlds, : g.nu] = v["ctrl"][:, : g.nu]
            s.act_force[g.worlds, : g.nu] = v["act_force"][:, : g.nu]
            s.act_vel[g.worlds, : g.nu] = v["act_vel"][:, : g.nu]
            s.ee_pos[g.worlds] = v["ee_pos"]
            s.ee_quat[g.worlds] = v["ee_quat"]
        return s


def _models(designs) -> tuple[list[mujoco.MjModel], tuple[str, ...]]:
    from tt.sim.backends.base import resolve_designs

    robots = resolve_designs(designs, who="the model's closed-loop rollout", contacts=False)
    return list(robots.models), robots.ee_sites


def closed_loop_rollout(
    designs,
    motions: Sequence[Motion],
    policy: Policy,
    *,
    config: IKConfig = IKConfig(),
    device: str | None = None,
    steps: int | None = None,
    progress: bool = False,
) -> Episode:
    """Run every design on every motion with `policy` choosing the commands; see the module docstring.

    designs: D tt Designs of one contact-free space, or MjModels with sites ee_0, ...;
    motions: M motions sampled at ``config.control_dt``, one arm per end effector;
    steps: control steps to run (None: the longest motion; fewer cuts every motion there);
    progress: a tqdm bar over control steps. Returns an Episode of W = D * M worlds on
    `device` (float32; joint fields zero-padded to the widest design).
    """
    models, sites = _models(designs)
    motions = tuple(motions)
    if not motions:
        raise TTError("motions is empty; a closed-loop rollout needs at least one motion")
    for j, m in enumerate(motions):
        if not isinstance(m, Motion):
            raise TypeError(f"motions[{j}] is a {type(m).__name__}; expected tt.sim.motions.base.Motion")
        if abs(m.dt - config.control_dt) > 1e-9:
            raise TTError(f"motions[{j}] ({m.name!r}) has dt = {m.dt} s; the controller runs at {config.control_dt} s")
        if m.arms != len(sites):
            raise TTError(
                f"motions[{j}] ({m.name!r}) has {m.arms} arm(s); the designs have {len(sites)} end effector(s)"
            )
    sim = ArmWorlds(models, sites, motions, config=config, device=device)
    log.debug(
        "closed loop: %d designs x %d motions in %d topology group(s), policy %s",
        len(models),
        len(motions),
        len(sim.groups),
        type(policy).__name__,
    )
    dev = sim.torch_device
    W, A = sim.world_count, len(sites)
    T = max(m.steps for m in motions) if steps is None else int(steps)
    if T < 1:
        raise TTError(f"steps = {steps}; a rollout needs at least one control step")
    lengths = torch.tensor([min(m.steps, T) for m in motions], device=dev)[sim.motion_index]  # (W,)
    horizon = max(T, max(m.steps for m in motions))
    pos = np.zeros((len(motions), horizon, A, 3), np.float32)
    quat = np.zeros((len(motions), horizon, A, 4), np.float32)
    for j, m in enumerate(motions):
        idx = np.minimum(np.arange(horizon), m.steps - 1)
        pos[j], quat[j] = m.pos[idx], m.quat[idx]
    target_pos = torch.as_tensor(pos, device=dev)[sim.motion_index]  # (W, horizon, A, 3)
    target_quat = torch.as_tensor(quat, device=dev)[sim.motion_index]
    ctx = LoopContext(
        models, motions, sim.design_index, sim.motion_index, target_pos, target_quat, lengths, config, sim
    )

    rec = {
        "qpos": torch.zeros(W, T, sim.nq, device=dev), "qvel": torch.zeros(W, T, sim.nq, device=dev),
        "ctrl": torch.zeros(W, T, sim.nu, device=dev), "act_force": torch.zeros(W, T, sim.nu, device=dev),
        "act_vel": torch.zeros(W, T, sim.nu, device=dev), "ee_pos": torch.zeros(W, T, A, 3, device=dev),
        "ee_quat": torch.zeros(W, T, A, 4, device=dev),
    }  # fmt: skip
    alive = torch.zeros(W, T, dtype=torch.bool, device=dev)
    running = torch.ones(W, dtype=torch.bool, device=dev)
    state = sim.reset()
    policy.reset(ctx)
    ctrl = state.ctrl.clone()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, desc="closed loop", unit="step")
    for k in range(T):
        running &= k < lengths
        worlds = running.nonzero().flatten()
        if len(worlds):
            cmd = policy(k, worlds, state)
            if tuple(cmd.shape[:1]) != (len(worlds),) or cmd.ndim != 2 or cmd.shape[1] < sim.nu:
                raise TTError(
                    f"policy returned commands of shape {tuple(cmd.shape)} at step {k}; expected "
                    f"({len(worlds)}, {sim.nu})"
                )
            ctrl[worlds] = cmd[:, : sim.nu].to(dev, torch.float32)
        # Stopped worlds keep their last command; their physics runs on unrecorded.
        state = sim.step(ctrl)
        fresh = {
            "qpos": state.qpos,
            "qvel": state.qvel,
            "ctrl": state.ctrl,
            "act_force": state.act_force,
            "act_vel": state.act_vel,
            "ee_pos": state.ee_pos,
            "ee_quat": state.ee_quat,
        }
        for name, x in rec.items():
            x[:, k] = torch.where(running.view(-1, *[1] * (x.ndim - 2)), fresh[name], x[:, k - 1] if k else fresh[name])
        err = torch.linalg.vector_norm(state.ee_pos - target_pos[:, k], dim=-1).sum(-1)  # (W,)
        # `<=` so that a NaN error (a diverged state) terminates like a large one.
        ok = running & (err <= config.termination_pos_error)
        alive[:, k] = ok
        running = ok
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return Episode(
        qpos=rec["qpos"], qvel=rec["qvel"], ctrl=rec["ctrl"], action=rec["ctrl"], act_force=rec["act_force"],
        act_vel=rec["act_vel"], ee_pos=rec["ee_pos"], ee_quat=rec["ee_quat"], target_pos=target_pos[:, :T].contiguous(),
        target_quat=target_quat[:, :T].contiguous(), alive=alive,
        fallen=torch.zeros(W, T, dtype=torch.bool, device=dev),
        design_index=sim.design_index.clone(), motion_index=sim.motion_index.clone(), dt=config.control_dt,
    )  # fmt: skip


__all__ = ["ArmWorlds", "LoopContext", "Policy", "StepState", "closed_loop_rollout"]
