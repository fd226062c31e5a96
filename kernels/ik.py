"""Batched damped-least-squares differential IK: the oracle's mink step, per world.

`tt.sim.controller` specifies the controller (`IKConfig`, `ik_step`) and turns its
settings into the numbers these kernels read (`IKConfig.ik_weights`): one mink
`solve_ik` step with a frame task per end-effector site, a posture task toward qpos0,
global damping and no inequality limits, then a clip to the joint range. For each site
with world pose T_b = (R, p) and target T_t:

    e    = log(T_b^-1 T_t) = (v, w)                          (mink's target.minus(frame))
    J    = -Jl^-1(e) [R^T jacp; R^T jacr]                    (d e / d q)
    H    = sum_sites J^T C^2 J + (c_q^2 + damping + mu) I,   C = diag(c_p I3, c_o I3)
    g    = -sum_sites J^T C^2 e - c_q^2 (q - qpos0)
    q_cmd = clip(q + H^-1 g, joint range)

with mu = lm_damping * sum_sites |C e|^2 (mink's Levenberg-Marquardt term), and, as in
mink, Jl^-1(e) replaced by the identity when |w|^2 < `tt.kernels.lie.MINK_JLOG_EPS` (an
orientation already on target). The functions here compute the same in float32 inside a
world's thread; `ik_step` runs them on W worlds.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.fk import kinematics_funcs, model_struct
from tt.kernels.lie import lie_funcs
from tt.kernels.ltdl import chain, ltdl_funcs
from tt.kernels.model import MODULE_OPTIONS, Topology, TreeArrays, TreeModel, local_types, module_name


@wp.struct
class IKWeights:
    """The task weights the IK step reads (`tt.sim.controller.IKConfig` documents them and
    builds this with `IKConfig.ik_weights`)."""

    # float64, so that the float64 start-posture iteration sees the settings' exact numbers.
    position_cost: wp.float64  # [1/m]
    orientation_cost: wp.float64  # [1/rad]
    posture_cost: wp.float64  # [1/rad]
    lm_damping: wp.float64  # unitless
    damping: wp.float64  # unitless


def ik_weights(
    *, position_cost: float, orientation_cost: float, posture_cost: float, lm_damping: float, damping: float
) -> IKWeights:
    """An `IKWeights` from its numbers (units as in the struct)."""
    w = IKWeights()
    w.position_cost = float(position_cost)
    w.orientation_cost = float(orientation_cost)
    w.posture_cost = float(posture_cost)
    w.lm_damping = float(lm_damping)
    w.damping = float(damping)
    return w


def ik_funcs(topology: Topology, dtype=wp.float32) -> SimpleNamespace:
    """See `_ik_funcs` (one cache entry per precision, however `dtype` is passed)."""
    return _ik_funcs(topology, dtype)


@functools.cache
def _ik_funcs(topology: Topology, dtype) -> SimpleNamespace:
    """Warp functions of one topology, computing in scalar type `dtype`.

    command(mid, model, xpos, xquat, axis, anchor, q, target_pos, target_quat, weights) -> q_cmd (NV,):
        the joint position command for joint positions q, their kinematics (from
        `kinematics_funcs(...).kinematics`) and site targets target_pos (NE, 3) [m],
        target_quat (NE, 4) (w, x, y, z); `model` is the model struct of the precision
        (`tt.kernels.fk.model_struct`), of which it reads dof_range, dof_ref and the sites.
    """
    T = local_types(topology, dtype)
    K = kinematics_funcs(topology, dtype)
    LIE = lie_funcs(dtype)
    S, vec3 = T.scalar, T.vec3
    Model = model_struct(dtype)
    NV, NE = topology.dof_count, topology.ee_count
    DENSE = ltdl_funcs(chain(NV), T.dof_mat, T.dof_vec)

    @wp.func
    def command(
        mid: int,
        model: Model,
        xpos: T.body_vec3,
        xquat: T.body_vec4,
        axis: T.dof_vec3,
        anchor: T.dof_vec3,
        q: T.dof_vec,
        target_pos: T.ee_vec3,
        target_quat: T.ee_vec4,
        weights: IKWeights,
    ):
        cp2 = S(weights.position_cost) * S(weights.position_cost)
        co2 = S(weights.orientation_cost) * S(weights.orientation_cost)
        H = T.dof_mat()
        g = T.dof_vec()
        mu = S(0.0)
        for e in range(NE):
            p, r = K.site_pose(e, xpos, xquat, model, mid)
            jac = K.site_jacobian(e, axis, anchor, p)
            rinv = wp.quat_inverse(r)
            ev, ew = LIE.se3_log(rinv * LIE.quat_wxyz(target_quat[e]), wp.quat_rotate(rinv, target_pos[e] - p))
            A, B = LIE.se3_jlog(ev, ew)
            Rt = wp.transpose(wp.quat_to_matrix(r))
            # Task Jacobian -Jl^-1(e) [R^T jacp; R^T jacr], split into its linear rows (Jv)
            # and angular rows (Jw).
            Jv = T.dof_vec3()
            Jw = T.dof_vec3()
            for d in range(NV):
                jp = Rt @ vec3(jac[0, d], jac[1, d], jac[2, d])
                jr = Rt @ vec3(jac[3, d], jac[4, d], jac[5, d])
                Jv[d] = -(A @ jp + B @ jr)
                Jw[d] = -(A @ jr)
            for i in range(NV):
                g[i] = g[i] - cp2 * wp.dot(Jv[i], ev) - co2 * wp.dot(Jw[i], ew)
                for j in range(NV):
                    if j <= i:
                        H[i, j] = H[i, j] + cp2 * wp.dot(Jv[i], Jv[j]) + co2 * wp.dot(Jw[i], Jw[j])
            mu += S(weights.lm_damping) * (cp2 * wp.dot(ev, ev) + co2 * wp.dot(ew, ew))
        cq2 = S(weights.posture_cost) * S(weights.posture_cost)
        for i in range(NV):
            g[i] = g[i] - cq2 * (q[i] - model.dof_ref[mid, i])
            H[i, i] = H[i, i] + cq2 + S(weights.damping) + mu
        L, D = DENSE.factor(H)
        dq = DENSE.solve(L, D, g)
        q_cmd = T.dof_vec()
        for i in range(NV):
            r_i = model.dof_range[mid, i]
            q_cmd[i] = wp.clamp(q[i] + dq[i], r_i[0], r_i[1])
        return q_cmd

    return SimpleNamespace(command=command)


def make_ik_kernel(topology: Topology, module: str):
    """The standalone IK kernel of one topology, registered in Warp module `module`."""
    T = local_types(topology)
    K = kinematics_funcs(topology)
    F = ik_funcs(topology)
    NV, NE = topology.dof_count, topology.ee_count

    @wp.kernel(module=module)
    def _ik_step(
        # Model:
        model: TreeArrays,
        # In:
        weights: IKWeights,
        qpos_in: wp.array2d(dtype=float),
        target_pos_in: wp.array2d(dtype=wp.vec3),
        target_quat_in: wp.array2d(dtype=wp.vec4),
        # Out:
        q_cmd_out: wp.array2d(dtype=float),
    ):
        worldid = wp.tid()
        mid = worldid % model.body_pos.shape[0]
        q = T.dof_vec()
        for d in range(NV):
            q[d] = qpos_in[worldid, d]
        tpos = T.ee_vec3()
        tquat = T.ee_vec4()
        for e in range(NE):
            tpos[e] = target_pos_in[worldid, e]
            tquat[e] = target_quat_in[worldid, e]
        xpos, xquat, axis, anchor = K.kinematics(mid, model, q)
        q_cmd = F.command(mid, model, xpos, xquat, axis, anchor, q, tpos, tquat, weights)
        for d in range(NV):
            q_cmd_out[worldid, d] = q_cmd[d]

    return _ik_step


@functools.cache
def ik_kernel(topology: Topology):
    """The standalone IK kernel of a topology, in its own module."""
    module = module_name(topology, "ik")
    wp.set_module_options(MODULE_OPTIONS, module)
    return make_ik_kernel(topology, module)


def ik_step(
    model: TreeModel,
    qpos: wp.array,
    target_pos: wp.array,
    target_quat: wp.array,
    weights: IKWeights,
    q_cmd_out: wp.array | None = None,
    *,
    device: str | None = None,
) -> wp.array:
    """One DiffIK step of W worlds (the batched `tt.sim.controller.ik_step`).

    weights: the task weights (`IKConfig.ik_weights()` of the controller's settings).
    qpos: measured joint positions [rad or m], (W, NV) float32.
    target_pos: site targets [m], (W, NE) vec3; target_quat: (W, NE) vec4 (w, x, y, z), in
    site order ``ee_0, ee_1, ...`` (the caller applies the look-ahead).
    Returns q_cmd (W, NV) float32: clip(q + dq, joint range), into `q_cmd_out` if given.
    """
    topo = model.topology
    device = device or model.device
    W = qpos.shape[0]
    if qpos.shape != (W, topo.dof_count):
        raise TTError(f"qpos has shape {qpos.shape}; expected (W, {topo.dof_count})")
    if target_pos.shape != (W, topo.ee_count) or target_quat.shape != (W, topo.ee_count):
        raise TTError(
            f"target_pos {target_pos.shape} and target_quat {target_quat.shape} must be (W={W}, {topo.ee_count})"
        )
    if q_cmd_out is None:
        q_cmd_out = wp.array(np.full((W, topo.dof_count), np.inf, np.float32), dtype=float, device=device)
    wp.launch(
        ik_kernel(topo),
        dim=W,
        inputs=[model.arrays, weights, qpos, target_pos, target_quat],
        outputs=[q_cmd_out],
        device=device,
    )
    return q_cmd_out
