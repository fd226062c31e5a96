"""Pose errors and the tracking reward as Warp functions and kernels.

The definitions are those of `tt.sim.rewards` (the one torch definition of every
reward): the position error is |p_target - p| [m]; the orientation error is the geodesic
angle 2 atan2(|v|, |w|) [rad] of the relative quaternion (w, v); with A end effectors the
errors are summed over them; a step's tracking term is
``exp(-eps_p^2 / sigma_p - eps_o^2 / sigma_o)``. The kernels here exist so that a rollout
on Warp can be scored and differentiated under `wp.Tape` without leaving Warp.
"""

from __future__ import annotations

import functools

import warp as wp

from tt.kernels.lie import quat_wxyz

#: Added under square roots so that their adjoints stay finite at exactly zero error; it
#: shifts an error by at most 1e-12 m or rad.
_SQRT_EPS = 1.0e-24


@wp.func
def position_error(pos: wp.vec3, target_pos: wp.vec3) -> float:
    """|target_pos - pos| [m]."""
    d = target_pos - pos
    return wp.sqrt(wp.dot(d, d) + _SQRT_EPS)


@wp.func
def orientation_error(quat: wp.vec4, target_quat: wp.vec4) -> float:
    """Geodesic angle [rad] in [0, pi] between orientations (w, x, y, z); scale and sign free."""
    r = wp.quat_inverse(quat_wxyz(quat)) * quat_wxyz(target_quat)
    v = wp.vec3(r[0], r[1], r[2])
    return 2.0 * wp.atan2(wp.sqrt(wp.dot(v, v) + _SQRT_EPS), wp.abs(r[3]))


@functools.cache
def _tracking_reward_kernel(ee_count: int):
    # One kernel per end-effector count: the sum over end effectors is unrolled, which the
    # adjoint needs (a dynamic loop that accumulates into a local is not differentiable).
    A = ee_count

    @wp.kernel(module="unique")
    def _tracking_reward(
        # In:
        sigma_p: float,
        sigma_o: float,
        ee_pos_in: wp.array3d(dtype=wp.vec3),
        ee_quat_in: wp.array3d(dtype=wp.vec4),
        target_pos_in: wp.array3d(dtype=wp.vec3),
        target_quat_in: wp.array3d(dtype=wp.vec4),
        counted_in: wp.array2d(dtype=wp.int32),
        # Out:
        reward_out: wp.array(dtype=float),
    ):
        worldid, t = wp.tid()
        if counted_in[worldid, t] != 0:
            eps_p = float(0.0)
            eps_o = float(0.0)
            for a in range(A):
                eps_p += position_error(ee_pos_in[worldid, t, a], target_pos_in[worldid, t, a])
                eps_o += orientation_error(ee_quat_in[worldid, t, a], target_quat_in[worldid, t, a])
            wp.atomic_add(reward_out, worldid, wp.exp(-eps_p * eps_p / sigma_p - eps_o * eps_o / sigma_o))

    return _tracking_reward


def tracking_reward(
    ee_pos: wp.array,
    ee_quat: wp.array,
    target_pos: wp.array,
    target_quat: wp.array,
    counted: wp.array,
    reward_out: wp.array,
    *,
    sigma_p: float = 0.01,
    sigma_o: float = 0.5,
    device: str | None = None,
) -> None:
    """Add each world's tracking reward sum_t counted * exp(-eps_p^2/sigma_p - eps_o^2/sigma_o).

    ee_pos, target_pos: (W, T, A) vec3 [m]; ee_quat, target_quat: (W, T, A) vec4 (w, x, y, z);
    counted: (W, T) int32, 1 where the step counts; reward_out: (W,) float, accumulated into
    (zero it first). sigma_p [m^2], sigma_o [rad^2]. Differentiable in the poses.
    """
    W, T = counted.shape
    wp.launch(
        _tracking_reward_kernel(ee_pos.shape[2]),
        dim=(W, T),
        inputs=[sigma_p, sigma_o, ee_pos, ee_quat, target_pos, target_quat, counted],
        outputs=[reward_out],
        device=device or ee_pos.device,
    )
