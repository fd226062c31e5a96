"""Compare a MuJoCo model with its tokenize -> detokenize round trip.

Bodies are not compared one by one: the detokenizer writes one body per rigid group (a
body and the static bodies welded to it), so the comparison is per *weld group*
(``body_weldid``), in world coordinates, which does not depend on where body frames sit:
group mass, centre of mass and inertia; joint anchors and axes; geom and end-effector
poses; loop-closure anchors. Forward kinematics is compared at random configurations.
Joint order is kept by the round trip, so qpos vectors transfer (free joints after moving
their body frame to the free link; see `RobotIndex.free_offset_*`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from tt.kernels.rotations import mat_to_quat, quat_to_mat
from tt.tokens.frames import compose
from tt.tokens.tokenize import RobotIndex

#: Inertia scale [kg m^2] below which inertia differences count absolutely (see the report).
INERTIA_FLOOR = 1e-4


@dataclass
class RoundTripReport:
    """Largest differences between a model and its round trip.

    structure: mismatches in the kinematic tree and element counts (empty when equal)
    fk_pos: joint anchors (not free joints'), geom centres, end-effector sites and
        loop-closure anchors [m]
    com_pos: centres of mass of the weld groups [m]
    fk_rot: joint axes, geom and end-effector orientations (matrix entries)
    mass_rel: group masses, relative; inertia_rel: group inertias (world, about the com),
        relative to the group's largest principal moment
    joint_rel: joint ranges, armature, damping, friction loss, stiffness, spring and
        position references (relative, 1e-6 absolute floor)
    actuator_rel: gains, gear, control and force ranges (relative, 1e-6 absolute floor)
    """

    structure: list[str] = field(default_factory=list)
    fk_pos: float = 0.0
    com_pos: float = 0.0
    fk_rot: float = 0.0
    mass_rel: float = 0.0
    inertia_rel: float = 0.0
    joint_rel: float = 0.0
    actuator_rel: float = 0.0

    def within(
        self,
        pos: float = 1e-5,
        rot: float = 1e-5,
        mass: float = 1e-5,
        inertia: float = 1e-5,
        joint: float = 1e-5,
        actuator: float = 1e-5,
    ) -> bool:
        return (
            not self.structure
            and self.fk_pos <= pos
            and self.com_pos <= pos
            and self.fk_rot <= rot
            and self.mass_rel <= mass
            and self.inertia_rel <= inertia
            and self.joint_rel <= joint
            and self.actuator_rel <= actuator
        )


def _rel(a, b, floor: float = 1e-6) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.size == 0:
        return 0.0
    return float(np.max(np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), floor)))


def _parent_joints(m: mujoco.MjModel) -> np.ndarray:
    """For each joint, the joint before it on the path to the world (-1 for none)."""
    out = np.full(m.njnt, -1)
    last = np.full(m.nbody, -1)
    for b in range(1, m.nbody):
        prev = last[m.body_parentid[b]]
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            out[j] = prev
            prev = j
        last[b] = prev
    return out


def _groups(m: mujoco.MjModel, d: mujoco.MjData) -> dict[int, tuple[float, np.ndarray, np.ndarray]]:
    """Weld groups keyed by their first joint (-1: welded to the world): mass, world com,
    world inertia about the com."""
    key_of_root = {}
    for b in range(m.nbody):
        w = m.body_weldid[b]
        if w not in key_of_root:
            key_of_root[w] = int(m.body_jntadr[w]) if m.body_jntnum[w] > 0 else -1
    out = {}
    for w, key in key_of_root.items():
        bodies = [b for b in range(m.nbody) if m.body_weldid[b] == w]
        mass = float(sum(m.body_mass[b] for b in bodies))
        if mass <= 0:
            out[key] = (0.0, np.zeros(3), np.zeros((3, 3)))
            continue
        com = sum(m.body_mass[b] * d.xipos[b] for b in bodies) / mass
        inertia = np.zeros((3, 3))
        for b in bodies:
            r = d.ximat[b].reshape(3, 3)
            rel = d.xipos[b] - com
            inertia += r @ np.diag(m.body_inertia[b]) @ r.T + m.body_mass[b] * (
                rel @ rel * np.eye(3) - np.outer(rel, rel)
            )
        out[key] = (mass, com, inertia)
    return out


def _random_qpos(m: mujoco.MjModel, rng: np.random.Generator) -> np.ndarray:
    q = m.qpos0.copy()
    for j in range(m.njnt):
        a = m.jnt_qposadr[j]
        t = m.jnt_type[j]
        if t == mujoco.mjtJoint.mjJNT_FREE:
            q[a : a + 3] = rng.uniform(-1, 1, 3)
            quat = rng.normal(size=4)
            q[a + 3 : a + 7] = quat / np.linalg.norm(quat)
        elif t == mujoco.mjtJoint.mjJNT_BALL:
            quat = rng.normal(size=4)
            q[a : a + 4] = quat / np.linalg.norm(quat)
        else:
            lo, hi = m.jnt_range[j] if m.jnt_limited[j] else (-np.pi, np.pi)
            q[a] = rng.uniform(lo, hi)
    return q


def _transfer_qpos(q: np.ndarray, m: mujoco.MjModel, index: RobotIndex) -> np.ndarray:
    """qpos of the original -> qpos of the round trip (free bodies move to their free link)."""
    q = q.copy()
    for f, adr in enumerate(index.free_qposadr):
        r, p = compose(
            quat_to_mat(q[adr + 3 : adr + 7]), q[adr : adr + 3], index.free_offset_rot[f], index.free_offset_pos[f]
        )
        q[adr : adr + 3] = p
        q[adr + 3 : adr + 7] = mat_to_quat(r)
    return q


def _anchors(m: mujoco.MjModel, d: mujoco.MjData, e: int) -> np.ndarray:
    if m.eq_objtype[e] == mujoco.mjtObj.mjOBJ_SITE:
        return np.stack([d.site_xpos[m.eq_obj1id[e]], d.site_xpos[m.eq_obj2id[e]]])
    out = []
    for k, b in enumerate((m.eq_obj1id[e], m.eq_obj2id[e])):
        out.append(d.xpos[b] + d.xmat[b].reshape(3, 3) @ m.eq_data[e, 3 * k : 3 * k + 3])
    return np.stack(out)


def compare_models(
    original: mujoco.MjModel, rebuilt: mujoco.MjModel, index: RobotIndex, samples: int = 4, seed: int = 0
) -> RoundTripReport:
    """Differences between `original` and its round trip `rebuilt` (`index` from tokenizing
    `original`), at qpos0 and `samples` random configurations."""
    rep = RoundTripReport()
    a, b = original, rebuilt
    for what in ("njnt", "nq", "nv"):
        if getattr(a, what) != getattr(b, what):
            rep.structure.append(f"{what}: {getattr(a, what)} != {getattr(b, what)}")
    acts = index.actuator_mj
    if len(acts) != b.nu:
        rep.structure.append(f"actuators: {len(acts)} tokenized, {b.nu} rebuilt")
    if rep.structure:
        return rep
    if not np.array_equal(a.jnt_type, b.jnt_type):
        rep.structure.append(f"joint types {a.jnt_type.tolist()} != {b.jnt_type.tolist()}")
    if not np.array_equal(_parent_joints(a), _parent_joints(b)):
        rep.structure.append(f"joint tree {_parent_joints(a).tolist()} != {_parent_joints(b).tolist()}")
    # Loop closures pair up by type, in order (tokens keep the order within a type only).
    kinds = (int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD))
    eq_pairs = []
    for k in kinds:
        ea = [e for e in range(a.neq) if int(a.eq_type[e]) == k]
        eb = [e for e in range(b.neq) if int(b.eq_type[e]) == k]
        if len(ea) != len(eb):
            rep.structure.append(f"loop closures of type {mujoco.mjtEq(k).name}: {len(ea)} != {len(eb)}")
        eq_pairs += list(zip(ea, eb))
    if not np.array_equal(a.actuator_trnid[acts, 0], b.actuator_trnid[:, 0]):
        rep.structure.append("actuator joints differ")
    if rep.structure:
        return rep

    # Joint parameters (free joints' qpos0 depend on the body frame: skipped).
    scalar = np.isin(a.jnt_type, (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE))
    ja, jb = a.jnt_qposadr[scalar], b.jnt_qposadr[scalar]
    da, db = a.jnt_dofadr, b.jnt_dofadr
    rep.joint_rel = max(
        _rel(a.jnt_limited, b.jnt_limited),
        _rel(a.jnt_range[a.jnt_limited.astype(bool)], b.jnt_range[b.jnt_limited.astype(bool)]),
        _rel(a.dof_armature[da], b.dof_armature[db]),
        _rel(a.dof_damping[da], b.dof_damping[db]),
        _rel(a.dof_frictionloss[da], b.dof_frictionloss[db]),
        _rel(a.jnt_stiffness, b.jnt_stiffness),
        _rel(a.qpos0[ja], b.qpos0[jb]),
        _rel(a.qpos_spring[ja], b.qpos_spring[jb]),
    )
    rep.actuator_rel = max(
        [0.0]
        if not len(acts)
        else [
            _rel(a.actuator_gainprm[acts, 0], b.actuator_gainprm[:, 0]),
            _rel(a.actuator_biasprm[acts, :3], b.actuator_biasprm[:, :3]),
            _rel(a.actuator_gear[acts, 0], b.actuator_gear[:, 0]),
            _rel(a.actuator_ctrllimited[acts], b.actuator_ctrllimited),
            _rel(a.actuator_forcelimited[acts], b.actuator_forcelimited),
            _rel(
                np.where(a.actuator_ctrllimited[acts, None], a.actuator_ctrlrange[acts], 0),
                np.where(b.actuator_ctrllimited[:, None], b.actuator_ctrlrange, 0),
            ),
            _rel(
                np.where(a.actuator_forcelimited[acts, None], a.actuator_forcerange[acts], 0),
                np.where(b.actuator_forcelimited[:, None], b.actuator_forcerange, 0),
            ),
        ]
    )

    # Forward kinematics, masses and inertias.
    link_geoms = [
        (lid, int(g))
        for lid, g in enumerate(index.link_geom)
        if g >= 0 and a.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH
    ]
    gid_b = {lid: mujoco.mj_name2id(b, mujoco.mjtObj.mjOBJ_GEOM, f"g{lid}") for lid, _ in link_geoms}
    ee = [mujoco.mj_id2name(a, mujoco.mjtObj.mjOBJ_SITE, int(index.link_site[lid])) for lid in index.track_link]
    ee_b = [mujoco.mj_name2id(b, mujoco.mjtObj.mjOBJ_SITE, f"ee_{k}") for k in range(len(ee))]
    if any(g < 0 for g in gid_b.values()) or any(s < 0 for s in ee_b):
        rep.structure.append("geoms or end-effector sites missing in the round trip")
        return rep
    ee_a = [mujoco.mj_name2id(a, mujoco.mjtObj.mjOBJ_SITE, n) for n in ee]
    rng = np.random.default_rng(seed)
    da_, db_ = mujoco.MjData(a), mujoco.MjData(b)
    for s in range(samples + 1):
        qa = a.qpos0.copy() if s == 0 else _random_qpos(a, rng)
        da_.qpos[:] = qa
        db_.qpos[:] = _transfer_qpos(qa, a, index)
        mujoco.mj_kinematics(a, da_)
        mujoco.mj_kinematics(b, db_)
        mujoco.mj_comPos(a, da_)
        mujoco.mj_comPos(b, db_)
        # A free joint's anchor is its body's origin, which the round trip moves to the link.
        hinge = a.jnt_type != mujoco.mjtJoint.mjJNT_FREE
        pos_err = [np.abs(da_.xanchor[hinge] - db_.xanchor[hinge]).max(initial=0)]
        rot_err = [np.abs(da_.xaxis[hinge] - db_.xaxis[hinge]).max(initial=0)]
        for lid, g in link_geoms:
            pos_err.append(np.abs(da_.geom_xpos[g] - db_.geom_xpos[gid_b[lid]]).max())
            rot_err.append(np.abs(da_.geom_xmat[g] - db_.geom_xmat[gid_b[lid]]).max())
        for sa, sb in zip(ee_a, ee_b):
            pos_err.append(np.abs(da_.site_xpos[sa] - db_.site_xpos[sb]).max())
            rot_err.append(np.abs(da_.site_xmat[sa] - db_.site_xmat[sb]).max())
        for ea, eb in eq_pairs:
            if int(a.eq_type[ea]) == int(mujoco.mjtEq.mjEQ_CONNECT):
                # The round trip orders a constraint's two sides by link ID.
                pa, pb = _anchors(a, da_, ea), _anchors(b, db_, eb)
                pos_err.append(min(np.abs(pa - pb).max(), np.abs(pa - pb[::-1]).max()))
        ga, gb = _groups(a, da_), _groups(b, db_)
        if set(ga) != set(gb):
            rep.structure.append(f"weld groups {sorted(ga)} != {sorted(gb)}")
            return rep
        for k in ga:
            (ma, ca, ia), (mb, cb, ib) = ga[k], gb[k]
            rep.mass_rel = max(rep.mass_rel, _rel(ma, mb, 1e-9))
            if ma > 0 and mb > 0:
                rep.com_pos = max(rep.com_pos, float(np.abs(ca - cb).max()))
                scale = max(np.linalg.eigvalsh(ia).max(), INERTIA_FLOOR)
                rep.inertia_rel = max(rep.inertia_rel, float(np.abs(ia - ib).max() / scale))
        rep.fk_pos = max(rep.fk_pos, float(max(pos_err)))
        rep.fk_rot = max(rep.fk_rot, float(max(rot_err)))
    return rep
