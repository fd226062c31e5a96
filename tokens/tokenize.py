"""Tokenizer: `mujoco.MjModel` (anything MuJoCo loads: MJCF, URDF) -> embodiment RoboTokens.

How a MuJoCo model becomes links and joints:

* Every primitive geom is a link whose frame is the geom's frame. A body's first geom is
  its *primary* link; the body's other geoms and its end-effector sites (``ee_0``,
  ``ee_1``, ...) become links fixed to it. A body without geoms is one geometry-less link
  at the body frame that carries the body's inertial.
* Each hinge / slide / ball joint becomes a joint between the primary link of the parent
  body (or the ground, link -1) and the body's primary link. A body with k > 1 joints gets
  k - 1 massless geometry-less links at its frame, chained by its joints in order, which is
  exactly MuJoCo's multi-joint body. A body without joints is fixed to its parent.
* A free joint makes the body's primary link a free link (no joint token).
* ``connect`` equalities become ball joints and ``weld`` equalities fixed joints between
  the two bodies' primary links; they close kinematic loops (IDs after the tree's joints).
* Masses: a body's lumped inertial is split over its links (`tt.tokens.inertia`), keeping
  the body's mass, centre of mass and inertia.
* Meshes become boxes of their bounding box in the geom frame (with a warning); planes and
  height fields (scene geometry), tendons, sensors, lights and cameras are dropped.

Link IDs follow MuJoCo's body order, so a joint's child always has the higher link ID.
Dynamic joint IDs follow MuJoCo's joint order (hinges and slides only), actuator IDs
MuJoCo's actuator order, track IDs the ``ee_k`` index.

Robots that share a topology share a `_Plan` (index arrays computed once); their numbers
are gathered from all models at once and every step below is a vectorised numpy op.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Sequence

import mujoco
import numpy as np

from tt.tokens.batch import TokenBatch
from tt.tokens.encodings import encode_attribute
from tt.tokens.frames import compose, invert, quat_to_mat, z_to_axis
from tt.tokens.inertia import SIZE_DIMS, fit_masses, principal_axes, split_lumped_inertia
from tt.tokens.schema import (
    ACTUATOR_TYPES,
    CONTACT_CONDIMS,
    GEOM_TYPES,
    MAX_DYNA_JOINTS,
    MAX_FREE_LINKS,
    MAX_LINKS,
    MAX_TRACK_LINKS,
    SCHEMA,
)

_G = mujoco.mjtGeom
_J = mujoco.mjtJoint
#: MuJoCo geom type -> link geometry code (meshes become boxes).
_GEOM_CODE = {
    int(_G.mjGEOM_SPHERE): GEOM_TYPES.index("sphere"),
    int(_G.mjGEOM_CAPSULE): GEOM_TYPES.index("capsule"),
    int(_G.mjGEOM_ELLIPSOID): GEOM_TYPES.index("ellipsoid"),
    int(_G.mjGEOM_CYLINDER): GEOM_TYPES.index("cylinder"),
    int(_G.mjGEOM_BOX): GEOM_TYPES.index("box"),
    int(_G.mjGEOM_MESH): GEOM_TYPES.index("box"),
}
_SCENE_GEOMS = {int(_G.mjGEOM_PLANE), int(_G.mjGEOM_HFIELD)}


class TokenizeError(ValueError):
    """A model RoboTokens cannot represent; the message names the element and the limit."""


class TokenizeWarning(UserWarning):
    """Something of the model was approximated or dropped (meshes, tendons, equalities)."""


@dataclass(frozen=True)
class TokenizeConfig:
    """Options of the tokenizer.

    ee_sites: site names of the track links in track-ID order; None finds ``ee_0``,
        ``ee_1``, ... in the model.
    dtype: float type of the token values.
    """

    ee_sites: tuple[str, ...] | None = None
    dtype: type = np.float32


# ------------------------------------------------------------------------------ the plan
@dataclass
class _Plan:
    """Everything about a robot that depends only on its topology: which MuJoCo element each
    link, joint and actuator comes from, and index arrays into the gathered model arrays."""

    # links
    link_kind: np.ndarray  # (L,) 0 geom, 1 mesh geom, 2 body (no geom), 3 intermediate, 4 site
    link_body: np.ndarray  # (L,) MuJoCo body of the link
    link_geom: np.ndarray  # (L,) MuJoCo geom or -1
    link_site: np.ndarray  # (L,) MuJoCo site or -1
    link_code: np.ndarray  # (L,) geometry code
    link_pose_row: np.ndarray  # (L,) row of the link's pose in its body frame, in the pose table
    link_free: np.ndarray  # (L,) free link ID or -1
    link_track: np.ndarray  # (L,) track link ID or -1
    primary: np.ndarray  # (nbody,) primary link of each body (-1 for the world)
    # mass split: bodies grouped by their number of geom links
    split_groups: list  # [(bodies (B,), links (B, k))]
    body_links: list  # links of a geometry-less body holding the inertial: [(body, link)]
    # edges, per token type: arrays (E,)
    edges: dict
    # MuJoCo element per token ID
    dyna_jnt: np.ndarray  # (D,) MuJoCo joint of each dynamic joint ID
    ball_jnt: np.ndarray  # (Bt,) MuJoCo joint of each tree ball joint ID
    free_jnt: np.ndarray  # (F,) MuJoCo free joint of each free link ID
    free_link: np.ndarray  # (F,) link of each free link ID
    track_site: np.ndarray  # (K,) MuJoCo site of each track link ID
    track_link: np.ndarray  # (K,) link of each track link ID
    act_mj: np.ndarray  # (A,) MuJoCo actuator of each actuator ID
    act_joint: np.ndarray  # (A,) dynamic joint ID each actuator drives
    eq_rows: list  # [(eq id, body1, body2, kind, site1, site2)] loop closures in token order
    n_pose_rows: int
    notes: tuple[str, ...]


#: Pose table rows: 0 identity, then bodies, geoms (+ mesh box centre), sites, joint frames,
#: then two rows per loop closure. Offsets per model are computed in `_pose_offsets`.
def _pose_offsets(m: mujoco.MjModel) -> dict[str, int]:
    off = {"identity": 0, "body": 1}
    off["geom"] = off["body"] + m.nbody
    off["site"] = off["geom"] + m.ngeom
    off["joint"] = off["site"] + m.nsite
    off["eq"] = off["joint"] + m.njnt
    off["end"] = off["eq"] + 2 * m.neq
    return off


def _name(m: mujoco.MjModel, obj: mujoco.mjtObj, i: int, kind: str) -> str:
    n = mujoco.mj_id2name(m, obj, i)
    return f"{kind} {n!r}" if n else f"{kind} #{i}"


def _ee_site_ids(m: mujoco.MjModel, names: tuple[str, ...] | None) -> list[int]:
    if names is None:
        out = []
        while True:
            sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"ee_{len(out)}")
            if sid < 0:
                return out
            out.append(sid)
    out = []
    for n in names:
        sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n)
        if sid < 0:
            raise TokenizeError(f"end-effector site {n!r} is not in the model")
        out.append(sid)
    return out


def _build_plan(m: mujoco.MjModel, ee_sites: list[int]) -> _Plan:
    off = _pose_offsets(m)
    notes: list[str] = []
    kind, lbody, lgeom, lsite, lcode, lrow, lfree, ltrack = ([] for _ in range(8))
    primary = np.full(m.nbody, -1)

    def new_link(k, body, geom=-1, site=-1, code=0, row=0, free=-1, track=-1) -> int:
        for lst, v in zip((kind, lbody, lgeom, lsite, lcode, lrow, lfree, ltrack), (k, body, geom, site, code, row, free, track)):
            lst.append(v)
        return len(kind) - 1

    # edges: parent link, child link, rows (jp_pre, jp, jc, lp, lc), MuJoCo joint
    edges = {"dyna_joint": [], "ball_joint": [], "fixed_joint": []}
    dyna_jnt, ball_jnt, free_jnt, free_link = [], [], [], []
    jnt_to_dyna = {}
    site_track = {s: k for k, s in enumerate(ee_sites)}
    track_link = [-1] * len(ee_sites)
    split_by_k: dict[int, list] = {}
    body_links = []
    mesh_warned = []

    def fixed_to(parent_link: int, link: int, body_row: int, lp_row: int) -> None:
        row = lrow[link]
        edges["fixed_joint"].append((parent_link, link, body_row, row, row, lp_row, row, -1))

    for b in range(m.nbody):
        geoms = range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b]) if m.body_geomnum[b] > 0 else []
        geoms = [g for g in geoms if int(m.geom_type[g]) not in _SCENE_GEOMS]
        for g in range(m.body_geomadr[b], m.body_geomadr[b] + max(m.body_geomnum[b], 0)):
            t = int(m.geom_type[g])
            if t not in _SCENE_GEOMS and t not in _GEOM_CODE:
                raise TokenizeError(f"{_name(m, mujoco.mjtObj.mjOBJ_GEOM, g, 'geom')} has type {mujoco.mjtGeom(t).name}; "
                                    "RoboTokens hold spheres, capsules, ellipsoids, cylinders, boxes and meshes (as boxes)")
        sites = [s for s in ee_sites if m.site_bodyid[s] == b]
        if b == 0:
            # World geoms that are not scene geometry are links welded to the ground.
            for g in geoms:
                link = new_link(1 if m.geom_type[g] == _G.mjGEOM_MESH else 0, 0, geom=g, code=_GEOM_CODE[int(m.geom_type[g])], row=off["geom"] + g)
                fixed_to(-1, link, 0, 0)
            for s in sites:
                link = new_link(4, 0, site=s, row=off["site"] + s, track=site_track[s])
                track_link[site_track[s]] = link
                fixed_to(-1, link, 0, 0)
            continue
        parent = int(m.body_parentid[b])
        parent_link = -1 if parent == 0 else int(primary[parent])
        jnts = list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])) if m.body_jntnum[b] > 0 else []
        free = [j for j in jnts if m.jnt_type[j] == _J.mjJNT_FREE]
        if free and len(jnts) > 1:
            raise TokenizeError(f"{_name(m, mujoco.mjtObj.mjOBJ_BODY, b, 'body')} has a free joint and other joints")
        moving = [] if free else jnts
        # Intermediate links sit at the body frame: their pose row is the identity.
        inter = [new_link(3, b, row=0) for _ in moving[:-1]]
        if geoms:
            g0 = geoms[0]
            p = new_link(1 if m.geom_type[g0] == _G.mjGEOM_MESH else 0, b, geom=g0, code=_GEOM_CODE[int(m.geom_type[g0])], row=off["geom"] + g0)
        else:
            p = new_link(2, b, row=0)
            body_links.append((b, p))
        primary[b] = p
        if free:
            free_jnt.append(free[0])
            free_link.append(p)
            lfree[p] = len(free_jnt) - 1
            if parent != 0:
                raise TokenizeError(f"{_name(m, mujoco.mjtObj.mjOBJ_BODY, b, 'body')} has a free joint but is not a child of the world")
        elif not moving:
            # lp: pose of the parent link in the parent body; jp_pre: this body in its parent.
            lp_row = 0 if parent == 0 else lrow[parent_link]
            edges["fixed_joint"].append((parent_link, p, off["body"] + b, lrow[p], lrow[p], lp_row, lrow[p], -1))
        else:
            chain = [parent_link, *inter, p]
            for i, j in enumerate(moving):
                lp_row = (0 if parent == 0 else lrow[parent_link]) if i == 0 else 0
                pre = off["body"] + b if i == 0 else 0
                jrow = off["joint"] + j
                lc_row = lrow[chain[i + 1]]
                e = (chain[i], chain[i + 1], pre, jrow, jrow, lp_row, lc_row, j)
                if m.jnt_type[j] == _J.mjJNT_BALL:
                    edges["ball_joint"].append(e)
                    ball_jnt.append(j)
                else:
                    jnt_to_dyna[j] = len(dyna_jnt)
                    edges["dyna_joint"].append(e)
                    dyna_jnt.append(j)
        mass_links = [p] if geoms else []
        for g in geoms[1:]:
            link = new_link(1 if m.geom_type[g] == _G.mjGEOM_MESH else 0, b, geom=g, code=_GEOM_CODE[int(m.geom_type[g])], row=off["geom"] + g)
            fixed_to(p, link, 0, lrow[p])
            mass_links.append(link)
        for g in geoms:
            if m.geom_type[g] == _G.mjGEOM_MESH:
                mesh_warned.append(_name(m, mujoco.mjtObj.mjOBJ_GEOM, g, "geom"))
        if mass_links:
            split_by_k.setdefault(len(mass_links), []).append((b, mass_links))
        for s in sites:
            link = new_link(4, b, site=s, row=off["site"] + s, track=site_track[s])
            track_link[site_track[s]] = link
            fixed_to(p, link, 0, lrow[p])

    if mesh_warned:
        notes.append(f"meshes approximated by boxes of their bounding boxes: {', '.join(mesh_warned)}")

    # Loop closures.
    eq_rows = []
    for e in range(m.neq):
        t = int(m.eq_type[e])
        ename = _name(m, mujoco.mjtObj.mjOBJ_EQUALITY, e, "equality")
        if t not in (int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD)):
            notes.append(f"{ename} of type {mujoco.mjtEq(t).name} dropped (RoboTokens hold connect and weld only)")
            continue
        objtype = int(m.eq_objtype[e])
        if objtype == int(mujoco.mjtObj.mjOBJ_SITE):
            s1, s2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
            b1, b2 = int(m.site_bodyid[s1]), int(m.site_bodyid[s2])
        else:
            s1 = s2 = -1
            b1, b2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
        l1 = -1 if b1 == 0 else int(primary[b1])
        l2 = -1 if b2 == 0 else int(primary[b2])
        rows = (off["eq"] + 2 * e, off["eq"] + 2 * e + 1)
        lp1 = 0 if b1 == 0 else lrow[l1]
        lp2 = 0 if b2 == 0 else lrow[l2]
        target = "ball_joint" if t == int(mujoco.mjtEq.mjEQ_CONNECT) else "fixed_joint"
        edges[target].append((l1, l2, 0, rows[0], rows[1], lp1, lp2, -1))
        eq_rows.append((e, b1, b2, t, s1, s2))

    # Actuators.
    act_mj, act_joint = [], []
    for a in range(m.nu):
        aname = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator")
        j = int(m.actuator_trnid[a, 0])
        if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT or j not in jnt_to_dyna:
            notes.append(f"{aname} dropped: RoboTokens hold actuators on hinge and slide joints only")
            continue
        if m.actuator_dyntype[a] != mujoco.mjtDyn.mjDYN_NONE:
            notes.append(f"{aname}: activation dynamics dropped")
        gt, bt = int(m.actuator_gaintype[a]), int(m.actuator_biastype[a])
        if gt != int(mujoco.mjtGain.mjGAIN_FIXED) or bt not in (int(mujoco.mjtBias.mjBIAS_AFFINE), int(mujoco.mjtBias.mjBIAS_NONE)):
            notes.append(f"{aname} dropped: only position, velocity and motor actuators are representable")
            continue
        act_mj.append(a)
        act_joint.append(jnt_to_dyna[j])
    if m.ntendon:
        notes.append(f"{m.ntendon} tendon(s) ignored")

    n_links = len(kind)
    for what, count, limit in (("links", n_links, MAX_LINKS), ("dynamic joints", len(dyna_jnt), MAX_DYNA_JOINTS),
                               ("free links", len(free_jnt), MAX_FREE_LINKS), ("track links", len(ee_sites), MAX_TRACK_LINKS)):
        if count > limit:
            raise TokenizeError(f"model {_model_name(m)!r} has {count} {what}; schema allows at most {limit}")

    def arr(rows):
        a = np.asarray(rows, dtype=np.int64).reshape(-1, 8)
        return {"parent": a[:, 0], "child": a[:, 1], "jp_pre": a[:, 2], "jp": a[:, 3], "jc": a[:, 4], "lp": a[:, 5], "lc": a[:, 6], "mj": a[:, 7]}

    split_groups = [(np.array([b for b, _ in v]), np.array([ls for _, ls in v])) for k, v in sorted(split_by_k.items())]
    return _Plan(
        link_kind=np.array(kind, dtype=np.int64), link_body=np.array(lbody, dtype=np.int64), link_geom=np.array(lgeom, dtype=np.int64),
        link_site=np.array(lsite, dtype=np.int64), link_code=np.array(lcode, dtype=np.int64), link_pose_row=np.array(lrow, dtype=np.int64),
        link_free=np.array(lfree, dtype=np.int64), link_track=np.array(ltrack, dtype=np.int64), primary=primary,
        split_groups=split_groups, body_links=body_links, edges={k: arr(v) for k, v in edges.items()},
        dyna_jnt=np.array(dyna_jnt, dtype=np.int64), ball_jnt=np.array(ball_jnt, dtype=np.int64), free_jnt=np.array(free_jnt, dtype=np.int64),
        free_link=np.array(free_link, dtype=np.int64), track_site=np.array(ee_sites, dtype=np.int64), track_link=np.array(track_link, dtype=np.int64),
        act_mj=np.array(act_mj, dtype=np.int64), act_joint=np.array(act_joint, dtype=np.int64), eq_rows=eq_rows,
        n_pose_rows=_pose_offsets(m)["end"], notes=tuple(notes),
    )


def _signature(m: mujoco.MjModel, ee_sites: list[int]) -> bytes:
    """Bytes that are equal for models with equal topology (the plan is then the same)."""
    parts = [
        np.array([m.nbody, m.njnt, m.ngeom, m.nsite, m.nu, m.neq, m.ntendon, *ee_sites], dtype=np.int32),
        m.body_parentid, m.body_jntnum, m.body_geomnum, m.jnt_type, m.geom_type,
    ]
    if m.nu:
        parts += [m.actuator_trntype, m.actuator_trnid.ravel(), m.actuator_gaintype, m.actuator_biastype, m.actuator_dyntype]
    if m.neq:
        parts += [m.eq_type, m.eq_objtype, m.eq_obj1id, m.eq_obj2id, m.site_bodyid]
    elif ee_sites:
        parts.append(m.site_bodyid[ee_sites])
    return np.concatenate(parts, dtype=np.int32).tobytes()


# ------------------------------------------------------------------------------ results
@dataclass
class RobotIndex:
    """Where each token of one tokenized robot comes from in its MuJoCo model; what the
    episode tokenizer and the round-trip checks need.

    dyna_qposadr / dyna_dofadr: qpos / qvel address of each dynamic joint ID, (D,)
    ball_qposadr / ball_dofadr: of each (tree) ball joint ID, (Bt,)
    free_qposadr: qpos address of each free link's free joint, (F,)
    free_offset_rot / free_offset_pos: pose of each free link in its body frame, (F, 3, 3), (F, 3)
    actuator_mj: MuJoCo actuator of each actuator ID, (A,)
    link_geom / link_body / link_site: MuJoCo geom / body / site of each link ID, (L,) (-1 none)
    track_link: link of each track link ID, (K,)
    notes: what was approximated or dropped
    """

    name: str
    dyna_qposadr: np.ndarray
    dyna_dofadr: np.ndarray
    ball_qposadr: np.ndarray
    ball_dofadr: np.ndarray
    free_qposadr: np.ndarray
    free_offset_rot: np.ndarray
    free_offset_pos: np.ndarray
    actuator_mj: np.ndarray
    link_geom: np.ndarray
    link_body: np.ndarray
    link_site: np.ndarray
    track_link: np.ndarray
    dyna_jnt: np.ndarray
    ball_jnt: np.ndarray
    free_jnt: np.ndarray
    notes: tuple[str, ...] = ()
    topology: int = 0

    @property
    def counts(self) -> dict[str, int]:
        return {"dyna_joint": len(self.dyna_qposadr), "ball_joint": len(self.ball_qposadr), "free_link": len(self.free_qposadr),
                "track_link": len(self.track_link), "actuator": len(self.actuator_mj)}


@dataclass
class Embodiments:
    """Embodiment tokens of N robots and, per robot, where they come from."""

    tokens: TokenBatch
    index: list[RobotIndex] = field(default_factory=list)


# ------------------------------------------------------------------------------ tokenize
class Tokenizer:
    """A tokenizer that keeps the plans of the topologies it has seen.

    Data generation tokenizes batch after batch of one design space; keeping one
    `Tokenizer` skips re-deriving a topology's plan and warns about approximations once per
    topology, not once per batch.
    """

    def __init__(self, config: TokenizeConfig = TokenizeConfig()):
        self.config = config
        self._plans: dict[bytes, _Plan] = {}

    def __call__(self, models: Sequence[mujoco.MjModel]) -> Embodiments:
        """Embodiment tokens (link, dyna_joint, ball_joint, fixed_joint, actuator) of N models.

        Models are grouped by topology and each group is tokenized with vectorised numpy.
        Raises `TokenizeError` for a model RoboTokens cannot hold; warns (`TokenizeWarning`)
        once per topology about approximations (meshes, dropped tendons / equalities /
        actuators).
        """
        models = list(models)
        if not models:
            raise ValueError("tokenize needs at least one model")
        groups: dict[bytes, list[int]] = {}
        for i, m in enumerate(models):
            if not isinstance(m, mujoco.MjModel):
                raise TypeError(f"models[{i}] is a {type(m).__name__}, expected mujoco.MjModel")
            sites = _ee_site_ids(m, self.config.ee_sites)
            key = _signature(m, sites)
            if key not in self._plans:
                self._plans[key] = _build_plan(m, sites)
                for note in self._plans[key].notes:
                    warnings.warn(f"tokenize: {note}", TokenizeWarning, stacklevel=2)
            groups.setdefault(key, []).append(i)
        parts = []
        index: list[RobotIndex | None] = [None] * len(models)
        for t, (key, members) in enumerate(groups.items()):
            tokens, idx = _tokenize_group(self._plans[key], [models[i] for i in members], self.config, topology=t)
            parts.append((members, tokens))
            for i, r in zip(members, idx):
                index[i] = r
        # Scatter the groups back into input order, padded to the longest robot.
        batch = TokenBatch.concatenate([p for _, p in parts])
        order = np.concatenate([np.asarray(mem) for mem, _ in parts])
        inverse = np.empty_like(order)
        inverse[order] = np.arange(len(order))
        return Embodiments(batch.select(inverse), index)


def tokenize_models(models: Sequence[mujoco.MjModel], config: TokenizeConfig = TokenizeConfig()) -> Embodiments:
    """Embodiment tokens of N models (a fresh `Tokenizer`; keep one to tokenize many batches)."""
    return Tokenizer(config)(models)


def tokenize_model(model: mujoco.MjModel, config: TokenizeConfig = TokenizeConfig()) -> Embodiments:
    """`tokenize_models` of one model."""
    return tokenize_models([model], config)


def _stack(models, name: str) -> np.ndarray:
    return np.array([getattr(m, name) for m in models])


def _tokenize_group(plan: _Plan, models: list[mujoco.MjModel], config: TokenizeConfig, topology: int):
    m0 = models[0]
    n = len(models)
    off = _pose_offsets(m0)
    # ---------------------------------------------------------------- pose table (n, P)
    rot = np.empty((n, plan.n_pose_rows, 3, 3))
    pos = np.zeros((n, plan.n_pose_rows, 3))
    rot[:, 0] = np.eye(3)
    rot[:, off["body"]:off["geom"]] = quat_to_mat(_stack(models, "body_quat"))
    pos[:, off["body"]:off["geom"]] = _stack(models, "body_pos")
    if m0.ngeom:
        geom_rot = quat_to_mat(_stack(models, "geom_quat"))
        geom_pos = _stack(models, "geom_pos")
        mesh = m0.geom_type == _G.mjGEOM_MESH
        geom_size = _stack(models, "geom_size").copy()
        if np.any(mesh):
            # A mesh's box: the bounding box in the geom frame (MuJoCo centres meshes on
            # their inertial frame, so the box centre is offset from the geom origin).
            aabb = _stack(models, "geom_aabb")
            geom_pos = geom_pos.copy()
            geom_pos[:, mesh] += (geom_rot[:, mesh] @ aabb[:, mesh, :3, None])[..., 0]
            geom_size[:, mesh] = aabb[:, mesh, 3:]
        rot[:, off["geom"]:off["site"]] = geom_rot
        pos[:, off["geom"]:off["site"]] = geom_pos
    if m0.nsite:
        rot[:, off["site"]:off["joint"]] = quat_to_mat(_stack(models, "site_quat"))
        pos[:, off["site"]:off["joint"]] = _stack(models, "site_pos")
    if m0.njnt:
        axis = _stack(models, "jnt_axis")
        jrot = z_to_axis(axis)
        # Ball and free joints have no axis: their frame keeps the body's orientation.
        no_axis = np.isin(m0.jnt_type, (_J.mjJNT_BALL, _J.mjJNT_FREE))
        jrot[:, no_axis] = np.eye(3)
        rot[:, off["joint"]:off["eq"]] = jrot
        pos[:, off["joint"]:off["eq"]] = _stack(models, "jnt_pos")
    if plan.eq_rows:
        _loop_closure_rows(plan, models, rot, pos, off["eq"])

    # ---------------------------------------------------------------- links (n, L)
    L = len(plan.link_kind)
    lrot = rot[:, plan.link_pose_row]
    lpos = pos[:, plan.link_pose_row]
    code = np.broadcast_to(plan.link_code, (n, L))
    size = np.zeros((n, L, 3))
    friction = np.zeros((n, L, 3))
    rgba = np.zeros((n, L, 4))
    contact = np.zeros((n, L), dtype=np.int64)
    has_geom = plan.link_geom >= 0
    g = plan.link_geom[has_geom]
    if len(g):
        size[:, has_geom] = geom_size[:, g]
        friction[:, has_geom] = _stack(models, "geom_friction")[:, g]
        rgba[:, has_geom] = _stack(models, "geom_rgba")[:, g]
        condim = _stack(models, "geom_condim")[:, g]
        collides = (_stack(models, "geom_contype")[:, g] != 0) | (_stack(models, "geom_conaffinity")[:, g] != 0)
        lut = np.zeros(7, dtype=np.int64)
        for c, d in enumerate(CONTACT_CONDIMS):
            lut[d] = c
        contact[:, has_geom] = np.where(collides, lut[condim], 0)
    # Unused size entries are zero so equal shapes have equal tokens.
    for c, k in SIZE_DIMS.items():
        sel = plan.link_code == c
        size[:, sel, k:] = 0.0

    mass = np.zeros((n, L))
    com = np.zeros((n, L, 3))  # in body frame
    tensor = np.zeros((n, L, 3, 3))  # about com, body frame
    body_mass = _stack(models, "body_mass")
    body_com = _stack(models, "body_ipos")
    body_irot = quat_to_mat(_stack(models, "body_iquat"))
    body_inertia = body_irot @ (_stack(models, "body_inertia")[..., :, None] * np.swapaxes(body_irot, -1, -2))
    inexact = []
    for bodies, links in plan.split_groups:
        k = links.shape[1]
        B = len(bodies)
        ms, cs, ts, exact = split_lumped_inertia(
            body_mass[:, bodies].reshape(-1), body_com[:, bodies].reshape(-1, 3), body_inertia[:, bodies].reshape(-1, 3, 3),
            np.broadcast_to(plan.link_code[links], (n, B, k)).reshape(-1, k), size[:, links].reshape(-1, k, 3),
            lpos[:, links].reshape(-1, k, 3), lrot[:, links].reshape(-1, k, 3, 3))
        if not exact.all():
            # Not a uniform density: fit per-primitive masses to the lumped inertias, then
            # split those bodies again.
            redo = np.flatnonzero(~exact)
            rr, jj = np.divmod(redo, B)
            args = (body_mass[rr, bodies[jj]], body_com[rr, bodies[jj]], body_inertia[rr, bodies[jj]],
                    plan.link_code[links[jj]], size[rr[:, None], links[jj]], lpos[rr[:, None], links[jj]], lrot[rr[:, None], links[jj]])
            fitted = fit_masses(*args)
            ms[redo], cs[redo], ts[redo], exact[redo] = split_lumped_inertia(*args, masses=fitted)
        mass[:, links] = ms.reshape(n, B, k)
        com[:, links] = cs.reshape(n, B, k, 3)
        tensor[:, links] = ts.reshape(n, B, k, 3, 3)
        if not exact.all():
            bad = np.argwhere(~exact.reshape(n, B))
            inexact.append((bad, bodies))
    for b, link in plan.body_links:
        mass[:, link] = body_mass[:, b]
        com[:, link] = body_com[:, b]
        tensor[:, link] = body_inertia[:, b]
    notes_extra = {}
    for bad, bodies in inexact:
        for r, j in bad:
            name = _name(models[r], mujoco.mjtObj.mjOBJ_BODY, int(bodies[j]), "body")
            notes_extra.setdefault(r, []).append(f"{name}: lumped inertia does not split exactly over its primitives; "
                                                 "links get solid inertias of best-fit masses")
    for r, msgs in notes_extra.items():
        for msg in msgs:
            warnings.warn(f"tokenize: {msg}", TokenizeWarning, stacklevel=3)
    # Inertial frame in the link frame, principal axes canonical.
    lrot_t = np.swapaxes(lrot, -1, -2)
    ipos = (lrot_t @ (com - lpos)[..., None])[..., 0]
    irot, moments = principal_axes(lrot_t @ tensor @ lrot)
    massless = mass <= 0
    ipos[massless] = 0.0
    irot[massless] = np.eye(3)
    moments[massless] = 0.0

    link_raw = {
        "geom_type": code, "size": size, "mass": mass[..., None], "ipos": ipos, "irot": irot, "inertia": moments,
        "friction": friction, "contact": contact, "rgba": rgba,
        "free_id": np.broadcast_to(plan.link_free, (n, L)), "track_id": np.broadcast_to(plan.link_track, (n, L)),
    }
    values = {"link": _encode("link", link_raw, config.dtype)}
    ids = {"link": np.broadcast_to(np.arange(L)[None, :, None], (n, L, 1)).copy()}

    # ---------------------------------------------------------------- joints (n, 2E)
    qpos0 = _stack(models, "qpos0") if m0.nq else np.zeros((n, 0))
    qspring = _stack(models, "qpos_spring") if m0.nq else np.zeros((n, 0))
    for tname, e in plan.edges.items():
        E = len(e["parent"])
        if E == 0:
            continue
        # Joint frame seen from each side, then each link in the joint frame.
        jp_r, jp_p = compose(rot[:, e["jp_pre"]], pos[:, e["jp_pre"]], rot[:, e["jp"]], pos[:, e["jp"]])
        ir, ip = invert(jp_r, jp_p)
        tp_r, tp_p = compose(ir, ip, rot[:, e["lp"]], pos[:, e["lp"]])
        ir, ip = invert(rot[:, e["jc"]], pos[:, e["jc"]])
        tc_r, tc_p = compose(ir, ip, rot[:, e["lc"]], pos[:, e["lc"]])
        # Order 0 is the lower link ID.
        swap = e["parent"] > e["child"]
        lo_id = np.where(swap, e["child"], e["parent"])
        hi_id = np.where(swap, e["parent"], e["child"])
        r0 = np.where(swap[None, :, None, None], tc_r, tp_r)
        p0 = np.where(swap[None, :, None], tc_p, tp_p)
        r1 = np.where(swap[None, :, None, None], tp_r, tc_r)
        p1 = np.where(swap[None, :, None], tp_p, tc_p)
        inter = lambda a, b: np.stack([a, b], 2).reshape(n, 2 * E, *a.shape[2:])  # noqa: E731
        raw = {"pos": inter(p0, p1), "rot": inter(r0, r1),
               "link_id": np.broadcast_to(np.stack([lo_id, hi_id], 1).reshape(-1), (n, 2 * E))}
        if tname != "fixed_joint":
            raw.update(_joint_params(m0, models, e["mj"], qpos0, qspring))
            raw = {k: (v if k in ("pos", "rot", "link_id") else np.repeat(v, 2, axis=1)) for k, v in raw.items()}
        values[tname] = _encode(tname, raw, config.dtype)
        jid = np.repeat(np.arange(E), 2)
        order = np.tile([0, 1], E)
        ids[tname] = np.broadcast_to(np.stack([jid, order], -1)[None], (n, 2 * E, 2)).copy()

    # ---------------------------------------------------------------- actuators (n, A)
    A = len(plan.act_mj)
    if A:
        a = plan.act_mj
        gain = _stack(models, "actuator_gainprm")[:, a, 0]
        bias = _stack(models, "actuator_biasprm")[:, a, :3]
        biastype = m0.actuator_biastype[a]
        affine = biastype == mujoco.mjtBias.mjBIAS_AFFINE
        is_pos = affine & (bias[..., 1] != 0)
        is_vel = affine & (bias[..., 1] == 0)
        atype = np.where(is_pos, ACTUATOR_TYPES.index("position"), np.where(is_vel, ACTUATOR_TYPES.index("velocity"), ACTUATOR_TYPES.index("motor")))
        kp = np.where(is_pos, gain, 0.0)
        kv = np.where(is_pos, -bias[..., 2], np.where(is_vel, gain, 0.0))
        ctrl = np.where(_stack(models, "actuator_ctrllimited")[:, a, None].astype(bool), _stack(models, "actuator_ctrlrange")[:, a], 0.0)
        force = np.where(_stack(models, "actuator_forcelimited")[:, a, None].astype(bool), _stack(models, "actuator_forcerange")[:, a], 0.0)
        raw = {"ctrlrange": ctrl, "forcerange": force, "kp": kp[..., None], "kv": kv[..., None],
               "gear": _stack(models, "actuator_gear")[:, a, :1], "type": atype,
               "joint_id": np.broadcast_to(plan.act_joint, (n, A))}
        values["actuator"] = _encode("actuator", raw, config.dtype)
        ids["actuator"] = np.broadcast_to(np.arange(A)[None, :, None], (n, A, 1)).copy()

    mask = {k: np.ones(v.shape[:2], dtype=bool) for k, v in values.items()}
    tokens = TokenBatch(values, ids, mask)

    # ---------------------------------------------------------------- per-robot index
    fl = plan.free_link
    free_rot = lrot[:, fl] if len(fl) else np.zeros((n, 0, 3, 3))
    free_pos = lpos[:, fl] if len(fl) else np.zeros((n, 0, 3))
    shared = dict(
        dyna_qposadr=m0.jnt_qposadr[plan.dyna_jnt].astype(np.int64), dyna_dofadr=m0.jnt_dofadr[plan.dyna_jnt].astype(np.int64),
        ball_qposadr=m0.jnt_qposadr[plan.ball_jnt].astype(np.int64), ball_dofadr=m0.jnt_dofadr[plan.ball_jnt].astype(np.int64),
        free_qposadr=m0.jnt_qposadr[plan.free_jnt].astype(np.int64),
        actuator_mj=plan.act_mj, link_geom=plan.link_geom, link_body=plan.link_body, link_site=plan.link_site,
        track_link=plan.track_link, dyna_jnt=plan.dyna_jnt, ball_jnt=plan.ball_jnt, free_jnt=plan.free_jnt, topology=topology,
    )
    index = [RobotIndex(name=_model_name(m), free_offset_rot=free_rot[r], free_offset_pos=free_pos[r],
                        notes=plan.notes + tuple(notes_extra.get(r, ())), **shared) for r, m in enumerate(models)]
    return tokens, index


def _model_name(m: mujoco.MjModel) -> str:
    raw = bytes(m.names)
    return raw[: raw.index(b"\0")].decode() if b"\0" in raw else ""


def _joint_params(m0, models, mj: np.ndarray, qpos0: np.ndarray, qspring: np.ndarray) -> dict:
    """Per-joint token parameters (n, E, ...) for MuJoCo joints `mj` (-1: a loop closure)."""
    n, E = len(models), len(mj)
    real = mj >= 0
    j = mj[real]
    out = {"type": np.zeros((n, E), dtype=np.int64), "range": np.zeros((n, E, 2))}
    for k in ("armature", "damping", "frictionloss", "stiffness", "springref", "ref"):
        out[k] = np.zeros((n, E, 1))
    if not len(j):
        return out
    jt = m0.jnt_type[j]
    out["type"][:, real] = np.where(jt == _J.mjJNT_SLIDE, 1, 0)
    limited = _stack(models, "jnt_limited")[:, j].astype(bool)
    out["range"][:, real] = np.where(limited[..., None], _stack(models, "jnt_range")[:, j], 0.0)
    dof = m0.jnt_dofadr[j]
    out["armature"][:, real, 0] = _stack(models, "dof_armature")[:, dof]
    out["damping"][:, real, 0] = _stack(models, "dof_damping")[:, dof]
    out["frictionloss"][:, real, 0] = _stack(models, "dof_frictionloss")[:, dof]
    out["stiffness"][:, real, 0] = _stack(models, "jnt_stiffness")[:, j]
    scalar = jt != _J.mjJNT_BALL
    qadr = m0.jnt_qposadr[j]
    out["ref"][:, real, 0] = np.where(scalar, qpos0[:, qadr], 0.0)
    out["springref"][:, real, 0] = np.where(scalar, qspring[:, qadr], 0.0)
    return out


def _loop_closure_rows(plan: _Plan, models, rot: np.ndarray, pos: np.ndarray, start: int) -> None:
    """Joint frames of loop closures in each of their two bodies, at the reference pose.

    connect: the frame sits at the anchors with the orientation of body 1; weld: body 1's
    frame. Body 2's side needs the bodies' relative pose at qpos0, where every joint is at
    its reference and each body sits at its own pos / quat: the product of those along the
    tree, for all models at once.
    """
    m0 = models[0]
    off = _pose_offsets(m0)
    n = len(models)
    wrot = np.empty((n, m0.nbody, 3, 3))
    wpos = np.empty((n, m0.nbody, 3))
    wrot[:, 0], wpos[:, 0] = np.eye(3), 0.0
    # Level by level from the world: one batched product per tree depth.
    depth = np.zeros(m0.nbody, dtype=np.int64)
    for b in range(1, m0.nbody):
        depth[b] = depth[m0.body_parentid[b]] + 1
    for level in range(1, int(depth.max(initial=0)) + 1):
        bs = np.flatnonzero(depth == level)
        ps = m0.body_parentid[bs]
        wrot[:, bs], wpos[:, bs] = compose(wrot[:, ps], wpos[:, ps], rot[:, off["body"] + bs], pos[:, off["body"] + bs])
    eq_data = _stack(models, "eq_data")
    site_pos = _stack(models, "site_pos") if m0.nsite else None
    for e, b1, b2, t, s1, s2 in plan.eq_rows:
        r1, r2 = wrot[:, b1], wrot[:, b2]
        r21 = np.swapaxes(r2, -1, -2) @ r1
        rot[:, start + 2 * e] = np.eye(3)
        rot[:, start + 2 * e + 1] = r21
        if t == int(mujoco.mjtEq.mjEQ_CONNECT):
            # Site-based connects anchor each side at its site (the sites coincide when the
            # loop is closed at qpos0); body-based ones at the compiler's two anchors.
            a1, a2 = (site_pos[:, s1], site_pos[:, s2]) if s1 >= 0 else (eq_data[:, e, 0:3], eq_data[:, e, 3:6])
            pos[:, start + 2 * e] = a1
            pos[:, start + 2 * e + 1] = a2
        else:
            pos[:, start + 2 * e] = 0.0
            pos[:, start + 2 * e + 1] = (np.swapaxes(r2, -1, -2) @ (wpos[:, b1] - wpos[:, b2])[..., None])[..., 0]


def _encode(tname: str, raw: dict, dtype) -> np.ndarray:
    """Raw attributes (n, L, dim...) -> encoded tokens (n, L, width)."""
    t = SCHEMA[tname]
    cols = []
    for a in t.attributes:
        v = np.asarray(raw[a.name])
        cols.append(np.asarray(encode_attribute(a, v), dtype=np.float64).reshape(*v.shape[:2], a.width))
    return np.concatenate(cols, axis=-1).astype(dtype)

