"""Batched whole-body differential IK for floating-base legged robots: the oracle's step, per world.

`tt.sim.wbc` specifies the controller (`WBCConfig`, `WholeBodyController.step`): one mink
`solve_ik` step over the model's whole tangent space (free joint first, then every hinge
and slide, passive ones included) with these weighted residual rows ``C_i (J_i dq + e_i)``:

* each end-effector site: the SE(3) frame task of `tt.kernels.ik`, ``e = log(T_b^-1 T_t)``,
  ``J = -Jl^-1(e) [R^T jacp; R^T jacr]``, costs ``(c_p I3, c_o I3)``, and mink's
  Levenberg-Marquardt term ``mu = lm_damping |C e|^2`` on the diagonal;
* each foot site: ``p_foot - p_stance`` (the ``home`` foot positions), Jacobian ``jacp``,
  cost ``foot_cost`` (the contact frames of a standing robot);
* the centre of mass of the root body's subtree: ``c(q) - c*`` (``c*`` the stance centre
  at z = 0), Jacobian ``mj_jacSubtreeCom``, costs ``(com_cost, com_cost, 0)``;
* posture: ``q - q_home`` on hinge and slide DoFs, Jacobian ``I``, per-DoF costs of
  `tt.sim.wbc.posture_costs`; nothing on the free joint;
* each active ``connect`` equality: ``p1 - p2`` with Jacobian ``jacp(p1) - jacp(p2)``
  (MuJoCo's ``efc_pos`` / ``efc_J``), cost ``equality_cost``.

``H = sum_i J_i^T C_i^2 J_i + (damping + mu) I``, ``dq = -H^-1 sum_i J_i^T C_i^2 e_i``
(mink's ``damping`` reaches the base DoFs too), ``q_cmd = q (+) dq`` (MuJoCo's
``mj_integratePos``: the base quaternion turns by ``dq[3:6]`` in the base frame), hinge and
slide joints clipped to their ranges.

What is reproduced and what is not. The oracle calls ``solve_ik(..., limits=[])``: no
inequality rows, so mink's QP is the unconstrained least squares above, which ``daqp``
solves exactly, and joint ranges act only through the clip after the step. The kernels
solve the same normal equations (dense Cholesky) and apply the same clip, so they agree
with the oracle wherever it is defined, limits active or not. They do not implement mink's
`ConfigurationLimit` / `VelocityLimit` inequalities (the oracle never uses them), equality
types other than ``connect``, or ball joints; `tt.sim.wbc_model.build_wbc_model` rejects
models that need them. mink's ``check_limits`` only logs and has no counterpart.

Why not `tt.kernels.ik`'s per-topology unrolled code: the quadruped space has 32 kinematic
topologies (rail or not x 16 leg combinations) and up to 33 DoFs; one unrolled kernel per
topology would compile for minutes each. These kernels read the tree (parents, joint
types, DoF parents) from per-world arrays, so one compiled module runs any mix of designs
in one launch, padded to the largest. They mirror MuJoCo's own loops (``mj_kinematics``,
``mj_jac``: walk from a body's last DoF up ``dof_parentid``) rather than tt's split-body
trees.

Why float64: the foot and loop rows weigh 100 against a damping of 1e-3, so ``H``'s
condition number reaches 1e5 (2.2e5 on 40 random standing states); float32 normal
equations solved there differed from float64 by up to 2e-5 rad, inside the oracle's
1e-3 tolerance but not round-off. In float64 the kernels reproduce the oracle's step to
about 1e-13, or 4e-9 where `tt.kernels.lie`'s small-angle series are used (their
coefficients are float32 constants), so closed-loop episodes driven by them are the host
controller's episodes (the contact dynamics would amplify any difference). The step is a
few tens of thousands of flops per world at 50 Hz, small against the MuJoCo-Warp physics
it drives even on GPUs with slow double precision. Inputs and outputs may be float32
(MuJoCo-Warp's ``qpos``).

Kernels, in launch order, each over worlds (and rows or matrix entries): `_load_qpos`,
`_load_targets` (state and targets into float64), `_kinematics` (body frames, DoF axes,
centre of mass), `_task_rows` (weighted Jacobian rows and errors, one thread per task),
`_normal_equations` (one thread per entry of ``H``; on the CPU `_normal_equations_rows`,
one per row, skipping zero Jacobian entries: the same numbers 4x faster there),
`_solve_integrate` (Cholesky, solve, integrate, clip).

The kernels take numbers, not configs: `WBCModel` holds the per-entry arrays and the
`WBCWeights`; `tt.sim.wbc_model.build_wbc_model` builds it from the MuJoCo models and a
`tt.sim.wbc.WBCConfig` (stance points, posture costs, home posture, weights).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.lie import MINK_JLOG_EPS, lie_funcs

_MODULE = "tt_wbc"
wp.set_module_options({"enable_backward": False}, _MODULE)

_LIE = lie_funcs(wp.float64)

#: mink 1.3's SE(3) ``jlog`` returns the identity when the squared rotation error is below
#: this [rad^2] (``EPS`` in ``mink/lie/_lie_ops_c.c``, as documented in `tt.sim.controller`),
#: dropping the coupling block ``-A Q A`` of ``Jl^-1``. That block is ``-1/2 [v]`` there, so
#: with centimetres of position error and an orientation already on target (a target taken
#: from the site's own pose) the oracle's Jacobian differs from the exact one by about
#: ``|v| / 2`` on rotational DoFs; the kernel follows the oracle.
# mink's threshold (`tt.kernels.lie.MINK_JLOG_EPS`) as a float64 constant: a float literal
# inside a kernel is float32 in Warp.
_MINK_JLOG_EPS64 = wp.constant(wp.float64(MINK_JLOG_EPS))

JOINT_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
JOINT_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
JOINT_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)


@wp.struct
class WBCWeights:
    """The task weights the step reads (`tt.sim.wbc.WBCConfig` documents them and builds this
    with `WBCConfig.wbc_weights`; per-DoF posture costs live on the model)."""

    position_cost: wp.float64  # [1/m]
    orientation_cost: wp.float64  # [1/rad]
    lm_damping: wp.float64  # unitless
    damping: wp.float64  # unitless
    foot_cost: wp.float64  # [1/m]
    com_cost: wp.float64  # [1/m]
    equality_cost: wp.float64  # [1/m]


def wbc_weights(
    *,
    position_cost: float,
    orientation_cost: float,
    lm_damping: float,
    damping: float,
    foot_cost: float,
    com_cost: float,
    equality_cost: float,
) -> WBCWeights:
    """A `WBCWeights` from its numbers (units as in the struct)."""
    w = WBCWeights()
    w.position_cost = float(position_cost)
    w.orientation_cost = float(orientation_cost)
    w.lm_damping = float(lm_damping)
    w.damping = float(damping)
    w.foot_cost = float(foot_cost)
    w.com_cost = float(com_cost)
    w.equality_cost = float(equality_cost)
    return w


@dataclass
class WBCModel:
    """N model entries for the whole-body step; world w reads entry ``w % entry_count``.

    Sizes are padded to the largest entry: NB bodies (world included), NJ joints, NQ / NV
    position / velocity coordinates, NE end effectors, NF feet, NC connect equalities.
    Layouts and numbering are MuJoCo's (bodies parents first, ``jnt_qposadr``,
    ``dof_parentid``, ...). Quaternions here are Warp's ``quatd`` (x, y, z, w); those in
    ``qpos`` and in the targets are (w, x, y, z) as everywhere in tt. Task rows: 6 per end
    effector, then 3 per foot, 3 for the centre of mass, 3 per connect (R in all).

    weights: the task weights (`WBCWeights`).
    body_count, jnt_count, dof_count: per entry, (N,) int32.
    body_parent: (N, NB) int32. body_pos [m]: (N, NB) vec3d; body_quat: (N, NB) quatd
        (offset in the parent frame). body_ipos: centre of mass in the body frame [m], (N, NB) vec3d.
    body_com_weight: mass of each body over the mass of the root body's subtree (0 outside
        it), (N, NB) float64; the centre-of-mass task is their weighted mean.
    body_jntadr, body_jntnum: first joint and joint count of each body, (N, NB) int32.
    body_lastdof: the last DoF of the body or of its nearest ancestor with DoFs (-1: none),
        where a Jacobian's walk up ``dof_parent`` starts (MuJoCo's ``mj_jac``), (N, NB) int32.
    jnt_type, jnt_qposadr, jnt_dofadr: (N, NJ) int32. jnt_axis (unit), jnt_pos [m]: in the
        body frame, (N, NJ) vec3d. jnt_limited: 1 for a limited hinge or slide (clipped), (N, NJ) int32.
    jnt_range: (lower, upper) [rad or m], (N, NJ) vec2d.
    qpos0: reference configuration [rad or m], (N, NQ) float64.
    dof_parent: MuJoCo's ``dof_parentid``, (N, NV) int32. dof_rot: 1 for a rotational DoF
        (hinge, free rotation), 0 for a translational one, (N, NV) int32.
    dof_qposadr: qpos address of hinge / slide DoFs (-1 on the free joint), (N, NV) int32.
    dof_posture_cost: posture cost [1/rad or 1/m] (`tt.sim.wbc.posture_costs`), (N, NV) float64.
    q_home: the ``home`` configuration, (N, NQ) float64.
    ee_body: (N, NE) int32; ee_pos [m]: (N, NE) vec3d; ee_quat: (N, NE) quatd: site frames in their body.
    foot_body, foot_active: (N, NF) int32 (padding feet inactive); foot_pos: site position in
        its body [m], (N, NF) vec3d; foot_target: stance point [m], (N, NF) vec3d.
    com_target: centre-of-mass target (stance centre x, y; z = 0, uncosted) [m], (N,) vec3d.
    eq_body1, eq_body2, eq_active: (N, NC) int32; eq_pos1, eq_pos2: the two points in their
        bodies [m], (N, NC) vec3d.
    """

    weights: WBCWeights
    nbody: int
    njnt: int
    nq: int
    nv: int
    ee_count: int
    foot_count: int
    eq_count: int
    body_count: wp.array
    jnt_count: wp.array
    dof_count: wp.array
    body_parent: wp.array
    body_pos: wp.array
    body_quat: wp.array
    body_ipos: wp.array
    body_com_weight: wp.array
    body_jntadr: wp.array
    body_jntnum: wp.array
    body_lastdof: wp.array
    jnt_type: wp.array
    jnt_qposadr: wp.array
    jnt_dofadr: wp.array
    jnt_axis: wp.array
    jnt_pos: wp.array
    jnt_limited: wp.array
    jnt_range: wp.array
    qpos0: wp.array
    dof_parent: wp.array
    dof_rot: wp.array
    dof_qposadr: wp.array
    dof_posture_cost: wp.array
    q_home: wp.array
    ee_body: wp.array
    ee_pos: wp.array
    ee_quat: wp.array
    foot_body: wp.array
    foot_active: wp.array
    foot_pos: wp.array
    foot_target: wp.array
    com_target: wp.array
    eq_body1: wp.array
    eq_body2: wp.array
    eq_active: wp.array
    eq_pos1: wp.array
    eq_pos2: wp.array
    device: str

    @property
    def entry_count(self) -> int:
        return self.body_parent.shape[0]

    @property
    def row_count(self) -> int:
        """Task rows R: 6 NE + 3 NF + 3 + 3 NC."""
        return 6 * self.ee_count + 3 * self.foot_count + 3 + 3 * self.eq_count


@dataclass
class WBCData:
    """Per-world working arrays of the step (W worlds), float64.

    q, q_cmd: measured and commanded configuration, (W, NQ). target_pos [m]: (W, NE) vec3d;
    target_quat: (W, NE) vec4d (w, x, y, z). xpos [m], xipos [m]: body frame origins and
    centres of mass, (W, NB) vec3d; xquat: (W, NB) quatd. dof_axis (unit), dof_anchor [m]:
    world axis and a point on it of each DoF, (W, NV) vec3d. com [m]: (W,) vec3d.
    jac: weighted task Jacobian rows ``C J``, (W, R, NV); err: weighted negative errors
    ``-C e``, (W, R); mu: the frame tasks' LM terms, (W, NE). hess: ``H`` (lower triangle,
    overwritten by its Cholesky factor), (W, NV, NV); grad: ``-J^T C^2 e - posture``, then
    ``dq``, (W, NV).
    """

    q: wp.array
    q_cmd: wp.array
    target_pos: wp.array
    target_quat: wp.array
    xpos: wp.array
    xipos: wp.array
    xquat: wp.array
    dof_axis: wp.array
    dof_anchor: wp.array
    com: wp.array
    jac: wp.array
    err: wp.array
    mu: wp.array
    hess: wp.array
    grad: wp.array

    @property
    def world_count(self) -> int:
        return self.q.shape[0]


def make_wbc_data(model: WBCModel, world_count: int, *, device: str | None = None) -> WBCData:
    """Working arrays for `world_count` worlds of `model` (zeros)."""
    device = device or model.device
    W, NB, NV, NQ, NE, R = world_count, model.nbody, model.nv, model.nq, model.ee_count, model.row_count

    def z(shape, dtype):
        return wp.zeros(shape, dtype=dtype, device=device)

    return WBCData(
        q=z((W, NQ), wp.float64), q_cmd=z((W, NQ), wp.float64),
        target_pos=z((W, NE), wp.vec3d), target_quat=z((W, NE), wp.vec4d),
        xpos=z((W, NB), wp.vec3d), xipos=z((W, NB), wp.vec3d), xquat=z((W, NB), wp.quatd),
        dof_axis=z((W, NV), wp.vec3d), dof_anchor=z((W, NV), wp.vec3d), com=z(W, wp.vec3d),
        jac=z((W, R, NV), wp.float64), err=z((W, R), wp.float64), mu=z((W, max(NE, 1)), wp.float64),
        hess=z((W, NV, NV), wp.float64), grad=z((W, NV), wp.float64),
    )  # fmt: skip


# --------------------------------------------------------------------------- kernels


@wp.func
def _dof_motion(rot: int, axis: wp.vec3d, anchor: wp.vec3d, point: wp.vec3d):
    """(linear, angular) world velocity of `point` per unit velocity of one DoF."""
    lin = axis
    ang = wp.vec3d()
    if rot != 0:
        lin = wp.cross(axis, point - anchor)
        ang = axis
    return lin, ang


@wp.kernel(module=_MODULE)
def _load_qpos(
    # In:
    qpos_in: wp.array2d(dtype=Any),
    # Data out:
    q_out: wp.array2d(dtype=wp.float64),
):
    worldid, i = wp.tid()
    q_out[worldid, i] = wp.float64(qpos_in[worldid, i])


@wp.kernel(module=_MODULE)
def _load_targets(
    # In:
    target_pos_in: wp.array2d(dtype=Any),
    target_quat_in: wp.array2d(dtype=Any),
    # Data out:
    target_pos_out: wp.array2d(dtype=wp.vec3d),
    target_quat_out: wp.array2d(dtype=wp.vec4d),
):
    worldid, e = wp.tid()
    p = target_pos_in[worldid, e]
    r = target_quat_in[worldid, e]
    target_pos_out[worldid, e] = wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))
    target_quat_out[worldid, e] = wp.vec4d(wp.float64(r[0]), wp.float64(r[1]), wp.float64(r[2]), wp.float64(r[3]))


@wp.kernel(module=_MODULE)
def _store_output(
    # Data in:
    q_cmd_in: wp.array2d(dtype=wp.float64),
    # Out:
    q_cmd_out: wp.array2d(dtype=Any),
):
    worldid, i = wp.tid()
    q_cmd_out[worldid, i] = q_cmd_out.dtype(q_cmd_in[worldid, i])


#: Precisions of the state arrays the step reads and writes (MuJoCo-Warp's float32, float64).
_QPOS_DTYPES = (wp.float32, wp.float64)
#: Target (position, orientation) types: tt's float32 motions, or float64 first poses.
_TARGET_DTYPES = ((wp.vec3, wp.vec4), (wp.vec3d, wp.vec4d))
for _t in _QPOS_DTYPES:
    wp.overload(_load_qpos, {"qpos_in": wp.array2d(dtype=_t)})
    wp.overload(_store_output, {"q_cmd_out": wp.array2d(dtype=_t)})
for _p, _r in _TARGET_DTYPES:
    wp.overload(_load_targets, {"target_pos_in": wp.array2d(dtype=_p), "target_quat_in": wp.array2d(dtype=_r)})


@wp.kernel(module=_MODULE)
def _home(
    # Model:
    q_home: wp.array2d(dtype=wp.float64),
    # Data out:
    q_out: wp.array2d(dtype=wp.float64),
):
    worldid, i = wp.tid()
    q_out[worldid, i] = q_home[worldid % q_home.shape[0], i]


@wp.kernel(module=_MODULE)
def _kinematics(
    # Model:
    body_count: wp.array(dtype=wp.int32),
    body_parent: wp.array2d(dtype=wp.int32),
    body_pos: wp.array2d(dtype=wp.vec3d),
    body_quat: wp.array2d(dtype=wp.quatd),
    body_ipos: wp.array2d(dtype=wp.vec3d),
    body_com_weight: wp.array2d(dtype=wp.float64),
    body_jntadr: wp.array2d(dtype=wp.int32),
    body_jntnum: wp.array2d(dtype=wp.int32),
    jnt_type: wp.array2d(dtype=wp.int32),
    jnt_qposadr: wp.array2d(dtype=wp.int32),
    jnt_dofadr: wp.array2d(dtype=wp.int32),
    jnt_axis: wp.array2d(dtype=wp.vec3d),
    jnt_pos: wp.array2d(dtype=wp.vec3d),
    qpos0: wp.array2d(dtype=wp.float64),
    # Data in:
    q_in: wp.array2d(dtype=wp.float64),
    # Data out:
    xpos_out: wp.array2d(dtype=wp.vec3d),
    xipos_out: wp.array2d(dtype=wp.vec3d),
    xquat_out: wp.array2d(dtype=wp.quatd),
    dof_axis_out: wp.array2d(dtype=wp.vec3d),
    dof_anchor_out: wp.array2d(dtype=wp.vec3d),
    com_out: wp.array(dtype=wp.vec3d),
):
    worldid = wp.tid()
    mid = worldid % body_parent.shape[0]
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    xpos_out[worldid, 0] = wp.vec3d()
    xipos_out[worldid, 0] = wp.vec3d()
    xquat_out[worldid, 0] = wp.quatd(zero, zero, zero, one)
    com = wp.vec3d()
    for b in range(1, body_count[mid]):
        parent = body_parent[mid, b]
        rot = xquat_out[worldid, parent]
        pos = xpos_out[worldid, parent] + wp.quat_rotate(rot, body_pos[mid, b])
        rot = rot * body_quat[mid, b]
        for k in range(body_jntnum[mid, b]):
            j = body_jntadr[mid, b] + k
            kind = jnt_type[mid, j]
            qa = jnt_qposadr[mid, j]
            da = jnt_dofadr[mid, j]
            if kind == wp.static(JOINT_FREE):
                # MuJoCo: the free joint sets the body frame from qpos (normalised quaternion);
                # it translates along the world axes and rotates about the body's own axes.
                pos = wp.vec3d(q_in[worldid, qa], q_in[worldid, qa + 1], q_in[worldid, qa + 2])
                rot = wp.normalize(
                    wp.quatd(q_in[worldid, qa + 4], q_in[worldid, qa + 5], q_in[worldid, qa + 6], q_in[worldid, qa + 3])
                )
                for i in range(3):
                    e = wp.vec3d()
                    e[i] = one
                    dof_axis_out[worldid, da + i] = e
                    dof_anchor_out[worldid, da + i] = pos
                    dof_axis_out[worldid, da + 3 + i] = wp.quat_rotate(rot, e)
                    dof_anchor_out[worldid, da + 3 + i] = pos
            else:
                local_axis = jnt_axis[mid, j]
                local_pos = jnt_pos[mid, j]
                axis = wp.quat_rotate(rot, local_axis)
                anchor = pos + wp.quat_rotate(rot, local_pos)
                dof_axis_out[worldid, da] = axis
                dof_anchor_out[worldid, da] = anchor
                dq = q_in[worldid, qa] - qpos0[mid, qa]
                if kind == wp.static(JOINT_HINGE):
                    rot = rot * wp.quat_from_axis_angle(local_axis, dq)
                    pos = anchor - wp.quat_rotate(rot, local_pos)
                else:
                    pos = pos + axis * dq
        rot = wp.normalize(rot)
        xpos_out[worldid, b] = pos
        xquat_out[worldid, b] = rot
        xipos = pos + wp.quat_rotate(rot, body_ipos[mid, b])
        xipos_out[worldid, b] = xipos
        com += body_com_weight[mid, b] * xipos
    com_out[worldid] = com


@wp.kernel(module=_MODULE)
def _task_rows(
    # Model:
    dof_count: wp.array(dtype=wp.int32),
    body_count: wp.array(dtype=wp.int32),
    body_lastdof: wp.array2d(dtype=wp.int32),
    body_com_weight: wp.array2d(dtype=wp.float64),
    dof_parent: wp.array2d(dtype=wp.int32),
    dof_rot: wp.array2d(dtype=wp.int32),
    ee_body: wp.array2d(dtype=wp.int32),
    ee_pos: wp.array2d(dtype=wp.vec3d),
    ee_quat: wp.array2d(dtype=wp.quatd),
    foot_body: wp.array2d(dtype=wp.int32),
    foot_active: wp.array2d(dtype=wp.int32),
    foot_pos: wp.array2d(dtype=wp.vec3d),
    foot_target: wp.array2d(dtype=wp.vec3d),
    com_target: wp.array(dtype=wp.vec3d),
    eq_body1: wp.array2d(dtype=wp.int32),
    eq_body2: wp.array2d(dtype=wp.int32),
    eq_active: wp.array2d(dtype=wp.int32),
    eq_pos1: wp.array2d(dtype=wp.vec3d),
    eq_pos2: wp.array2d(dtype=wp.vec3d),
    weights: WBCWeights,
    ee_count: int,
    foot_count: int,
    # Data in:
    target_pos_in: wp.array2d(dtype=wp.vec3d),
    target_quat_in: wp.array2d(dtype=wp.vec4d),
    xpos_in: wp.array2d(dtype=wp.vec3d),
    xipos_in: wp.array2d(dtype=wp.vec3d),
    xquat_in: wp.array2d(dtype=wp.quatd),
    dof_axis_in: wp.array2d(dtype=wp.vec3d),
    dof_anchor_in: wp.array2d(dtype=wp.vec3d),
    com_in: wp.array(dtype=wp.vec3d),
    # Data out:
    jac_out: wp.array3d(dtype=wp.float64),
    err_out: wp.array2d(dtype=wp.float64),
    mu_out: wp.array2d(dtype=wp.float64),
):
    worldid, task = wp.tid()
    mid = worldid % dof_count.shape[0]
    # Row layout: 6 per end effector, 3 per foot, 3 for the CoM, 3 per connect.
    row = 0
    width = 3
    if task < ee_count:
        row = 6 * task
        width = 6
    elif task < ee_count + foot_count:
        row = 6 * ee_count + 3 * (task - ee_count)
    else:
        row = 6 * ee_count + 3 * foot_count + 3 * (task - ee_count - foot_count)
    for k in range(width):
        err_out[worldid, row + k] = wp.float64(0.0)
        for d in range(jac_out.shape[2]):
            jac_out[worldid, row + k, d] = wp.float64(0.0)

    if task < ee_count:
        # The SE(3) frame task, as tt.kernels.ik: error in the site frame, body Jacobian
        # through the inverse left Jacobian of SE(3).
        b = ee_body[mid, task]
        rb = xquat_in[worldid, b]
        p = xpos_in[worldid, b] + wp.quat_rotate(rb, ee_pos[mid, task])
        r = wp.normalize(rb * ee_quat[mid, task])
        rinv = wp.quat_inverse(r)
        ev, ew = _LIE.se3_log(
            rinv * _LIE.quat_wxyz(target_quat_in[worldid, task]), wp.quat_rotate(rinv, target_pos_in[worldid, task] - p)
        )
        A, B = _LIE.se3_ljacinv(ev, ew)
        if wp.dot(ew, ew) < _MINK_JLOG_EPS64:
            # mink's jlog switches to the identity below this rotation error (see
            # MINK_JLOG_EPS): a discontinuity of the oracle that the kernel reproduces.
            A = wp.identity(n=3, dtype=wp.float64)
            B = wp.mat33d()
        Rt = wp.transpose(wp.quat_to_matrix(r))
        cp = weights.position_cost
        co = weights.orientation_cost
        for k in range(3):
            err_out[worldid, row + k] = -cp * ev[k]
            err_out[worldid, row + 3 + k] = -co * ew[k]
        mu_out[worldid, task] = weights.lm_damping * (cp * cp * wp.dot(ev, ev) + co * co * wp.dot(ew, ew))
        d = body_lastdof[mid, b]
        while d >= 0:
            lin, ang = _dof_motion(dof_rot[mid, d], dof_axis_in[worldid, d], dof_anchor_in[worldid, d], p)
            jp = Rt @ lin
            jr = Rt @ ang
            jv = -(A @ jp + B @ jr)
            jw = -(A @ jr)
            for k in range(3):
                jac_out[worldid, row + k, d] = cp * jv[k]
                jac_out[worldid, row + 3 + k, d] = co * jw[k]
            d = dof_parent[mid, d]
    elif task < ee_count + foot_count:
        f = task - ee_count
        if foot_active[mid, f] != 0:
            b = foot_body[mid, f]
            p = xpos_in[worldid, b] + wp.quat_rotate(xquat_in[worldid, b], foot_pos[mid, f])
            c = weights.foot_cost
            e = p - foot_target[mid, f]
            for k in range(3):
                err_out[worldid, row + k] = -c * e[k]
            d = body_lastdof[mid, b]
            while d >= 0:
                lin, ang = _dof_motion(dof_rot[mid, d], dof_axis_in[worldid, d], dof_anchor_in[worldid, d], p)
                for k in range(3):
                    jac_out[worldid, row + k, d] = c * lin[k]
                d = dof_parent[mid, d]
    elif task == ee_count + foot_count:
        # mj_jacSubtreeCom of the root: the mass-weighted mean of the bodies' CoM Jacobians.
        cost = wp.vec3d(weights.com_cost, weights.com_cost, wp.float64(0.0))
        e = com_in[worldid] - com_target[mid]
        for k in range(3):
            err_out[worldid, row + k] = -cost[k] * e[k]
        for b in range(1, body_count[mid]):
            w = body_com_weight[mid, b]
            if w != wp.float64(0.0):
                p = xipos_in[worldid, b]
                d = body_lastdof[mid, b]
                while d >= 0:
                    lin, ang = _dof_motion(dof_rot[mid, d], dof_axis_in[worldid, d], dof_anchor_in[worldid, d], p)
                    for k in range(3):
                        jac_out[worldid, row + k, d] += cost[k] * w * lin[k]
                    d = dof_parent[mid, d]
    else:
        n = task - ee_count - foot_count - 1
        if eq_active[mid, n] != 0:
            # MuJoCo's connect rows: efc_pos = p1 - p2, efc_J = jacp(p1) - jacp(p2).
            c = weights.equality_cost
            b1 = eq_body1[mid, n]
            b2 = eq_body2[mid, n]
            p1 = xpos_in[worldid, b1] + wp.quat_rotate(xquat_in[worldid, b1], eq_pos1[mid, n])
            p2 = xpos_in[worldid, b2] + wp.quat_rotate(xquat_in[worldid, b2], eq_pos2[mid, n])
            e = p1 - p2
            for k in range(3):
                err_out[worldid, row + k] = -c * e[k]
            d = body_lastdof[mid, b1]
            while d >= 0:
                lin, ang = _dof_motion(dof_rot[mid, d], dof_axis_in[worldid, d], dof_anchor_in[worldid, d], p1)
                for k in range(3):
                    jac_out[worldid, row + k, d] += c * lin[k]
                d = dof_parent[mid, d]
            d = body_lastdof[mid, b2]
            while d >= 0:
                lin, ang = _dof_motion(dof_rot[mid, d], dof_axis_in[worldid, d], dof_anchor_in[worldid, d], p2)
                for k in range(3):
                    jac_out[worldid, row + k, d] -= c * lin[k]
                d = dof_parent[mid, d]


@wp.func
def _diagonal_terms(
    worldid: int,
    mid: int,
    i: int,
    dof_qposadr: wp.array2d(dtype=wp.int32),
    dof_posture_cost: wp.array2d(dtype=wp.float64),
    q_home: wp.array2d(dtype=wp.float64),
    weights: WBCWeights,
    q_in: wp.array2d(dtype=wp.float64),
    mu_in: wp.array2d(dtype=wp.float64),
):
    """What DoF i adds beyond the task rows: to ``H[i, i]`` its posture cost squared, the
    damping and the limit terms ``mu``; to the gradient (subtracted) its posture pull. One
    definition for both launches of the normal equations, so they stay equal bit for bit."""
    c = dof_posture_cost[mid, i]
    mu = wp.float64(0.0)
    for e in range(mu_in.shape[1]):
        mu += mu_in[worldid, e]
    posture = wp.float64(0.0)
    qa = dof_qposadr[mid, i]
    if qa >= 0:
        posture = c * c * (q_in[worldid, qa] - q_home[mid, qa])
    return c * c + weights.damping + mu, posture


@wp.kernel(module=_MODULE)
def _normal_equations(
    # Model:
    dof_count: wp.array(dtype=wp.int32),
    dof_qposadr: wp.array2d(dtype=wp.int32),
    dof_posture_cost: wp.array2d(dtype=wp.float64),
    q_home: wp.array2d(dtype=wp.float64),
    weights: WBCWeights,
    # Data in:
    q_in: wp.array2d(dtype=wp.float64),
    jac_in: wp.array3d(dtype=wp.float64),
    err_in: wp.array2d(dtype=wp.float64),
    mu_in: wp.array2d(dtype=wp.float64),
    # Data out:
    hess_out: wp.array3d(dtype=wp.float64),
    grad_out: wp.array2d(dtype=wp.float64),
):
    worldid, i, j = wp.tid()
    mid = worldid % dof_count.shape[0]
    nv = dof_count[mid]
    if i >= nv or j > i:
        return
    rows = jac_in.shape[1]
    h = wp.float64(0.0)
    for r in range(rows):
        h += jac_in[worldid, r, i] * jac_in[worldid, r, j]
    if i == j:
        extra, posture = _diagonal_terms(worldid, mid, i, dof_qposadr, dof_posture_cost, q_home, weights, q_in, mu_in)
        h += extra
        g = wp.float64(0.0)
        for r in range(rows):
            g += jac_in[worldid, r, i] * err_in[worldid, r]
        g -= posture
        grad_out[worldid, i] = g
    hess_out[worldid, i, j] = h


@wp.kernel(module=_MODULE)
def _normal_equations_rows(
    # Model:
    dof_count: wp.array(dtype=wp.int32),
    dof_qposadr: wp.array2d(dtype=wp.int32),
    dof_posture_cost: wp.array2d(dtype=wp.float64),
    q_home: wp.array2d(dtype=wp.float64),
    weights: WBCWeights,
    # Data in:
    q_in: wp.array2d(dtype=wp.float64),
    jac_in: wp.array3d(dtype=wp.float64),
    err_in: wp.array2d(dtype=wp.float64),
    mu_in: wp.array2d(dtype=wp.float64),
    # Data out:
    hess_out: wp.array3d(dtype=wp.float64),
    grad_out: wp.array2d(dtype=wp.float64),
):
    """`_normal_equations` with one thread per row of ``H`` (the CPU's launch): the task rows
    where DoF i's Jacobian entry is zero add nothing and are skipped (a leg DoF appears in
    about 9 of the 33-45 rows), and every entry sums the same terms in the same order, so
    ``H`` and the gradient are those of `_normal_equations` bit for bit."""
    worldid, i = wp.tid()
    mid = worldid % dof_count.shape[0]
    nv = dof_count[mid]
    if i >= nv:
        return
    zero = wp.float64(0.0)
    for j in range(i + 1):
        hess_out[worldid, i, j] = zero
    g = zero
    for r in range(jac_in.shape[1]):
        a = jac_in[worldid, r, i]
        if a != zero:
            for j in range(i + 1):
                hess_out[worldid, i, j] = hess_out[worldid, i, j] + a * jac_in[worldid, r, j]
            g += a * err_in[worldid, r]
    extra, posture = _diagonal_terms(worldid, mid, i, dof_qposadr, dof_posture_cost, q_home, weights, q_in, mu_in)
    hess_out[worldid, i, i] = hess_out[worldid, i, i] + extra
    grad_out[worldid, i] = g - posture


@wp.kernel(module=_MODULE)
def _solve_integrate(
    # Model:
    dof_count: wp.array(dtype=wp.int32),
    jnt_count: wp.array(dtype=wp.int32),
    jnt_type: wp.array2d(dtype=wp.int32),
    jnt_qposadr: wp.array2d(dtype=wp.int32),
    jnt_dofadr: wp.array2d(dtype=wp.int32),
    jnt_limited: wp.array2d(dtype=wp.int32),
    jnt_range: wp.array2d(dtype=wp.vec2d),
    # Data in:
    q_in: wp.array2d(dtype=wp.float64),
    # Data in/out (factored and solved in place):
    hess: wp.array3d(dtype=wp.float64),
    grad: wp.array2d(dtype=wp.float64),
    # Data out:
    q_cmd_out: wp.array2d(dtype=wp.float64),
):
    worldid = wp.tid()
    mid = worldid % dof_count.shape[0]
    n = dof_count[mid]
    # Dense Cholesky H = L L^T in the lower triangle (H is SPD for damping > 0).
    for j in range(n):
        s = hess[worldid, j, j]
        for k in range(j):
            s -= hess[worldid, j, k] * hess[worldid, j, k]
        djj = wp.sqrt(s)
        hess[worldid, j, j] = djj
        for i in range(j + 1, n):
            t = hess[worldid, i, j]
            for k in range(j):
                t -= hess[worldid, i, k] * hess[worldid, j, k]
            hess[worldid, i, j] = t / djj
    for i in range(n):
        t = grad[worldid, i]
        for k in range(i):
            t -= hess[worldid, i, k] * grad[worldid, k]
        grad[worldid, i] = t / hess[worldid, i, i]
    for ii in range(n):
        i = n - 1 - ii
        t = grad[worldid, i]
        for k in range(i + 1, n):
            t -= hess[worldid, k, i] * grad[worldid, k]
        grad[worldid, i] = t / hess[worldid, i, i]
    # q_cmd = q (+) dq (mj_integratePos with v dt = dq), then the clip of limited joints.
    for i in range(q_in.shape[1]):
        q_cmd_out[worldid, i] = q_in[worldid, i]
    for j in range(jnt_count[mid]):
        qa = jnt_qposadr[mid, j]
        da = jnt_dofadr[mid, j]
        if jnt_type[mid, j] == wp.static(JOINT_FREE):
            for k in range(3):
                q_cmd_out[worldid, qa + k] = q_in[worldid, qa + k] + grad[worldid, da + k]
            quat = wp.normalize(
                wp.quatd(q_in[worldid, qa + 4], q_in[worldid, qa + 5], q_in[worldid, qa + 6], q_in[worldid, qa + 3])
            )
            w = wp.vec3d(grad[worldid, da + 3], grad[worldid, da + 4], grad[worldid, da + 5])
            angle = wp.length(w)
            if angle > wp.float64(0.0):
                quat = quat * wp.quat_from_axis_angle(w / angle, angle)
            q_cmd_out[worldid, qa + 3] = quat[3]
            q_cmd_out[worldid, qa + 4] = quat[0]
            q_cmd_out[worldid, qa + 5] = quat[1]
            q_cmd_out[worldid, qa + 6] = quat[2]
        else:
            v = q_in[worldid, qa] + grad[worldid, da]
            if jnt_limited[mid, j] != 0:
                r = jnt_range[mid, j]
                v = wp.clamp(v, r[0], r[1])
            q_cmd_out[worldid, qa] = v


# --------------------------------------------------------------------------- launches


def _check_inputs(model: WBCModel, qpos: wp.array | None, target_pos: wp.array, target_quat: wp.array) -> int:
    W = target_pos.shape[0]
    if qpos is not None:
        W = qpos.shape[0]
        if qpos.ndim != 2 or qpos.shape[1] != model.nq or qpos.dtype not in _QPOS_DTYPES:
            raise TTError(
                f"qpos has shape {qpos.shape} and dtype {qpos.dtype.__name__}; expected (W, {model.nq}) "
                "float32 or float64"
            )
    kinds = [(p, r) for p, r in _TARGET_DTYPES if wp.types.types_equal(target_pos.dtype, p)]
    for name, arr, index in (("target_pos", target_pos, 0), ("target_quat", target_quat, 1)):
        if arr.shape != (W, model.ee_count) or not kinds or not wp.types.types_equal(arr.dtype, kinds[0][index]):
            raise TTError(
                f"{name} has shape {arr.shape} and dtype {arr.dtype.__name__}; expected (W={W}, {model.ee_count}) "
                "vec3 / vec4 (or vec3d / vec4d for both)"
            )
    return W


def _load_step_targets(target_pos: wp.array, target_quat: wp.array, data: WBCData, device: str) -> None:
    wp.launch(
        _load_targets, dim=target_pos.shape, inputs=[target_pos, target_quat],
        outputs=[data.target_pos, data.target_quat], device=device,
    )  # fmt: skip


def _step(model: WBCModel, data: WBCData, W: int, device: str) -> None:
    """One step from data.q / data.target_* to data.q_cmd."""
    m, d = model, data
    wp.launch(
        _kinematics, dim=W,
        inputs=[
            m.body_count, m.body_parent, m.body_pos, m.body_quat, m.body_ipos, m.body_com_weight, m.body_jntadr,
            m.body_jntnum, m.jnt_type, m.jnt_qposadr, m.jnt_dofadr, m.jnt_axis, m.jnt_pos, m.qpos0, d.q,
        ],
        outputs=[d.xpos, d.xipos, d.xquat, d.dof_axis, d.dof_anchor, d.com],
        device=device,
    )  # fmt: skip
    wp.launch(
        _task_rows, dim=(W, m.ee_count + m.foot_count + 1 + m.eq_count),
        inputs=[
            m.dof_count, m.body_count, m.body_lastdof, m.body_com_weight, m.dof_parent, m.dof_rot, m.ee_body,
            m.ee_pos, m.ee_quat, m.foot_body, m.foot_active, m.foot_pos, m.foot_target, m.com_target, m.eq_body1,
            m.eq_body2, m.eq_active, m.eq_pos1, m.eq_pos2, m.weights, m.ee_count, m.foot_count,
            d.target_pos, d.target_quat, d.xpos, d.xipos, d.xquat, d.dof_axis, d.dof_anchor, d.com,
        ],
        outputs=[d.jac, d.err, d.mu],
        device=device,
    )  # fmt: skip
    # One thread per entry of H suits a GPU; on the CPU, where a launch runs its threads one
    # after another, one per row skips the zero Jacobian entries (4x faster, same numbers).
    rows = wp.get_device(device).is_cpu
    wp.launch(
        _normal_equations_rows if rows else _normal_equations, dim=(W, m.nv) if rows else (W, m.nv, m.nv),
        inputs=[m.dof_count, m.dof_qposadr, m.dof_posture_cost, m.q_home, m.weights, d.q, d.jac, d.err, d.mu],
        outputs=[d.hess, d.grad],
        device=device,
    )  # fmt: skip
    wp.launch(
        _solve_integrate, dim=W,
        inputs=[m.dof_count, m.jnt_count, m.jnt_type, m.jnt_qposadr, m.jnt_dofadr, m.jnt_limited, m.jnt_range, d.q],
        outputs=[d.hess, d.grad, d.q_cmd],
        device=device,
    )  # fmt: skip


def wbc_step(
    model: WBCModel,
    qpos: wp.array,
    target_pos: wp.array,
    target_quat: wp.array,
    q_cmd_out: wp.array | None = None,
    *,
    data: WBCData | None = None,
    device: str | None = None,
) -> wp.array:
    """One whole-body IK step of W worlds (the batched `tt.sim.wbc.WholeBodyController.step`).

    qpos: measured configurations (free joint first: position [m], quaternion (w, x, y, z);
        then hinge / slide [rad or m]), (W, NQ) float32 or float64, zero-padded past each
        entry's nq; world w uses model entry ``w % model.entry_count``.
    target_pos: end-effector targets [m], (W, NE) vec3; target_quat: (W, NE) vec4 (w, x, y,
        z), in site order (the caller applies the look-ahead); vec3d / vec4d also do.
    q_cmd_out: (W, NQ) array of qpos's dtype to write into (allocated when None).
    data: working arrays from `make_wbc_data` (allocated when None; pass one to avoid
        allocations in a control loop).
    Returns q_cmd (W, NQ): ``q (+) dq`` with hinge and slide joints clipped to their
    ranges, base included; actuators take the entries at their joints' qpos addresses.
    ``H`` must be positive definite (``damping > 0`` makes it so); a world whose ``H`` is
    not gets NaN.
    """
    device = device or model.device
    W = _check_inputs(model, qpos, target_pos, target_quat)
    if data is None:
        data = make_wbc_data(model, W, device=device)
    elif data.world_count != W:
        raise TTError(f"data holds {data.world_count} worlds; qpos has {W}")
    if q_cmd_out is None:
        q_cmd_out = wp.empty((W, model.nq), dtype=qpos.dtype, device=device)
    elif q_cmd_out.shape != (W, model.nq) or q_cmd_out.dtype != qpos.dtype:
        raise TTError(f"q_cmd_out has shape {q_cmd_out.shape}; expected (W={W}, {model.nq}) of qpos's dtype")
    wp.launch(_load_qpos, dim=qpos.shape, inputs=[qpos], outputs=[data.q], device=device)
    _load_step_targets(target_pos, target_quat, data, device)
    _step(model, data, W, device)
    wp.launch(_store_output, dim=(W, model.nq), inputs=[data.q_cmd], outputs=[q_cmd_out], device=device)
    return q_cmd_out


def wbc_initial_q(
    model: WBCModel,
    target_pos: wp.array,
    target_quat: wp.array,
    iterations: int,
    *,
    data: WBCData | None = None,
    device: str | None = None,
) -> wp.array:
    """Start postures of W worlds (the batched `WholeBodyController.initial_q`): `iterations`
    (the controller's ``init_iterations``) whole-body steps from ``home`` toward the
    targets, applied kinematically in float64 (q <- q_cmd).

    target_pos: (W, NE) vec3 [m]; target_quat: (W, NE) vec4 (w, x, y, z); or vec3d / vec4d
    (a motion's first poses in float64, `tt.kernels.rollout.MotionArrays.first_pos`).
    Returns (W, NQ) float64.
    """
    device = device or model.device
    W = _check_inputs(model, None, target_pos, target_quat)
    iterations = int(iterations)
    if iterations < 0:
        raise TTError(f"iterations = {iterations}; must be >= 0")
    if data is None:
        data = make_wbc_data(model, W, device=device)
    _load_step_targets(target_pos, target_quat, data, device)
    wp.launch(_home, dim=(W, model.nq), inputs=[model.q_home], outputs=[data.q], device=device)
    for _ in range(iterations):
        _step(model, data, W, device)
        wp.copy(data.q, data.q_cmd)
    out = wp.empty((W, model.nq), dtype=wp.float64, device=device)
    wp.copy(out, data.q)
    return out


def load_wbc_kernels(device: str | None = None) -> None:
    """Compile (or load from Warp's cache) the whole-body kernels on `device` now: a caller
    that launches them from several threads loads them once, before the threads start."""
    wp.load_module(_kinematics.module, device=device)


__all__ = [
    "WBCData",
    "WBCModel",
    "WBCWeights",
    "load_wbc_kernels",
    "make_wbc_data",
    "wbc_initial_q",
    "wbc_step",
    "wbc_weights",
]
