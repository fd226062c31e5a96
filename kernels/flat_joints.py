"""Kernels over flat joint vectors: MuJoCo's actuators and tt's records on Newton's state.

Newton keeps every world's generalized coordinates in one flat vector (``State.joint_q``,
``joint_qd``; world i's start at ``q_start[i]`` / ``qd_start[i]``). These kernels, one
thread per (world, entry), move a group of Wg worlds between that layout and tt's (Wg, n)
arrays, apply MuJoCo's stateless affine position servos as joint forces (``force =
clamp(gain ctrl + b0 + b1 gear q + b2 gear qd, forcerange)``, ``joint_f = gear force``),
record the actuator forces and velocities of a state, and read end-effector poses from
body transforms and site offsets (quaternion signs as MuJoCo's, `tt.kernels.records.mat2quat`).
The ``newton`` backend (`tt.sim.newton_backend`) launches them.
"""

from __future__ import annotations

import warp as wp

from tt.kernels.records import mat2quat


@wp.kernel(module="unique")
def _apply_actuators(
    # Model:
    q_start: wp.array(dtype=int),
    qd_start: wp.array(dtype=int),
    act_qpos: wp.array(dtype=int),
    act_gain: wp.array2d(dtype=float),
    act_bias: wp.array2d(dtype=wp.vec3),
    act_gear: wp.array2d(dtype=float),
    act_forcerange: wp.array2d(dtype=wp.vec2),
    # In:
    ctrl_in: wp.array2d(dtype=float),
    joint_q_in: wp.array(dtype=float),
    joint_qd_in: wp.array(dtype=float),
    # Out:
    joint_f_out: wp.array(dtype=float),
):
    i, u = wp.tid()
    a = act_qpos[u]
    gear = act_gear[i, u]
    length = gear * joint_q_in[q_start[i] + a]
    velocity = gear * joint_qd_in[qd_start[i] + a]
    b = act_bias[i, u]
    r = act_forcerange[i, u]
    force = wp.clamp(act_gain[i, u] * ctrl_in[i, u] + b[0] + b[1] * length + b[2] * velocity, r[0], r[1])
    joint_f_out[qd_start[i] + a] = gear * force


@wp.kernel(module="unique")
def _gather_state(
    # Model:
    q_start: wp.array(dtype=int),
    qd_start: wp.array(dtype=int),
    # In:
    joint_q_in: wp.array(dtype=float),
    joint_qd_in: wp.array(dtype=float),
    # Out:
    qpos_out: wp.array2d(dtype=float),
    qvel_out: wp.array2d(dtype=float),
):
    i, d = wp.tid()
    qpos_out[i, d] = joint_q_in[q_start[i] + d]
    qvel_out[i, d] = joint_qd_in[qd_start[i] + d]


@wp.kernel(module="unique")
def _actuator_record(
    # Model:
    act_qpos: wp.array(dtype=int),
    act_gain: wp.array2d(dtype=float),
    act_bias: wp.array2d(dtype=wp.vec3),
    act_gear: wp.array2d(dtype=float),
    act_forcerange: wp.array2d(dtype=wp.vec2),
    # In:
    ctrl_in: wp.array2d(dtype=float),
    qpos_in: wp.array2d(dtype=float),
    qvel_in: wp.array2d(dtype=float),
    # Out:
    act_force_out: wp.array2d(dtype=float),
    act_vel_out: wp.array2d(dtype=float),
):
    i, u = wp.tid()
    a = act_qpos[u]
    gear = act_gear[i, u]
    velocity = gear * qvel_in[i, a]
    b = act_bias[i, u]
    r = act_forcerange[i, u]
    act_force_out[i, u] = wp.clamp(
        act_gain[i, u] * ctrl_in[i, u] + b[0] + b[1] * gear * qpos_in[i, a] + b[2] * velocity, r[0], r[1]
    )
    act_vel_out[i, u] = velocity


@wp.kernel(module="unique")
def _site_poses(
    # Model:
    ee_body: wp.array2d(dtype=int),
    ee_offset: wp.array2d(dtype=wp.transform),
    # Data in:
    body_q_in: wp.array(dtype=wp.transform),
    # Out:
    ee_pos_out: wp.array2d(dtype=wp.vec3),
    ee_quat_out: wp.array2d(dtype=wp.vec4),
):
    i, e = wp.tid()
    x = wp.transform_multiply(body_q_in[ee_body[i, e]], ee_offset[i, e])
    ee_pos_out[i, e] = wp.transform_get_translation(x)
    # Through the rotation matrix, so the quaternion's sign follows MuJoCo's rule (the oracle's).
    ee_quat_out[i, e] = mat2quat(wp.quat_to_matrix(wp.transform_get_rotation(x)))


def apply_actuators(
    q_start: wp.array,
    qd_start: wp.array,
    act_qpos: wp.array,
    act_gain: wp.array,
    act_bias: wp.array,
    act_gear: wp.array,
    act_forcerange: wp.array,
    ctrl: wp.array,
    joint_q: wp.array,
    joint_qd: wp.array,
    joint_f: wp.array,
    *,
    device: str,
) -> None:
    """MuJoCo's servo forces of Wg worlds into the flat ``joint_f``: act_qpos (NU,) int (the
    coordinate each actuator drives, within a world), act_gain / act_gear (Wg, NU) float,
    act_bias (Wg, NU) vec3, act_forcerange (Wg, NU) vec2 [N m or N], ctrl (Wg, NU)."""
    wp.launch(
        _apply_actuators, dim=ctrl.shape,
        inputs=[q_start, qd_start, act_qpos, act_gain, act_bias, act_gear, act_forcerange, ctrl, joint_q, joint_qd],
        outputs=[joint_f], device=device,
    )  # fmt: skip


def gather_state(
    q_start: wp.array,
    qd_start: wp.array,
    joint_q: wp.array,
    joint_qd: wp.array,
    qpos: wp.array,
    qvel: wp.array,
    *,
    device: str,
) -> None:
    """qpos (Wg, nq) and qvel (Wg, nq) of Wg worlds from the flat joint vectors."""
    wp.launch(
        _gather_state,
        dim=qpos.shape,
        inputs=[q_start, qd_start, joint_q, joint_qd],
        outputs=[qpos, qvel],
        device=device,
    )


def actuator_record(
    act_qpos: wp.array,
    act_gain: wp.array,
    act_bias: wp.array,
    act_gear: wp.array,
    act_forcerange: wp.array,
    ctrl: wp.array,
    qpos: wp.array,
    qvel: wp.array,
    act_force: wp.array,
    act_vel: wp.array,
    *,
    device: str,
) -> None:
    """Actuator forces [N m or N] and velocities (Wg, NU) at the state qpos, qvel (Wg, nq)
    under ctrl (parameters as `apply_actuators`)."""
    wp.launch(
        _actuator_record, dim=act_force.shape,
        inputs=[act_qpos, act_gain, act_bias, act_gear, act_forcerange, ctrl, qpos, qvel],
        outputs=[act_force, act_vel], device=device,
    )  # fmt: skip


def body_site_poses(
    ee_body: wp.array, ee_offset: wp.array, body_q: wp.array, ee_pos: wp.array, ee_quat: wp.array, *, device: str
) -> None:
    """End-effector poses ee_pos (Wg, NE) vec3 [m], ee_quat (Wg, NE) vec4 (w, x, y, z) from
    body transforms body_q (flat, Newton's ``State.body_q``), the body of each end effector
    ee_body (Wg, NE) int and the site frame in it, ee_offset (Wg, NE) transform."""
    wp.launch(
        _site_poses, dim=ee_body.shape, inputs=[ee_body, ee_offset, body_q], outputs=[ee_pos, ee_quat], device=device
    )


__all__ = ["actuator_record", "apply_actuators", "body_site_poses", "gather_state"]
