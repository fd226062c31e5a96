"""Episode records written by kernels, for backends whose physics is not tt's fused rollout.

The ``mjwarp`` and ``newton`` backends step their own physics and, after every control
step, hand the state of a group of Wg worlds to `record_step`, which writes it into the
rows of one Episode-shaped set of Warp arrays (`RecordArrays`, W worlds of every group,
zero-padded to the widest design) with the oracle's rules (`tt.sim.validate`): targets at
index min(t, T_m - 1), termination at the first step whose summed end-effector position
error exceeds the threshold (or, for a floating base, that falls), and every later step
(also past a motion's end) repeating the last record with alive False. `site_poses`
reads end-effector poses from MuJoCo-Warp's site frames, with `mat2quat` giving the
quaternion the sign MuJoCo's `mju_mat2Quat` gives it (the one the oracle records).
The backends turn the records into an `Episode` of zero-copy torch views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import warp as wp


@wp.func
def mat2quat(m: wp.mat33) -> wp.vec4:
    """(w, x, y, z) of a rotation matrix, MuJoCo's `mju_mat2Quat` branch for branch (so the
    sign of the quaternion is the one the oracle records)."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    q = wp.vec4()
    if tr > 0.0:
        w = 0.5 * wp.sqrt(1.0 + tr)
        q = wp.vec4(w, 0.25 * (m[2, 1] - m[1, 2]) / w, 0.25 * (m[0, 2] - m[2, 0]) / w, 0.25 * (m[1, 0] - m[0, 1]) / w)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        x = 0.5 * wp.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = wp.vec4(0.25 * (m[2, 1] - m[1, 2]) / x, x, 0.25 * (m[0, 1] + m[1, 0]) / x, 0.25 * (m[0, 2] + m[2, 0]) / x)
    elif m[1, 1] > m[2, 2]:
        y = 0.5 * wp.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
        q = wp.vec4(0.25 * (m[0, 2] - m[2, 0]) / y, 0.25 * (m[0, 1] + m[1, 0]) / y, y, 0.25 * (m[1, 2] + m[2, 1]) / y)
    else:
        z = 0.5 * wp.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
        q = wp.vec4(0.25 * (m[1, 0] - m[0, 1]) / z, 0.25 * (m[0, 2] + m[2, 0]) / z, 0.25 * (m[1, 2] + m[2, 1]) / z, z)
    return wp.normalize(q)


@wp.kernel(module="unique")
def _site_frames(
    # Model:
    site_ids: wp.array(dtype=int),
    # Data in:
    site_xpos_in: wp.array2d(dtype=wp.vec3),
    site_xmat_in: wp.array2d(dtype=wp.mat33),
    # Out:
    ee_pos_out: wp.array2d(dtype=wp.vec3),
    ee_quat_out: wp.array2d(dtype=wp.vec4),
):
    worldid, e = wp.tid()
    sid = site_ids[e]
    ee_pos_out[worldid, e] = site_xpos_in[worldid, sid]
    ee_quat_out[worldid, e] = mat2quat(site_xmat_in[worldid, sid])


@wp.kernel(module="unique")
def _record_step(
    # In:
    t: int,
    threshold: float,
    base_qpos: int,
    fall_height: wp.array(dtype=float),
    fall_cos_tilt: float,
    world_row: wp.array(dtype=int),
    world_motion: wp.array(dtype=int),
    motion_steps_in: wp.array(dtype=wp.int32),
    motion_pos_in: wp.array3d(dtype=wp.vec3),
    motion_quat_in: wp.array3d(dtype=wp.vec4),
    qpos_in: wp.array2d(dtype=float),
    qvel_in: wp.array2d(dtype=float),
    ctrl_in: wp.array2d(dtype=float),
    act_force_in: wp.array2d(dtype=float),
    act_vel_in: wp.array2d(dtype=float),
    ee_pos_in: wp.array2d(dtype=wp.vec3),
    ee_quat_in: wp.array2d(dtype=wp.vec4),
    # Out:
    qpos_out: wp.array3d(dtype=float),
    qvel_out: wp.array3d(dtype=float),
    ctrl_out: wp.array3d(dtype=float),
    act_force_out: wp.array3d(dtype=float),
    act_vel_out: wp.array3d(dtype=float),
    ee_pos_out: wp.array3d(dtype=wp.vec3),
    ee_quat_out: wp.array3d(dtype=wp.vec4),
    target_pos_out: wp.array3d(dtype=wp.vec3),
    target_quat_out: wp.array3d(dtype=wp.vec4),
    alive_out: wp.array2d(dtype=wp.bool),
    fallen_out: wp.array2d(dtype=wp.bool),
):
    i = wp.tid()
    w = world_row[i]
    motionid = world_motion[i]
    steps = motion_steps_in[motionid]
    record = wp.min(t, steps - 1)
    ne = ee_pos_in.shape[1]
    for e in range(ne):
        target_pos_out[w, t, e] = motion_pos_in[motionid, record, e]
        target_quat_out[w, t, e] = motion_quat_in[motionid, record, e]
    stopped = t >= steps
    if t > 0:
        if not alive_out[w, t - 1]:
            stopped = True
    if stopped:
        # Past termination or the motion's end: repeat the last record (the oracle's rule).
        for d in range(qpos_in.shape[1]):
            qpos_out[w, t, d] = qpos_out[w, t - 1, d]
        for d in range(qvel_in.shape[1]):
            qvel_out[w, t, d] = qvel_out[w, t - 1, d]
        for u in range(ctrl_in.shape[1]):
            ctrl_out[w, t, u] = ctrl_out[w, t - 1, u]
            act_force_out[w, t, u] = act_force_out[w, t - 1, u]
            act_vel_out[w, t, u] = act_vel_out[w, t - 1, u]
        for e in range(ne):
            ee_pos_out[w, t, e] = ee_pos_out[w, t - 1, e]
            ee_quat_out[w, t, e] = ee_quat_out[w, t - 1, e]
        fallen_out[w, t] = fallen_out[w, t - 1]
        alive_out[w, t] = False
    else:
        for d in range(qpos_in.shape[1]):
            qpos_out[w, t, d] = qpos_in[i, d]
        for d in range(qvel_in.shape[1]):
            qvel_out[w, t, d] = qvel_in[i, d]
        for u in range(ctrl_in.shape[1]):
            ctrl_out[w, t, u] = ctrl_in[i, u]
            act_force_out[w, t, u] = act_force_in[i, u]
            act_vel_out[w, t, u] = act_vel_in[i, u]
        error = float(0.0)
        for e in range(ne):
            p = ee_pos_in[i, e]
            ee_pos_out[w, t, e] = p
            ee_quat_out[w, t, e] = ee_quat_in[i, e]
            error += wp.length(motion_pos_in[motionid, record, e] - p)
        fell = False
        if base_qpos >= 0:
            z = qpos_in[i, base_qpos + 2]
            qw = qpos_in[i, base_qpos + 3]
            qx = qpos_in[i, base_qpos + 4]
            qy = qpos_in[i, base_qpos + 5]
            qz = qpos_in[i, base_qpos + 6]
            norm2 = qw * qw + qx * qx + qy * qy + qz * qz
            # cos of the base z axis's angle to the world's: R_zz of the normalised quaternion.
            cos_tilt = (qw * qw - qx * qx - qy * qy + qz * qz) / wp.max(norm2, 1.0e-30)
            finite = wp.isfinite(z) and wp.isfinite(norm2)
            # `not (>=)` so that a NaN height or tilt counts as a fall, like a low one.
            fell = (not finite) or (not (z >= fall_height[i])) or (not (cos_tilt >= fall_cos_tilt))
        fallen_out[w, t] = fell
        # `<=` so that a NaN error (a diverged state) terminates like a large one.
        alive_out[w, t] = (error <= threshold) and (not fell)


@dataclass
class RecordArrays:
    """Records of W worlds over T control steps as Warp arrays (meanings: `tt.sim.episode.Episode`).

    qpos (W, T, NQ), qvel (W, T, NV), ctrl / act_force / act_vel (W, T, NU) float;
    ee_pos, target_pos (W, T, NE) vec3 [m]; ee_quat, target_quat (W, T, NE) vec4 (w, x, y, z);
    alive, fallen (W, T) bool. NQ, NV, NU are the widest design's; narrower designs
    leave their extra columns zero (the oracle's padding).
    """

    qpos: wp.array
    qvel: wp.array
    ctrl: wp.array
    act_force: wp.array
    act_vel: wp.array
    ee_pos: wp.array
    ee_quat: wp.array
    target_pos: wp.array
    target_quat: wp.array
    alive: wp.array
    fallen: wp.array

    @classmethod
    def zeros(cls, W: int, T: int, nq: int, nv: int, nu: int, ne: int, *, device: str) -> "RecordArrays":
        def z(shape, dtype):
            return wp.zeros(shape, dtype=dtype, device=device)

        return cls(
            qpos=z((W, T, nq), float), qvel=z((W, T, nv), float), ctrl=z((W, T, max(nu, 1)), float),
            act_force=z((W, T, max(nu, 1)), float), act_vel=z((W, T, max(nu, 1)), float),
            ee_pos=z((W, T, ne), wp.vec3), ee_quat=z((W, T, ne), wp.vec4),
            target_pos=z((W, T, ne), wp.vec3), target_quat=z((W, T, ne), wp.vec4),
            alive=z((W, T), wp.bool), fallen=z((W, T), wp.bool),
        )  # fmt: skip


def record_step(
    records: RecordArrays,
    t: int,
    *,
    threshold: float,
    world_row: wp.array,
    world_motion: wp.array,
    motions,
    qpos: wp.array,
    qvel: wp.array,
    ctrl: wp.array,
    act_force: wp.array,
    act_vel: wp.array,
    ee_pos: wp.array,
    ee_quat: wp.array,
    base_qpos: int = -1,
    fall_height: wp.array | None = None,
    fall_tilt: float = math.pi,
    device: str,
) -> None:
    """Write control step t of a group of Wg worlds into `records` (rows `world_row`).

    qpos (Wg, nq), qvel (Wg, nv), ctrl / act_force / act_vel (Wg, nu) float and ee_pos
    (Wg, NE) vec3, ee_quat (Wg, NE) vec4: the state after the step's physics and what
    belongs to it. motions: `tt.kernels.rollout.MotionArrays`; world_motion (Wg,) int: each
    world's motion. base_qpos: qpos address of a floating base (-1: fixed base, never
    fallen); fall_height (Wg,) [m] and fall_tilt [rad]: the fall test of `tt.sim.wbc.fallen`.
    """
    Wg = qpos.shape[0]
    if fall_height is None:
        fall_height = wp.zeros(1, dtype=float, device=device)
    wp.launch(
        _record_step,
        dim=Wg,
        inputs=[
            t,
            float(threshold),
            int(base_qpos),
            fall_height,
            float(math.cos(fall_tilt)),
            world_row,
            world_motion,
            motions.steps,
            motions.pos,
            motions.quat,
            qpos,
            qvel,
            ctrl,
            act_force,
            act_vel,
            ee_pos,
            ee_quat,
        ],  # fmt: skip
        outputs=[
            records.qpos,
            records.qvel,
            records.ctrl,
            records.act_force,
            records.act_vel,
            records.ee_pos,
            records.ee_quat,
            records.target_pos,
            records.target_quat,
            records.alive,
            records.fallen,
        ],  # fmt: skip
        device=device,
    )


def site_poses(
    site_ids: wp.array, site_xpos: wp.array, site_xmat: wp.array, ee_pos: wp.array, ee_quat: wp.array, *, device: str
) -> None:
    """End-effector poses of Wg worlds from site frames: ee_pos (Wg, NE) vec3 [m] and ee_quat
    (Wg, NE) vec4 (w, x, y, z) of sites `site_ids` (NE,) int, from site_xpos (Wg, nsite) vec3
    and site_xmat (Wg, nsite) mat33 (MuJoCo-Warp's ``Data`` fields)."""
    wp.launch(
        _site_frames,
        dim=ee_pos.shape,
        inputs=[site_ids, site_xpos, site_xmat],
        outputs=[ee_pos, ee_quat],
        device=device,
    )


__all__ = ["RecordArrays", "mat2quat", "record_step", "site_poses"]
