"""One control step of externally commanded worlds: physics with the command held, then the record.

For controllers outside the kernels (the DiT policy of `tt.dit.closed_loop`): each call
advances W worlds of one topology by `substeps` physics steps (`tt.kernels.dynamics`)
with the given commands clamped to ctrlrange and held, then writes what belongs to the
new state, the actuator forces and velocities and the end-effector poses, exactly as the
fused rollout kernel (`tt.kernels.rollout`) records a step. The state goes through memory
each substep, as in the fused kernel, so both produce the same bits for the same commands.
"""

from __future__ import annotations

import functools

import warp as wp

from tt.kernels.dynamics import dynamics_funcs
from tt.kernels.fk import kinematics_funcs
from tt.kernels.lie import wxyz
from tt.kernels.model import MODULE_OPTIONS, Topology, TreeArrays, TreeModel, local_types, module_name


def make_control_step_kernel(topology: Topology, module: str):
    """The control-step kernel of one topology, registered in Warp module `module`."""
    T = local_types(topology)
    K = kinematics_funcs(topology)
    Dyn = dynamics_funcs(topology)
    NV, NU, NE = topology.dof_count, topology.actuator_count, topology.ee_count

    @wp.kernel(module=module)
    def _control_step(
        # Model:
        model: TreeArrays,
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
        mid = worldid % model.body_pos.shape[0]
        ctrl = T.act_vec()
        for u in range(NU):
            cr = model.act_ctrlrange[mid, u]
            ctrl[u] = wp.clamp(ctrl_in[worldid, u], cr[0], cr[1])
        for k in range(substeps):
            qk = T.dof_vec()
            qdk = T.dof_vec()
            for d in range(NV):
                qk[d] = qpos_state[worldid, d]
                qdk[d] = qvel_state[worldid, d]
            qn, qdn, force, vel, active = Dyn.step(mid, model, qk, qdk, ctrl)
            for d in range(NV):
                qpos_state[worldid, d] = qn[d]
                qvel_state[worldid, d] = qdn[d]
        q1 = T.dof_vec()
        qd1 = T.dof_vec()
        for d in range(NV):
            q1[d] = qpos_state[worldid, d]
            qd1[d] = qvel_state[worldid, d]
        qfrc, force1, vel1 = Dyn.actuation(mid, model, q1, qd1, ctrl)
        for u in range(NU):
            act_force_out[worldid, u] = force1[u]
            act_vel_out[worldid, u] = vel1[u]
        xpos1, xquat1, axis1, anchor1 = K.kinematics(mid, model, q1)
        for e in range(NE):
            p, r = K.site_pose(e, xpos1, xquat1, model, mid)
            ee_pos_out[worldid, e] = p
            ee_quat_out[worldid, e] = wxyz(r)

    return _control_step


@functools.cache
def control_step_kernel(topology: Topology):
    """The control-step kernel of a topology, in its own Warp module (compiled once)."""
    module = module_name(topology, "control_step")
    wp.set_module_options(MODULE_OPTIONS, module)
    return make_control_step_kernel(topology, module)


def control_step(
    model: TreeModel,
    ctrl: wp.array,
    qpos: wp.array,
    qvel: wp.array,
    act_force: wp.array,
    act_vel: wp.array,
    ee_pos: wp.array,
    ee_quat: wp.array,
    *,
    substeps: int,
    device: str | None = None,
) -> None:
    """Advance W worlds (world w: model entry w % model.world_count) by one control period.

    ctrl: joint position targets (W, max(NU, 1)) float, clamped to ctrlrange and held.
    qpos, qvel: the physics state (W, NV) [rad or m, rad/s or m/s], updated in place.
    act_force [N m or N], act_vel: (W, max(NU, 1)) float; ee_pos (W, NE) vec3 [m], ee_quat
    (W, NE) vec4 (w, x, y, z): written with the record of the new state.
    substeps: physics steps (0 records the current state without stepping).
    """
    wp.launch(
        control_step_kernel(model.topology),
        dim=qpos.shape[0],
        inputs=[model.arrays, int(substeps), ctrl, qpos, qvel],
        outputs=[act_force, act_vel, ee_pos, ee_quat],
        device=device or model.device,
    )


__all__ = ["control_step", "control_step_kernel"]
