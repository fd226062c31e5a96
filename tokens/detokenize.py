"""Detokenizer: embodiment RoboTokens -> MJCF text that MuJoCo loads.

Decoding is robust to noisy model output. Binary fields are clipped and rounded,
rotations projected onto SO(3), masses / gains / inertias kept non-negative, inverted
ranges sorted; joints whose link IDs point nowhere (or whose two halves do not match),
actuators whose joint does not exist and padding tokens are dropped. Every repair is
written to the result's ``notes``; a model MuJoCo still refuses comes back with the
reason in ``error`` (never an exception).

From tokens to bodies:

* Links joined by fixed joints form one rigid group = one MJCF body (links fixed to the
  ground form static bodies under the world). The group's body frame is the frame of the
  link its parent joint attaches to; for a ball joint, the joint frame (so the ball's
  quaternion means what it meant in the tokenized model).
* The tree is a spanning forest grown from the ground and the free links, taking hinge /
  slide, then fixed, then ball joints in ID order. Joints that would close a loop become
  equality constraints: ball -> ``connect``, fixed -> ``weld`` (hinge / slide -> ``connect``,
  with a note).
* Each group's inertial is the sum of its links' (parallel axis theorem), written
  explicitly, so masses and inertias come back exactly.
* A massless, geometry-less group between two hinge / slide joints is folded into its
  child body as a multi-joint body, which is how tokenized multi-joint bodies come back.
* Track links become sites ``ee_<track id>``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import mujoco
import numpy as np

from tt.tokens.batch import TokenBatch
from tt.tokens.encodings import decode_attribute
from tt.tokens.frames import compose, invert
from tt.tokens.inertia import SIZE_DIMS, principal_axes, repair_moments
from tt.tokens.schema import ACTUATOR_TYPES, CONTACT_CONDIMS, GEOM_TYPES, JOINT_TYPES, SCHEMA, check_version

logger = logging.getLogger(__name__)

#: Smallest size [m] a decoded geom keeps (MuJoCo rejects non-positive sizes).
MIN_SIZE = 1e-4
#: Mass [kg] and principal moment [kg m^2] given to a moving body that decoded massless.
MIN_MOVING_MASS = 1e-3
MIN_MOVING_INERTIA = 1e-7
#: Geometry-less links lighter than this [kg] count as massless frames (foldable into a
#: multi-joint body). It is the log offset of masses: below it the encoding has no
#: resolution, and noise on a zero mass decodes to ~1e-5 kg.
MASSLESS = 1e-4


@dataclass(frozen=True)
class DetokenizeConfig:
    """The MJCF around the robot (RoboTokens hold the robot, not the simulation options).

    model: MJCF model name; timestep [s]; integrator: MuJoCo integrator name; gravity [m/s^2];
    contacts: False writes ``<flag contact="disable"/>``; floor: add a ground plane (None:
    when any link takes part in contacts); self_collision: contact-enabled links also
    collide with each other (else only with the scene); connect_solref: solref of the loop
    closures (their stiffness is not part of RoboTokens).
    """

    model: str = "robot"
    timestep: float = 0.002
    integrator: str = "Euler"
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    contacts: bool = True
    floor: bool | None = None
    self_collision: bool = False
    connect_solref: tuple[float, float] = (0.005, 1.0)


@dataclass
class DetokenizeResult:
    """One decoded robot: MJCF text, the compiled model (None when MuJoCo refused it, with
    the reason in `error`), and notes on everything repaired or dropped."""

    xml: str
    model: mujoco.MjModel | None
    error: str | None
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.model is not None


# ------------------------------------------------------------------------------ decoding
def decode_robot(tokens: TokenBatch, index: int) -> dict[str, dict[str, np.ndarray]]:
    """Raw attributes of robot `index`'s real tokens, per type: attribute -> (n, ...) and
    "ids" -> (n, k) int. Robust decoding (see module docstring)."""
    check_version(tokens.version, "token batch")
    out = {}
    for name in tokens.types:
        if SCHEMA[name].role.value != "embodiment":
            continue
        t = SCHEMA[name]
        mask = np.asarray(_np(tokens.mask[name])[index], dtype=bool)
        vals = np.asarray(_np(tokens.values[name])[index], dtype=np.float64)[mask]
        dec = {a.name: decode_attribute(a, vals[:, t.slice(a.name)]) for a in t.attributes}
        dec["ids"] = np.asarray(_np(tokens.ids[name])[index])[mask].astype(np.int64)
        out[name] = dec
    return out


def _np(x):
    if hasattr(x, "detach"):
        return x.detach().cpu().numpy()
    return np.asarray(x)


@dataclass
class _Joint:
    kind: str  # dyna | ball | fixed
    jid: int
    a: int  # lower link ID
    b: int  # higher link ID
    ta: tuple  # (R, p) pose of link a in the joint frame
    tb: tuple
    params: dict


def _collect_joints(dec: dict, kind: str, notes: list[str], links: set[int]) -> list[_Joint]:
    name = {"dyna": "dyna_joint", "ball": "ball_joint", "fixed": "fixed_joint"}[kind]
    if name not in dec:
        return []
    d = dec[name]
    out = []
    for jid in np.unique(d["ids"][:, 0]):
        rows = np.flatnonzero(d["ids"][:, 0] == jid)
        if len(rows) != 2:
            notes.append(f"{name} {jid}: {len(rows)} halves instead of 2; dropped")
            continue
        la, lb = (int(d["link_id"][r]) for r in rows)
        if la == lb or any(lid != -1 and lid not in links for lid in (la, lb)):
            notes.append(f"{name} {jid}: link IDs ({la}, {lb}) do not name two existing links; dropped")
            continue
        if lb < la:
            rows = rows[::-1]
            la, lb = lb, la
        params = {}
        if kind != "fixed":
            for k in ("range", "armature", "damping", "frictionloss", "stiffness", "springref", "ref"):
                params[k] = 0.5 * (d[k][rows[0]] + d[k][rows[1]])
            params["type"] = int(d["type"][rows[0]])
        out.append(
            _Joint(
                kind,
                int(jid),
                la,
                lb,
                (d["rot"][rows[0]], d["pos"][rows[0]]),
                (d["rot"][rows[1]], d["pos"][rows[1]]),
                params,
            )
        )
    return out


class _UnionFind:
    def __init__(self):
        self.parent: dict[int, int] = {}

    def find(self, x: int) -> int:
        self.parent.setdefault(x, x)
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.parent[rb] = ra
        return True


def _quat(r) -> np.ndarray:
    """(w, x, y, z) of one rotation matrix (MuJoCo's converter: fast for single matrices)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(r, dtype=np.float64).reshape(9))
    return -q if q[0] < 0 else q


def _principal(inertia: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`principal_axes` of one tensor, without the batching overhead (same canonical frame)."""
    d = np.diag(inertia)
    if np.abs(inertia - np.diag(d)).max() <= 1e-9 * np.abs(d).sum():
        return np.eye(3), d.copy()
    rot, mom = principal_axes(inertia[None])
    return rot[0], mom[0]


def _pose(r, p) -> str:
    q = _quat(r)
    out = ""
    if np.linalg.norm(p) > 0:
        out += f' pos="{_fmt(p)}"'
    if abs(q[0] - 1.0) > 1e-15:
        out += f' quat="{_fmt(q)}"'
    return out


def _fmt(v) -> str:
    """Numbers with 8 significant digits: tokens are float32 (~7.2 digits), so this loses
    nothing they hold (relative error <= 5e-9) and prints their short decimals short.
    Round-off below 1e-12 prints as 0."""
    return " ".join("0" if abs(x) < 1e-12 else "%.8g" % x for x in np.asarray(v, dtype=np.float64).reshape(-1).tolist())


# ------------------------------------------------------------------------------ MJCF
def robot_to_mjcf(dec: dict, config: DetokenizeConfig = DetokenizeConfig()) -> tuple[str, list[str]]:
    """MJCF text of one decoded robot (from `decode_robot`) and notes on what was repaired."""
    lk = dec.get("link")
    if lk is None or len(lk["ids"]) == 0:
        raise _NoRobot("no link tokens")
    return _RobotTree(dec, config).mjcf()


class _RobotTree:
    """The kinematic tree of one decoded robot and its MJCF writer.

    Groups are rigid link groups (one MJCF body each) keyed by a representative link; -1 is
    the world. ``in_body[link]`` is a link's pose in its group's body frame.
    """

    def __init__(self, dec: dict, config: DetokenizeConfig):
        self.dec, self.config, self.notes = dec, config, []
        lk = self.lk = dec["link"]
        self.row: dict[int, int] = {}
        for r, lid in enumerate(lk["ids"][:, 0]):
            if int(lid) in self.row:
                self.notes.append(f"link {lid}: duplicate token dropped")
                continue
            self.row[int(lid)] = r
        links = set(self.row)
        joints = {k: _collect_joints(dec, k, self.notes, links) for k in ("fixed", "dyna", "ball")}
        self._spanning_forest(joints, links)
        self._grow_tree()
        self._place_links()
        self._pick_track_links()

    def _pick_track_links(self) -> None:
        """One link per track ID: a (generated) robot may mark several links as the same
        end effector, which MuJoCo rejects as a repeated site name; the deepest link in the
        tree keeps it (an end effector sits at a chain's tip), the others lose it."""
        parent = {c: g for g, cs in self.children.items() for c in cs}

        def depth(g: int) -> int:
            d = 0
            while g in parent and parent[g] != -1:
                g, d = parent[g], d + 1
            return d

        by_tid: dict[int, list[int]] = {}
        for lid, r in self.row.items():
            tid = int(self.lk["track_id"][r])
            if tid >= 0:
                by_tid.setdefault(tid, []).append(lid)
        self.track_link: dict[int, int] = {}
        for tid, lids in sorted(by_tid.items()):
            keep = max(lids, key=lambda lid: (depth(self.group_of[lid]), lid))
            if len(lids) > 1:
                self.notes.append(
                    f"track link {tid}: marked on links {sorted(lids)}; kept on link {keep} (deepest), "
                    "dropped from the others"
                )
            self.track_link[tid] = keep

    # ------------------------------------------------------------------ structure
    def _spanning_forest(self, joints: dict, links: set[int]) -> None:
        uf = _UnionFind()
        self.tree: list[_Joint] = []
        self.loops: list[_Joint] = []
        # Hinges and slides first: a weld loop closure must come after the tree joints on
        # its cycle (only a cycle through a tree ball joint then comes back as connect +
        # weld instead of ball + weld); connect loop closures are ball tokens with IDs after
        # the tree's balls.
        for k in ("dyna", "fixed", "ball"):
            for j in joints[k]:
                (self.tree if uf.union(j.a, j.b) else self.loops).append(j)
        # Rigid groups: fixed tree joints not touching the ground.
        groups = _UnionFind()
        for lid in links:
            groups.find(lid)
        for j in self.tree:
            if j.kind == "fixed" and j.a != -1:
                groups.union(j.a, j.b)
        self.members: dict[int, list[int]] = {}
        for lid in sorted(links):
            self.members.setdefault(groups.find(lid), []).append(lid)
        self.group_of = {lid: groups.find(lid) for lid in links}

    def _grow_tree(self) -> None:
        """Parent joint, children and anchor link of every group: BFS from the ground, then
        from the free links, then from groups attached to nothing (welded to the world)."""
        lk = self.lk
        adj: dict[int, list[_Joint]] = {}
        for j in self.tree:
            if not (j.kind == "fixed" and j.a != -1):
                for end in (j.a, j.b):
                    adj.setdefault(-1 if end == -1 else self.group_of[end], []).append(j)
        self.free_of = {int(lk["ids"][r, 0]): int(lk["free_id"][r]) for r in self.row.values() if lk["free_id"][r] >= 0}
        self.parent_edge: dict[int, _Joint | None] = {-1: None}
        self.children: dict[int, list[int]] = {}
        self.anchor: dict[int, int] = {}
        self.roots: list[int] = []

        def bfs(root: int) -> None:
            queue = [root]
            while queue:
                g = queue.pop(0)
                for j in adj.get(g, []):
                    near_a = (j.a == -1 and g == -1) or (j.a != -1 and self.group_of[j.a] == g)
                    other = j.b if near_a else j.a
                    og = -1 if other == -1 else self.group_of[other]
                    if og == -1 or og in self.parent_edge:
                        continue
                    self.parent_edge[og] = j
                    self.anchor[og] = other
                    self.children.setdefault(g, []).append(og)
                    queue.append(og)

        bfs(-1)
        for lid in sorted(self.free_of, key=lambda lid: self.free_of[lid]):
            g = self.group_of[lid]
            if g in self.parent_edge:
                self.notes.append(f"link {lid}: free link already attached to the tree; its free joint is dropped")
                continue
            self.parent_edge[g], self.anchor[g] = None, lid
            self.roots.append(g)
            bfs(g)
        self.free_roots = set(self.roots)
        for g in sorted(self.members, key=lambda g: self.members[g][0]):
            if g not in self.parent_edge:
                self.notes.append(f"links {self.members[g]} attach to nothing; welded to the world at the origin")
                self.parent_edge[g], self.anchor[g] = None, self.members[g][0]
                self.roots.append(g)
                bfs(g)

    def _place_links(self) -> None:
        """Each link's pose in its group's body frame: the anchor link's frame, or for a
        group hanging from a ball joint, the joint frame (so the ball's quaternion means
        what it meant in the tokenized model)."""
        fixed_adj: dict[int, list[_Joint]] = {}
        for j in self.tree:
            if j.kind == "fixed" and j.a != -1:
                fixed_adj.setdefault(j.a, []).append(j)
                fixed_adj.setdefault(j.b, []).append(j)
        self.in_body: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for g in self.members:
            a = self.anchor[g]
            pe = self.parent_edge.get(g)
            self.in_body[a] = (
                (pe.tb if a == pe.b else pe.ta) if pe is not None and pe.kind == "ball" else (np.eye(3), np.zeros(3))
            )
            stack = [a]
            while stack:
                lid = stack.pop()
                for j in fixed_adj.get(lid, []):
                    o = j.b if j.a == lid else j.a
                    if o in self.in_body:
                        continue
                    t_l, t_o = (j.ta, j.tb) if j.a == lid else (j.tb, j.ta)
                    r, p = compose(*self.in_body[lid], *invert(*t_l))
                    self.in_body[o] = compose(r, p, *t_o)
                    stack.append(o)

    # ------------------------------------------------------------------ geometry of the tree
    def group_inertial(self, g: int) -> tuple[float, np.ndarray, np.ndarray]:
        """Mass, centre of mass and inertia about it of a group, in its body frame."""
        lk = self.lk
        parts = []
        for lid in self.members[g]:
            row = self.row[lid]
            m = float(lk["mass"][row, 0])
            if m <= 0:
                continue
            rb, pb = self.in_body[lid]
            mom = lk["inertia"][row]
            i1, i2, i3 = (float(x) for x in mom)
            tol = 1e-9 * (i1 + i2 + i3)
            if min(i1, i2, i3) < 0 or i1 + i2 < i3 - tol or i1 + i3 < i2 - tol or i2 + i3 < i1 - tol:
                self.notes.append(f"link {lid}: principal moments ({_fmt(mom)}) repaired")
                mom = repair_moments(mom)
            ri = rb @ lk["irot"][row]
            parts.append((m, rb @ lk["ipos"][row] + pb, ri @ np.diag(mom) @ ri.T))
        total = sum(m for m, _, _ in parts)
        if total <= 0:
            return 0.0, np.zeros(3), np.zeros((3, 3))
        com = sum(m * c for m, c, _ in parts) / total
        inertia = sum(i + m * ((c - com) @ (c - com) * np.eye(3) - np.outer(c - com, c - com)) for m, c, i in parts)
        return total, com, inertia

    def foldable(self, g: int) -> bool:
        """A massless geometry-less group between two hinge / slide joints."""
        pe = self.parent_edge.get(g)
        kids = self.children.get(g, [])
        if pe is None or pe.kind != "dyna" or len(kids) != 1 or self.parent_edge[kids[0]].kind != "dyna":
            return False
        lk = self.lk
        return all(
            lk["geom_type"][r] == 0 and lk["mass"][r, 0] <= MASSLESS and lk["track_id"][r] < 0 and lk["free_id"][r] < 0
            for r in (self.row[lid] for lid in self.members[g])
        )

    def joint_in_body(self, g: int) -> dict:
        """The joint of a group's parent edge in the group's body frame. Its coordinate moves
        the higher link ID relative to the lower, so the axis flips when the tree hangs the
        other way."""
        j, a = self.parent_edge[g], self.anchor[g]
        t_anchor, other = (j.tb, j.a) if a == j.b else (j.ta, j.b)
        jr, jp = compose(*self.in_body[a], *invert(*t_anchor))
        return {"joint": j, "pos": jp, "axis": (1.0 if a > other else -1.0) * jr[:, 2]}

    def body_pose(self, g: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose of group g's body frame in its parent group's body frame (or the world)."""
        j, a = self.parent_edge[g], self.anchor[g]
        other = j.a if a == j.b else j.b
        t_other, t_anchor = (j.ta, j.tb) if a == j.b else (j.tb, j.ta)
        base = (np.eye(3), np.zeros(3)) if other == -1 else self.in_body[other]
        r, p = compose(*compose(*base, *invert(*t_other)), *t_anchor)  # anchor link in the parent body
        return compose(r, p, *invert(*self.in_body[a]))

    # ------------------------------------------------------------------ MJCF
    def _loop_closures(self) -> tuple[list[str], dict[int, list[str]]]:
        """Equality lines and the sites they need per group. Site-based constraints: each side
        anchors at its own half's joint frame, exactly as the tokens say (a body-based connect
        would re-derive the second anchor from qpos0)."""
        eq_lines: list[str] = []
        sites: dict[int, list[str]] = {}
        solref = _fmt(self.config.connect_solref)
        for j in self.loops:
            if j.a == -1:
                self.notes.append(f"{j.kind} joint {j.jid}: a second attachment to the ground; dropped")
                continue
            ga, gb = self.group_of[j.a], self.group_of[j.b]
            if ga == gb:
                self.notes.append(f"{j.kind} joint {j.jid}: both links in one rigid body; dropped")
                continue
            if j.kind == "dyna":
                self.notes.append(f"dyna joint {j.jid} closes a loop; written as a connect (point) constraint")
            name = f"loop_{j.kind}{j.jid}"
            for g, link, t, side in ((ga, j.a, j.ta, "a"), (gb, j.b, j.tb, "b")):
                r, p = compose(*self.in_body[link], *invert(*t))
                sites.setdefault(g, []).append(f'<site name="{name}_{side}"{_pose(r, p)} size="0.005"/>')
            kind = "weld" if j.kind == "fixed" else "connect"
            eq_lines.append(f'    <{kind} name="{name}" site1="{name}_a" site2="{name}_b" solref="{solref}"/>')
        return eq_lines, sites

    def _emit_children(self, g: int, depth: int) -> None:
        for ch in sorted(self.children.get(g, []), key=lambda c: self.anchor[c]):
            pose = self.body_pose(ch)
            joints = [] if self.parent_edge[ch].kind == "fixed" else [self.joint_in_body(ch)]
            # Fold massless intermediate groups into their child (a multi-joint body).
            while joints and self.foldable(ch):
                gc = self.children[ch][0]
                t_gc = self.body_pose(gc)
                ir, ip = invert(*t_gc)
                joints = [{**ji, "pos": ir @ ji["pos"] + ip, "axis": ir @ ji["axis"]} for ji in joints] + [
                    self.joint_in_body(gc)
                ]
                pose = compose(*pose, *t_gc)
                ch = gc
            self._emit(ch, pose, joints, depth)

    def _emit(self, g: int, pose, joints: list[dict], depth: int) -> None:
        lk, pad, name = self.lk, "  " * depth, f"b{self.anchor[g]}"
        self.lines.append(f'{pad}<body name="{name}"{_pose(*pose)}>')
        if g in self.free_roots:
            free = self._unique("joint", f"free{self.free_of[self.anchor[g]]}")
            self.lines.append(f'{pad}  <freejoint name="{free}"/>')
        for ji in joints:
            j = ji["joint"]
            jname = self._unique("joint", f"ball{j.jid}" if j.kind == "ball" else f"j{j.jid}")
            self.lines.append(pad + "  " + _joint_xml(ji, self.notes, jname))
            if j.kind == "dyna":
                self.actuated[j.jid] = jname
        m, com, inertia = self.group_inertial(g)
        moving = bool(joints) or g in self.free_roots
        if m <= 1e-12 and moving:
            self.notes.append(f"body {name}: moves but decoded massless; given {MIN_MOVING_MASS} kg")
            m, com, inertia = MIN_MOVING_MASS, np.zeros(3), MIN_MOVING_INERTIA * np.eye(3)
        if m > 0:
            rot, mom = _principal(inertia)
            if moving and mom.max() < MIN_MOVING_INERTIA:
                self.notes.append(f"body {name}: moves with near-zero inertia; moments raised to {MIN_MOVING_INERTIA}")
                mom = np.maximum(mom, MIN_MOVING_INERTIA)
            mom = repair_moments(mom)
            self.lines.append(
                f'{pad}  <inertial pos="{_fmt(com)}" quat="{_fmt(_quat(rot))}" mass="{_fmt(m)}" '
                f'diaginertia="{_fmt(mom)}"/>'
            )
        for lid in self.members[g]:
            row = self.row[lid]
            code = int(lk["geom_type"][row])
            rb, pb = self.in_body[lid]
            if code > 0:
                self.lines.append(pad + "  " + _geom_xml(lid, code, lk, row, rb, pb, self.config, self.notes))
            tid = int(lk["track_id"][row])
            if tid >= 0 and self.track_link.get(tid) == lid:
                self.lines.append(f'{pad}  <site name="ee_{tid}"{_pose(rb, pb)} size="0.01"/>')
        self.lines += [f"{pad}  {site}" for site in self.loop_sites.get(g, [])]
        self._emit_children(g, depth + 1)
        self.lines.append(f"{pad}</body>")

    def _unique(self, kind: str, name: str) -> str:
        """`name`, or `name` with a suffix if an element of `kind` has it: noisy tokens may
        repeat an ID (several free links with free ID 0), and MuJoCo rejects two joints (or
        actuators) of one name."""
        taken = self.names.setdefault(kind, set())
        unique, k = name, 1
        while unique in taken:
            unique, k = f"{name}_{k}", k + 1
        taken.add(unique)
        return unique

    def mjcf(self) -> tuple[str, list[str]]:
        config, lk = self.config, self.lk
        eq_lines, self.loop_sites = self._loop_closures()
        self.lines: list[str] = []
        self.actuated: dict[int, str] = {}
        self.names: dict[str, set[str]] = {}
        self._emit_children(-1, 2)
        for g in self.roots:
            self._emit(g, (np.eye(3), np.zeros(3)), [], 2)
        act_lines = []
        if "actuator" in self.dec:
            ad = self.dec["actuator"]
            for r in np.argsort(ad["ids"][:, 0], kind="stable"):
                aid, jid = int(ad["ids"][r, 0]), int(ad["joint_id"][r])
                if jid not in self.actuated:
                    self.notes.append(f"actuator {aid}: dynamic joint {jid} is not in the tree; dropped")
                    continue
                name = self._unique("actuator", f"a{aid}")
                act_lines.append("    " + _actuator_xml(aid, name, self.actuated[jid], ad, r, self.notes))
        any_contact = bool(np.any(lk["contact"][list(self.row.values())] > 0))
        floor = any_contact if config.floor is None else config.floor
        flag = "" if config.contacts else '\n    <flag contact="disable"/>'
        out = [
            f'<mujoco model="{config.model}">',
            '  <compiler angle="radian" autolimits="true" inertiafromgeom="false"/>',
            f'  <option timestep="{config.timestep!r}" integrator="{config.integrator}" '
            f'gravity="{_fmt(config.gravity)}">{flag}',
            "  </option>",
            "  <worldbody>",
        ]
        if floor:
            out.append(
                '    <geom name="floor" type="plane" size="0 0 0.05" contype="1" conaffinity="1" rgba="0.85 '
                '0.85 0.8 1"/>'
            )
        out += self.lines
        out.append("  </worldbody>")
        if act_lines:
            out += ["  <actuator>", *act_lines, "  </actuator>"]
        if eq_lines:
            out += ["  <equality>", *eq_lines, "  </equality>"]
        out.append("</mujoco>\n")
        return "\n".join(out), self.notes


class _NoRobot(ValueError):
    pass


def _joint_xml(ji: dict, notes: list[str], name: str) -> str:
    j: _Joint = ji["joint"]
    prm = j.params
    if j.kind == "ball":
        jtype = "ball"
    else:
        t = prm["type"]
        if not 0 <= t < len(JOINT_TYPES):
            notes.append(f"dyna joint {j.jid}: type code {t} is not a joint type; read as hinge")
            t = 0
        jtype = JOINT_TYPES[t]
    s = f'<joint name="{name}" type="{jtype}"'
    if np.linalg.norm(ji["pos"]) > 0:
        s += f' pos="{_fmt(ji["pos"])}"'
    if j.kind != "ball":
        axis = ji["axis"] / max(np.linalg.norm(ji["axis"]), 1e-12)
        s += f' axis="{_fmt(axis)}"'
    lo, hi = sorted(float(x) for x in prm["range"])
    if j.kind == "ball":
        hi = max(abs(lo), abs(hi))
        if hi > 1e-9:
            s += f' range="0 {_fmt(hi)}"'
    elif hi - lo > 1e-9:
        s += f' range="{_fmt([lo, hi])}"'
    for k in ("armature", "damping", "frictionloss", "stiffness"):
        v = float(prm[k][0])
        if v > 0:
            s += f' {k}="{_fmt(v)}"'
    if j.kind != "ball":
        ref, springref = float(prm["ref"][0]), float(prm["springref"][0])
        if ref != 0:
            s += f' ref="{_fmt(ref)}"'
        if springref != 0:
            s += f' springref="{_fmt(springref)}"'
    return s + "/>"


def _geom_xml(lid: int, code: int, lk: dict, row: int, rb, pb, config: DetokenizeConfig, notes: list[str]) -> str:
    if code >= len(GEOM_TYPES):
        notes.append(f"link {lid}: geometry code {code} is not a geometry type; written as a box")
        code = GEOM_TYPES.index("box")
    size = np.asarray(lk["size"][row], dtype=np.float64)[: SIZE_DIMS[code]]
    if np.any(size < MIN_SIZE):
        notes.append(f"link {lid}: size ({_fmt(size)}) raised to >= {MIN_SIZE} m")
        size = np.maximum(size, MIN_SIZE)
    contact = int(lk["contact"][row])
    if contact >= len(CONTACT_CONDIMS):
        notes.append(f"link {lid}: contact code {contact} is not a condim; contacts off")
        contact = 0
    friction = np.maximum(np.asarray(lk["friction"][row], dtype=np.float64), 0.0)
    rgba = np.clip(np.asarray(lk["rgba"][row], dtype=np.float64), 0.0, 1.0)
    s = f'<geom name="g{lid}" type="{GEOM_TYPES[code]}" size="{_fmt(size)}"{_pose(rb, pb)}'
    if contact == 0:
        s += ' contype="0" conaffinity="0"'
    else:
        s += f' contype="1" conaffinity="{1 if config.self_collision else 0}" condim="{CONTACT_CONDIMS[contact]}"'
    return s + f' friction="{_fmt(friction)}" rgba="{_fmt(rgba)}"/>'


def _actuator_xml(aid: int, name: str, joint: str, ad: dict, r: int, notes: list[str]) -> str:
    t = int(ad["type"][r])
    if not 0 <= t < len(ACTUATOR_TYPES):
        notes.append(f"actuator {aid}: type code {t} is not an actuator type; read as position")
        t = 0
    kind = ACTUATOR_TYPES[t]
    s = f'<{"motor" if kind == "motor" else kind} name="{name}" joint="{joint}"'
    kp, kv, gear = float(ad["kp"][r, 0]), float(ad["kv"][r, 0]), float(ad["gear"][r, 0])
    if kind == "position":
        s += f' kp="{_fmt(kp)}"'
        if kv > 0:
            s += f' kv="{_fmt(kv)}"'
    elif kind == "velocity":
        s += f' kv="{_fmt(kv)}"'
    if gear != 1.0:
        s += f' gear="{_fmt(gear)}"'
    for attr in ("ctrlrange", "forcerange"):
        lo, hi = sorted(float(x) for x in ad[attr][r])
        if hi - lo > 1e-9:
            s += f' {attr}="{_fmt([lo, hi])}"'
    return s + "/>"


# ------------------------------------------------------------------------------ public
def detokenize(tokens: TokenBatch, config: DetokenizeConfig = DetokenizeConfig()) -> list[DetokenizeResult]:
    """MJCF of every robot in `tokens`, compiled with MuJoCo; never raises for bad tokens."""
    check_version(tokens.version, "token batch")
    out = []
    for i in range(len(tokens)):
        try:
            dec = decode_robot(tokens, i)
            xml, notes = robot_to_mjcf(dec, config)
        except _NoRobot as e:
            out.append(DetokenizeResult("", None, f"robot {i}: {e}", []))
            continue
        except Exception as e:  # the contract is to report, not to crash, on any token content
            logger.debug("detokenize robot %d failed", i, exc_info=True)
            out.append(DetokenizeResult("", None, f"robot {i}: decoding failed: {type(e).__name__}: {e}", []))
            continue
        try:
            model = mujoco.MjModel.from_xml_string(xml)
            out.append(DetokenizeResult(xml, model, None, notes))
        except ValueError as e:
            out.append(DetokenizeResult(xml, None, f"robot {i}: MuJoCo rejected the MJCF: {e}", notes))
    return out
