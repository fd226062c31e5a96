"""The ``newton`` rollout backend: Newton's Featherstone solver, a differentiable second reference.

All designs go into one Newton model: each design's MJCF text is imported with Newton's
MJCF importer (`newton.ModelBuilder.add_mjcf`) into a builder of its own, and that
builder is added as one world per motion (`ModelBuilder.add_world`), so world
``d * M + m`` is design d on motion m, as in every tt backend. Designs of any topology
mix in one model; `newton.solvers.SolverFeatherstone` integrates them together in
generalized coordinates (``State.joint_q``, ``joint_qd``).

What is made to match MuJoCo (the MJCF is the one source of truth):

* actuators: MuJoCo's position servos with force limits, ``force = clamp(gain ctrl + b0 +
  b1 gear q + b2 gear qd, forcerange)``, applied as ``Control.joint_f = gear force``
  every physics step (Newton's own joint drive has no force limit, so its gains are
  zeroed);
* joint damping: MuJoCo's Euler integrator treats ``dof_damping`` implicitly, i.e. solves
  ``(M + h diag(damping)) qacc = f``; adding ``h * damping`` to Newton's armature gives
  Featherstone's semi-implicit Euler the same update (Featherstone's explicit
  ``-damping qd`` stays in ``f`` as in MuJoCo). Without it the light wrist joints drift
  by ~1e-3 rad in 0.1 s;
* ``angular_damping`` of the solver is 0 (MuJoCo has none);
* joint limits are Newton penalty springs, not MuJoCo's soft constraints: their
  stiffness and damping are set from MuJoCo's ``solref`` reference acceleration
  (``k = 1 / (dmax^2 timeconst^2 dampratio^2)``, ``b = 2 / (dmax timeconst)``) times the
  dof's inertia at qpos0 (``1 / dof_invweight0``). This is an approximation: away from
  the limits Newton matches MuJoCo C to float32 round-off, at a limit it does not.

Contacts are off (arms only: Featherstone has no equality constraints, which the
quadruped's linkage legs need). The controller is the oracle's DiffIK computed by tt's
batched IK kernel on Newton's ``joint_q`` (one launch per topology group), the start
posture the oracle's float64 IK; end-effector poses are read from Newton's body frames
(``State.body_q`` after `newton.eval_fk`) and the MuJoCo site offsets. This module is host
code: the kernels it launches live in `tt.kernels` (`flat_joints`: actuators, state and
site poses on Newton's flat joint vectors; `control`, `records`: the IK targets, actuator
commands and Episode records shared with the ``mjwarp`` backend).

Open-loop simulation (`newton_simulate`) can be recorded on a `wp.Tape` with
``requires_grad=True``: one State per physics step, gradients of the trajectory with
respect to the commands flow through Featherstone (MuJoCo-Warp's do not, see
`tt.sim.mjwarp_backend`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.flat_joints import actuator_record, apply_actuators, body_site_poses, gather_state
from tt.sim.backends import Robots, get_backend
from tt.sim.controller import IKConfig, actuated_qpos, check_fixed_base, model_name
from tt.sim.designs import Design
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion

logger = logging.getLogger(__name__)

_HINGE_OR_SLIDE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
#: MuJoCo's bounds on constraint impedance and its smallest positive value.
_MJ_MINIMP, _MJ_MAXIMP, _MJ_MINVAL = 1e-4, 0.9999, 1e-15


# --------------------------------------------------------------------------- model


def _limit_gains(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Penalty stiffness [N m/rad or N/m] and damping [N m s/rad or N s/m] per dof that
    approximate MuJoCo's joint-limit constraint (see the module docstring), (nv,) each."""
    ke = np.zeros(m.nv)
    kd = np.zeros(m.nv)
    refsafe = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    for j in range(m.njnt):
        if int(m.jnt_type[j]) not in _HINGE_OR_SLIDE:
            continue
        timeconst, dampratio = m.jnt_solref[j]
        dmax = float(np.clip(m.jnt_solimp[j, 1], _MJ_MINIMP, _MJ_MAXIMP))
        if refsafe and timeconst > 0:
            timeconst = max(timeconst, 2.0 * m.opt.timestep)
        if timeconst <= 0:  # MuJoCo's direct form: solref = (-stiffness, -damping)
            k, b = -timeconst, -dampratio
        else:
            k = 1.0 / max(_MJ_MINVAL, dmax * dmax * timeconst * timeconst * dampratio * dampratio)
            b = 2.0 / max(_MJ_MINVAL, dmax * timeconst)
        dof = int(m.jnt_dofadr[j])
        inertia = 1.0 / max(float(m.dof_invweight0[dof]), _MJ_MINVAL)
        ke[dof], kd[dof] = k * inertia, b * inertia
    return ke, kd


def _check_newton_model(m: mujoco.MjModel, index: int) -> None:
    """Raise ValueError naming what the newton backend cannot simulate like MuJoCo."""
    check_fixed_base(m)
    where = f"designs[{index}] ({model_name(m)!r})"
    kinds = set(int(t) for t in m.jnt_type)
    if not kinds <= set(_HINGE_OR_SLIDE):
        raise TTError(f"{where}: joint types {sorted(kinds)}; the newton backend simulates hinge and slide joints")
    contact_off = bool(m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT)
    if not contact_off and (np.any((m.geom_contype[:, None] & m.geom_conaffinity[None, :]) != 0) or m.npair):
        raise TTError(f"{where} has contacts; the newton backend runs contact-free arms (use backend='mjwarp')")
    if m.neq or m.ntendon:
        raise TTError(
            f"{where}: neq = {m.neq}, ntendon = {m.ntendon}; Featherstone has no equality constraints or tendons"
        )
    if int(m.opt.integrator) != int(mujoco.mjtIntegrator.mjINT_EULER):
        raise TTError(
            f"{where}: integrator {mujoco.mjtIntegrator(m.opt.integrator).name}; the newton backend matches Euler"
        )
    for u in range(m.nu):
        if (
            int(m.actuator_gaintype[u]) != int(mujoco.mjtGain.mjGAIN_FIXED)
            or int(m.actuator_biastype[u]) not in (int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE))
            or int(m.actuator_dyntype[u]) != int(mujoco.mjtDyn.mjDYN_NONE)
        ):
            raise TTError(f"{where}: actuator {u} is not a stateless fixed-gain affine actuator (position servo)")
    if len(set(m.actuator_trnid[:, 0].tolist())) != m.nu:
        raise TTError(f"{where}: several actuators drive one joint; the newton backend applies one force per joint")
    if np.any(m.body_gravcomp != 0):
        raise TTError(
            f"{where}: body_gravcomp is nonzero; gravity compensation is not replicated on Newton "
            "(use backend='warp', 'mjwarp' or 'mujoco')"
        )
    if np.any(m.dof_frictionloss != 0):
        raise TTError(f"{where}: dof_frictionloss is nonzero; friction loss is not replicated on Newton")


def _design_inputs(designs: Sequence[Design] | Robots) -> tuple[list[mujoco.MjModel], list[str], tuple[str, ...]]:
    """MuJoCo models, MJCF texts and end-effector sites of tt Designs (one contact-free space)."""
    robots = designs if isinstance(designs, Robots) else get_backend("newton").resolve(designs)
    for i, xml in enumerate(robots.mjcf):
        if xml is None:
            raise TypeError(
                f"designs[{i}] is a {type(robots.models[i]).__name__}; the newton backend imports MJCF text and needs "
                "tt Designs (an MjModel does not carry its MJCF)"
            )
    for i, m in enumerate(robots.models):
        _check_newton_model(m, i)
    return list(robots.models), list(robots.mjcf), robots.ee_sites


@dataclass
class NewtonWorlds:
    """W worlds of tt designs in one Newton model, with the index maps tt needs.

    worlds_of_design: world w runs ``models[design_of_world[w]]``.
    q_start, qd_start: (W,) first joint coordinate / dof of world w's MuJoCo joints in
        ``State.joint_q`` / ``joint_qd``; the design's qpos are the next nq entries in
        MuJoCo's order.
    """

    model: object  # newton.Model
    solver: object  # newton.solvers.SolverFeatherstone
    mj_models: list
    design_of_world: np.ndarray
    q_start: np.ndarray
    qd_start: np.ndarray
    device: str

    @property
    def world_count(self) -> int:
        return len(self.design_of_world)


def build_worlds(
    mj_models: Sequence[mujoco.MjModel],
    xmls: Sequence[str],
    repeats: int = 1,
    *,
    device: str,
    requires_grad: bool = False,
) -> NewtonWorlds:
    """Newton model with ``repeats`` worlds of each design (design-major), set up to match
    MuJoCo (see the module docstring); one MJCF import per design."""
    import newton

    builder = newton.ModelBuilder()
    for xml in xmls:
        sub = newton.ModelBuilder()
        sub.add_mjcf(xml, parse_visuals=False, parse_sites=False)
        for _ in range(repeats):
            builder.add_world(sub)
    model = builder.finalize(device=device, requires_grad=requires_grad)
    W = len(xmls) * repeats
    design_of_world = np.repeat(np.arange(len(xmls)), repeats)
    if model.articulation_count != W:
        raise ValueError(
            f"Newton built {model.articulation_count} articulations for {W} worlds; expected one per world"
        )

    labels = model.joint_label
    art = model.articulation_start.numpy()
    jtype = model.joint_type.numpy()
    jq = model.joint_q_start.numpy()
    jqd = model.joint_qd_start.numpy()
    q_start = np.zeros(W, np.int64)
    qd_start = np.zeros(W, np.int64)
    for w in range(W):
        m = mj_models[design_of_world[w]]
        joints = [j for j in range(art[w], art[w + 1]) if jtype[j] != int(newton.JointType.FIXED)]
        names = [labels[j].rsplit("/", 1)[-1] for j in joints]
        expected = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)]
        if names != expected:
            raise ValueError(f"world {w}: Newton's joints {names} do not follow the MuJoCo joints {expected}")
        q_start[w], qd_start[w] = jq[joints[0]], jqd[joints[0]]
        if jq[joints[-1]] - jq[joints[0]] != m.nq - 1:
            raise ValueError(f"world {w}: Newton's joint coordinates of {model_name(m)!r} are not contiguous")

    # MuJoCo's servos replace Newton's drives; implicit Euler damping folds into armature.
    model.joint_target_ke.zero_()
    model.joint_target_kd.zero_()
    armature = model.joint_armature.numpy()
    limit_ke = model.joint_limit_ke.numpy()
    limit_kd = model.joint_limit_kd.numpy()
    for w in range(W):
        m = mj_models[design_of_world[w]]
        dofs = slice(qd_start[w], qd_start[w] + m.nv)
        damper = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_DAMPER)
        armature[dofs] = m.dof_armature + (m.opt.timestep * m.dof_damping if damper else 0.0)
        limit_ke[dofs], limit_kd[dofs] = _limit_gains(m)
    model.joint_armature.assign(armature)
    model.joint_limit_ke.assign(limit_ke)
    model.joint_limit_kd.assign(limit_kd)
    solver = newton.solvers.SolverFeatherstone(model, angular_damping=0.0)
    return NewtonWorlds(model, solver, list(mj_models), design_of_world, q_start, qd_start, device)


@dataclass
class _Actuators:
    """Actuator parameters of a set of worlds of one topology, (Wg, NU) each."""

    act_qpos: wp.array
    gain: wp.array
    bias: wp.array
    gear: wp.array
    forcerange: wp.array


def _actuators(models: Sequence[mujoco.MjModel], *, device: str) -> _Actuators:
    m0 = models[0]
    forcerange = np.tile(np.array([-1e10, 1e10], np.float32), (len(models), m0.nu, 1))
    for i, m in enumerate(models):
        limited = m.actuator_forcelimited.astype(bool)
        forcerange[i, limited] = m.actuator_forcerange[limited]
    actuation = [not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_ACTUATION) for m in models]

    def arr(x, dtype):
        return wp.array(np.ascontiguousarray(x, dtype=np.float32), dtype=dtype, device=device)

    return _Actuators(
        act_qpos=wp.array(actuated_qpos(m0).astype(np.int32), dtype=int, device=device),
        gain=arr(np.stack([m.actuator_gainprm[:, 0] * on for m, on in zip(models, actuation)]), float),
        bias=arr(np.stack([m.actuator_biasprm[:, :3] * on for m, on in zip(models, actuation)]), wp.vec3),
        gear=arr(np.stack([m.actuator_gear[:, 0] for m in models]), float),
        forcerange=arr(forcerange, wp.vec2),
    )


# --------------------------------------------------------------------------- rollout


@dataclass
class _IKGroup:
    """The worlds of one topology in a Newton model: tt's IK kernel runs on them in one
    launch. Arrays are (Wg, ...) over the group's worlds, in the order of ``rows``."""

    rows: np.ndarray  # (Wg,) world (= Episode row) of each group world
    nq: int
    nu: int
    tree: object  # tt.kernels.model.TreeModel
    world_row: wp.array
    world_motion: wp.array
    q_start: wp.array  # first joint coordinate of each world in State.joint_q
    qd_start: wp.array  # first dof of each world in State.joint_qd
    act: _Actuators
    ranges: wp.array  # ctrl clamp, (Wg, NU) vec2
    ee_body: wp.array  # Newton body of each end effector, (Wg, NE) int
    ee_offset: wp.array  # site frame in that body's frame, (Wg, NE) transform
    qpos: wp.array
    qvel: wp.array
    q_cmd: wp.array
    ctrl: wp.array
    act_force: wp.array
    act_vel: wp.array
    target_pos: wp.array
    target_quat: wp.array
    ee_pos: wp.array
    ee_quat: wp.array

    @classmethod
    def build(
        cls, worlds: NewtonWorlds, rows: np.ndarray, models, sites, motion_count: int, *, device: str
    ) -> "_IKGroup":
        from tt.kernels.model import build_tree_model
        from tt.sim.mjwarp_backend import ctrl_ranges

        m0 = models[0]
        Wg, A, nu = len(rows), len(sites), max(m0.nu, 1)

        def zeros(width, dtype=float):
            return wp.zeros((Wg, width), dtype=dtype, device=device)

        def ints(x):
            return wp.array(np.asarray(x, np.int32), dtype=int, device=device)

        return cls(
            rows=rows, nq=m0.nq, nu=m0.nu, tree=build_tree_model(models, sites, device=device),
            world_row=ints(rows), world_motion=ints(np.arange(Wg) % motion_count),
            q_start=ints(worlds.q_start[rows]), qd_start=ints(worlds.qd_start[rows]),
            act=_actuators(models, device=device), ranges=wp.array(ctrl_ranges(models), dtype=wp.vec2, device=device),
            **_ee_frames(worlds, rows, models, sites, device=device),
            qpos=zeros(m0.nq), qvel=zeros(m0.nv), q_cmd=zeros(m0.nq), ctrl=zeros(nu), act_force=zeros(nu),
            act_vel=zeros(nu), target_pos=zeros(A, wp.vec3), target_quat=zeros(A, wp.vec4),
            ee_pos=zeros(A, wp.vec3), ee_quat=zeros(A, wp.vec4),
        )  # fmt: skip

    @property
    def world_count(self) -> int:
        return len(self.rows)

    def gather(self, state, device: str) -> None:
        """qpos, qvel of the group's worlds from Newton's flat joint vectors."""
        gather_state(self.q_start, self.qd_start, state.joint_q, state.joint_qd, self.qpos, self.qvel, device=device)

    def apply_actuators(self, state, control, device: str) -> None:
        """MuJoCo's servo forces at `state` into ``control.joint_f``."""
        if self.nu:
            a = self.act
            apply_actuators(
                self.q_start, self.qd_start, a.act_qpos, a.gain, a.bias, a.gear, a.forcerange, self.ctrl,
                state.joint_q, state.joint_qd, control.joint_f, device=device,
            )  # fmt: skip

    def observe(self, state, device: str) -> None:
        """The recorded quantities after a control step: qpos, qvel, actuator forces and
        velocities, end-effector poses (``state.body_q`` must be current)."""
        self.gather(state, device)
        if self.nu:
            a = self.act
            actuator_record(
                a.act_qpos, a.gain, a.bias, a.gear, a.forcerange, self.ctrl, self.qpos, self.qvel,
                self.act_force, self.act_vel, device=device,
            )  # fmt: skip
        body_site_poses(self.ee_body, self.ee_offset, state.body_q, self.ee_pos, self.ee_quat, device=device)


def newton_rollout(
    designs: Sequence[Design] | Robots,
    motions: Sequence[Motion],
    *,
    config: IKConfig = IKConfig(),
    device: str | None = None,
    progress: bool = False,
) -> Episode:
    """Run every design on every motion on Newton (Featherstone); an Episode of W = D * M worlds.

    designs: D tt Designs of one contact-free arm space (viperx, aloha, bimanual), or their
        `Robots` (`tt.sim.backends.base.resolve_designs`).
    motions: M motions sampled at ``config.control_dt``, one arm per end effector.
    Returns the oracle's Episode (`tt.sim.validate.oracle_rollout`'s conventions): worlds
    design-major, joint fields zero-padded, records repeated after termination.
    """
    import newton

    from tt.kernels.control import joint_command, lookahead_targets
    from tt.kernels.device import resolve_device
    from tt.kernels.ik import ik_step
    from tt.kernels.model import topology_key
    from tt.kernels.records import RecordArrays, record_step
    from tt.kernels.rollout import start_postures
    from tt.sim.mjwarp_backend import padded_motions, records_episode

    device = resolve_device(device)
    models, xmls, sites = _design_inputs(designs)
    D, M, A = len(models), len(motions), len(sites)
    substeps = config.substeps(models[0])
    dt = float(models[0].opt.timestep)
    if any(config.substeps(m) != substeps or m.opt.timestep != dt for m in models):
        raise TTError("designs have different timesteps; one Newton model steps all worlds with one dt")
    marrays, T = padded_motions(motions, A, config.control_dt, device=device)
    worlds = build_worlds(models, xmls, M, device=device)
    model, solver = worlds.model, worlds.solver

    # One Newton model for all worlds; tt's IK runs per topology group.
    members: dict[tuple, list[int]] = {}
    for d, m in enumerate(models):
        members.setdefault(topology_key(m, sites), []).append(d)
    logger.debug("newton rollout: %d designs in %d topology group(s), %d motions, T=%d", D, len(members), M, T)

    state, state_next = model.state(), model.state()
    control = model.control()
    control.joint_f.zero_()
    records = RecordArrays.zeros(
        D * M, T, max(m.nq for m in models), max(m.nv for m in models), max(m.nu for m in models), A, device=device
    )
    groups = []
    weights = config.ik_weights()
    joint_q = state.joint_q.numpy()
    for ds in members.values():
        rows = np.array([d * M + j for d in ds for j in range(M)], dtype=np.int64)
        g = _IKGroup.build(worlds, rows, [models[d] for d in ds for _ in range(M)], sites, M, device=device)
        start = start_postures(g.tree, marrays, config.init_ik_weights(), config.init_iterations, device=device).numpy()
        for i, w in enumerate(rows):
            joint_q[worlds.q_start[w] : worlds.q_start[w] + g.nq] = start[i]
        groups.append(g)
    state.joint_q.assign(joint_q)
    state.joint_qd.zero_()

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, desc="newton", unit="step")
    for t in range(T):
        for g in groups:
            g.gather(state, device)
            lookahead_targets(
                t, config.lookahead_steps, g.world_motion, marrays, g.target_pos, g.target_quat, device=device
            )
            ik_step(g.tree, g.qpos, g.target_pos, g.target_quat, weights, g.q_cmd, device=device)
            joint_command(g.q_cmd, g.act.act_qpos, g.ranges, g.ctrl, device=device)
        for _ in range(substeps):
            for g in groups:
                g.apply_actuators(state, control, device)
            solver.step(state, state_next, control, None, dt)
            state, state_next = state_next, state
        newton.eval_fk(model, state.joint_q, state.joint_qd, state)
        for g in groups:
            g.observe(state, device)
            record_step(
                records, t, threshold=config.termination_pos_error, world_row=g.world_row,
                world_motion=g.world_motion, motions=marrays, qpos=g.qpos, qvel=g.qvel, ctrl=g.ctrl,
                act_force=g.act_force, act_vel=g.act_vel, ee_pos=g.ee_pos, ee_quat=g.ee_quat, device=device,
            )  # fmt: skip
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return records_episode(records, D, M, max(m.nu for m in models), config.control_dt)


def _ee_frames(worlds: NewtonWorlds, rows: np.ndarray, models: Sequence[mujoco.MjModel], sites, *, device: str) -> dict:
    """Newton body index (Wg, NE) and site offset in that body's frame (Wg, NE) of each end
    effector, from the MuJoCo sites; bodies are matched by name within each world."""
    model = worlds.model
    labels = model.body_label
    starts = model.body_world_start.numpy()
    body = np.zeros((len(rows), len(sites)), np.int32)
    offset = np.zeros((len(rows), len(sites), 7), np.float32)
    for i, (w, m) in enumerate(zip(rows, models)):
        names = {labels[b].rsplit("/", 1)[-1]: b for b in range(starts[w], starts[w + 1])}
        for e, s in enumerate(sites):
            sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s)
            bname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.site_bodyid[sid]))
            if bname not in names:
                raise ValueError(f"world {w}: Newton has no body {bname!r} carrying site {s!r}")
            body[i, e] = names[bname]
            qw, qx, qy, qz = m.site_quat[sid]
            offset[i, e] = [*m.site_pos[sid], qx, qy, qz, qw]
    return {
        "ee_body": wp.array(body, dtype=int, device=device),
        "ee_offset": wp.array(offset, dtype=wp.transform, device=device),
    }


# --------------------------------------------------------------------------- open loop


@dataclass
class NewtonTrajectory:
    """Result of `newton_simulate`.

    qpos (W, S + 1, NQ), qvel (W, S + 1, NV): float64, zero-padded, entry 0 the initial state.
    With ``requires_grad``, the Warp arrays a `wp.Tape` differentiates: ``ctrl``, a list of
    (worlds, commands) pairs, worlds (Wg,) int and commands (Wg, S, nu) float, one per
    actuator layout; ``states``, the S + 1 Newton States (``joint_q`` of state s is the
    flat joint vector after s steps; ``worlds.q_start`` locates each world in it).
    """

    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: wp.array | None = None
    states: list | None = None
    worlds: NewtonWorlds | None = None


def newton_simulate(
    designs: Sequence[Design],
    ctrl: np.ndarray,
    *,
    qpos: np.ndarray | None = None,
    qvel: np.ndarray | None = None,
    device: str | None = None,
    requires_grad: bool = False,
) -> NewtonTrajectory:
    """Open-loop Featherstone simulation of W designs under given actuator commands.

    ctrl: commands per physics step, (W, S, NU) with NU >= every design's nu (extra
        columns ignored). qpos, qvel: initial state (W, NQ), (W, NV) zero-padded (None:
        qpos0, at rest). requires_grad: keep one State per step and a differentiable
        ``ctrl`` array, and run inside the caller's `wp.Tape` (record the call on a tape to
        take gradients of the returned ``states`` with respect to ``ctrl``).
    """
    from tt.kernels.device import resolve_device

    device = resolve_device(device)
    models, xmls, _ = _design_inputs(designs)
    W = len(models)
    nq, nv, nu = (max(getattr(m, k) for m in models) for k in ("nq", "nv", "nu"))
    ctrl = np.asarray(ctrl, dtype=np.float64)
    if ctrl.ndim != 3 or ctrl.shape[0] != W or ctrl.shape[2] < nu:
        raise TTError(f"ctrl has shape {ctrl.shape}; expected (W={W}, S, >= {nu})")
    S = ctrl.shape[1]
    dt = float(models[0].opt.timestep)
    if any(m.opt.timestep != dt for m in models):
        raise TTError("designs have different timesteps; one Newton model steps all worlds with one dt")
    worlds = build_worlds(models, xmls, 1, device=device, requires_grad=requires_grad)
    model, solver = worlds.model, worlds.solver

    # Worlds grouped by actuator layout (which qpos each actuator drives), so each group's
    # parameters are rectangular; one launch per group and physics step.
    layouts: dict[tuple, list[int]] = {}
    for w, m in enumerate(models):
        if m.nu:
            layouts.setdefault(tuple(actuated_qpos(m)), []).append(w)
    packs = []
    for rows in layouts.values():
        rows = np.array(rows)
        n = models[rows[0]].nu
        packs.append(dict(
            Wg=len(rows), nu=n, rows=rows,
            q_start=wp.array(worlds.q_start[rows].astype(np.int32), dtype=int, device=device),
            qd_start=wp.array(worlds.qd_start[rows].astype(np.int32), dtype=int, device=device),
            act=_actuators([models[w] for w in rows], device=device),
            ctrl_all=wp.array(ctrl[rows][:, :, :n].astype(np.float32), dtype=float, device=device,
                              requires_grad=requires_grad),
        ))  # fmt: skip

    q0 = model.joint_q.numpy()
    v0 = np.zeros(model.joint_dof_count, np.float32)
    for w, m in enumerate(models):
        q0[worlds.q_start[w] : worlds.q_start[w] + m.nq] = m.qpos0 if qpos is None else qpos[w, : m.nq]
        if qvel is not None:
            v0[worlds.qd_start[w] : worlds.qd_start[w] + m.nv] = qvel[w, : m.nv]
    count = S + 1 if requires_grad else 2
    states = [model.state(requires_grad=requires_grad) for _ in range(count)]
    states[0].joint_q.assign(q0)
    states[0].joint_qd.assign(v0)
    controls = [model.control(requires_grad=requires_grad) for _ in range(S if requires_grad else 1)]
    for c in controls:
        c.joint_f.zero_()

    qpos_out = np.zeros((W, S + 1, nq))
    qvel_out = np.zeros((W, S + 1, nv))

    def store(s: int, state) -> None:
        q, v = state.joint_q.numpy(), state.joint_qd.numpy()
        for w, m in enumerate(models):
            qpos_out[w, s, : m.nq] = q[worlds.q_start[w] : worlds.q_start[w] + m.nq]
            qvel_out[w, s, : m.nv] = v[worlds.qd_start[w] : worlds.qd_start[w] + m.nv]

    store(0, states[0])
    for s in range(S):
        src = states[s] if requires_grad else states[s % 2]
        dst = states[s + 1] if requires_grad else states[(s + 1) % 2]
        control = controls[s] if requires_grad else controls[0]
        for p in packs:
            a = p["act"]
            apply_actuators(
                p["q_start"], p["qd_start"], a.act_qpos, a.gain, a.bias, a.gear, a.forcerange, p["ctrl_all"][:, s],
                src.joint_q, src.joint_qd, control.joint_f, device=device,
            )  # fmt: skip
        solver.step(src, dst, control, None, dt)
        store(s + 1, dst)
    return NewtonTrajectory(
        qpos=qpos_out,
        qvel=qvel_out,
        ctrl=[(p["rows"], p["ctrl_all"]) for p in packs] if requires_grad else None,
        states=states if requires_grad else None,
        worlds=worlds,
    )


__all__ = ["NewtonTrajectory", "NewtonWorlds", "build_worlds", "newton_rollout", "newton_simulate"]
