"""The quadruped's MuJoCo models as the arrays of tt's whole-body IK kernels.

`build_wbc_model` reads, from each floating-base model and a `WBCConfig`, what the batched
whole-body step (`tt.kernels.wbc`) needs: the kinematic tree in MuJoCo's layout, the
end-effector and foot sites, the stance points the feet hold and the stance centre the
centre of mass is held over, the per-DoF posture costs, the ``home`` posture, the active
``connect`` equalities and the task weights, padded to the largest model of the batch
(`tt.kernels.wbc.WBCModel`). The controller these numbers specify is `tt.sim.wbc`'s.
"""

from __future__ import annotations

from typing import Sequence

import mujoco
import numpy as np
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.wbc import JOINT_FREE, JOINT_HINGE, JOINT_SLIDE, WBCModel
from tt.sim.controller import ee_site_names, model_name
from tt.sim.wbc import WBCConfig, foot_site_names, free_joint, home_qpos, posture_costs, stance_points


def _check_model(m: mujoco.MjModel, index: int) -> None:
    """Raise ValueError naming the first feature of `m` that the kernels lack."""
    where = f"model {index} ({model_name(m)!r})"
    joint = free_joint(m)
    if joint is None:
        raise TTError(f"{where} has no free joint; the whole-body kernels drive floating bases (arms: tt.kernels.ik)")
    if int(m.jnt_bodyid[joint]) != 1 or int(m.body_jntadr[1]) != joint:
        raise TTError(
            f"{where}: the free joint must be the first joint of body 1 (the robot's root), as the oracle needs"
        )
    kinds = set(int(t) for t in m.jnt_type)
    if not kinds <= {JOINT_FREE, JOINT_HINGE, JOINT_SLIDE}:
        raise TTError(f"{where}: jnt_type {sorted(kinds)}; the whole-body kernels support free, hinge and slide joints")
    for e in range(m.neq):
        if int(m.eq_type[e]) != int(mujoco.mjtEq.mjEQ_CONNECT):
            raise TTError(
                f"{where}: equality {e} has eq_type {mujoco.mjtEq(m.eq_type[e]).name}; only connect "
                "equalities are supported"
            )
        if int(m.eq_objtype[e]) not in (int(mujoco.mjtObj.mjOBJ_SITE), int(mujoco.mjtObj.mjOBJ_BODY)):
            raise TTError(f"{where}: equality {e} connects objects of type {m.eq_objtype[e]}; expected sites or bodies")


def _connects(m: mujoco.MjModel) -> list[tuple[int, np.ndarray, int, np.ndarray]]:
    """(body1, point in body1 [m], body2, point in body2 [m]) of each equality row block that
    ``mj_makeConstraint`` instantiates (active connects; none when equalities are disabled)."""
    if m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EQUALITY:
        return []
    out = []
    for e in range(m.neq):
        if not m.eq_active0[e]:
            continue
        a, b = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
        if int(m.eq_objtype[e]) == int(mujoco.mjtObj.mjOBJ_SITE):
            out.append((int(m.site_bodyid[a]), m.site_pos[a].copy(), int(m.site_bodyid[b]), m.site_pos[b].copy()))
        else:
            out.append((a, m.eq_data[e, 0:3].copy(), b, m.eq_data[e, 3:6].copy()))
    return out


def _subtree(m: mujoco.MjModel, root: int) -> np.ndarray:
    """Bool mask of the bodies in `root`'s subtree, (nbody,)."""
    inside = np.zeros(m.nbody, bool)
    inside[root] = True
    for b in range(root + 1, m.nbody):
        inside[b] = inside[m.body_parentid[b]]
    return inside


def _xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    return np.concatenate([quat_wxyz[..., 1:], quat_wxyz[..., :1]], axis=-1)


def build_wbc_model(
    models: Sequence[mujoco.MjModel],
    config: WBCConfig = WBCConfig(),
    *,
    device: str | None = None,
    stance: Sequence[np.ndarray] | None = None,
) -> WBCModel:
    """A `WBCModel` with one entry per MuJoCo model (any mix of structures; the same object
    may repeat and is read once).

    models: floating-base legged models with the oracle's layout (a free joint on body 1,
        foot sites ``foot_*``, end-effector sites ``ee_0``, ..., a ``home`` keyframe).
    config: the whole-body controller's settings (`WBCConfig`): its weights, and the
        per-DoF posture costs it implies.
    stance: each model's stance points, (F, 3) [m] in `tt.sim.wbc.foot_site_names` order,
        where the caller has them (the foot sites' positions in the ``home`` pose, which
        `tt.sim.wbc.stance_points` computes with an MjData of its own); None computes them.
    Raises ValueError naming the first model the kernels cannot drive.
    """
    from tt.kernels.device import resolve_device

    device = resolve_device(device)
    if len(models) == 0:
        raise TTError("models is empty; build_wbc_model needs at least one MuJoCo model")
    distinct: dict[int, dict] = {}
    for i, m in enumerate(models):
        if id(m) in distinct:
            continue
        _check_model(m, i)
        sites = ee_site_names(m)
        feet = foot_site_names(m)
        if stance is not None and np.shape(stance[i]) != (len(feet), 3):
            raise TTError(
                f"stance[{i}] has shape {np.shape(stance[i])}; model {i} has {len(feet)} feet: ({len(feet)}, 3)"
            )
        distinct[id(m)] = dict(
            sites=sites, feet=feet, connects=_connects(m),
            stance=stance_points(m, feet) if stance is None else np.asarray(stance[i], dtype=np.float64),
            posture=posture_costs(m, config), home=home_qpos(m),
        )  # fmt: skip
    ne = {len(v["sites"]) for v in distinct.values()}
    if len(ne) > 1:
        raise TTError(f"the models have different end-effector counts {sorted(ne)}; one batch tracks one motion layout")
    NE = ne.pop()
    NB = max(m.nbody for m in models)
    NJ = max(m.njnt for m in models)
    NQ = max(m.nq for m in models)
    NV = max(m.nv for m in models)
    NF = max(len(v["feet"]) for v in distinct.values())
    NC = max(len(v["connects"]) for v in distinct.values())
    N = len(models)

    def f(*shape):
        return np.zeros(shape)

    def i32(*shape):
        return np.zeros(shape, np.int32)

    a = dict(
        body_count=i32(N), jnt_count=i32(N), dof_count=i32(N),
        body_parent=i32(N, NB), body_pos=f(N, NB, 3), body_quat=np.tile([0.0, 0.0, 0.0, 1.0], (N, NB, 1)),
        body_ipos=f(N, NB, 3), body_com_weight=f(N, NB), body_jntadr=i32(N, NB), body_jntnum=i32(N, NB),
        body_lastdof=np.full((N, NB), -1, np.int32),
        jnt_type=i32(N, NJ), jnt_qposadr=i32(N, NJ), jnt_dofadr=i32(N, NJ), jnt_axis=f(N, NJ, 3),
        jnt_pos=f(N, NJ, 3), jnt_limited=i32(N, NJ), jnt_range=f(N, NJ, 2), qpos0=f(N, NQ),
        dof_parent=np.full((N, NV), -1, np.int32), dof_rot=i32(N, NV), dof_qposadr=np.full((N, NV), -1, np.int32),
        dof_posture_cost=f(N, NV), q_home=f(N, NQ),
        ee_body=i32(N, NE), ee_pos=f(N, NE, 3), ee_quat=np.tile([0.0, 0.0, 0.0, 1.0], (N, NE, 1)),
        foot_body=i32(N, NF), foot_active=i32(N, NF), foot_pos=f(N, NF, 3), foot_target=f(N, NF, 3),
        com_target=f(N, 3),
        eq_body1=i32(N, max(NC, 1)), eq_body2=i32(N, max(NC, 1)), eq_active=i32(N, max(NC, 1)),
        eq_pos1=f(N, max(NC, 1), 3), eq_pos2=f(N, max(NC, 1), 3),
    )  # fmt: skip
    for i, m in enumerate(models):
        v = distinct[id(m)]
        nb, nj, nv, nq = m.nbody, m.njnt, m.nv, m.nq
        a["body_count"][i], a["jnt_count"][i], a["dof_count"][i] = nb, nj, nv
        a["body_parent"][i, :nb] = m.body_parentid
        a["body_pos"][i, :nb] = m.body_pos
        a["body_quat"][i, :nb] = _xyzw(m.body_quat)
        a["body_ipos"][i, :nb] = m.body_ipos
        inside = _subtree(m, 1)
        a["body_com_weight"][i, :nb] = np.where(inside, m.body_mass, 0.0) / m.body_subtreemass[1]
        a["body_jntadr"][i, :nb] = m.body_jntadr
        a["body_jntnum"][i, :nb] = m.body_jntnum
        for b in range(nb):
            # MuJoCo's mj_jac: skip bodies without DoFs, start at the last DoF of the first with some.
            c = b
            while c > 0 and m.body_dofnum[c] == 0:
                c = int(m.body_parentid[c])
            if c > 0:
                a["body_lastdof"][i, b] = int(m.body_dofadr[c] + m.body_dofnum[c] - 1)
        a["jnt_type"][i, :nj] = m.jnt_type
        a["jnt_qposadr"][i, :nj] = m.jnt_qposadr
        a["jnt_dofadr"][i, :nj] = m.jnt_dofadr
        a["jnt_axis"][i, :nj] = m.jnt_axis
        a["jnt_pos"][i, :nj] = m.jnt_pos
        hinge_or_slide = np.isin(m.jnt_type, (JOINT_HINGE, JOINT_SLIDE))
        a["jnt_limited"][i, :nj] = m.jnt_limited.astype(bool) & hinge_or_slide
        a["jnt_range"][i, :nj] = m.jnt_range
        a["qpos0"][i, :nq] = m.qpos0
        a["dof_parent"][i, :nv] = m.dof_parentid
        for j in range(nj):
            d0 = int(m.jnt_dofadr[j])
            if int(m.jnt_type[j]) == JOINT_FREE:
                a["dof_rot"][i, d0 + 3 : d0 + 6] = 1
            else:
                a["dof_rot"][i, d0] = int(m.jnt_type[j]) == JOINT_HINGE
                a["dof_qposadr"][i, d0] = int(m.jnt_qposadr[j])
        a["dof_posture_cost"][i, :nv] = v["posture"]
        a["q_home"][i, :nq] = v["home"]
        for e, s in enumerate(v["sites"]):
            sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s)
            a["ee_body"][i, e] = m.site_bodyid[sid]
            a["ee_pos"][i, e] = m.site_pos[sid]
            a["ee_quat"][i, e] = _xyzw(m.site_quat[sid])
        for k, s in enumerate(v["feet"]):
            sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s)
            a["foot_body"][i, k] = m.site_bodyid[sid]
            a["foot_active"][i, k] = 1
            a["foot_pos"][i, k] = m.site_pos[sid]
            a["foot_target"][i, k] = v["stance"][k]
        centre = v["stance"].mean(axis=0)
        a["com_target"][i] = (centre[0], centre[1], 0.0)
        for k, (b1, p1, b2, p2) in enumerate(v["connects"]):
            a["eq_body1"][i, k], a["eq_pos1"][i, k] = b1, p1
            a["eq_body2"][i, k], a["eq_pos2"][i, k] = b2, p2
            a["eq_active"][i, k] = 1

    vec_types = {3: wp.vec3d, 2: wp.vec2d}
    quats = {"body_quat", "ee_quat"}
    arrays = {}
    for name, x in a.items():
        if x.dtype == np.int32:
            arrays[name] = wp.array(x, dtype=wp.int32, device=device)
        elif name in quats:
            arrays[name] = wp.array(x, dtype=wp.quatd, device=device)
        elif name in ("qpos0", "q_home", "body_com_weight", "dof_posture_cost"):
            arrays[name] = wp.array(x, dtype=wp.float64, device=device)
        else:
            arrays[name] = wp.array(x, dtype=vec_types[x.shape[-1]], device=device)
    return WBCModel(
        weights=config.wbc_weights(), nbody=NB, njnt=NJ, nq=NQ, nv=NV, ee_count=NE, foot_count=NF,
        eq_count=NC, device=device, **arrays,
    )  # fmt: skip


__all__ = ["build_wbc_model"]
