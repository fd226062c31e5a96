"""Batched articulated trees: the Warp-side model that tt's kernels simulate.

A `TreeModel` holds W worlds of one topology: a fixed-base kinematic tree of hinge and
slide joints without contacts, built from MuJoCo models (the one source of truth for a
robot) or from fields a design space computes the way MuJoCo's compiler would (`TreeFields`,
tested against MuJoCo's compile). Everything that may differ between designs of one topology (link offsets, mount
pose, joint axes, masses, gains) is a per-world array; the topology itself (which body
hangs from which, joint types, which joints the actuators drive, which bodies carry the
end-effector sites) is a `Topology`, and kernels are compiled once per topology with it
compiled in as constants (short loops unrolled into straight-line code, `MODULE_OPTIONS`).

The per-world arrays are one flat `@wp.struct`, `TreeArrays`: every tree kernel and
`wp.func` takes it as its ``model`` parameter (passed in, never returned from a
`wp.func`, a case whose adjoints Warp has had bugs in), and gradients under `wp.Tape`
reach its members' ``.grad``. It is the one list of the model's fields: adding one is an edit of
`TreeArrays` and of `tree_fields`, which reads it from MuJoCo (`tree_model` uploads any
`TreeFields`; a space that computes its own must add it too); `ENTITY_FIELDS` (the fields a
design's continuous choices may change, which `tt.guidance.simgrad` differentiates) is
derived from it. `Kinematics64` holds float64 copies of the kinematic fields for the
start posture.

MuJoCo lets one body carry several joints, each expressed in the frame left by the joints
before it. tt splits such a body into a chain of bodies with one joint each (the first
keeps the body's offset, the last its mass and sites), which is the same kinematics, so
every tree body here has at most one joint and dof i belongs to exactly one body.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass, field, replace
from typing import Sequence

import mujoco
import numpy as np
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.rotations import quat_to_mat

#: MuJoCo joint types that tt's kernels simulate.
JOINT_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
JOINT_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)

#: Stand-in for an unlimited range: float32 keeps it finite, so clamps and comparisons
#: against it never produce inf - inf.
UNLIMITED = 1.0e10


@dataclass(frozen=True)
class Topology:
    """The structure shared by all worlds of a `TreeModel`; kernels are compiled per topology.

    Tree bodies are numbered 0 (world) .. body_count - 1, parents before children.

    body_parent: parent tree body of each body, (body_count,); the world's entry is 0.
    body_dof: dof (= joint) index of each body, or -1 for a body welded to its parent, (body_count,).
    dof_type: MuJoCo joint type of each dof, `JOINT_HINGE` or `JOINT_SLIDE`, (dof_count,).
    actuator_dof: dof driven by each actuator, (actuator_count,).
    ee_body: tree body carrying each end-effector site, (ee_count,).
    """

    body_parent: tuple[int, ...]
    body_dof: tuple[int, ...]
    dof_type: tuple[int, ...]
    actuator_dof: tuple[int, ...]
    ee_body: tuple[int, ...]

    @property
    def body_count(self) -> int:
        return len(self.body_parent)

    @property
    def dof_count(self) -> int:
        return len(self.dof_type)

    @property
    def actuator_count(self) -> int:
        return len(self.actuator_dof)

    @property
    def ee_count(self) -> int:
        return len(self.ee_body)

    @property
    def dof_body(self) -> tuple[int, ...]:
        """Tree body of each dof, (dof_count,)."""
        out = [0] * self.dof_count
        for b, d in enumerate(self.body_dof):
            if d >= 0:
                out[d] = b
        return tuple(out)

    @property
    def dof_parent(self) -> tuple[int, ...]:
        """Nearest ancestor dof of each dof (-1 at a root), (dof_count,)."""
        out = []
        for b in self.dof_body:
            b = self.body_parent[b]
            while b != 0 and self.body_dof[b] < 0:
                b = self.body_parent[b]
            out.append(self.body_dof[b] if b != 0 else -1)
        return tuple(out)

    def body_path(self, body: int) -> tuple[int, ...]:
        """Bodies from `body` up to (excluding) the world, deepest first."""
        path = []
        while body != 0:
            path.append(body)
            body = self.body_parent[body]
        return tuple(path)

    def dof_support(self, dof: int) -> tuple[int, ...]:
        """Dofs whose motion moves dof `dof`'s body: itself and its ancestors, ascending."""
        return self.body_support(self.dof_body[dof])

    def body_support(self, body: int) -> tuple[int, ...]:
        """Dofs whose motion moves `body` (the dofs on its path to the world), ascending."""
        return tuple(sorted(self.body_dof[b] for b in self.body_path(body) if self.body_dof[b] >= 0))

    @property
    def digest(self) -> str:
        """Short stable name of the topology (compiled kernels are cached under it)."""
        text = repr((self.body_parent, self.body_dof, self.dof_type, self.actuator_dof, self.ee_body))
        return hashlib.sha1(text.encode()).hexdigest()[:10]


def topology_key(model: mujoco.MjModel, ee_sites: Sequence[str]) -> tuple:
    """What must match for two MuJoCo models to share compiled kernels.

    (body_parentid, jnt_type, jnt_bodyid, actuator joints, end-effector site bodies).
    """
    ee_bodies = tuple(int(model.site_bodyid[_site_id(model, s)]) for s in ee_sites)
    return (
        tuple(int(p) for p in model.body_parentid),
        tuple(int(t) for t in model.jnt_type),
        tuple(int(b) for b in model.jnt_bodyid),
        tuple(int(j) for j in model.actuator_trnid[:, 0]),
        ee_bodies,
    )


def _site_id(model: mujoco.MjModel, name: str) -> int:
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
    if sid < 0:
        names = [model.site(i).name for i in range(model.nsite)]
        raise TTError(f"end-effector site {name!r} is not in the model; its sites are {names}")
    return sid


def check_supported(model: mujoco.MjModel, index: int = 0) -> None:
    """Raise ValueError naming the first feature of `model` that tt's tree kernels lack."""
    where = f"model {index}"
    types = set(int(t) for t in model.jnt_type)
    if not types <= {JOINT_HINGE, JOINT_SLIDE}:
        raise TTError(
            f"{where}: jnt_type {sorted(types)}; the warp tree kernels support hinge (3) and slide (2) joints only"
        )
    if model.nq != model.nv or model.nv != model.njnt:
        raise TTError(f"{where}: nq={model.nq}, nv={model.nv}, njnt={model.njnt} must be equal for a hinge/slide tree")
    contact_disabled = bool(model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT)
    collides = np.any((model.geom_contype[:, None] & model.geom_conaffinity[None, :]) != 0) or model.npair > 0
    if collides and not contact_disabled:
        raise TTError(
            f"{where} has contacts (geom contype/conaffinity or contact pairs); the warp backend is contact-free"
        )
    if int(model.opt.integrator) != int(mujoco.mjtIntegrator.mjINT_EULER):
        raise TTError(
            f"{where}: integrator {mujoco.mjtIntegrator(model.opt.integrator).name}; only Euler is replicated"
        )
    for name, count in (("neq", model.neq), ("ntendon", model.ntendon), ("na", model.na)):
        if count:
            raise TTError(
                f"{where}: {name} = {count}; equality constraints, tendons and actuator activations are not supported"
            )
    if np.any(model.dof_frictionloss != 0):
        raise TTError(f"{where}: dof_frictionloss is nonzero; friction loss is a constraint the tree kernels lack")
    if np.any(model.jnt_actfrclimited):
        raise TTError(f"{where}: jnt_actfrclimited is set; joint-level actuator force limits are not supported")
    if np.any(model.jnt_margin != 0):
        raise TTError(f"{where}: jnt_margin is nonzero; joint limits with margins are not supported")
    if (
        np.any(model.body_gravcomp != 0)
        and np.any(model.jnt_actgravcomp)
        and model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_ACTUATION
    ):
        raise TTError(
            f"{where}: gravity compensation through actuators (actuatorgravcomp) with the actuation flag "
            "disabled; MuJoCo then drops those joints' compensation, which the tree kernels do not replicate"
        )
    for i in range(model.nu):
        if int(model.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            raise TTError(
                f"{where}: actuator {i} transmission {model.actuator_trntype[i]}; only joint transmissions "
                "are supported"
            )
        if int(model.actuator_dyntype[i]) != int(mujoco.mjtDyn.mjDYN_NONE):
            raise TTError(f"{where}: actuator {i} has activation dynamics; only stateless actuators are supported")
        if int(model.actuator_gaintype[i]) != int(mujoco.mjtGain.mjGAIN_FIXED) or int(
            model.actuator_biastype[i]
        ) not in (int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE)):
            raise TTError(f"{where}: actuator {i} gain/bias type; only fixed gain with affine or no bias is supported")


def _gravcomp_enabled(model: mujoco.MjModel) -> bool:
    """Whether MuJoCo applies `model`'s body_gravcomp: gravity on, and not both the spring
    and the damper flag disabled (MuJoCo's passive forces, gravity compensation among them,
    are skipped then)."""
    D = mujoco.mjtDisableBit
    off = int(model.opt.disableflags)
    return not (off & D.mjDSBL_GRAVITY) and not ((off & D.mjDSBL_SPRING) and (off & D.mjDSBL_DAMPER))


@dataclass
class _Split:
    """Tree bodies of one MuJoCo model (see the module docstring)."""

    parent: list[int]
    dof: list[int]
    head: list[int]  # MuJoCo body -> first tree body (carries the body offset)
    tail: list[int]  # MuJoCo body -> last tree body (carries mass, children, sites)


def _split(model: mujoco.MjModel) -> _Split:
    parent, dof = [0], [-1]
    head, tail = [0], [0]
    for b in range(1, model.nbody):
        up = tail[model.body_parentid[b]]
        n = int(model.body_jntnum[b])
        adr = int(model.body_jntadr[b])
        first = len(parent)
        if n == 0:
            parent.append(up)
            dof.append(-1)
        for k in range(n):
            parent.append(up if k == 0 else len(parent) - 1)
            dof.append(int(model.jnt_dofadr[adr + k]))
        head.append(first)
        tail.append(len(parent) - 1)
    return _Split(parent, dof, head, tail)


def topology_of(model: mujoco.MjModel, ee_sites: Sequence[str]) -> Topology:
    """The `Topology` of one MuJoCo model."""
    split = _split(model)
    return Topology(
        body_parent=tuple(split.parent),
        body_dof=tuple(split.dof),
        dof_type=tuple(int(t) for t in model.jnt_type),
        actuator_dof=tuple(int(model.jnt_dofadr[j]) for j in model.actuator_trnid[:, 0]),
        ee_body=tuple(split.tail[model.site_bodyid[_site_id(model, s)]] for s in ee_sites),
    )


#: MuJoCo's bounds on constraint impedance and its smallest positive value.
MJ_MINIMP, MJ_MAXIMP, MJ_MINVAL = 0.0001, 0.9999, 1e-15


def _limit_kb(m: mujoco.MjModel) -> np.ndarray:
    """(k, b) of each joint's limit constraint: aref = -b vel - k imp pos (MuJoCo's solref)."""
    out = np.zeros((m.njnt, 2))
    refsafe = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    for j in range(m.njnt):
        timeconst, dampratio = m.jnt_solref[j]
        dmax = float(np.clip(m.jnt_solimp[j, 1], MJ_MINIMP, MJ_MAXIMP))
        if refsafe and timeconst > 0:
            timeconst = max(timeconst, 2.0 * m.opt.timestep)
        if timeconst <= 0:
            k = -timeconst / max(MJ_MINVAL, dmax * dmax)
        else:
            k = 1.0 / max(MJ_MINVAL, dmax * dmax * timeconst * timeconst * dampratio * dampratio)
        b = -dampratio / max(MJ_MINVAL, dmax) if dampratio <= 0 else 2.0 / max(MJ_MINVAL, dmax * timeconst)
        out[j] = k, b
    return out


@wp.struct
class TreeArrays:
    """The per-world arrays of a `TreeModel` (float32), one flat struct that every tree
    kernel takes as its ``model`` parameter; the one list of the model's fields.

    Per-world fields have a leading dimension of 1 or W; kernels read entry
    ``worldid % field.shape[0]``. Quaternions are (w, x, y, z) vec4, as in MuJoCo and tt's
    motions and episodes (kernels convert to Warp's (x, y, z, w) internally). Shapes use
    NB = topology.body_count (tree bodies, world included), NV = topology.dof_count,
    NU = topology.actuator_count, NE = topology.ee_count.

    body_pos: body frame position in the parent frame [m], (W, NB) vec3.
    body_quat: body frame orientation in the parent frame, (W, NB) vec4.
    body_mass: body mass [kg], (W, NB) float.
    body_ipos: center of mass in the body frame [m], (W, NB) vec3.
    body_iquat: principal inertia frame in the body frame, (W, NB) vec4.
    body_inertia: principal moments of inertia about the center of mass [kg m^2], (W, NB) vec3.
    body_gravcomp: gravity compensation, the share of the body's weight cancelled by an
        upward force at its center of mass (MuJoCo's body_gravcomp, a passive force; 0 where
        the gravity flag or both the spring and damper flags are disabled), (W, NB) float.
    dof_axis: joint axis in the body frame (unit), (W, NV) vec3.
    dof_pos: joint anchor in the body frame [m], (W, NV) vec3.
    dof_ref: reference position qpos0 (hinge angle or slide offset at which the body sits
        at its offset) [rad or m], (W, NV) float.
    dof_armature: rotor inertia added to the mass matrix diagonal [kg m^2 or kg], (W, NV) float.
    dof_damping: viscous joint damping [N m s/rad or N s/m], (W, NV) float.
    dof_stiffness: joint spring stiffness [N m/rad or N/m], (W, NV) float.
    dof_springref: spring rest position [rad or m], (W, NV) float.
    dof_range: joint limits (lower, upper) [rad or m], +-UNLIMITED when unlimited, (W, NV) vec2.
    dof_limit_kb: limit constraint reference stiffness k [1/s^2] and damping b [1/s] from
        MuJoCo's solref (timeconst clamped to 2 timesteps, as refsafe does), (W, NV) vec2.
    dof_solimp: limit constraint impedance (dmin, dmax, width [m or rad], midpoint, power), (W, NV, 5) float.
    dof_invweight0: MuJoCo's inverse inertia of the dof at qpos0 (limit regularizer scale), (W, NV) float.
    act_gain: actuator gain (force per unit ctrl), (W, NU) float.
    act_bias: affine bias (b0, b1 per unit length, b2 per unit velocity), (W, NU) vec3.
    act_gear: transmission gear (length = gear * q), (W, NU) float.
    act_ctrlrange: ctrl clamp (lower, upper), +-UNLIMITED when not clamped, (W, NU) vec2.
    act_forcerange: force clamp (lower, upper) [N m or N], +-UNLIMITED when unlimited, (W, NU) vec2.
    ee_pos: end-effector site position in its body frame [m], (W, NE) vec3.
    ee_quat: end-effector site orientation in its body frame, (W, NE) vec4.
    gravity: gravitational acceleration [m/s^2], (W,) vec3.
    timestep: physics timestep [s], (W,) float.
    limit_enabled: 1 when joint-limit constraints are simulated (MuJoCo's limit flag), (W,) int32.
    limit_sweeps: projected Gauss-Seidel sweeps of the joint-limit force solve (one is exact
        for a single active limit), (1,) int32.

    Gradients (`wp.Tape`) flow to the members' ``.grad`` arrays: give the arrays
    ``requires_grad`` before assigning them to the struct (`tree_arrays`).
    """

    body_pos: wp.array2d(dtype=wp.vec3)
    body_quat: wp.array2d(dtype=wp.vec4)
    body_mass: wp.array2d(dtype=float)
    body_ipos: wp.array2d(dtype=wp.vec3)
    body_iquat: wp.array2d(dtype=wp.vec4)
    body_inertia: wp.array2d(dtype=wp.vec3)
    body_gravcomp: wp.array2d(dtype=float)
    dof_axis: wp.array2d(dtype=wp.vec3)
    dof_pos: wp.array2d(dtype=wp.vec3)
    dof_ref: wp.array2d(dtype=float)
    dof_armature: wp.array2d(dtype=float)
    dof_damping: wp.array2d(dtype=float)
    dof_stiffness: wp.array2d(dtype=float)
    dof_springref: wp.array2d(dtype=float)
    dof_range: wp.array2d(dtype=wp.vec2)
    dof_limit_kb: wp.array2d(dtype=wp.vec2)
    dof_solimp: wp.array3d(dtype=float)
    dof_invweight0: wp.array2d(dtype=float)
    act_gain: wp.array2d(dtype=float)
    act_bias: wp.array2d(dtype=wp.vec3)
    act_gear: wp.array2d(dtype=float)
    act_ctrlrange: wp.array2d(dtype=wp.vec2)
    act_forcerange: wp.array2d(dtype=wp.vec2)
    ee_pos: wp.array2d(dtype=wp.vec3)
    ee_quat: wp.array2d(dtype=wp.vec4)
    gravity: wp.array(dtype=wp.vec3)
    timestep: wp.array(dtype=float)
    limit_enabled: wp.array(dtype=wp.int32)
    limit_sweeps: wp.array(dtype=wp.int32)


@wp.struct
class Kinematics64:
    """float64 copies of the kinematic fields of `TreeArrays` (same names, meanings and
    shapes), built from the MuJoCo models rather than from the float32 fields: the start
    posture's IK iteration amplifies round-off, so it runs on these."""

    body_pos: wp.array2d(dtype=wp.vec3d)
    body_quat: wp.array2d(dtype=wp.vec4d)
    dof_axis: wp.array2d(dtype=wp.vec3d)
    dof_pos: wp.array2d(dtype=wp.vec3d)
    dof_ref: wp.array2d(dtype=wp.float64)
    dof_range: wp.array2d(dtype=wp.vec2d)
    ee_pos: wp.array2d(dtype=wp.vec3d)
    ee_quat: wp.array2d(dtype=wp.vec4d)


#: Names of the `TreeArrays` members, in declaration order.
TREE_FIELDS: tuple[str, ...] = tuple(TreeArrays.vars)
#: The members that hold one value per body, dof, actuator or end effector (the fields a
#: design's continuous choices may change); the rest are per-world options.
ENTITY_FIELDS: tuple[str, ...] = tuple(n for n, v in TreeArrays.vars.items() if v.type.ndim >= 2)
#: Names of the `Kinematics64` members.
KINEMATICS64_FIELDS: tuple[str, ...] = tuple(Kinematics64.vars)


def _struct(cls, fields: dict, names: Sequence[str]):
    missing = sorted(set(names) - set(fields))
    extra = sorted(set(fields) - set(names))
    if missing or extra:
        raise ValueError(f"{cls.key} fields: missing {missing}, unknown {extra}")
    out = cls()
    for name in names:
        setattr(out, name, fields[name])
    return out


def tree_arrays(**fields: wp.array) -> TreeArrays:
    """A `TreeArrays` from one array per member (every member, no others)."""
    return _struct(TreeArrays, fields, TREE_FIELDS)


def kinematics64(**fields: wp.array) -> Kinematics64:
    """A `Kinematics64` from one array per member (every member, no others)."""
    return _struct(Kinematics64, fields, KINEMATICS64_FIELDS)


@dataclass
class TreeModel:
    """W worlds of one `Topology`: the topology, the kernels' arrays and host-side facts.

    topology: the shared structure (see `Topology`).
    arrays: the per-world float32 model fields (`TreeArrays`, documented there); kernels
        take it as one parameter.
    kinematics64: float64 copies of the kinematic fields for the start posture (`Kinematics64`).
    device: the Warp device the arrays live on.
    timestep_host: host copies of the timesteps [s], (W,), for launch planning without a
        device round trip.
    """

    topology: Topology
    arrays: TreeArrays
    kinematics64: Kinematics64
    device: str = "cpu"
    timestep_host: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def world_count(self) -> int:
        """Number of distinct model entries (1 or W)."""
        return self.arrays.body_pos.shape[0]

    def with_fields(self, fields: dict[str, wp.array], fields64: dict[str, wp.array] | None = None) -> "TreeModel":
        """A copy whose structs hold `fields` (member name -> array) in place of their own
        members, and `fields64` in place of `Kinematics64` members; the rest are shared.
        New structs are built, so this model is unchanged. Arrays that a tape should
        differentiate must have ``requires_grad`` already."""
        arrays = tree_arrays(**{n: fields.get(n, getattr(self.arrays, n)) for n in TREE_FIELDS})
        f64 = fields64 or {}
        k64 = kinematics64(**{n: f64.get(n, getattr(self.kinematics64, n)) for n in KINEMATICS64_FIELDS})
        return replace(self, arrays=arrays, kinematics64=k64)


@dataclass
class TreeFields:
    """Host-side (numpy, float64) values of the `TreeArrays` members for n model entries of
    one topology: what `tree_model` uploads. Built from MuJoCo models (`tree_fields`) or
    straight from a design space's parameters (`tt.sim.designs.chain_tree`).

    topology: the shared structure.
    values: member name -> array with a leading dimension n, in `TreeArrays`' units and
        shapes (every member but ``limit_sweeps``, a launch option of `tree_model`).
    """

    topology: Topology
    values: dict[str, np.ndarray]

    @property
    def count(self) -> int:
        """Number of entries n."""
        return len(self.values["timestep"])

    def take(self, index: Sequence[int] | np.ndarray) -> "TreeFields":
        """The entries `index` (repeats allowed), in that order."""
        index = np.asarray(index, dtype=np.int64)
        return TreeFields(self.topology, {k: v[index] for k, v in self.values.items()})


#: The `TreeArrays` members that `TreeFields.values` holds (all but the launch option).
FIELD_NAMES: tuple[str, ...] = tuple(n for n in TREE_FIELDS if n != "limit_sweeps")


def tree_fields(models: Sequence[mujoco.MjModel], ee_sites: Sequence[str]) -> TreeFields:
    """The `TreeFields` of MuJoCo models of one topology, one entry per model.

    Raises ValueError naming the first model whose topology or features do not fit.
    """
    if len(models) == 0:
        raise TTError("models is empty; a tree model needs at least one MuJoCo model")
    key0 = topology_key(models[0], ee_sites)
    for i, m in enumerate(models):
        check_supported(m, i)
        if i and topology_key(m, ee_sites) != key0:
            raise TTError(
                f"model {i} has a different topology from model 0 (body parents, joint types, "
                f"joint bodies, actuator joints or end-effector bodies differ); group models by "
                f"`topology_key` first"
            )
    topo = topology_of(models[0], ee_sites)
    nb, nv, nu, ne = topo.body_count, topo.dof_count, topo.actuator_count, topo.ee_count
    n = len(models)

    body_pos = np.zeros((n, nb, 3))
    body_quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, nb, 1))
    body_mass = np.zeros((n, nb))
    body_ipos = np.zeros((n, nb, 3))
    body_iquat = np.tile([1.0, 0.0, 0.0, 0.0], (n, nb, 1))
    body_inertia = np.zeros((n, nb, 3))
    body_gravcomp = np.zeros((n, nb))
    dof_range = np.tile([-UNLIMITED, UNLIMITED], (n, nv, 1))
    act_ctrlrange = np.tile([-UNLIMITED, UNLIMITED], (n, nu, 1))
    act_forcerange = np.tile([-UNLIMITED, UNLIMITED], (n, nu, 1))
    ee_pos = np.zeros((n, ne, 3))
    ee_quat = np.zeros((n, ne, 4))
    for i, m in enumerate(models):
        split = _split(m)
        head, tail = np.array(split.head), np.array(split.tail)
        body_pos[i, head[1:]] = m.body_pos[1:]
        body_quat[i, head[1:]] = m.body_quat[1:]
        body_mass[i, tail[1:]] = m.body_mass[1:]
        body_ipos[i, tail[1:]] = m.body_ipos[1:]
        body_iquat[i, tail[1:]] = m.body_iquat[1:]
        body_inertia[i, tail[1:]] = m.body_inertia[1:]
        # Every tree body of a split MuJoCo body carries its gravcomp (only the tail has mass).
        for b in range(1, m.nbody):
            body_gravcomp[i, head[b] : tail[b] + 1] = m.body_gravcomp[b] * _gravcomp_enabled(m)
        limited = m.jnt_limited.astype(bool)
        dof_range[i, limited] = m.jnt_range[limited]
        clamp = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
        cl = m.actuator_ctrllimited.astype(bool) & clamp
        act_ctrlrange[i, cl] = m.actuator_ctrlrange[cl]
        fl = m.actuator_forcelimited.astype(bool)
        act_forcerange[i, fl] = m.actuator_forcerange[fl]
        for e, s in enumerate(ee_sites):
            sid = _site_id(m, s)
            ee_pos[i, e] = m.site_pos[sid]
            ee_quat[i, e] = m.site_quat[sid]

    def flag_off(m, bit) -> bool:
        return bool(m.opt.disableflags & bit)

    D = mujoco.mjtDisableBit
    for i, m in enumerate(models):
        if flag_off(m, D.mjDSBL_EULERDAMP) and np.any(m.dof_damping > 0):
            raise TTError(f"model {i}: the eulerdamp flag is disabled; tt replicates Euler with implicit damping only")
        if m.opt.timestep <= 0:
            raise TTError(f"model {i}: timestep {m.opt.timestep} must be positive")
    values = dict(
        body_pos=body_pos,
        body_quat=body_quat,
        body_mass=body_mass,
        body_ipos=body_ipos,
        body_iquat=body_iquat,
        body_inertia=body_inertia,
        body_gravcomp=body_gravcomp,
        dof_axis=np.stack([m.jnt_axis for m in models]),
        dof_pos=np.stack([m.jnt_pos for m in models]),
        dof_ref=np.stack([m.qpos0 for m in models]),
        dof_armature=np.stack([m.dof_armature for m in models]),
        dof_damping=np.stack([m.dof_damping * (not flag_off(m, D.mjDSBL_DAMPER)) for m in models]),
        dof_stiffness=np.stack([m.jnt_stiffness * (not flag_off(m, D.mjDSBL_SPRING)) for m in models]),
        dof_springref=np.stack([m.qpos_spring for m in models]),
        dof_range=dof_range,
        dof_limit_kb=np.stack([_limit_kb(m) for m in models]),
        dof_solimp=np.stack([m.jnt_solimp for m in models]),
        dof_invweight0=np.stack([m.dof_invweight0 for m in models]),
        act_gain=np.stack([m.actuator_gainprm[:, 0] * (not flag_off(m, D.mjDSBL_ACTUATION)) for m in models]),
        act_bias=np.stack([m.actuator_biasprm[:, :3] * (not flag_off(m, D.mjDSBL_ACTUATION)) for m in models]),
        act_gear=np.stack([m.actuator_gear[:, 0] for m in models]),
        act_ctrlrange=act_ctrlrange,
        act_forcerange=act_forcerange,
        ee_pos=ee_pos,
        ee_quat=ee_quat,
        gravity=np.stack([m.opt.gravity * (not flag_off(m, D.mjDSBL_GRAVITY)) for m in models]),
        timestep=np.array([m.opt.timestep for m in models], dtype=np.float64),
        limit_enabled=np.array([0 if flag_off(m, D.mjDSBL_LIMIT) else 1 for m in models], dtype=np.int32),
    )
    return TreeFields(topo, {k: np.asarray(v) for k, v in values.items()})


def tree_model(
    fields: TreeFields,
    *,
    world_entry: np.ndarray | None = None,
    device: str | None = None,
    requires_grad: bool = False,
    limit_sweeps: int = 24,
) -> TreeModel:
    """Upload `fields` as a `TreeModel`: world w reads entry ``world_entry[w]`` (None: world
    w reads entry w). Missing or unknown members raise ValueError.

    requires_grad: allocate gradients on the continuous fields (for `wp.Tape`).
    limit_sweeps: Gauss-Seidel sweeps of the joint-limit force solve.
    """
    from tt.kernels.device import resolve_device

    device = resolve_device(device)
    missing = sorted(set(FIELD_NAMES) - set(fields.values))
    extra = sorted(set(fields.values) - set(FIELD_NAMES))
    if missing or extra:
        raise ValueError(f"tree fields: missing {missing}, unknown {extra}")
    v = fields.values
    entry = np.arange(fields.count) if world_entry is None else np.asarray(world_entry, dtype=np.int64)

    def arr(name, dtype):
        x = np.asarray(v[name], dtype=np.float32)[entry]
        return wp.array(np.ascontiguousarray(x), dtype=dtype, device=device, requires_grad=requires_grad)

    def arr64(name, dtype):
        return wp.array(np.ascontiguousarray(np.asarray(v[name], dtype=np.float64)[entry]), dtype=dtype, device=device)

    # Each member's Warp dtype is its declaration's, so a new field needs no edit here.
    k64 = kinematics64(**{name: arr64(name, Kinematics64.vars[name].type.dtype) for name in KINEMATICS64_FIELDS})
    # The arrays get requires_grad at allocation, before they enter the struct.
    members = {name: arr(name, TreeArrays.vars[name].type.dtype) for name in FIELD_NAMES if name != "limit_enabled"}
    members["limit_enabled"] = wp.array(
        np.asarray(v["limit_enabled"], dtype=np.int32)[entry], dtype=wp.int32, device=device
    )
    members["limit_sweeps"] = wp.array([limit_sweeps], dtype=wp.int32, device=device)
    return TreeModel(
        topology=fields.topology,
        arrays=tree_arrays(**members),
        kinematics64=k64,
        device=device,
        timestep_host=np.asarray(v["timestep"], dtype=np.float64)[entry],
    )


def build_tree_model(
    models: Sequence[mujoco.MjModel],
    ee_sites: Sequence[str],
    *,
    device: str | None = None,
    requires_grad: bool = False,
    limit_sweeps: int = 24,
) -> TreeModel:
    """A `TreeModel` with one world per MuJoCo model; all must share one topology.

    models: MuJoCo models of one topology (the same object may repeat).
    ee_sites: site names of the end effectors, in the order motions address them.
    requires_grad: allocate gradients on the continuous fields (for `wp.Tape`).
    limit_sweeps: Gauss-Seidel sweeps of the joint-limit force solve.
    Raises ValueError naming the first model whose topology or features do not fit.
    """
    if len(models) == 0:
        raise TTError("models is empty; build_tree_model needs at least one MuJoCo model")
    # Each distinct model object is read once and the worlds gather its rows: a rollout of
    # D designs on M motions passes each model M times.
    entry_of: dict[int, int] = {}
    position: list[int] = []  # index in `models` of each distinct model (for messages)
    world_entry = np.empty(len(models), dtype=np.int64)
    for i, m in enumerate(models):
        if id(m) not in entry_of:
            entry_of[id(m)] = len(position)
            position.append(i)
        world_entry[i] = entry_of[id(m)]
    try:
        fields = tree_fields([models[i] for i in position], ee_sites)
    except ValueError as e:
        # tree_fields names models by their index among the distinct ones; name them by `models`.
        raise TTError(_renumber(str(e), position)) from None
    return tree_model(
        fields, world_entry=world_entry, device=device, requires_grad=requires_grad, limit_sweeps=limit_sweeps
    )


def _renumber(message: str, position: list[int]) -> str:
    """`message` with its leading "model k" naming ``position[k]`` instead."""
    import re

    return re.sub(r"^model (\d+)", lambda g: f"model {position[int(g.group(1))]}", message)


def dof_invweight0(fields: TreeFields) -> np.ndarray:
    """MuJoCo's ``dof_invweight0`` of every entry: the diagonal of the inverse joint-space
    inertia (armature included) at the reference posture ``dof_ref``, (n, NV) float64.

    It scales the joint-limit constraint's regularizer, so a model built without MuJoCo's
    compiler needs it. At the reference posture every body sits at its offset (MuJoCo's
    qpos0); the mass matrix there is M = sum over bodies of m Jp^T Jp + Jr^T I Jr, with Jp
    the Jacobian of the body's center of mass and Jr its rotation's.
    """
    topo = fields.topology
    v = fields.values
    n, nb, nv = fields.count, topo.body_count, topo.dof_count
    world_pos = np.zeros((n, nb, 3))
    world_rot = np.tile(np.eye(3), (n, nb, 1, 1))
    axis_w = np.zeros((n, nv, 3))
    anchor_w = np.zeros((n, nv, 3))
    for b in range(1, nb):
        p = topo.body_parent[b]
        rot = world_rot[:, p] @ quat_to_mat(v["body_quat"][:, b])
        pos = world_pos[:, p] + np.einsum("nij,nj->ni", world_rot[:, p], v["body_pos"][:, b])
        d = topo.body_dof[b]
        if d >= 0:
            axis = v["dof_axis"][:, d] / np.linalg.norm(v["dof_axis"][:, d], axis=-1, keepdims=True)
            anchor_local = v["dof_pos"][:, d]
            axis_w[:, d] = np.einsum("nij,nj->ni", rot, axis)
            anchor_w[:, d] = pos + np.einsum("nij,nj->ni", rot, anchor_local)
        world_pos[:, b], world_rot[:, b] = pos, rot
    mass_matrix = np.zeros((n, nv, nv))
    for b in range(1, nb):
        support = topo.body_support(b)
        if not support:
            continue
        com = world_pos[:, b] + np.einsum("nij,nj->ni", world_rot[:, b], v["body_ipos"][:, b])
        irot = world_rot[:, b] @ quat_to_mat(v["body_iquat"][:, b])
        inertia = np.einsum("nij,nj,nkj->nik", irot, v["body_inertia"][:, b], irot)
        jp = np.zeros((n, 3, nv))
        jr = np.zeros((n, 3, nv))
        for d in support:
            if topo.dof_type[d] == JOINT_HINGE:
                jr[:, :, d] = axis_w[:, d]
                jp[:, :, d] = np.cross(axis_w[:, d], com - anchor_w[:, d])
            else:
                jp[:, :, d] = axis_w[:, d]
        mass_matrix += v["body_mass"][:, b, None, None] * np.einsum("nki,nkj->nij", jp, jp)
        mass_matrix += np.einsum("nki,nkl,nlj->nij", jr, inertia, jr)
    mass_matrix[:, np.arange(nv), np.arange(nv)] += v["dof_armature"]
    return np.diagonal(np.linalg.inv(mass_matrix), axis1=1, axis2=2).copy()


@dataclass(frozen=True)
class LocalTypes:
    """Fixed-size Warp vector/matrix types for one topology's per-world working memory.

    Kernels keep a world's whole state in these (registers or thread-local memory), so a
    world's step needs no scratch arrays and its adjoint no overwritten global memory.
    """

    scalar: type  # wp.float32 or wp.float64
    vec2: type
    vec3: type
    vec4: type
    quat: type
    mat33: type
    body_vec3: type  # (NB, 3): one 3-vector per body
    body_vec4: type  # (NB, 4): one quaternion (w, x, y, z) per body
    body_mat9: type  # (NB, 9): one row-major 3x3 matrix per body
    body_scalar: type  # (NB,)
    dof_vec: type  # (NV,)
    dof_vec3: type  # (NV, 3): one 3-vector per dof
    dof_mat: type  # (NV, NV)
    act_vec: type  # (NU,)
    ee_jac: type  # (6, NV): one end effector's Jacobian (rows: 3 translation, 3 rotation)
    ee_vec3: type  # (NE, 3): one 3-vector per end effector
    ee_vec4: type  # (NE, 4): one quaternion (w, x, y, z) per end effector


def local_types(topology: Topology, dtype=wp.float32) -> LocalTypes:
    """See `_local_types` (one cache entry per precision, however `dtype` is passed)."""
    return _local_types(topology, dtype)


@functools.cache
def _local_types(topology: Topology, dtype) -> LocalTypes:
    """The `LocalTypes` of a topology in scalar type `dtype` (cached: one set of type objects)."""
    nb, nv, nu = topology.body_count, topology.dof_count, max(topology.actuator_count, 1)
    ne = max(topology.ee_count, 1)
    f32 = dtype
    return LocalTypes(
        scalar=dtype,
        vec2=wp.types.vector(2, dtype),
        vec3=wp.types.vector(3, dtype),
        vec4=wp.types.vector(4, dtype),
        quat=wp.types.quaternion(dtype),
        mat33=wp.types.matrix((3, 3), dtype),
        body_vec3=wp.types.matrix(shape=(nb, 3), dtype=f32),
        body_vec4=wp.types.matrix(shape=(nb, 4), dtype=f32),
        body_mat9=wp.types.matrix(shape=(nb, 9), dtype=f32),
        body_scalar=wp.types.vector(length=nb, dtype=f32),
        dof_vec=wp.types.vector(length=nv, dtype=f32),
        dof_vec3=wp.types.matrix(shape=(nv, 3), dtype=f32),
        dof_mat=wp.types.matrix(shape=(nv, nv), dtype=f32),
        act_vec=wp.types.vector(length=nu, dtype=f32),
        ee_jac=wp.types.matrix(shape=(6, nv), dtype=f32),
        ee_vec3=wp.types.matrix(shape=(ne, 3), dtype=f32),
        ee_vec4=wp.types.matrix(shape=(ne, 4), dtype=f32),
    )


#: Dof sets are bit masks of int32 constants (`topology_constants`).
MAX_DOFS = 31


@dataclass(frozen=True)
class TopologyConstants:
    """A topology's index lists as Warp int32 vectors, for kernels to index with their loop
    counters (each at least one entry long; padding is 0): constants the C++ compiler folds
    where the loop is unrolled (`MODULE_OPTIONS`), loads from a constant table where not.

    body_parent, body_dof: (body_count,); dof_type, dof_body: (dof_count,);
    actuator_dof: (actuator_count,); ee_body: (ee_count,).
    ee_support: per end effector, the dofs that move it, as a bit mask (bit d: dof d).
    dof_support: per dof, itself and its ancestor dofs, as a bit mask.
    """

    body_parent: object
    body_dof: object
    dof_type: object
    dof_body: object
    actuator_dof: object
    ee_body: object
    ee_support: object
    dof_support: object


@functools.cache
def topology_constants(topology: Topology) -> TopologyConstants:
    """The `TopologyConstants` of a topology (cached: one set of vectors)."""
    if topology.dof_count > MAX_DOFS:
        raise TTError(f"a tree has {topology.dof_count} dofs; tt's kernels take at most {MAX_DOFS}")

    def ints(values) -> object:
        values = tuple(int(v) for v in values) or (0,)
        return wp.types.vector(length=len(values), dtype=wp.int32)(*values)

    def mask(dofs) -> int:
        return sum(1 << d for d in dofs)

    return TopologyConstants(
        body_parent=ints(topology.body_parent),
        body_dof=ints(topology.body_dof),
        dof_type=ints(topology.dof_type),
        dof_body=ints(topology.dof_body),
        actuator_dof=ints(topology.actuator_dof),
        ee_body=ints(topology.ee_body),
        ee_support=ints(mask(topology.body_support(b)) for b in topology.ee_body),
        dof_support=ints(mask(topology.dof_support(d)) for d in range(topology.dof_count)),
    )


def module_name(topology: Topology, family: str) -> str:
    """Warp module holding one family of a topology's kernels ("fk", "dynamics", "ik",
    "rollout", "rollout_grad"): each compiles once per topology, on its first launch, and
    a user of one family never waits for another's compile."""
    return f"tt_tree_{topology.digest}_{family}"


#: Module options of tt's per-topology forward kernels. Loops of up to 8 iterations are
#: unrolled (a ViperX arm's bodies and dofs, vector components: its three topologies get the
#: same C++ as with every loop unrolled); longer ones, over a 12-17-dof bimanual robot's dofs,
#: stay loops. Unrolling every loop (64) gave the same records bit for bit, 2.5-2.8x the C++
#: and 3.2-3.8x the compile time on ALOHA and the mobile bimanual robot, and stepped 4.5-9.4 %
#: slower there (benchmarks/results/compile_cost.md).
MODULE_OPTIONS = {"max_unroll": 8, "enable_backward": False}
#: Module options of the differentiable rollout (`tt.kernels.rollout.grad_kernels`): every loop
#: unrolled, so Warp's adjoint replays the fixed joint-limit sweeps exactly (`tt.kernels.dynamics`).
DIFFERENTIABLE_MODULE_OPTIONS = {"max_unroll": 64, "enable_backward": True}
