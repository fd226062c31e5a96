"""Controller glue kernels: IK targets from motions, actuator commands from IK commands.

For backends that run tt's IK kernels (`tt.kernels.ik`, `tt.kernels.wbc`) on another
simulator's state, one control step at a time: `lookahead_targets` picks each world's IK
target (the motion pose min(t + lookahead, T_m - 1), the oracle's look-ahead),
`joint_command` turns a joint command into each actuator's clamped position command, and
`live_joint_command` does the same for worlds still running (a terminated world keeps its
last command, as the oracle stops it).
"""

from __future__ import annotations

import warp as wp


@wp.kernel(module="unique")
def _lookahead_targets(
    # In:
    t: int,
    lookahead: int,
    world_motion: wp.array(dtype=int),
    motion_steps_in: wp.array(dtype=wp.int32),
    motion_pos_in: wp.array3d(dtype=wp.vec3),
    motion_quat_in: wp.array3d(dtype=wp.vec4),
    # Out:
    target_pos_out: wp.array2d(dtype=wp.vec3),
    target_quat_out: wp.array2d(dtype=wp.vec4),
):
    worldid, e = wp.tid()
    motionid = world_motion[worldid]
    goal = wp.min(t + lookahead, motion_steps_in[motionid] - 1)
    target_pos_out[worldid, e] = motion_pos_in[motionid, goal, e]
    target_quat_out[worldid, e] = motion_quat_in[motionid, goal, e]


@wp.kernel(module="unique")
def _joint_command(
    # Model:
    actuator_qpos: wp.array(dtype=int),
    ctrl_range: wp.array2d(dtype=wp.vec2),
    # In:
    q_cmd_in: wp.array2d(dtype=float),
    # Out:
    ctrl_out: wp.array2d(dtype=float),
):
    worldid, u = wp.tid()
    r = ctrl_range[worldid % ctrl_range.shape[0], u]
    ctrl_out[worldid, u] = wp.clamp(q_cmd_in[worldid, actuator_qpos[u]], r[0], r[1])


@wp.kernel(module="unique")
def _live_joint_command(
    # Model:
    actuator_qpos: wp.array(dtype=int),
    ctrl_range: wp.array2d(dtype=wp.vec2),
    # In:
    t: int,
    world_row: wp.array(dtype=int),
    alive_in: wp.array2d(dtype=wp.bool),
    q_cmd_in: wp.array2d(dtype=float),
    # Out:
    ctrl_out: wp.array2d(dtype=float),
):
    worldid, u = wp.tid()
    # A terminated world keeps its last command: the oracle stops it, and its state may
    # have diverged. (alive_in holds the Episode's records; step t - 1 is the last written.)
    if t > 0:
        if not alive_in[world_row[worldid], t - 1]:
            return
    r = ctrl_range[worldid % ctrl_range.shape[0], u]
    ctrl_out[worldid, u] = wp.clamp(q_cmd_in[worldid, actuator_qpos[u]], r[0], r[1])


def joint_command(
    q_cmd: wp.array, actuator_qpos: wp.array, ctrl_range: wp.array, ctrl: wp.array, *, device: str
) -> None:
    """ctrl (Wg, NU) = clip(q_cmd[:, actuator_qpos], ctrl_range): the position command of each
    actuator from the IK's joint command q_cmd (Wg, NQ); actuator_qpos (NU,) int is the qpos
    address each actuator drives (`tt.sim.controller.actuated_qpos`), ctrl_range (1 or Wg, NU)
    vec2 its clamp (`tt.sim.mjwarp_backend.ctrl_ranges`)."""
    if ctrl.shape[1] and actuator_qpos.shape[0]:
        wp.launch(
            _joint_command,
            dim=(q_cmd.shape[0], actuator_qpos.shape[0]),
            inputs=[actuator_qpos, ctrl_range, q_cmd],
            outputs=[ctrl],
            device=device,
        )


def live_joint_command(
    q_cmd: wp.array,
    actuator_qpos: wp.array,
    ctrl_range: wp.array,
    t: int,
    world_row: wp.array,
    alive: wp.array,
    ctrl: wp.array,
    *,
    device: str,
) -> None:
    """`joint_command` for the worlds alive at control step t - 1 only: alive (W, T) bool are
    the records' alive flags (`tt.kernels.records.RecordArrays.alive`), world_row (Wg,) int
    each world's row in them; the others keep their ctrl."""
    wp.launch(
        _live_joint_command, dim=(q_cmd.shape[0], actuator_qpos.shape[0]),
        inputs=[actuator_qpos, ctrl_range, t, world_row, alive, q_cmd], outputs=[ctrl], device=device,
    )  # fmt: skip


def lookahead_targets(
    t: int, lookahead: int, world_motion: wp.array, motions, target_pos: wp.array, target_quat: wp.array, *, device: str
) -> None:
    """IK targets of control step t: motion pose min(t + lookahead, T_m - 1) of each world's
    motion, into target_pos (Wg, NE) vec3 and target_quat (Wg, NE) vec4."""
    wp.launch(
        _lookahead_targets,
        dim=target_pos.shape,
        inputs=[t, lookahead, world_motion, motions.steps, motions.pos, motions.quat],
        outputs=[target_pos, target_quat],
        device=device,
    )


__all__ = ["joint_command", "live_joint_command", "lookahead_targets"]
