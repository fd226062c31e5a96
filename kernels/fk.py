"""Batched forward kinematics and end-effector Jacobians of articulated trees.

Conventions are MuJoCo's (`mj_kinematics`, `mj_jacSite`): a body's frame is its parent's
frame moved by the body offset (`body_pos`, `body_quat`) and then by its joint: a hinge
rotates by q - qpos0 about its axis through its anchor, a slide translates by q - qpos0
along its axis. An end-effector Jacobian is 6 x NV in the world frame: rows 0-2 map joint
velocities to the site's linear velocity, rows 3-5 to the body's angular velocity.

The per-world functions (`kinematics_funcs`) are specialised to a `Topology` (short loops
over bodies and dofs unrolled, parents and joint types compiled in) and shared by the fused
dynamics, IK and rollout kernels; the kernels here expose them for testing and for users
who need poses without simulating.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.lie import lie_funcs, wxyz
from tt.kernels.model import (
    JOINT_HINGE,
    MODULE_OPTIONS,
    Kinematics64,
    Topology,
    TreeArrays,
    TreeModel,
    local_types,
    module_name,
    topology_constants,
)


def model_struct(dtype=wp.float32):
    """The model struct the functions of precision `dtype` read: `TreeArrays` (float32) or
    `Kinematics64` (float64)."""
    return Kinematics64 if dtype == wp.float64 else TreeArrays


def kinematics_funcs(topology: Topology, dtype=wp.float32) -> SimpleNamespace:
    """See `_kinematics_funcs` (one cache entry per precision, however `dtype` is passed)."""
    return _kinematics_funcs(topology, dtype)


@functools.cache
def _kinematics_funcs(topology: Topology, dtype) -> SimpleNamespace:
    """Warp functions of one topology in scalar type `dtype`; they read the model struct of
    that precision (float32: `TreeArrays`, ``TreeModel.arrays``; float64: `Kinematics64`,
    ``TreeModel.kinematics64``), passed in as ``model``.

    kinematics(mid, model, q)
        -> (xpos (NB, 3) [m], xquat (NB, 4) (w, x, y, z), axis (NV, 3), anchor (NV, 3) [m]):
        body frames, and each dof's world axis and anchor, for joint positions q (NV,).
    site_pose(e, xpos, xquat, model, mid) -> (pos vec3 [m], quat) of end effector e.
    site_jacobian(e, axis, anchor, point) -> (6, NV) world-frame Jacobian of end effector e
        at world point `point` (its site position).

    The topology enters as constant index vectors (`topology_constants`), indexed by the
    loop counters; where a loop is unrolled (up to `MODULE_OPTIONS`' max_unroll iterations)
    the C++ compiler folds them and the branches on them, and Warp hashes them as constants
    (no per-process code generation, see `tt.kernels.generated`).
    The site functions are inlined so that a constant `e` folds too.
    """
    T = local_types(topology, dtype)
    LIE = lie_funcs(dtype)
    S, vec3, vec4 = T.scalar, T.vec3, T.vec4
    Model = model_struct(dtype)
    NB = topology.body_count
    NV = topology.dof_count
    C = topology_constants(topology)
    PARENT, BDOF, DTYPE, EE_BODY, EE_SUPPORT = C.body_parent, C.body_dof, C.dof_type, C.ee_body, C.ee_support

    @wp.func
    def kinematics(mid: int, model: Model, q: T.dof_vec):
        xpos = T.body_vec3()
        xquat = T.body_vec4()
        axis = T.dof_vec3()
        anchor = T.dof_vec3()
        xquat[0] = vec4(S(1.0), S(0.0), S(0.0), S(0.0))
        for b in range(1, NB):
            p = PARENT[b]
            rot_p = LIE.quat_wxyz(xquat[p])
            pos = xpos[p] + wp.quat_rotate(rot_p, model.body_pos[mid, b])
            rot = rot_p * LIE.quat_wxyz(model.body_quat[mid, b])
            if BDOF[b] >= 0:
                d = BDOF[b]
                jaxis = model.dof_axis[mid, d]
                jpos = model.dof_pos[mid, d]
                a = wp.quat_rotate(rot, jaxis)
                c = pos + wp.quat_rotate(rot, jpos)
                axis[d] = a
                anchor[d] = c
                if DTYPE[d] == JOINT_HINGE:
                    rot = rot * wp.quat_from_axis_angle(jaxis, q[d] - model.dof_ref[mid, d])
                    pos = c - wp.quat_rotate(rot, jpos)
                else:
                    pos = pos + a * (q[d] - model.dof_ref[mid, d])
            xpos[b] = pos
            xquat[b] = LIE.wxyz(wp.normalize(rot))
        return xpos, xquat, axis, anchor

    @wp.func(inline=True)
    def site_pose(e: int, xpos: T.body_vec3, xquat: T.body_vec4, model: Model, mid: int):
        b = EE_BODY[e]
        rot = LIE.quat_wxyz(xquat[b])
        return xpos[b] + wp.quat_rotate(rot, model.ee_pos[mid, e]), rot * LIE.quat_wxyz(model.ee_quat[mid, e])

    @wp.func(inline=True)
    def site_jacobian(e: int, axis: T.dof_vec3, anchor: T.dof_vec3, point: vec3):
        jac = T.ee_jac()
        for d in range(NV):
            if (EE_SUPPORT[e] >> d) & 1 != 0:
                a = axis[d]
                if DTYPE[d] == JOINT_HINGE:
                    lin = wp.cross(a, point - anchor[d])
                    jac[0, d] = lin[0]
                    jac[1, d] = lin[1]
                    jac[2, d] = lin[2]
                    jac[3, d] = a[0]
                    jac[4, d] = a[1]
                    jac[5, d] = a[2]
                else:
                    jac[0, d] = a[0]
                    jac[1, d] = a[1]
                    jac[2, d] = a[2]
        return jac

    return SimpleNamespace(kinematics=kinematics, site_pose=site_pose, site_jacobian=site_jacobian)


def make_fk_kernel(topology: Topology, module: str):
    """The forward-kinematics kernel of one topology, registered in Warp module `module`."""
    T = local_types(topology)
    F = kinematics_funcs(topology)
    NB, NV, NE = topology.body_count, topology.dof_count, topology.ee_count

    @wp.kernel(module=module)
    def _forward_kinematics(
        # Model:
        model: TreeArrays,
        # Data in:
        qpos_in: wp.array2d(dtype=float),
        # Data out:
        xpos_out: wp.array2d(dtype=wp.vec3),
        xquat_out: wp.array2d(dtype=wp.vec4),
        site_pos_out: wp.array2d(dtype=wp.vec3),
        site_quat_out: wp.array2d(dtype=wp.vec4),
        site_jac_out: wp.array4d(dtype=float),
    ):
        worldid = wp.tid()
        mid = worldid % model.body_pos.shape[0]
        q = T.dof_vec()
        for d in range(NV):
            q[d] = qpos_in[worldid, d]
        xpos, xquat, axis, anchor = F.kinematics(mid, model, q)
        for b in range(NB):
            xpos_out[worldid, b] = xpos[b]
            xquat_out[worldid, b] = xquat[b]
        for e in range(NE):
            p, r = F.site_pose(e, xpos, xquat, model, mid)
            site_pos_out[worldid, e] = p
            site_quat_out[worldid, e] = wxyz(r)
            jac = F.site_jacobian(e, axis, anchor, p)
            for i in range(6):
                for d in range(NV):
                    site_jac_out[worldid, e, i, d] = jac[i, d]

    return _forward_kinematics


@functools.cache
def fk_kernel(topology: Topology):
    """The forward-kinematics kernel of a topology, in its own module."""
    module = module_name(topology, "fk")
    wp.set_module_options(MODULE_OPTIONS, module)
    return make_fk_kernel(topology, module)


def forward_kinematics(
    model: TreeModel,
    qpos: wp.array,
    out: SimpleNamespace | None = None,
    *,
    device: str | None = None,
) -> SimpleNamespace:
    """Body frames, end-effector poses and Jacobians of W worlds.

    qpos: joint positions [rad or m], (W, NV) float32; world w uses model entry
    w % model.world_count.
    out: arrays to fill (see `kinematics_outputs`); allocated when None.
    Returns `out`: xpos (W, NB) vec3 [m] and xquat (W, NB) vec4 (w, x, y, z) of the tree
    bodies; site_pos (W, NE) vec3 [m], site_quat (W, NE) vec4; site_jac (W, NE, 6, NV)
    float (world frame, rows: linear then angular).
    """
    topo = model.topology
    device = device or model.device
    if qpos.ndim != 2 or qpos.shape[1] != topo.dof_count:
        raise TTError(f"qpos has shape {qpos.shape}; expected (W, {topo.dof_count})")
    W = qpos.shape[0]
    if out is None:
        out = kinematics_outputs(model, W, device=device)
    wp.launch(
        fk_kernel(topo),
        dim=W,
        inputs=[model.arrays, qpos],
        outputs=[out.xpos, out.xquat, out.site_pos, out.site_quat, out.site_jac],
        device=device,
    )
    return out


def kinematics_outputs(
    model: TreeModel, world_count: int, *, fill: float = 0.0, device: str | None = None
) -> SimpleNamespace:
    """Output arrays of `forward_kinematics` for `world_count` worlds, every entry `fill`."""
    topo = model.topology
    device = device or model.device
    W, NB, NE, NV = world_count, topo.body_count, topo.ee_count, topo.dof_count

    def full(shape, dtype, n):
        return wp.array(np.full(shape + (n,), fill, dtype=np.float32), dtype=dtype, device=device)

    return SimpleNamespace(
        xpos=full((W, NB), wp.vec3, 3),
        xquat=full((W, NB), wp.vec4, 4),
        site_pos=full((W, NE), wp.vec3, 3),
        site_quat=full((W, NE), wp.vec4, 4),
        site_jac=wp.array(np.full((W, NE, 6, NV), fill, dtype=np.float32), dtype=float, device=device),
    )
