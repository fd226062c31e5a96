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

Robots that share a topology share a `_Plan` (index arrays computed once). A call gathers
the numbers of all its models, whatever their topologies, into concatenated arrays and runs
every step below once over all of them as a vectorised numpy op (`_Layout` says where each
robot's pieces start), so its cost does not grow with the number of topologies.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Sequence

import mujoco
import numpy as np

from tt.kernels.errors import TTError
from tt.kernels.rotations import quat_to_mat
from tt.tokens.batch import TokenBatch
from tt.tokens.encodings import encode_attribute
from tt.tokens.frames import compose, invert, z_to_axis
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
# Plain ints: comparing a numpy array with a MuJoCo enum goes element by element through
# Python objects (microseconds per element).
_MESH, _BALL, _FREE, _SLIDE = int(_G.mjGEOM_MESH), int(_J.mjJNT_BALL), int(_J.mjJNT_FREE), int(_J.mjJNT_SLIDE)
_AFFINE, _CONNECT = int(mujoco.mjtBias.mjBIAS_AFFINE), int(mujoco.mjtEq.mjEQ_CONNECT)


class TokenizeError(TTError):
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
    split_groups: dict  # {k: (bodies (B,), links (B, k))}
    inertial_body: np.ndarray  # (Bl,) geometry-less bodies, whose one link holds the inertial
    inertial_link: np.ndarray  # (Bl,) that link
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
    eq: np.ndarray  # (Q, 6) eq_rows as an array
    n_pose_rows: int
    pose_off: dict  # `_pose_offsets` of the topology
    counts: dict  # MuJoCo element counts: body, geom, site, jnt, eq, act, dof, qpos
    body_parent: np.ndarray  # (nbody,) MuJoCo parent body
    body_depth: np.ndarray  # (nbody,) depth in the body tree (world 0)
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
    # Python lists: the loops below read them element by element, which is slow through
    # MjModel attributes (a new array view per access) and numpy scalars.
    geom_type, site_bodyid, jnt_type = m.geom_type.tolist(), m.site_bodyid.tolist(), m.jnt_type.tolist()
    body_geomadr, body_geomnum = m.body_geomadr.tolist(), m.body_geomnum.tolist()
    body_jntadr, body_jntnum, body_parentid = m.body_jntadr.tolist(), m.body_jntnum.tolist(), m.body_parentid.tolist()

    def new_link(k, body, geom=-1, site=-1, code=0, row=0, free=-1, track=-1) -> int:
        for lst, v in zip(
            (kind, lbody, lgeom, lsite, lcode, lrow, lfree, ltrack), (k, body, geom, site, code, row, free, track)
        ):
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
        geoms = range(body_geomadr[b], body_geomadr[b] + body_geomnum[b]) if body_geomnum[b] > 0 else []
        geoms = [g for g in geoms if geom_type[g] not in _SCENE_GEOMS]
        for g in range(body_geomadr[b], body_geomadr[b] + max(body_geomnum[b], 0)):
            t = geom_type[g]
            if t not in _SCENE_GEOMS and t not in _GEOM_CODE:
                raise TokenizeError(
                    f"{_name(m, mujoco.mjtObj.mjOBJ_GEOM, g, 'geom')} has type {mujoco.mjtGeom(t).name}; "
                    "RoboTokens hold spheres, capsules, ellipsoids, cylinders, boxes and meshes (as boxes)"
                )
        sites = [s for s in ee_sites if site_bodyid[s] == b]
        if b == 0:
            # World geoms that are not scene geometry are links welded to the ground.
            for g in geoms:
                link = new_link(
                    1 if geom_type[g] == _MESH else 0, 0, geom=g, code=_GEOM_CODE[geom_type[g]], row=off["geom"] + g
                )
                fixed_to(-1, link, 0, 0)
            for s in sites:
                link = new_link(4, 0, site=s, row=off["site"] + s, track=site_track[s])
                track_link[site_track[s]] = link
                fixed_to(-1, link, 0, 0)
            continue
        parent = body_parentid[b]
        parent_link = -1 if parent == 0 else int(primary[parent])
        jnts = list(range(body_jntadr[b], body_jntadr[b] + body_jntnum[b])) if body_jntnum[b] > 0 else []
        free = [j for j in jnts if jnt_type[j] == _FREE]
        if free and len(jnts) > 1:
            raise TokenizeError(f"{_name(m, mujoco.mjtObj.mjOBJ_BODY, b, 'body')} has a free joint and other joints")
        moving = [] if free else jnts
        # Intermediate links sit at the body frame: their pose row is the identity.
        inter = [new_link(3, b, row=0) for _ in moving[:-1]]
        if geoms:
            g0 = geoms[0]
            p = new_link(
                1 if geom_type[g0] == _MESH else 0, b, geom=g0, code=_GEOM_CODE[geom_type[g0]], row=off["geom"] + g0
            )
        else:
            p = new_link(2, b, row=0)
            body_links.append((b, p))
        primary[b] = p
        if free:
            free_jnt.append(free[0])
            free_link.append(p)
            lfree[p] = len(free_jnt) - 1
            if parent != 0:
                raise TokenizeError(
                    f"{_name(m, mujoco.mjtObj.mjOBJ_BODY, b, 'body')} has a free joint but is not a child of the world"
                )
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
                if jnt_type[j] == _BALL:
                    edges["ball_joint"].append(e)
                    ball_jnt.append(j)
                else:
                    jnt_to_dyna[j] = len(dyna_jnt)
                    edges["dyna_joint"].append(e)
                    dyna_jnt.append(j)
        mass_links = [p] if geoms else []
        for g in geoms[1:]:
            link = new_link(
                1 if geom_type[g] == _MESH else 0, b, geom=g, code=_GEOM_CODE[geom_type[g]], row=off["geom"] + g
            )
            fixed_to(p, link, 0, lrow[p])
            mass_links.append(link)
        for g in geoms:
            if geom_type[g] == _MESH:
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
        if gt != int(mujoco.mjtGain.mjGAIN_FIXED) or bt not in (
            int(mujoco.mjtBias.mjBIAS_AFFINE),
            int(mujoco.mjtBias.mjBIAS_NONE),
        ):
            notes.append(f"{aname} dropped: only position, velocity and motor actuators are representable")
            continue
        act_mj.append(a)
        act_joint.append(jnt_to_dyna[j])
    if m.ntendon:
        notes.append(f"{m.ntendon} tendon(s) ignored")

    n_links = len(kind)
    for what, count, limit in (
        ("links", n_links, MAX_LINKS),
        ("dynamic joints", len(dyna_jnt), MAX_DYNA_JOINTS),
        ("free links", len(free_jnt), MAX_FREE_LINKS),
        ("track links", len(ee_sites), MAX_TRACK_LINKS),
    ):
        if count > limit:
            raise TokenizeError(f"model {_model_name(m)!r} has {count} {what}; schema allows at most {limit}")

    def arr(rows):
        a = np.asarray(rows, dtype=np.int64).reshape(-1, 8)
        return {
            "parent": a[:, 0],
            "child": a[:, 1],
            "jp_pre": a[:, 2],
            "jp": a[:, 3],
            "jc": a[:, 4],
            "lp": a[:, 5],
            "lc": a[:, 6],
            "mj": a[:, 7],
        }

    split_groups = {
        k: (np.array([b for b, _ in v], dtype=np.int64), np.array([ls for _, ls in v], dtype=np.int64))
        for k, v in sorted(split_by_k.items())
    }
    depth = np.zeros(m.nbody, dtype=np.int64)
    for b in range(1, m.nbody):
        depth[b] = depth[m.body_parentid[b]] + 1
    return _Plan(
        link_kind=np.array(kind, dtype=np.int64),
        link_body=np.array(lbody, dtype=np.int64),
        link_geom=np.array(lgeom, dtype=np.int64),
        link_site=np.array(lsite, dtype=np.int64),
        link_code=np.array(lcode, dtype=np.int64),
        link_pose_row=np.array(lrow, dtype=np.int64),
        link_free=np.array(lfree, dtype=np.int64),
        link_track=np.array(ltrack, dtype=np.int64),
        primary=primary,
        split_groups=split_groups,
        inertial_body=np.array([b for b, _ in body_links], dtype=np.int64),
        inertial_link=np.array([link for _, link in body_links], dtype=np.int64),
        edges={k: arr(v) for k, v in edges.items()},
        dyna_jnt=np.array(dyna_jnt, dtype=np.int64),
        ball_jnt=np.array(ball_jnt, dtype=np.int64),
        free_jnt=np.array(free_jnt, dtype=np.int64),
        free_link=np.array(free_link, dtype=np.int64),
        track_site=np.array(ee_sites, dtype=np.int64),
        track_link=np.array(track_link, dtype=np.int64),
        act_mj=np.array(act_mj, dtype=np.int64),
        act_joint=np.array(act_joint, dtype=np.int64),
        eq_rows=eq_rows,
        eq=np.array(eq_rows, dtype=np.int64).reshape(-1, 6),
        n_pose_rows=off["end"],
        pose_off=off,
        counts={
            "body": m.nbody,
            "geom": m.ngeom,
            "site": m.nsite,
            "jnt": m.njnt,
            "eq": m.neq,
            "act": m.nu,
            "dof": m.nv,
            "qpos": m.nq,
        },
        body_parent=m.body_parentid.astype(np.int64),
        body_depth=depth,
        notes=tuple(notes),
    )


def _signature(m: mujoco.MjModel, ee_sites: list[int]) -> bytes:
    """Bytes that are equal for models with equal topology (the plan is then the same)."""
    parts = [
        np.array([m.nbody, m.njnt, m.ngeom, m.nsite, m.nu, m.neq, m.ntendon, *ee_sites], dtype=np.int32),
        m.body_parentid,
        m.body_jntnum,
        m.body_geomnum,
        m.jnt_type,
        m.geom_type,
    ]
    if m.nu:
        parts += [m.actuator_trntype, m.actuator_trnid, m.actuator_gaintype, m.actuator_biastype, m.actuator_dyntype]
    if m.neq:
        parts += [m.eq_type, m.eq_objtype, m.eq_obj1id, m.eq_obj2id, m.site_bodyid]
    elif ee_sites:
        parts.append(m.site_bodyid[ee_sites])
    # Joined bytes of int32 arrays: what one concatenated array would give, without the
    # concatenation (this runs once per model).
    return b"".join(np.asarray(a, dtype=np.int32).tobytes() for a in parts)


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
        return {
            "dyna_joint": len(self.dyna_qposadr),
            "ball_joint": len(self.ball_qposadr),
            "free_link": len(self.free_qposadr),
            "track_link": len(self.track_link),
            "actuator": len(self.actuator_mj),
        }


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

        Models are grouped by topology and tokenized together with vectorised numpy.
        Raises `TokenizeError` for a model RoboTokens cannot hold; warns (`TokenizeWarning`)
        once per topology about approximations (meshes, dropped tendons / equalities /
        actuators).
        """
        models = list(models)
        if not models:
            raise TTError("tokenize needs at least one model")
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
        lay = _Layout([self._plans[k] for k in groups], list(groups.values()), models)
        tokens, index = _tokenize_batch(lay, self.config)
        return Embodiments(tokens, index)


def tokenize_models(models: Sequence[mujoco.MjModel], config: TokenizeConfig = TokenizeConfig()) -> Embodiments:
    """Embodiment tokens of N models (a fresh `Tokenizer`; keep one to tokenize many batches)."""
    return Tokenizer(config)(models)


def tokenize_model(model: mujoco.MjModel, config: TokenizeConfig = TokenizeConfig()) -> Embodiments:
    """`tokenize_models` of one model."""
    return tokenize_models([model], config)


class _Layout:
    """The robots of one call sorted by topology, and where each robot's pieces start in
    arrays that concatenate every robot's pieces (model arrays, pose table, tokens).

    Every step of the tokenizer then runs once over all robots of the call instead of once
    per topology: a design space with 32 topologies would otherwise pay numpy's per-call
    overhead 32 times for groups of a few robots each.
    """

    def __init__(self, plans: list[_Plan], groups: list[list[int]], models: Sequence[mujoco.MjModel]):
        self.plans = plans
        self.sizes = np.array([len(g) for g in groups], dtype=np.int64)  # (G,) robots per topology
        self.bounds = np.concatenate([[0], np.cumsum(self.sizes)])  # robots of plan p: bounds[p]:bounds[p + 1]
        self.order = np.concatenate(
            [np.asarray(g, dtype=np.int64) for g in groups]
        )  # (N,) input position of each robot
        self.group = np.repeat(np.arange(len(plans)), self.sizes)  # (N,) plan of each robot
        self.models = [models[i] for i in self.order]
        self._cat: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.order)

    def cat(self, name: str) -> np.ndarray:
        """A MuJoCo model array of every robot, concatenated along its first axis (gathered
        once per call; callers must not write into it)."""
        if name not in self._cat:
            self._cat[name] = np.concatenate([getattr(m, name) for m in self.models])
        return self._cat[name]

    def fixed(self, name: str) -> np.ndarray:
        """A MuJoCo model array that the topology fixes (in `_signature`, or derived from what
        is), concatenated over robots from one model per plan."""
        if name not in self._cat:
            self._cat[name] = self.tile([getattr(self.models[lo], name) for lo in self.bounds[:-1]])
        return self._cat[name]

    def per_robot(self, per_plan) -> np.ndarray:
        """One number per plan -> (N,), one per robot."""
        return np.repeat(np.asarray(per_plan, dtype=np.int64), self.sizes)

    def starts(self, per_plan) -> np.ndarray:
        """(N,) start of each robot's piece when pieces of ``per_plan[p]`` elements are concatenated."""
        c = self.per_robot(per_plan)
        return np.cumsum(c) - c

    def ranges(self, per_plan, base: np.ndarray) -> np.ndarray:
        """``base[s] + arange(per_plan[p])`` for each robot s (of plan p), concatenated."""
        if len(self.plans) == 1:  # one topology (every single-robot call): plain broadcasting
            return (base[:, None] + np.arange(per_plan[0])).ravel()
        c = self.per_robot(per_plan)
        return np.repeat(base - (np.cumsum(c) - c), c) + np.arange(int(c.sum()))

    def tile(self, per_plan: list[np.ndarray]) -> np.ndarray:
        """Per-plan arrays (E_p, ...) repeated for each robot of the plan and concatenated."""
        if len(self.plans) == 1:
            a = per_plan[0]
            return np.tile(a, (len(self),) + (1,) * (a.ndim - 1))
        count = np.array([len(a) for a in per_plan], dtype=np.int64)
        return np.concatenate(per_plan)[self.ranges(count, self.per_robot(np.cumsum(count) - count))]

    def shift(self, per_plan: list[np.ndarray], start: np.ndarray) -> np.ndarray:
        """Per-plan non-negative indices (E_p, ...) plus each robot's `start` (N,), concatenated
        over robots along the first axis: the global index of every (robot, element)."""
        if len(self.plans) == 1:
            a = per_plan[0]
            return (start.reshape(-1, *([1] * a.ndim)) + a[None]).reshape(-1, *a.shape[1:])
        t = self.tile(per_plan)
        return t + np.repeat(start, self.per_robot([len(a) for a in per_plan])).reshape(-1, *([1] * (t.ndim - 1)))

    def robot_of(self, per_plan) -> np.ndarray:
        """Robot of each element when each robot has ``per_plan[p]`` elements, concatenated."""
        return np.repeat(np.arange(len(self)), self.per_robot(per_plan))


def _tokenize_batch(lay: _Layout, config: TokenizeConfig) -> tuple[TokenBatch, list[RobotIndex]]:
    """Embodiment tokens and indices of all robots of `lay`, in input order."""
    plans = lay.plans
    cnt = {k: [p.counts[k] for p in plans] for k in plans[0].counts}
    start = {k: lay.starts(v) for k, v in cnt.items()}  # (N,) first element of each robot
    pose_start = lay.starts([p.n_pose_rows for p in plans])

    # ---------------------------------------------------------------- pose table (P,)
    n_rows = int(sum(p.n_pose_rows * n for p, n in zip(plans, lay.sizes)))
    rot = np.empty((n_rows, 3, 3))
    pos = np.zeros((n_rows, 3))
    rot[pose_start] = np.eye(3)

    def rows(section: str, k: str) -> np.ndarray:
        return lay.ranges(cnt[k], pose_start + lay.per_robot([p.pose_off[section] for p in plans]))

    body_rows = rows("body", "body")
    rot[body_rows] = quat_to_mat(lay.cat("body_quat"))
    pos[body_rows] = lay.cat("body_pos")
    geom_type = lay.fixed("geom_type")
    geom_rot = quat_to_mat(lay.cat("geom_quat"))
    geom_pos = lay.cat("geom_pos")
    geom_size = lay.cat("geom_size")
    mesh = geom_type == _MESH
    if np.any(mesh):
        # A mesh's box: the bounding box in the geom frame (MuJoCo centres meshes on
        # their inertial frame, so the box centre is offset from the geom origin).
        aabb = lay.cat("geom_aabb")
        geom_pos, geom_size = geom_pos.copy(), geom_size.copy()
        geom_pos[mesh] += (geom_rot[mesh] @ aabb[mesh, :3, None])[..., 0]
        geom_size[mesh] = aabb[mesh, 3:]
    geom_rows = rows("geom", "geom")
    rot[geom_rows] = geom_rot
    pos[geom_rows] = geom_pos
    site_rows = rows("site", "site")
    rot[site_rows] = quat_to_mat(lay.cat("site_quat"))
    site_pos = lay.cat("site_pos")
    pos[site_rows] = site_pos
    jnt_type = lay.fixed("jnt_type")
    jrot = z_to_axis(lay.cat("jnt_axis"))
    # Ball and free joints have no axis: their frame keeps the body's orientation.
    jrot[(jnt_type == _BALL) | (jnt_type == _FREE)] = np.eye(3)
    joint_rows = rows("joint", "jnt")
    rot[joint_rows] = jrot
    pos[joint_rows] = lay.cat("jnt_pos")
    if any(p.eq_rows for p in plans):
        _loop_closure_rows(lay, rot, pos, start, pose_start, site_pos)

    # ---------------------------------------------------------------- links (TL,)
    link_count = [len(p.link_kind) for p in plans]
    link_start = lay.starts(link_count)
    lrow = lay.shift([p.link_pose_row for p in plans], pose_start)
    lrot = rot[lrow]
    lpos = pos[lrow]
    code = lay.tile([p.link_code for p in plans])
    n_links = len(code)
    size = np.zeros((n_links, 3))
    friction = np.zeros((n_links, 3))
    rgba = np.zeros((n_links, 4))
    contact = np.zeros(n_links, dtype=np.int64)
    link_geom = lay.tile([p.link_geom for p in plans])
    has_geom = link_geom >= 0
    g = (link_geom + np.repeat(start["geom"], lay.per_robot(link_count)))[has_geom]
    if len(g):
        size[has_geom] = geom_size[g]
        friction[has_geom] = lay.cat("geom_friction")[g]
        rgba[has_geom] = lay.cat("geom_rgba")[g]
        condim = lay.cat("geom_condim")[g]
        collides = (lay.cat("geom_contype")[g] != 0) | (lay.cat("geom_conaffinity")[g] != 0)
        lut = np.zeros(7, dtype=np.int64)
        for c, d in enumerate(CONTACT_CONDIMS):
            lut[d] = c
        contact[has_geom] = np.where(collides, lut[condim], 0)
    # Unused size entries are zero so equal shapes have equal tokens.
    for c, k in SIZE_DIMS.items():
        size[code == c, k:] = 0.0

    mass = np.zeros(n_links)
    com = np.zeros((n_links, 3))  # in body frame
    tensor = np.zeros((n_links, 3, 3))  # about com, body frame
    body_mass = lay.cat("body_mass")
    body_com = lay.cat("body_ipos")
    body_irot = quat_to_mat(lay.cat("body_iquat"))
    body_inertia = body_irot @ (lay.cat("body_inertia")[..., :, None] * np.swapaxes(body_irot, -1, -2))
    # Bodies grouped by their number of geom links k, over all topologies.
    inexact_notes: dict[int, list[str]] = {}
    none = np.zeros(0, dtype=np.int64)
    for k in sorted(set().union(*(p.split_groups for p in plans))):
        groups = [p.split_groups.get(k, (none, none.reshape(0, k))) for p in plans]
        bf = lay.shift([b for b, _ in groups], start["body"])  # (R,) bodies with k geom links
        lf = lay.shift([ls for _, ls in groups], link_start)  # (R, k) their links
        if k == 1:
            # One primitive takes the body's inertial as it is: `split_lumped_inertia`'s
            # answer for k = 1, without the solids it would compute and discard.
            mass[lf[:, 0]], com[lf[:, 0]], tensor[lf[:, 0]] = body_mass[bf], body_com[bf], body_inertia[bf]
            continue
        args = (body_mass[bf], body_com[bf], body_inertia[bf], code[lf], size[lf], lpos[lf], lrot[lf])
        ms, cs, ts, exact = split_lumped_inertia(*args)
        if not exact.all():
            # Not a uniform density: fit per-primitive masses to the lumped inertias, then
            # split those bodies again.
            redo = np.flatnonzero(~exact)
            args = tuple(a[redo] for a in args)
            fitted = fit_masses(*args)
            ms[redo], cs[redo], ts[redo], exact[redo] = split_lumped_inertia(*args, masses=fitted)
        mass[lf] = ms
        com[lf] = cs
        tensor[lf] = ts
        if not exact.all():
            robot = np.searchsorted(start["body"], bf, side="right") - 1
            for row in np.flatnonzero(~exact):
                s = int(robot[row])
                name = _name(lay.models[s], mujoco.mjtObj.mjOBJ_BODY, int(bf[row] - start["body"][s]), "body")
                inexact_notes.setdefault(s, []).append(
                    f"{name}: lumped inertia does not split exactly over its primitives; "
                    "links get solid inertias of best-fit masses"
                )
    ib = lay.shift([p.inertial_body for p in plans], start["body"])
    il = lay.shift([p.inertial_link for p in plans], link_start)
    mass[il] = body_mass[ib]
    com[il] = body_com[ib]
    tensor[il] = body_inertia[ib]
    # Warnings in topology order, each topology's robots as their bodies were found.
    for s in sorted(inexact_notes, key=lambda s: lay.group[s]):
        for msg in inexact_notes[s]:
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
        "geom_type": code,
        "size": size,
        "mass": mass[..., None],
        "ipos": ipos,
        "irot": irot,
        "inertia": moments,
        "friction": friction,
        "contact": contact,
        "rgba": rgba,
        "free_id": lay.tile([p.link_free for p in plans]),
        "track_id": lay.tile([p.link_track for p in plans]),
    }
    flat = {"link": (_encode("link", link_raw, config.dtype), link_count)}

    # ---------------------------------------------------------------- joints (2 TE,)
    qpos0 = lay.cat("qpos0")
    qspring = lay.cat("qpos_spring")
    for tname in ("dyna_joint", "ball_joint", "fixed_joint"):
        count = [len(p.edges[tname]["parent"]) for p in plans]
        if not sum(count):
            continue
        e = {k: lay.shift([p.edges[tname][k] for p in plans], pose_start) for k in ("jp_pre", "jp", "jc", "lp", "lc")}
        parent = lay.tile([p.edges[tname]["parent"] for p in plans])
        child = lay.tile([p.edges[tname]["child"] for p in plans])
        # Joint frame seen from each side, then each link in the joint frame.
        jp_r, jp_p = compose(rot[e["jp_pre"]], pos[e["jp_pre"]], rot[e["jp"]], pos[e["jp"]])
        ir, ip = invert(jp_r, jp_p)
        tp_r, tp_p = compose(ir, ip, rot[e["lp"]], pos[e["lp"]])
        ir, ip = invert(rot[e["jc"]], pos[e["jc"]])
        tc_r, tc_p = compose(ir, ip, rot[e["lc"]], pos[e["lc"]])
        # Order 0 is the lower link ID.
        swap = parent > child
        lo_id = np.where(swap, child, parent)
        hi_id = np.where(swap, parent, child)
        r0 = np.where(swap[:, None, None], tc_r, tp_r)
        p0 = np.where(swap[:, None], tc_p, tp_p)
        r1 = np.where(swap[:, None, None], tp_r, tc_r)
        p1 = np.where(swap[:, None], tp_p, tc_p)
        inter = lambda a, b: np.stack([a, b], 1).reshape(-1, *a.shape[1:])  # noqa: E731
        raw = {"pos": inter(p0, p1), "rot": inter(r0, r1), "link_id": np.stack([lo_id, hi_id], 1).reshape(-1)}
        if tname != "fixed_joint":
            mj = lay.tile([p.edges[tname]["mj"] for p in plans])
            mj = np.where(mj >= 0, mj + np.repeat(start["jnt"], lay.per_robot(count)), -1)
            params = _joint_params(lay, mj, start, jnt_type, qpos0, qspring)
            raw.update({k: np.repeat(v, 2, axis=0) for k, v in params.items()})
        flat[tname] = (_encode(tname, raw, config.dtype), [2 * E for E in count])

    # ---------------------------------------------------------------- actuators (TA,)
    count = [len(p.act_mj) for p in plans]
    if sum(count):
        a = lay.shift([p.act_mj for p in plans], start["act"])
        gain = lay.cat("actuator_gainprm")[a, 0]
        bias = lay.cat("actuator_biasprm")[a, :3]
        affine = lay.fixed("actuator_biastype")[a] == _AFFINE
        is_pos = affine & (bias[..., 1] != 0)
        is_vel = affine & (bias[..., 1] == 0)
        atype = np.where(
            is_pos,
            ACTUATOR_TYPES.index("position"),
            np.where(is_vel, ACTUATOR_TYPES.index("velocity"), ACTUATOR_TYPES.index("motor")),
        )
        kp = np.where(is_pos, gain, 0.0)
        kv = np.where(is_pos, -bias[..., 2], np.where(is_vel, gain, 0.0))
        ctrl = np.where(lay.cat("actuator_ctrllimited")[a, None].astype(bool), lay.cat("actuator_ctrlrange")[a], 0.0)
        force = np.where(lay.cat("actuator_forcelimited")[a, None].astype(bool), lay.cat("actuator_forcerange")[a], 0.0)
        raw = {
            "ctrlrange": ctrl,
            "forcerange": force,
            "kp": kp[..., None],
            "kv": kv[..., None],
            "gear": lay.cat("actuator_gear")[a, :1],
            "type": atype,
            "joint_id": lay.tile([p.act_joint for p in plans]),
        }
        flat["actuator"] = (_encode("actuator", raw, config.dtype), count)

    # ---------------------------------------------------------------- padded batch, input order
    values, ids, mask = {}, {}, {}
    for tname in SCHEMA.names():
        if tname not in flat:
            continue
        v, count = flat[tname]
        per = lay.per_robot(count)
        row = np.repeat(lay.order, per)
        col = lay.ranges(count, np.zeros(len(lay), dtype=np.int64))  # token position in its robot
        # IDs: the link / actuator ID, or (joint ID, order) with a joint's two tokens adjacent.
        i = col[:, None] if tname in ("link", "actuator") else np.stack([col // 2, col % 2], -1)
        longest = int(per.max())
        values[tname] = np.zeros((len(lay), longest, v.shape[-1]), dtype=v.dtype)
        ids[tname] = np.zeros((len(lay), longest, i.shape[-1]), dtype=np.int64)
        mask[tname] = np.zeros((len(lay), longest), dtype=bool)
        values[tname][row, col] = v
        ids[tname][row, col] = i
        mask[tname][row, col] = True
    tokens = TokenBatch(values, ids, mask)

    # ---------------------------------------------------------------- per-robot index
    index: list[RobotIndex | None] = [None] * len(lay)
    for p, plan in enumerate(plans):
        lo, hi = lay.bounds[p], lay.bounds[p + 1]
        m0 = lay.models[lo]
        shared = dict(
            dyna_qposadr=m0.jnt_qposadr[plan.dyna_jnt].astype(np.int64),
            dyna_dofadr=m0.jnt_dofadr[plan.dyna_jnt].astype(np.int64),
            ball_qposadr=m0.jnt_qposadr[plan.ball_jnt].astype(np.int64),
            ball_dofadr=m0.jnt_dofadr[plan.ball_jnt].astype(np.int64),
            free_qposadr=m0.jnt_qposadr[plan.free_jnt].astype(np.int64),
            actuator_mj=plan.act_mj,
            link_geom=plan.link_geom,
            link_body=plan.link_body,
            link_site=plan.link_site,
            track_link=plan.track_link,
            dyna_jnt=plan.dyna_jnt,
            ball_jnt=plan.ball_jnt,
            free_jnt=plan.free_jnt,
            topology=p,
        )
        free = link_start[lo:hi, None] + plan.free_link[None]  # (n, F)
        free_rot, free_pos = lrot[free], lpos[free]
        for r, s in enumerate(range(lo, hi)):
            index[lay.order[s]] = RobotIndex(
                name=_model_name(lay.models[s]),
                free_offset_rot=free_rot[r],
                free_offset_pos=free_pos[r],
                notes=plan.notes + tuple(inexact_notes.get(s, ())),
                **shared,
            )
    return tokens, index


def _model_name(m: mujoco.MjModel) -> str:
    raw = bytes(m.names)
    return raw[: raw.index(b"\0")].decode() if b"\0" in raw else ""


def _joint_params(
    lay: _Layout, mj: np.ndarray, start: dict, jnt_type: np.ndarray, qpos0: np.ndarray, qspring: np.ndarray
) -> dict:
    """Token parameters (E, ...) of joints `mj`: indices into the concatenated joint arrays
    of `lay` (-1: a loop closure). `start`: each robot's first joint / dof / qpos entry."""
    E = len(mj)
    real = mj >= 0
    j = mj[real]
    out = {"type": np.zeros(E, dtype=np.int64), "range": np.zeros((E, 2))}
    for k in ("armature", "damping", "frictionloss", "stiffness", "springref", "ref"):
        out[k] = np.zeros((E, 1))
    if not len(j):
        return out
    # Each joint's dof / qpos address in the concatenated arrays: its robot's start + its own.
    robot = lay.robot_of([p.counts["jnt"] for p in lay.plans])[j]
    jt = jnt_type[j]
    out["type"][real] = np.where(jt == _SLIDE, 1, 0)
    limited = lay.cat("jnt_limited")[j].astype(bool)
    out["range"][real] = np.where(limited[..., None], lay.cat("jnt_range")[j], 0.0)
    dof = lay.fixed("jnt_dofadr")[j] + start["dof"][robot]
    out["armature"][real, 0] = lay.cat("dof_armature")[dof]
    out["damping"][real, 0] = lay.cat("dof_damping")[dof]
    out["frictionloss"][real, 0] = lay.cat("dof_frictionloss")[dof]
    out["stiffness"][real, 0] = lay.cat("jnt_stiffness")[j]
    scalar = jt != _BALL
    qadr = lay.fixed("jnt_qposadr")[j] + start["qpos"][robot]
    out["ref"][real, 0] = np.where(scalar, qpos0[qadr], 0.0)
    out["springref"][real, 0] = np.where(scalar, qspring[qadr], 0.0)
    return out


def _loop_closure_rows(
    lay: _Layout, rot: np.ndarray, pos: np.ndarray, start: dict, pose_start: np.ndarray, site_pos: np.ndarray
) -> None:
    """Joint frames of loop closures in each of their two bodies, at the reference pose, for
    every robot of `lay` (written into the pose table rows of its closures).

    connect: the frame sits at the anchors with the orientation of body 1; weld: body 1's
    frame. Body 2's side needs the bodies' relative pose at qpos0, where every joint is at
    its reference and each body sits at its own pos / quat: the product of those along the
    tree, for all robots at once.
    """
    plans = lay.plans
    closed = [bool(p.eq_rows) for p in plans]
    some = lambda per_plan, empty: [a if c else empty for a, c in zip(per_plan, closed)]  # noqa: E731
    none = np.zeros(0, dtype=np.int64)
    # World pose of every body of the robots with loops, level by level from the world: one
    # batched product per tree depth.
    wrot = np.empty((int(lay.per_robot([p.counts["body"] for p in plans]).sum()), 3, 3))
    wpos = np.empty((len(wrot), 3))
    roots = lay.shift(some([np.zeros(1, dtype=np.int64)] * len(plans), none), start["body"])
    wrot[roots], wpos[roots] = np.eye(3), 0.0
    body = lay.shift(some([np.arange(p.counts["body"]) for p in plans], none), start["body"])
    parent = lay.shift(some([p.body_parent for p in plans], none), start["body"])
    row = lay.shift(some([p.pose_off["body"] + np.arange(p.counts["body"]) for p in plans], none), pose_start)
    depth = lay.tile(some([p.body_depth for p in plans], none))
    for level in range(1, int(depth.max(initial=0)) + 1):
        sel = depth == level
        bs, ps, rs = body[sel], parent[sel], row[sel]
        wrot[bs], wpos[bs] = compose(wrot[ps], wpos[ps], rot[rs], pos[rs])
    # One row per (robot, closure): eq id, body 1, body 2, type, site 1, site 2.
    eq = lay.tile(some([p.eq for p in plans], np.zeros((0, 6), dtype=np.int64)))
    robot = lay.robot_of(some([len(p.eq) for p in plans], 0))
    e, t, s1, s2 = eq[:, 0], eq[:, 3], eq[:, 4], eq[:, 5]
    b1, b2 = eq[:, 1] + start["body"][robot], eq[:, 2] + start["body"][robot]
    r0 = pose_start[robot] + lay.per_robot([p.pose_off["eq"] for p in plans])[robot] + 2 * e
    r1, r2 = wrot[b1], wrot[b2]
    r21 = np.swapaxes(r2, -1, -2) @ r1
    rot[r0] = np.eye(3)
    rot[r0 + 1] = r21
    connect = t == _CONNECT
    # Site-based connects anchor each side at its site (the sites coincide when the loop is
    # closed at qpos0); body-based ones at the compiler's two anchors.
    eq_data = lay.cat("eq_data")[e + start["eq"][robot]]
    a1, a2 = eq_data[:, 0:3].copy(), eq_data[:, 3:6].copy()
    at_site = connect & (s1 >= 0)
    a1[at_site] = site_pos[s1[at_site] + start["site"][robot[at_site]]]
    a2[at_site] = site_pos[s2[at_site] + start["site"][robot[at_site]]]
    pos[r0[connect]] = a1[connect]
    pos[r0[connect] + 1] = a2[connect]
    weld = ~connect
    pos[r0[weld]] = 0.0
    pos[r0[weld] + 1] = (np.swapaxes(r2[weld], -1, -2) @ (wpos[b1[weld]] - wpos[b2[weld]])[..., None])[..., 0]


def _encode(tname: str, raw: dict, dtype) -> np.ndarray:
    """Raw attributes (T, dim...) of T tokens -> encoded tokens (T, width)."""
    t = SCHEMA[tname]
    out = None
    col = 0
    for a in t.attributes:
        v = np.asarray(raw[a.name])
        if out is None:
            out = np.empty((len(v), t.width), dtype=dtype)
        # Encoded in float64, rounded to `dtype` by the assignment (as astype would).
        out[:, col : col + a.width] = np.asarray(encode_attribute(a, v), dtype=np.float64).reshape(len(v), a.width)
        col += a.width
    return out
