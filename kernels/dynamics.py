"""Joint-space dynamics of contact-free articulated trees, stepped like MuJoCo's Euler.

One physics step of a world (all in thread-local memory, see `dynamics_funcs`):

1. Kinematics (`tt.kernels.fk`), then each body's mass m, first moment h = m c and
   rotational inertia J about a reference point (the first body's origin, which keeps
   float32 lever arms short), and each dof's motion axis s = (w, v) there.
2. Mass matrix by the composite-rigid-body algorithm, plus armature on the diagonal.
3. Bias forces C(q, qd) qd + g(q) by recursive Newton-Euler with the base accelerating at -g.
   Gravity compensation (MuJoCo's body_gravcomp, a passive force) cancels each body's
   share of its weight in the same pass: body b's wrench gains gravcomp_b (m g, h x g).
4. Passive forces: -damping qd - stiffness (q - springref).
5. Actuators (MuJoCo's stateless affine actuators on joint transmissions):
   ctrl clamped to ctrlrange, force = gain ctrl + b0 + b1 gear q + b2 gear qd clamped to
   forcerange, joint force gear * force. A position actuator is gain = kp, b = (0, -kp, -kv).
6. Joint limits as MuJoCo's soft constraints (solref / solimp): a limit row is active when
   q is past its range; its force minimises MuJoCo's dual objective
   1/2 f (A + R) f + f (J qacc_smooth - aref), f >= 0 (A = J M^-1 J^T), solved by
   projected Gauss-Seidel (at most `TreeArrays.limit_sweeps` sweeps, until the forces change
   by less than 1e-6 relative), which for the one or two rows a robot's limits produce at a
   time converges to the solution of MuJoCo's Newton solver.
7. Euler with implicit joint damping, as MuJoCo integrates it:
   qacc = (M + h D)^-1 (qfrc_smooth + qfrc_constraint); qd' = qd + h qacc; q' = q + h qd'.

Matrices are factored as M = L^T D L in tree order (`tt.kernels.ltdl`, MuJoCo's
`mj_factorI`), which has no fill-in, so branched trees (two arms) cost less than a dense
Cholesky.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.fk import kinematics_funcs
from tt.kernels.ltdl import ltdl_funcs
from tt.kernels.model import (
    JOINT_HINGE,
    MJ_MAXIMP,
    MJ_MINIMP,
    MJ_MINVAL,
    MODULE_OPTIONS,
    Topology,
    TreeArrays,
    TreeModel,
    local_types,
    module_name,
    topology_constants,
)

#: Gauss-Seidel sweeps of the joint-limit solve in differentiable kernels (exact for one
#: active row; two or three rows, what a robot's limits produce, converge in a few).
LIMIT_SWEEPS_DIFFERENTIABLE = 8

vec9 = wp.types.vector(length=9, dtype=wp.float32)


@wp.func
def _mat33(v: vec9) -> wp.mat33:
    return wp.mat33(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8])


@wp.func
def _vec9(m: wp.mat33) -> vec9:
    return vec9(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])


@wp.func
def limit_impedance(pos: float, dmin: float, dmax: float, width: float, midpoint: float, power: float) -> float:
    """MuJoCo's constraint impedance at violation `pos` for solimp (dmin, dmax, width, mid, power)."""
    dmin = wp.clamp(dmin, MJ_MINIMP, MJ_MAXIMP)
    dmax = wp.clamp(dmax, MJ_MINIMP, MJ_MAXIMP)
    midpoint = wp.clamp(midpoint, MJ_MINIMP, MJ_MAXIMP)
    power = wp.max(1.0, power)
    if dmin == dmax or width <= MJ_MINVAL:
        return 0.5 * (dmin + dmax)
    x = wp.abs(pos) / width
    if x >= 1.0:
        return dmax
    if x <= 0.0:
        return dmin
    y = float(0.0)
    if x <= midpoint:
        y = wp.pow(x, power) / wp.pow(midpoint, power - 1.0)
    else:
        y = 1.0 - wp.pow(1.0 - x, power) / wp.pow(1.0 - midpoint, power - 1.0)
    return dmin + y * (dmax - dmin)


def dynamics_funcs(topology: Topology, differentiable: bool = False) -> SimpleNamespace:
    """See `_dynamics_funcs` (one cache entry per variant, however the flag is passed)."""
    return _dynamics_funcs(topology, bool(differentiable))


@functools.cache
def _dynamics_funcs(topology: Topology, differentiable: bool) -> SimpleNamespace:
    """Warp functions of one topology (see the module docstring for the algorithm).

    differentiable: the variant for kernels with adjoints: the joint-limit solve runs a
    fixed `LIMIT_SWEEPS_DIFFERENTIABLE` sweeps in unrolled loops (exact adjoint) instead
    of dynamic loops that stop at convergence (`TreeArrays.limit_sweeps` at most).

    step(mid, model, q, qd, ctrl) -> (q', qd', act_force, act_vel, active_limits):
        one Euler step of world-model entry `mid` of `model` (`TreeArrays`) from joint
        positions q and velocities qd
        (NV,) under actuator commands ctrl (NU,); act_force [N m or N] and act_vel are the
        actuator forces and velocities at the start of the step (MuJoCo's
        actuator_force / actuator_velocity after mj_step); active_limits counts limit rows.
    actuation(mid, model, q, qd, ctrl) -> (joint forces, act_force, act_vel).
    mass_matrix(...), bias_forces(...), factor(A) -> (L, D), solve(L, D, b): the stages.
    """
    T = local_types(topology)
    K = kinematics_funcs(topology)
    DIFFERENTIABLE = differentiable
    NB, NV, NU = topology.body_count, topology.dof_count, topology.actuator_count
    C = topology_constants(topology)
    PARENT, BDOF, DOF_BODY, DTYPE, ACT_DOF = C.body_parent, C.body_dof, C.dof_body, C.dof_type, C.actuator_dof
    DOF_SUPPORT = C.dof_support
    LTDL = ltdl_funcs(topology.dof_parent, T.dof_mat, T.dof_vec)
    factor = LTDL.factor
    solve = LTDL.solve

    @wp.func
    def body_inertias(mid: int, model: TreeArrays, xpos: T.body_vec3, xquat: T.body_vec4, ref: wp.vec3):
        # Per body: mass, first moment m c and rotational inertia about `ref`, world axes.
        bm = T.body_scalar()
        bh = T.body_vec3()
        bJ = T.body_mat9()
        for b in range(1, NB):
            m = model.body_mass[mid, b]
            xq = wp.quat(xquat[b][1], xquat[b][2], xquat[b][3], xquat[b][0])
            iq = model.body_iquat[mid, b]
            # The inertia frame in one quaternion product and one matrix, and Ri diag(I) Ri^T
            # as a sum over the principal axes (columns of Ri): about half the arithmetic of
            # two rotation matrices, their product and two dense 3x3 products, every step.
            Ri = wp.quat_to_matrix(xq * wp.quat(iq[1], iq[2], iq[3], iq[0]))
            c = xpos[b] + wp.quat_rotate(xq, model.body_ipos[mid, b]) - ref
            inertia = model.body_inertia[mid, b]
            a0 = wp.vec3(Ri[0, 0], Ri[1, 0], Ri[2, 0])
            a1 = wp.vec3(Ri[0, 1], Ri[1, 1], Ri[2, 1])
            a2 = wp.vec3(Ri[0, 2], Ri[1, 2], Ri[2, 2])
            Ic = wp.outer(inertia[0] * a0, a0) + wp.outer(inertia[1] * a1, a1) + wp.outer(inertia[2] * a2, a2)
            J = Ic + m * (wp.dot(c, c) * wp.identity(n=3, dtype=float) - wp.outer(c, c))
            bm[b] = m
            bh[b] = m * c
            bJ[b] = _vec9(J)
        return bm, bh, bJ

    @wp.func
    def motion_subspace(axis: T.dof_vec3, anchor: T.dof_vec3, ref: wp.vec3):
        # Spatial motion (angular w, linear v at `ref`) of each dof per unit velocity.
        s_ang = T.dof_vec3()
        s_lin = T.dof_vec3()
        for d in range(NV):
            if DTYPE[d] == JOINT_HINGE:
                s_ang[d] = axis[d]
                s_lin[d] = wp.cross(anchor[d] - ref, axis[d])
            else:
                s_lin[d] = axis[d]
        return s_ang, s_lin

    @wp.func
    def mass_matrix(bm: T.body_scalar, bh: T.body_vec3, bJ: T.body_mat9, s_ang: T.dof_vec3, s_lin: T.dof_vec3):
        # Composite inertias, leaves to root; M[i, j] = s_j . (I_composite(body_i) s_i).
        # The arguments are this function's own copies: accumulate the composites in them.
        # (No second name for them: with differentiable component writes an alias would
        # stop seeing the updates.)
        for k in range(1, NB):
            b = NB - k
            p = PARENT[b]
            if p > 0:
                bm[p] = bm[p] + bm[b]
                bh[p] = bh[p] + bh[b]
                bJ[p] = bJ[p] + bJ[b]
        # Momentum (L, P) of each dof's composite body moving at unit dof velocity.
        FL = T.dof_vec3()
        FP = T.dof_vec3()
        for i in range(NV):
            b = DOF_BODY[i]
            w = s_ang[i]
            v = s_lin[i]
            FL[i] = _mat33(bJ[b]) @ w + wp.cross(bh[b], v)
            FP[i] = bm[b] * v + wp.cross(w, bh[b])
        M = T.dof_mat()
        # The lower triangle on the tree pattern: j = i or an ancestor of i.
        for i in range(NV):
            for j in range(NV):
                if (DOF_SUPPORT[i] >> j) & 1 != 0:
                    M[i, j] = wp.dot(s_ang[j], FL[i]) + wp.dot(s_lin[j], FP[i])
        return M

    @wp.func
    def bias_forces(
        bm: T.body_scalar,
        bh: T.body_vec3,
        bJ: T.body_mat9,
        s_ang: T.dof_vec3,
        s_lin: T.dof_vec3,
        qd: T.dof_vec,
        gravity: wp.vec3,
        gravcomp: T.body_scalar,
    ):
        # RNEA with zero joint accelerations and the base accelerating at -g. A body's
        # gravity compensation gravcomp[b] removes that share of its weight's wrench
        # (m g at the center of mass: force m g, moment h x g about the reference point),
        # which is MuJoCo's qfrc_gravcomp taken off the bias force.
        v_ang = T.body_vec3()
        v_lin = T.body_vec3()
        a_ang = T.body_vec3()
        a_lin = T.body_vec3()
        f_ang = T.body_vec3()
        f_lin = T.body_vec3()
        a_lin[0] = -gravity
        for b in range(1, NB):
            p = PARENT[b]
            w = v_ang[p]
            v = v_lin[p]
            aw = a_ang[p]
            av = a_lin[p]
            if BDOF[b] >= 0:
                d = BDOF[b]
                sw = s_ang[d]
                sv = s_lin[d]
                # d/dt of the dof's axis moving with the parent: (w, v) x s.
                aw = aw + qd[d] * wp.cross(w, sw)
                av = av + qd[d] * (wp.cross(w, sv) + wp.cross(v, sw))
                w = w + qd[d] * sw
                v = v + qd[d] * sv
            v_ang[b] = w
            v_lin[b] = v
            a_ang[b] = aw
            a_lin[b] = av
            J = _mat33(bJ[b])
            h = bh[b]
            m = bm[b]
            # f = I a + V x* (I V), I V = (J w + h x v, m v + w x h).
            L = J @ w + wp.cross(h, v)
            P = m * v + wp.cross(w, h)
            f_ang[b] = J @ aw + wp.cross(h, av) + wp.cross(w, L) + wp.cross(v, P) + gravcomp[b] * wp.cross(h, gravity)
            f_lin[b] = m * av + wp.cross(aw, h) + wp.cross(w, P) + gravcomp[b] * m * gravity
        for k in range(1, NB):
            b = NB - k
            p = PARENT[b]
            if p > 0:
                f_ang[p] = f_ang[p] + f_ang[b]
                f_lin[p] = f_lin[p] + f_lin[b]
        bias = T.dof_vec()
        for d in range(NV):
            b = DOF_BODY[d]
            bias[d] = wp.dot(s_ang[d], f_ang[b]) + wp.dot(s_lin[d], f_lin[b])
        return bias

    @wp.func
    def actuation(mid: int, model: TreeArrays, q: T.dof_vec, qd: T.dof_vec, ctrl: T.act_vec):
        # Joint forces of the actuators, and each actuator's force and velocity.
        qfrc = T.dof_vec()
        act_force = T.act_vec()
        act_vel = T.act_vec()
        for u in range(NU):
            d = ACT_DOF[u]
            gear = model.act_gear[mid, u]
            cr = model.act_ctrlrange[mid, u]
            fr = model.act_forcerange[mid, u]
            b = model.act_bias[mid, u]
            vel = gear * qd[d]
            c = wp.clamp(ctrl[u], cr[0], cr[1])
            force = wp.clamp(model.act_gain[mid, u] * c + b[0] + b[1] * gear * q[d] + b[2] * vel, fr[0], fr[1])
            act_force[u] = force
            act_vel[u] = vel
            qfrc[d] = qfrc[d] + gear * force
        return qfrc, act_force, act_vel

    @wp.func
    def minv_column(Lm: T.dof_mat, Dm: T.dof_vec, d: int):
        e = T.dof_vec()
        e[d] = 1.0
        return solve(Lm, Dm, e)

    @wp.func
    def pgs_sweep(sign: T.dof_vec, offset: T.dof_vec, reg: T.dof_vec, Minv: T.dof_mat, f: T.dof_vec):
        # One projected Gauss-Seidel sweep over the active rows; returns the forces, the
        # largest change and the largest force.
        change = float(0.0)
        size = float(0.0)
        for d in range(NV):
            if sign[d] != 0.0:
                res = offset[d] + reg[d] * f[d]
                for j in range(NV):
                    res += sign[d] * sign[j] * Minv[d, j] * f[j]
                f_new = wp.max(0.0, f[d] - res / (Minv[d, d] + reg[d]))
                change = wp.max(change, wp.abs(f_new - f[d]))
                size = wp.max(size, wp.abs(f_new))
                f[d] = f_new
        return f, change, size

    @wp.func
    def limit_forces(
        mid: int,
        model: TreeArrays,
        M: T.dof_mat,
        q: T.dof_vec,
        qd: T.dof_vec,
        qfrc_smooth: T.dof_vec,
    ):
        # Joint-space force of the active limit rows (zero when none is active).
        sign = T.dof_vec()
        dist = T.dof_vec()
        active = int(0)
        for d in range(NV):
            r = model.dof_range[mid, d]
            lo = q[d] - r[0]
            hi = r[1] - q[d]
            if lo < 0.0 and lo <= hi:
                sign[d] = 1.0
                dist[d] = lo
                active += 1
            elif hi < 0.0:
                sign[d] = -1.0
                dist[d] = hi
                active += 1
        qfrc = T.dof_vec()
        if active == 0:
            return qfrc, active
        Lm, Dm = factor(M)
        acc0 = solve(Lm, Dm, qfrc_smooth)
        # Columns of M^-1 for the active rows only. In the forward-only build the loops over
        # rows and sweeps are dynamic (bounds from arrays: only their bodies are unrolled)
        # and the sweeps stop once converged; the differentiable build unrolls them with a
        # fixed sweep count, which Warp's adjoint replays exactly.
        Minv = T.dof_mat()
        if wp.static(DIFFERENTIABLE):
            for d in range(NV):
                if sign[d] != 0.0:
                    col = minv_column(Lm, Dm, d)
                    for i in range(NV):
                        Minv[i, d] = col[i]
        else:
            for d in range(model.dof_range.shape[1]):
                if sign[d] != 0.0:
                    col = minv_column(Lm, Dm, d)
                    for i in range(NV):
                        Minv[i, d] = col[i]
        # Row data: residual offset J acc0 - aref and regulariser R.
        offset = T.dof_vec()
        reg = T.dof_vec()
        for d in range(NV):
            if sign[d] != 0.0:
                kb = model.dof_limit_kb[mid, d]
                imp = limit_impedance(
                    dist[d],
                    model.dof_solimp[mid, d, 0],
                    model.dof_solimp[mid, d, 1],
                    model.dof_solimp[mid, d, 2],
                    model.dof_solimp[mid, d, 3],
                    model.dof_solimp[mid, d, 4],
                )
                vel = sign[d] * qd[d]
                aref = -kb[1] * vel - kb[0] * imp * dist[d]
                offset[d] = sign[d] * acc0[d] - aref
                reg[d] = wp.max(MJ_MINVAL, (1.0 - imp) * model.dof_invweight0[mid, d] / imp)
        f = T.dof_vec()
        if wp.static(DIFFERENTIABLE):
            for sweep in range(LIMIT_SWEEPS_DIFFERENTIABLE):
                f, change, size = pgs_sweep(sign, offset, reg, Minv, f)
        else:
            for sweep in range(model.limit_sweeps[mid % model.limit_sweeps.shape[0]]):
                f, change, size = pgs_sweep(sign, offset, reg, Minv, f)
                # Converged (one sweep already is, for a single row): stop early.
                if change <= 1.0e-6 * size:
                    break
        for d in range(NV):
            qfrc[d] = sign[d] * f[d]
        return qfrc, active

    @wp.func
    def step(mid: int, model: TreeArrays, q: T.dof_vec, qd: T.dof_vec, ctrl: T.act_vec):
        h = model.timestep[mid % model.timestep.shape[0]]
        xpos, xquat, axis, anchor = K.kinematics(mid, model, q)
        ref = xpos[1]
        bm, bh, bJ = body_inertias(mid, model, xpos, xquat, ref)
        s_ang, s_lin = motion_subspace(axis, anchor, ref)
        M = mass_matrix(bm, bh, bJ, s_ang, s_lin)
        for d in range(NV):
            M[d, d] = M[d, d] + model.dof_armature[mid, d]
        gravcomp = T.body_scalar()
        for b in range(1, NB):
            gravcomp[b] = model.body_gravcomp[mid, b]
        bias = bias_forces(bm, bh, bJ, s_ang, s_lin, qd, model.gravity[mid % model.gravity.shape[0]], gravcomp)
        qfrc = T.dof_vec()
        for d in range(NV):
            qfrc[d] = (
                -bias[d]
                - model.dof_damping[mid, d] * qd[d]
                - model.dof_stiffness[mid, d] * (q[d] - model.dof_springref[mid, d])
            )
        qfrc_act, act_force, act_vel = actuation(mid, model, q, qd, ctrl)
        qfrc = qfrc + qfrc_act
        active = int(0)
        if model.limit_enabled[mid % model.limit_enabled.shape[0]] != 0:
            qfrc_limit, active = limit_forces(mid, model, M, q, qd, qfrc)
            qfrc = qfrc + qfrc_limit
        for d in range(NV):
            M[d, d] = M[d, d] + h * model.dof_damping[mid, d]
        L, D = factor(M)
        qacc = solve(L, D, qfrc)
        qd_new = qd + h * qacc
        q_new = q + h * qd_new
        return q_new, qd_new, act_force, act_vel, active

    return SimpleNamespace(
        body_inertias=body_inertias,
        motion_subspace=motion_subspace,
        mass_matrix=mass_matrix,
        bias_forces=bias_forces,
        factor=factor,
        solve=solve,
        actuation=actuation,
        limit_forces=limit_forces,
        step=step,
    )


def make_simulate_kernel(topology: Topology, module: str):
    """The open-loop simulation kernel of one topology, registered in Warp module `module`."""
    T = local_types(topology)
    F = dynamics_funcs(topology)
    NV, NU = topology.dof_count, topology.actuator_count

    @wp.kernel(module=module)
    def _simulate(
        # Model:
        model: TreeArrays,
        # Data in:
        qpos_in: wp.array2d(dtype=float),
        qvel_in: wp.array2d(dtype=float),
        ctrl_in: wp.array3d(dtype=float),
        # Data out:
        qpos_out: wp.array3d(dtype=float),
        qvel_out: wp.array3d(dtype=float),
        act_force_out: wp.array3d(dtype=float),
        limit_count_out: wp.array2d(dtype=wp.int32),
    ):
        worldid = wp.tid()
        mid = worldid % model.body_pos.shape[0]
        q = T.dof_vec()
        qd = T.dof_vec()
        for d in range(NV):
            q[d] = qpos_in[worldid, d]
            qd[d] = qvel_in[worldid, d]
            qpos_out[worldid, 0, d] = q[d]
            qvel_out[worldid, 0, d] = qd[d]
        for s in range(ctrl_in.shape[1]):
            ctrl = T.act_vec()
            for u in range(NU):
                ctrl[u] = ctrl_in[worldid, s, u]
            q, qd, force, vel, active = F.step(mid, model, q, qd, ctrl)
            for d in range(NV):
                qpos_out[worldid, s + 1, d] = q[d]
                qvel_out[worldid, s + 1, d] = qd[d]
            for u in range(NU):
                act_force_out[worldid, s, u] = force[u]
            limit_count_out[worldid, s] = active

    return _simulate


@functools.cache
def simulate_kernel(topology: Topology):
    """The open-loop simulation kernel of a topology, in its own module."""
    module = module_name(topology, "dynamics")
    wp.set_module_options(MODULE_OPTIONS, module)
    return make_simulate_kernel(topology, module)


def simulate(
    model: TreeModel,
    qpos: wp.array,
    qvel: wp.array,
    ctrl: wp.array,
    *,
    device: str | None = None,
) -> SimpleNamespace:
    """Open-loop simulation of W worlds for S physics steps in one launch.

    qpos, qvel: initial joint positions [rad or m] and velocities, (W, NV) float32.
    ctrl: actuator commands per physics step, (W, S, NU) float32.
    Returns a namespace of Warp arrays: qpos, qvel (W, S + 1, NV) (entry 0 is the initial
    state), act_force (W, S, NU) [N m or N] at the start of each step, limit_count (W, S)
    int32 active joint-limit rows per step.
    """
    topo = model.topology
    device = device or model.device
    W, NV, NU = qpos.shape[0], topo.dof_count, topo.actuator_count
    if qpos.shape != (W, NV) or qvel.shape != (W, NV):
        raise TTError(f"qpos {qpos.shape} and qvel {qvel.shape} must both be (W, {NV})")
    if ctrl.ndim != 3 or ctrl.shape[0] != W or ctrl.shape[2] != NU:
        raise TTError(f"ctrl has shape {ctrl.shape}; expected (W={W}, S, {NU})")
    S = ctrl.shape[1]
    out = SimpleNamespace(
        qpos=wp.array(np.full((W, S + 1, NV), np.inf, np.float32), dtype=float, device=device),
        qvel=wp.array(np.full((W, S + 1, NV), np.inf, np.float32), dtype=float, device=device),
        act_force=wp.array(np.full((W, S, max(NU, 1)), np.inf, np.float32), dtype=float, device=device),
        limit_count=wp.zeros((W, S), dtype=wp.int32, device=device),
    )
    wp.launch(
        simulate_kernel(topo),
        dim=W,
        inputs=[model.arrays, qpos, qvel, ctrl],
        outputs=[out.qpos, out.qvel, out.act_force, out.limit_count],
        device=device,
    )
    return out
