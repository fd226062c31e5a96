"""ViperX-300S-like single arm: mount, DoF count, joint axes and link lengths vary.

Discrete choices (paper, appendix "Procedural Generation"):
  mount: left | right | upright | downward
  dof: 5 | 6 | 7  (6 is the ViperX-300S; 5 drops the forearm roll; 7 adds an upper-arm roll)
  axis_<joint>: x | y | z for every joint after the shoulder ("upper joints")
Continuous choices:
  mount_x, mount_y, mount_z: mount position offset [m] within 0.7 / 1.0 / 0.6 m boxes
  mount_yaw: rotation of the mount about the world z axis [rad] in [-pi/2, pi/2]
  dlen_<segment>: change of each link length [m] in [-0.05, +0.20]

Actuators are the ViperX 300 S's servos, the same for every design (`_ROLES`,
`tt.sim.designs.servos`): each joint's force limit is its Dynamixel's stall torque and its
back-EMF a joint damping of stall / no-load speed, from the ROBOTIS datasheets at 12 V. The
space varies the arm, not its motors, so what a longer or heavier arm costs is torque and
speed: it saturates where the nominal arm does not, and a fast motion (a 2.5 m/s toss) asks
more speed of its joints than 30 rpm can give unless the links are long enough to turn it
into tip speed. Position gains kp stay stiffer than the servos' factory P gain (about 49 N m/rad
per XM540-W270 below saturation) because tt's IK controller, like the paper's, has no
integral or gravity term to remove the sag such a gain leaves.

The arm's zero configuration is an "L": the upper arm points up and the forearm, wrist and
gripper point forward (+x of the mount). The end-effector site ``ee_0`` has the last
link's frame, so with the upright mount at yaw 0 its x axis is the approach direction and
the identity quaternion means "gripper pointing forward, level".
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from tt.sim.designs.base import ContinuousParam, Design, DesignError, DesignSpace, DiscreteParam, FixedStructureSpace
from tt.sim.designs.mjcf import (
    JointSpec,
    Segment,
    actuators_xml,
    axis_angle_quat,
    chain_xml,
    fmt,
    header_xml,
    quat_mul,
    quat_mul_batch,
)
from tt.sim.designs.servos import XM430_W350, XM540_W270, ServoJoint

if TYPE_CHECKING:
    from tt.sim.designs.chain_tree import ChainBatch
    from tt.sim.designs.trees import DesignTrees

MOUNTS = ("left", "right", "upright", "downward")
DOFS = ("5", "6", "7")
AXES = ("x", "y", "z")
_AXIS_VEC = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}

#: Nominal mount pose per orientation: position [m] of the base and its rotation
#: (w, x, y, z). Side mounts sit on walls facing the workspace; the downward mount hangs
#: from a gantry, so every orientation can reach the motions in front of the origin.
MOUNT_POSES = {
    "upright": ((0.0, 0.0, 0.0), axis_angle_quat((1, 0, 0), 0.0)),
    "downward": ((0.0, 0.0, 0.85), axis_angle_quat((1, 0, 0), np.pi)),
    "left": ((0.0, 0.45, 0.3), axis_angle_quat((1, 0, 0), np.pi / 2)),
    "right": ((0.0, -0.45, 0.3), axis_angle_quat((1, 0, 0), -np.pi / 2)),
}

MOUNT_RANGE = {"mount_x": 0.35, "mount_y": 0.5, "mount_z": 0.3}
DLEN_RANGE = (-0.05, 0.20)


#: Joint friction of a servo [N m s/rad], on top of its back-EMF damping.
FRICTION_DAMPING = 0.1


def _joint(name: str, axis: str, rng: tuple[float, float], kp: float, servo: ServoJoint, armature: float) -> JointSpec:
    # kv near critical damping for the joint's own reflected inertia. The servo's voltage
    # limit is the force limit and its back-EMF a joint damping (tt.sim.designs.servos).
    kv = 2.0 * np.sqrt(kp * armature)
    return JointSpec(
        name,
        _AXIS_VEC[axis],
        rng,
        kp=kp,
        kv=float(round(kv, 4)),
        force=servo.force,
        armature=armature,
        damping=float(round(FRICTION_DAMPING + servo.damping, 4)),
    )


#: (joint name, nominal axis, range, kp, servos, armature) by role, base to tip. The
#: servos are the ViperX 300 S's (Trossen Robotics' specification): XM540-W270 at the waist,
#: two at the shoulder and two at the elbow, one each at the forearm roll and the wrist
#: angle, an XM430-W350 at the wrist rotate; the 7-DoF variant's upper-arm roll gets an
#: XM540-W270. Every design of a space keeps these servos, so a longer, heavier arm on a
#: fast motion saturates them: at 30 rpm unloaded the shoulder cannot swing a 0.8 m arm's
#: tip much faster than 2.5 m/s, and every N m it holds against gravity is lost to speed.
_ROLES = {
    "waist": ("z", (-np.pi, np.pi), 300.0, ServoJoint(XM540_W270), 0.08),
    "shoulder": ("y", (-1.88, 1.99), 500.0, ServoJoint(XM540_W270, 2), 0.1),
    "upper_roll": ("z", (-np.pi, np.pi), 200.0, ServoJoint(XM540_W270), 0.05),
    "elbow": ("y", (-2.15, 1.6), 400.0, ServoJoint(XM540_W270, 2), 0.08),
    "forearm_roll": ("x", (-np.pi, np.pi), 100.0, ServoJoint(XM540_W270), 0.03),
    "wrist_angle": ("y", (-1.75, 2.15), 100.0, ServoJoint(XM540_W270), 0.03),
    "wrist_rotate": ("x", (-np.pi, np.pi), 60.0, ServoJoint(XM430_W350), 0.02),
}

#: Joints of each DoF variant, base to tip.
_JOINTS = {
    "5": ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate"),
    "6": ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate"),
    "7": ("waist", "shoulder", "upper_roll", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate"),
}

#: Segment after each joint: (direction, nominal length [m], capsule radius [m]). The
#: upper arm and forearm split at the roll joints so total lengths match the 6-DoF arm.
_SEGMENTS = {
    "waist": ((0, 0, 1), 0.127, 0.035),
    "shoulder": ((0, 0, 1), 0.30, 0.03),
    "upper_roll": ((0, 0, 1), 0.20, 0.03),
    "elbow": ((1, 0, 0), 0.30, 0.025),
    "forearm_roll": ((1, 0, 0), 0.20, 0.025),
    "wrist_angle": ((1, 0, 0), 0.07, 0.022),
    "wrist_rotate": ((1, 0, 0), 0.10, 0.02),
}


def segment_vectors(dof: str, dlens: np.ndarray) -> np.ndarray:
    """Segment vectors [m] of a DoF variant for length changes `dlens` [m], (..., J) ->
    (..., J, 3). With a 7-DoF arm the shoulder segment shrinks to the part below the
    upper-arm roll; with 6 and 7 the elbow segment is the part before the forearm roll."""
    names = _JOINTS[dof]
    nominal = np.array([_SEGMENTS[n][1] for n in names])
    if dof == "7":
        nominal[names.index("shoulder")] = 0.10
    if dof in ("6", "7"):
        nominal[names.index("elbow")] = 0.10
    direction = np.array([_SEGMENTS[n][0] for n in names], dtype=float)
    return (nominal + np.asarray(dlens, dtype=float))[..., None] * direction


def joint_axes(dof: str, axis_choices: np.ndarray) -> np.ndarray:
    """Joint axes of a DoF variant, (..., J - 2) indices into `AXES` for every joint after
    the shoulder -> (..., J, 3) (waist and shoulder keep their nominal axes)."""
    names = _JOINTS[dof]
    choices = np.asarray(axis_choices, dtype=np.int64)
    table = np.array([_AXIS_VEC[a] for a in AXES])
    fixed = np.array([_AXIS_VEC[_ROLES[n][0]] for n in names[:2]])
    return np.concatenate([np.broadcast_to(fixed, choices.shape[:-1] + fixed.shape), table[choices]], axis=-2)


def arm_parts(
    dof: str, axes: Sequence[str], dlens: Sequence[float], prefix_roles: bool = False
) -> tuple[list[JointSpec], list[Segment]]:
    """Joints and segments of one ViperX-like arm.

    axes: axis name for every joint after the shoulder; dlens: length change [m] per segment
    (`segment_vectors`).
    """
    names = _JOINTS[dof]
    upper = names[2:]
    if len(axes) != len(upper) or len(dlens) != len(names):
        raise ValueError(f"{dof}-DoF arm needs {len(upper)} axes and {len(names)} length changes")
    axis_of = dict(zip(upper, axes))
    vectors = segment_vectors(dof, np.asarray(dlens, dtype=float))
    joints, segments = [], []
    for name, vec in zip(names, vectors):
        nominal_axis, rng, kp, servo, armature = _ROLES[name]
        joints.append(_joint(name, axis_of.get(name, nominal_axis), rng, kp, servo, armature))
        segments.append(Segment(tuple(float(c) for c in vec), _SEGMENTS[name][2]))
    return joints, segments


def segment_names(dof: str) -> tuple[str, ...]:
    """Names of the link-length parameters of a DoF variant."""
    return tuple(f"dlen_{n}" for n in _JOINTS[dof])


# The parameters of each DoF variant, built once: validating thousands of designs asks for
# them once per discrete prefix of every design.
_FIRST_PARAMS = (DiscreteParam("mount", MOUNTS), DiscreteParam("dof", DOFS))
_DISCRETE_PARAMS = {
    dof: _FIRST_PARAMS + tuple(DiscreteParam(f"axis_{j}", AXES) for j in _JOINTS[dof][2:]) for dof in DOFS
}
_CONTINUOUS_PARAMS = {
    dof: (
        *(ContinuousParam(k, -v, v) for k, v in MOUNT_RANGE.items()),
        ContinuousParam("mount_yaw", -np.pi / 2, np.pi / 2, "rad"),
        *(ContinuousParam(n, *DLEN_RANGE) for n in segment_names(dof)),
    )
    for dof in DOFS
}


class ViperXSpace(DesignSpace):
    """The ViperX design space."""

    name = "viperx"
    ee_count = 1

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        if len(discrete) < 2:
            return _FIRST_PARAMS
        return _DISCRETE_PARAMS[DOFS[discrete[1]] if 0 <= discrete[1] < len(DOFS) else "6"]

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        return _CONTINUOUS_PARAMS[DOFS[discrete[1]]]

    def nominal(self) -> Design:
        dof = "6"
        axes = [AXES.index(_ROLES[j][0]) for j in _JOINTS[dof][2:]]
        discrete = (MOUNTS.index("upright"), DOFS.index(dof), *axes)
        return Design(self.name, discrete, tuple(0.0 for _ in self.continuous_params(discrete)))

    def _mjcf(self, discrete, values, options) -> str:
        dof = options["dof"]
        axes = [options[f"axis_{j}"] for j in _JOINTS[dof][2:]]
        dlens = [values[n] for n in segment_names(dof)]
        joints, segments = arm_parts(dof, axes, dlens)
        pos, quat = mount_pose(options["mount"], values)
        body = chain_xml("", joints, segments, "ee_0", indent="  ")
        body = "\n".join("    " + line for line in body.splitlines())
        return f"""{header_xml("viperx", contacts=False)}
  <worldbody>
    <body name="base" pos="{fmt(pos)}" quat="{fmt(quat)}">
      <geom name="base_plate" type="cylinder" size="0.06 0.02" pos="0 0 -0.02" rgba="0.2 0.2 0.2 1"/>
{body}
    </body>
  </worldbody>
  <actuator>
{actuators_xml("", joints)}
  </actuator>
</mujoco>
"""

    def trees(self, designs: Sequence[Design]) -> "DesignTrees":
        """The designs' tree fields without MJCF (`tt.sim.designs.chain_tree`): one MuJoCo
        compile per DoF variant (the template), the rest numpy over the variant's designs."""
        import torch

        from tt.kernels.model import tree_fields
        from tt.sim.designs.chain_tree import chain_fields, chain_sizes
        from tt.sim.designs.trees import DesignTrees
        from tt.sim.rewards import robot_size

        designs = list(designs)
        if not designs:
            raise DesignError("designs is empty; trees needs at least one design")
        groups: dict[int, list[int]] = {}
        self.validate_many(designs)
        for i, d in enumerate(designs):
            groups.setdefault(int(d.discrete[1]), []).append(i)
        sizes, masses = np.zeros(len(designs)), np.zeros(len(designs))
        out = []
        for dof_index, members in sorted(groups.items()):
            dof = DOFS[dof_index]
            chains = self._chains([designs[i] for i in members], dof)
            template = self.model(designs[members[0]])
            fields = chain_fields(
                tree_fields([template], self.ee_sites()),
                chains,
                base_body=1,
                chain_bodies=range(2, 2 + len(_JOINTS[dof])),
            )
            # The base's geoms: the template's size less its chain's share.
            base_size = float(robot_size([template], dtype=torch.float64)[0]) - float(chain_sizes(chains.take([0]))[0])
            idx = np.asarray(members, dtype=np.int64)
            sizes[idx] = base_size + chain_sizes(chains)
            masses[idx] = fields.values["body_mass"][:, 1:].sum(axis=1)
            out.append((idx, fields))
        return DesignTrees(self.name, self.ee_sites(), tuple(out), sizes, masses)

    def _chains(self, designs: Sequence[Design], dof: str) -> "ChainBatch":
        """The chain arrays of valid designs of one DoF variant (what `_mjcf` writes as MJCF)."""
        from tt.sim.designs.chain_tree import ChainBatch

        names = _JOINTS[dof]
        discrete = np.array([d.discrete for d in designs], dtype=np.int64)
        continuous = np.array([d.continuous for d in designs], dtype=float)
        cnames = [p.name for p in self.continuous_params(designs[0].discrete)]
        col = {n: continuous[:, cnames.index(n)] for n in cnames}
        base_pos, base_quat = mount_poses(discrete[:, 0], col)
        vectors = segment_vectors(dof, np.stack([col[n] for n in segment_names(dof)], axis=-1))
        radii = np.broadcast_to([_SEGMENTS[n][2] for n in names], (len(designs), len(names)))
        return ChainBatch(
            base_pos, base_quat, joint_axes(dof, discrete[:, 2:]), vectors, np.array(radii), hinge=(True,) * len(names)
        )


def mount_poses(mounts: np.ndarray, values: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """`mount_pose` of N arms: mount indices into `MOUNTS` (N,) and value columns (N,) ->
    positions (N, 3) [m] and quaternions (w, x, y, z) (N, 4)."""
    pos = np.array([MOUNT_POSES[m][0] for m in MOUNTS], dtype=float)[mounts]
    quat = np.array([MOUNT_POSES[m][1] for m in MOUNTS], dtype=float)[mounts]
    pos = pos + np.stack([values["mount_x"], values["mount_y"], values["mount_z"]], axis=-1)
    half = 0.5 * np.asarray(values["mount_yaw"], dtype=float)
    yaw = np.stack([np.cos(half), 0.0 * half, 0.0 * half, np.sin(half)], axis=-1)
    return pos, quat_mul_batch(yaw, quat)


def mount_pose(mount: str, values: dict[str, float], nominal: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World position [m] and quaternion (w, x, y, z) of an arm's base."""
    base_pos, base_quat = (nominal or MOUNT_POSES)[mount]
    pos = np.asarray(base_pos) + np.array([values["mount_x"], values["mount_y"], values["mount_z"]])
    quat = quat_mul(axis_angle_quat((0, 0, 1), values["mount_yaw"]), np.asarray(base_quat))
    return pos, quat


SPACE = ViperXSpace()

#: ViperX with the nominal arm's discrete choices (upright mount, 6 DoF, the ViperX-300S's
#: joint axes) fixed; mount offset, yaw and link lengths vary. The learnability ladder's
#: one-structure rung (`tt designs --space viperx-nominal`).
NOMINAL_SPACE = FixedStructureSpace("viperx-nominal", SPACE, SPACE.nominal().discrete)
