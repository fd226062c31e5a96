"""The DiT as a cross-embodiment controller, closed loop in a batched simulation.

`closed_loop_rollout(designs, motions, policy)` runs W = D * M worlds (design-major, world
``d * M + m`` is design d on motion m) like `tt.sim.rollout.rollout`, but every control
step asks a `Policy` for the joint position targets instead of running the DiffIK in the
kernel. Physics is tt's Warp kernels (`tt.kernels.dynamics`: the "warp" backend's
contact-free trees, one launch per topology group and control step, `substeps` physics
steps with the command held). The result is an `Episode` with the oracle's conventions
(`tt.sim.validate`): start at rest at the oracle's start posture, record the state after
each step, end a world at the first step whose summed position error exceeds the
threshold (that record kept with alive False, later ones repeated), targets at index
``min(k, T_m - 1)``; so `tt.sim.rewards` scores it like any other rollout.

Policies:

* `ModelPolicy`: the trained DiT's control task (`tt.dit.tasks`), 5 DDIM steps per
  control step (the paper's), batched over the worlds still running.
* `IKPolicy`: the oracle's DiffIK with look-ahead (`tt.kernels.ik`), the reference the
  model is compared with; with it the loop reproduces the "warp" backend's rollout.

What the model is given at control step k, mirroring training. In the data, the record
of step j holds the state *after* the physics of step j and the command of step j, and
the DiffIK command of step j + 1 is computed from the state of record j and the target
at j + 1 + 4 (look-ahead). A control-task training window starts at a step j and holds:
the embodiment tokens (clean), the dynamics tokens of record j (clean: the "current
state"), the target poses of steps j .. j + 7 (clean) and, diffused, the commands of
steps j .. j + 7 and the states of records j + 1 .. j + 7. At control step k >= 1 the
measured state is record k - 1, so the query is the window starting at j = k - 1 (time
IDs k - 1 .. k + 6), and the command executed is the predicted command of the window's
second step, step k: the one that followed from that state in the data. At k = 0 there
is no record yet: the start posture at rest (with the command that holds it) stands in
for record 0 and the window's first command is executed. Targets past the motion's end
repeat its last pose, as the DiffIK's look-ahead does.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, Sequence

import mujoco
import numpy as np
import torch

from tt.dit.checkpoint import TrainedModel, load_checkpoint, load_model
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import STEP_ROLES
from tt.dit.layout import Layout, LayoutError
from tt.dit.sampling import sample
from tt.dit.tasks import CONTROL, TaskSpec
from tt.sim.controller import IKConfig, check_fixed_base
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion

log = logging.getLogger(__name__)

#: Controllers of `tt validate --controller`.
CONTROLLERS = ("ik", "model")


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


# ------------------------------------------------------------------------------ physics
def _make_step_kernel(topology, module: str):
    """Physics of one control step for W worlds of one topology: `substeps` Euler steps with
    the command held, then the record of the new state (the actuator force and velocity
    and end-effector poses that belong to it), exactly as the fused rollout kernel does."""
    import warp as wp

    from tt.kernels.dynamics import dynamics_funcs
    from tt.kernels.fk import kinematics_funcs
    from tt.kernels.lie import wxyz
    from tt.kernels.model import local_types

    T = local_types(topology)
    K = kinematics_funcs(topology)
    Dyn = dynamics_funcs(topology)
    NV, NU, NE = topology.dof_count, topology.actuator_count, topology.ee_count

    @wp.kernel(module=module)
    def _control_step(
        # Model:
        body_pos: wp.array2d(dtype=wp.vec3),
        body_quat: wp.array2d(dtype=wp.vec4),
        body_mass: wp.array2d(dtype=float),
        body_ipos: wp.array2d(dtype=wp.vec3),
        body_iquat: wp.array2d(dtype=wp.vec4),
        body_inertia: wp.array2d(dtype=wp.vec3),
        dof_axis: wp.array2d(dtype=wp.vec3),
        dof_pos: wp.array2d(dtype=wp.vec3),
        dof_ref: wp.array2d(dtype=float),
        dof_armature: wp.array2d(dtype=float),
        dof_damping: wp.array2d(dtype=float),
        dof_stiffness: wp.array2d(dtype=float),
        dof_springref: wp.array2d(dtype=float),
        dof_range: wp.array2d(dtype=wp.vec2),
        dof_limit_kb: wp.array2d(dtype=wp.vec2),
        dof_solimp: wp.array3d(dtype=float),
        dof_invweight0: wp.array2d(dtype=float),
        act_gain: wp.array2d(dtype=float),
        act_bias: wp.array2d(dtype=wp.vec3),
        act_gear: wp.array2d(dtype=float),
        act_ctrlrange: wp.array2d(dtype=wp.vec2),
        act_forcerange: wp.array2d(dtype=wp.vec2),
        gravity: wp.array(dtype=wp.vec3),
        timestep: wp.array(dtype=float),
        limit_enabled: wp.array(dtype=wp.int32),
        limit_sweeps: wp.array(dtype=wp.int32),
        ee_pos: wp.array2d(dtype=wp.vec3),
        ee_quat: wp.array2d(dtype=wp.vec4),
        # In:
        substeps: int,
        ctrl_in: wp.array2d(dtype=float),
        # Data in / out (physics state):
        qpos_state: wp.array2d(dtype=float),
        qvel_state: wp.array2d(dtype=float),
        # Data out (the record of the new state):
        act_force_out: wp.array2d(dtype=float),
        act_vel_out: wp.array2d(dtype=float),
        ee_pos_out: wp.array2d(dtype=wp.vec3),
        ee_quat_out: wp.array2d(dtype=wp.vec4),
    ):
        worldid = wp.tid()
        mid = worldid % body_pos.shape[0]
        ctrl = T.act_vec()
        for u in range(NU):
            cr = act_ctrlrange[mid, u]
            ctrl[u] = wp.clamp(ctrl_in[worldid, u], cr[0], cr[1])
        for k in range(substeps):
            # The state goes through memory each substep, as in the fused rollout kernel.
            qk = T.dof_vec()
            qdk = T.dof_vec()
            for d in range(NV):
                qk[d] = qpos_state[worldid, d]
                qdk[d] = qvel_state[worldid, d]
            qn, qdn, force, vel, active = Dyn.step(
                mid,
                body_pos, body_quat, body_mass, body_ipos, body_iquat, body_inertia,
                dof_axis, dof_pos, dof_ref, dof_armature, dof_damping, dof_stiffness, dof_springref,
                dof_range, dof_limit_kb, dof_solimp, dof_invweight0,
                act_gain, act_bias, act_gear, act_ctrlrange, act_forcerange,
                gravity, timestep, limit_enabled, limit_sweeps,
                qk, qdk, ctrl,
            )  # fmt: skip
            for d in range(NV):
                qpos_state[worldid, d] = qn[d]
                qvel_state[worldid, d] = qdn[d]
        q1 = T.dof_vec()
        qd1 = T.dof_vec()
        for d in range(NV):
            q1[d] = qpos_state[worldid, d]
            qd1[d] = qvel_state[worldid, d]
        qfrc, force1, vel1 = Dyn.actuation(mid, act_gain, act_bias, act_gear, act_ctrlrange, act_forcerange, q1, qd1, ctrl)
        for u in range(NU):
            act_force_out[worldid, u] = force1[u]
            act_vel_out[worldid, u] = vel1[u]
        xpos1, xquat1, axis1, anchor1 = K.kinematics(mid, body_pos, body_quat, dof_axis, dof_pos, dof_ref, q1)
        for e in range(NE):
            p, r = wp.static(K.site_pose[e])(xpos1, xquat1, ee_pos, ee_quat, mid)
            ee_pos_out[worldid, e] = p
            ee_quat_out[worldid, e] = wxyz(r)

    return _control_step


@functools.cache
def _step_kernel(topology):
    """The control-step kernel of a topology, in its own Warp module (compiled once)."""
    import warp as wp

    from tt.kernels.model import MODULE_OPTIONS, module_name

    module = module_name(topology, "dit_control")
    wp.set_module_options(MODULE_OPTIONS, module)
    return _make_step_kernel(topology, module)


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

    def __init__(self, models: Sequence[mujoco.MjModel], sites: Sequence[str], motions: Sequence[Motion], *,
                 config: IKConfig = IKConfig(), device: str | None = None):
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
            raise ValueError(f"need at least one design and one motion, got {D} and {M}")
        for i, m in enumerate(self.models):
            check_fixed_base(m)
            check_supported(m, i)
        subs = {config.substeps(m) for m in self.models}
        if len(subs) != 1:
            raise ValueError(f"designs need different physics steps per control step {sorted(subs)}; give designs of one timestep")
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

        from tt.kernels.ik import ik_weights
        from tt.kernels.rollout import motion_arrays, rollout_kernels

        M, A = len(self.motions), len(self.sites)
        first_pos = np.stack([m.pos[:1] for m in self.motions])  # (M, 1, A, 3)
        first_quat = np.stack([m.quat[:1] for m in self.motions])
        marrays = motion_arrays(first_pos, first_quat, [1] * M, device=self.device)
        hold = torch.zeros(self.world_count, self.nu, device=self.torch_device)
        for g in self.groups:
            wg = len(g.worlds)
            k64 = g.tree.kinematics64
            q_iter = wp.zeros((wg, 1, g.nv), dtype=wp.float64, device=self.device)
            start = wp.zeros((wg, 1, g.nv), dtype=float, device=self.device)
            wp.launch(
                rollout_kernels(g.tree.topology).initial_posture,
                dim=wg,
                inputs=[
                    k64.body_pos, k64.body_quat, k64.dof_axis, k64.dof_pos, k64.dof_ref, k64.dof_range,
                    k64.ee_pos, k64.ee_quat, ik_weights(self.config), int(self.config.init_iterations),
                    marrays.first_pos, marrays.first_quat,
                ],  # fmt: skip
                outputs=[q_iter, start],
                device=self.device,
            )
            g.views["qpos"].copy_(wp.to_torch(start)[:, 0])
            g.views["qvel"].zero_()
            act = torch.as_tensor(g.tree.topology.actuator_dof, dtype=torch.long, device=self.torch_device)
            hold[g.worlds, : g.nu] = g.views["qpos"][:, act]
        self._advance(hold, 0)
        return self.state

    def step(self, ctrl: torch.Tensor) -> StepState:
        """One control period of every world with joint position targets `ctrl` (W, NU)
        (clipped to each actuator's ctrlrange, as MuJoCo executes them); returns the new state."""
        if tuple(ctrl.shape) != (self.world_count, self.nu):
            raise ValueError(f"ctrl has shape {tuple(ctrl.shape)}; expected (W={self.world_count}, NU={self.nu})")
        return self._advance(ctrl, self.substeps)

    def _advance(self, ctrl: torch.Tensor, substeps: int) -> StepState:
        import warp as wp

        from tt.kernels.dynamics import model_inputs

        ctrl = torch.minimum(torch.maximum(ctrl.to(self.torch_device, torch.float32), self.ctrl_low), self.ctrl_high)
        s = self.state
        for g in self.groups:
            a, v = g.arrays, g.views
            v["ctrl"][:, : g.nu].copy_(ctrl[g.worlds, : g.nu])
            wp.launch(
                _step_kernel(g.tree.topology),
                dim=len(g.worlds),
                inputs=[*model_inputs(g.tree), g.tree.ee_pos, g.tree.ee_quat, int(substeps), a["ctrl"], a["qpos"], a["qvel"]],
                outputs=[a["act_force"], a["act_vel"], a["ee_pos"], a["ee_quat"]],
                device=self.device,
            )
            s.qpos[g.worlds, : g.nv] = v["qpos"]
            s.qvel[g.worlds, : g.nv] = v["qvel"]
            s.ctrl[g.worlds, : g.nu] = v["ctrl"][:, : g.nu]
            s.act_force[g.worlds, : g.nu] = v["act_force"][:, : g.nu]
            s.act_vel[g.worlds, : g.nu] = v["act_vel"][:, : g.nu]
            s.ee_pos[g.worlds] = v["ee_pos"]
            s.ee_quat[g.worlds] = v["ee_quat"]
        return s


# ------------------------------------------------------------------------------ the loop
def _models(designs) -> tuple[list[mujoco.MjModel], tuple[str, ...]]:
    from tt.sim.backends.base import resolve_designs

    robots = resolve_designs(designs, who="the model's closed-loop rollout", contacts=False)
    return list(robots.models), robots.ee_sites


def closed_loop_rollout(designs, motions: Sequence[Motion], policy: Policy, *, config: IKConfig = IKConfig(),
                        device: str | None = None, steps: int | None = None, progress: bool = False) -> Episode:
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
        raise ValueError("motions is empty; a closed-loop rollout needs at least one motion")
    for j, m in enumerate(motions):
        if not isinstance(m, Motion):
            raise TypeError(f"motions[{j}] is a {type(m).__name__}; expected tt.sim.motions.base.Motion")
        if abs(m.dt - config.control_dt) > 1e-9:
            raise ValueError(f"motions[{j}] ({m.name!r}) has dt = {m.dt} s; the controller runs at {config.control_dt} s")
        if m.arms != len(sites):
            raise ValueError(f"motions[{j}] ({m.name!r}) has {m.arms} arm(s); the designs have {len(sites)} end effector(s)")
    sim = ArmWorlds(models, sites, motions, config=config, device=device)
    log.debug("closed loop: %d designs x %d motions in %d topology group(s), policy %s",
              len(models), len(motions), len(sim.groups), type(policy).__name__)
    dev = sim.torch_device
    W, A = sim.world_count, len(sites)
    T = max(m.steps for m in motions) if steps is None else int(steps)
    if T < 1:
        raise ValueError(f"steps = {steps}; a rollout needs at least one control step")
    lengths = torch.tensor([min(m.steps, T) for m in motions], device=dev)[sim.motion_index]  # (W,)
    horizon = max(T, max(m.steps for m in motions))
    pos = np.zeros((len(motions), horizon, A, 3), np.float32)
    quat = np.zeros((len(motions), horizon, A, 4), np.float32)
    for j, m in enumerate(motions):
        idx = np.minimum(np.arange(horizon), m.steps - 1)
        pos[j], quat[j] = m.pos[idx], m.quat[idx]
    target_pos = torch.as_tensor(pos, device=dev)[sim.motion_index]  # (W, horizon, A, 3)
    target_quat = torch.as_tensor(quat, device=dev)[sim.motion_index]
    ctx = LoopContext(models, motions, sim.design_index, sim.motion_index, target_pos, target_quat, lengths, config, sim)

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
                raise ValueError(f"policy returned commands of shape {tuple(cmd.shape)} at step {k}; expected ({len(worlds)}, {sim.nu})")
            ctrl[worlds] = cmd[:, : sim.nu].to(dev, torch.float32)
        # Stopped worlds keep their last command; their physics runs on unrecorded.
        state = sim.step(ctrl)
        fresh = {"qpos": state.qpos, "qvel": state.qvel, "ctrl": state.ctrl, "act_force": state.act_force,
                 "act_vel": state.act_vel, "ee_pos": state.ee_pos, "ee_quat": state.ee_quat}
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
        target_quat=target_quat[:, :T].contiguous(), alive=alive, fallen=torch.zeros(W, T, dtype=torch.bool, device=dev),
        design_index=sim.design_index.clone(), motion_index=sim.motion_index.clone(), dt=config.control_dt,
    )  # fmt: skip


# ------------------------------------------------------------------------------ policies
class IKPolicy:
    """The oracle's controller as a policy: one DiffIK step (`tt.kernels.ik.ik_step`, mink's
    problem in float32) toward the motion pose ``min(k + lookahead, T_m - 1)``, the command
    of each actuated joint. With it `closed_loop_rollout` reproduces the "warp" backend."""

    def reset(self, ctx: LoopContext) -> None:
        self.ctx = ctx
        dev = ctx.target_pos.device
        self._act = [torch.as_tensor(g.tree.topology.actuator_dof, dtype=torch.long, device=dev) for g in ctx.worlds.groups]

    def __call__(self, step: int, worlds: torch.Tensor, state: StepState) -> torch.Tensor:
        import warp as wp

        from tt.kernels.ik import ik_step

        ctx = self.ctx
        sim = ctx.worlds
        goal = min(step + ctx.config.lookahead_steps, ctx.target_pos.shape[1] - 1)
        ctrl = torch.zeros(ctx.world_count, sim.nu, device=state.qpos.device)
        for g, act in zip(sim.groups, self._act):
            q = wp.from_torch(state.qpos[g.worlds, : g.nv].contiguous())
            tpos = wp.from_torch(ctx.target_pos[g.worlds, goal].contiguous(), dtype=wp.vec3)
            tquat = wp.from_torch(ctx.target_quat[g.worlds, goal].contiguous(), dtype=wp.vec4)
            q_cmd = wp.to_torch(ik_step(g.tree, q, tpos, tquat, ctx.config, device=sim.device))
            ctrl[g.worlds, : g.nu] = q_cmd[:, act]
        return ctrl[worlds]


@dataclass(frozen=True)
class ControllerConfig:
    """How the model controls. num_steps: DDIM steps per control step (the paper's 5, all
    of the control process's); eta: DDIM noise (0: deterministic given the seed); seed: of
    the initial noise of every query (one generator for the whole run)."""

    num_steps: int = 5
    eta: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.num_steps < 1:
            raise ValueError(f"ControllerConfig.num_steps = {self.num_steps}; must be >= 1")
        if not self.eta >= 0:
            raise ValueError(f"ControllerConfig.eta = {self.eta}; must be >= 0")


def control_task(checkpoint: str | Path) -> TaskSpec:
    """The control task a checkpoint was trained on (its diffusion steps and whether it
    diffused the future states), `tt.dit.tasks.CONTROL` when the checkpoint does not say."""
    path = Path(checkpoint)
    if path.is_dir():
        from tt.dit.checkpoint import latest_checkpoint

        found = latest_checkpoint(path)
        if found is None:
            raise FileNotFoundError(f"run folder {path} has no checkpoints under {path / 'checkpoints'}")
        path = found
    cfg = load_checkpoint(path).get("train_config") or {}
    if cfg.get("task", "control") == "robot":
        raise ValueError(f"checkpoint {path} was trained on the robot task only; the controller needs task control or both")
    return TaskSpec("control", int(cfg.get("control_diffusion_steps", CONTROL.diffusion_steps)), "consecutive",
                    bool(cfg.get("future_states", CONTROL.future_states)))


class ModelPolicy:
    """The DiT's control task as a batched policy (see the module docstring for the query).

    trained: the model (EMA weights), its normaliser and layout; task: the control task it
    was trained on (`control_task`); config: `ControllerConfig`.
    """

    def __init__(self, trained: TrainedModel, *, task: TaskSpec = CONTROL, config: ControllerConfig = ControllerConfig()):
        if task.name != "control":
            raise ValueError(f"ModelPolicy runs the control task, got task {task.name!r}")
        if config.num_steps > task.diffusion_steps:
            raise ValueError(f"ControllerConfig.num_steps = {config.num_steps}; the control process has {task.diffusion_steps} steps")
        layout = trained.layout
        need = {"control", "target_pose"}
        missing = sorted(need - set(layout.names))
        if missing:
            raise LayoutError(f"the model's layout lacks {missing}; the controller needs control and target_pose tokens")
        self.trained = trained
        self.task = task
        self.config = config
        self.layout: Layout = layout
        self.model = trained.model.eval()
        self.device = next(self.model.parameters()).device

    def reset(self, ctx: LoopContext) -> None:
        """Tokenize the designs (embodiment tokens, padded to the layout) and index their actuators."""
        from tt.dit.layout import robot_embodiment

        self.ctx = ctx
        layout, dev = self.layout, self.device
        static, self.robots = robot_embodiment(layout, self.trained.normalizer, ctx.models, dev)
        self._static = {n: (static.values[n], static.ids[n], static.mask[n]) for n in static.values}
        for s in layout.specs:
            if s.role in STEP_ROLES:
                widest = max(_step_count(s.name, r) for r in self.robots)
                if widest > s.per_step:
                    raise LayoutError(f"a design has {widest} {s.name} tokens per step; the model's layout holds {s.per_step}")
        P = layout["control"].per_step
        act = torch.full((len(self.robots), P), -1, dtype=torch.long)
        for d, r in enumerate(self.robots):
            act[d, : len(r.actuator_mj)] = torch.as_tensor(np.asarray(r.actuator_mj), dtype=torch.long)
        self._actuator = act.to(ctx.target_pos.device)  # (D, P): MuJoCo actuator of each control slot
        self.generator = torch.Generator(device=dev).manual_seed(int(self.config.seed))

    def query(self, step: int, worlds: torch.Tensor, state: StepState) -> tuple[TokenBatch, int]:
        """Normalised control-task tokens of worlds `worlds` at control step `step`, and the
        window slot whose command is executed (1, or 0 at step 0)."""
        from tt.tokens.episodes import episode_tokens

        ctx, layout, norm = self.ctx, self.layout, self.trained.normalizer
        S = layout.steps
        start = max(step - 1, 0)
        slot = 1 if step >= 1 else 0
        n = len(worlds)
        horizon = ctx.target_pos.shape[1]
        idx = torch.clamp(torch.arange(start, start + S, device=worlds.device), max=horizon - 1)
        # An S-step episode whose every record is the current state: the tokens of its first
        # step are the window's clean state; the later ones are diffused (their values unused).
        rep = lambda x: x[worlds][:, None].expand(n, S, *x.shape[1:]).contiguous()  # noqa: E731
        ep = Episode(
            qpos=rep(state.qpos), qvel=rep(state.qvel), ctrl=rep(state.ctrl), action=rep(state.ctrl),
            act_force=rep(state.act_force), act_vel=rep(state.act_vel), ee_pos=rep(state.ee_pos), ee_quat=rep(state.ee_quat),
            target_pos=ctx.target_pos[worlds][:, idx], target_quat=ctx.target_quat[worlds][:, idx],
            alive=torch.ones(n, S, dtype=torch.bool, device=worlds.device),
            fallen=torch.zeros(n, S, dtype=torch.bool, device=worlds.device),
            design_index=ctx.design_index[worlds], motion_index=ctx.motion_index[worlds], dt=ctx.config.control_dt,
        )  # fmt: skip
        window = episode_tokens(ep, self.robots, step_index=torch.arange(S, device=worlds.device).expand(n, S))
        dev = self.device
        design = ctx.design_index[worlds].to(dev)
        values, ids, mask = {}, {}, {}
        for s in layout.specs:
            if s.role not in STEP_ROLES:
                v, i, m = self._static[s.name]
                values[s.name], ids[s.name], mask[s.name] = v[design], i[design], m[design]
                continue
            P = s.per_step
            if s.name in window.values:
                v = window.values[s.name].to(dev)
                e = v.shape[1] // S
                v = v.reshape(n, S, e, -1)
                i = window.ids[s.name].to(dev).reshape(n, S, e, -1)
                m = window.mask[s.name].to(dev).reshape(n, S, e)
            else:  # a type none of these designs has: all padding
                e = 0
                v = torch.zeros(n, S, 0, s.dim, device=dev)
                i = torch.zeros(n, S, 0, len(s.ids), dtype=torch.long, device=dev)
                m = torch.zeros(n, S, 0, dtype=torch.bool, device=dev)
            pad = P - e
            v = torch.cat([v, v.new_zeros(n, S, pad, s.dim)], 2)
            i = torch.cat([i, i.new_zeros(n, S, pad, len(s.ids))], 2)
            m = torch.cat([m, m.new_zeros(n, S, pad)], 2)
            i[..., s.time_index] = torch.arange(start, start + S, device=dev)[None, :, None]
            values[s.name] = norm.normalize_values(s.name, v.reshape(n, S * P, s.dim), m.reshape(n, S * P))
            ids[s.name] = i.reshape(n, S * P, -1)
            mask[s.name] = m.reshape(n, S * P)
        return TokenBatch(values, ids, mask), slot

    def __call__(self, step: int, worlds: torch.Tensor, state: StepState) -> torch.Tensor:
        from tt.dit.ddim import CosineDDIM

        tokens, slot = self.query(step, worlds, state)
        c = self.config
        with torch.no_grad():
            res = sample(self.model, tokens, self.task, scheduler=CosineDDIM(self.task.diffusion_steps),
                         num_steps=c.num_steps, eta=c.eta, generator=self.generator)
        P = self.layout["control"].per_step
        n = len(worlds)
        out = res.tokens.values["control"].reshape(n, self.layout.steps, P, -1)[:, slot]  # (n, P, 1)
        target = self.trained.normalizer.denormalize_values("control", out.float())[..., 0]  # (n, P) [rad or m]
        target = target.to(worlds.device)
        act = self._actuator[self.ctx.design_index[worlds]]  # (n, P)
        sim = self.ctx.worlds
        ctrl = state.ctrl[worlds].clone()
        rows = torch.arange(n, device=worlds.device)[:, None].expand(n, P)
        real = act >= 0
        ctrl[rows[real], act[real]] = target[real]
        return ctrl[:, : sim.nu]


def _step_count(name: str, robot) -> int:
    """Tokens per control step of per-step type `name` for one tokenized robot."""
    counts = robot.counts
    key = {"free_link_obs": "free_link", "track_link_obs": "track_link", "dyna_joint_obs": "dyna_joint",
           "ball_joint_obs": "ball_joint", "actuator_obs": "actuator", "control": "actuator",
           "target_pose": "track_link"}.get(name)
    return counts[key] if key is not None else 0


def model_rollout(designs, motions: Sequence[Motion], model: TrainedModel | str | Path, *,
                  config: ControllerConfig = ControllerConfig(), task: TaskSpec | None = None,
                  ik_config: IKConfig = IKConfig(), device: str | None = None, steps: int | None = None,
                  progress: bool = False) -> Episode:
    """`closed_loop_rollout` with the DiT as the controller.

    model: a loaded model, or a checkpoint file / run folder (loaded with EMA weights on
    `device`; its control task read from the checkpoint); task: the control task (default:
    the checkpoint's, or `tt.dit.tasks.CONTROL` for a loaded model).
    """
    if not isinstance(model, TrainedModel):
        import warp as wp

        from tt.kernels.device import resolve_device

        task = control_task(model) if task is None else task
        model = load_model(model, device=str(wp.device_to_torch(resolve_device(device))))
    policy = ModelPolicy(model, task=task or CONTROL, config=config)
    return closed_loop_rollout(designs, motions, policy, config=ik_config, device=device, steps=steps, progress=progress)


__all__ = [
    "CONTROLLERS",
    "ArmWorlds",
    "ControllerConfig",
    "IKPolicy",
    "LoopContext",
    "ModelPolicy",
    "Policy",
    "StepState",
    "closed_loop_rollout",
    "control_task",
    "model_rollout",
]
