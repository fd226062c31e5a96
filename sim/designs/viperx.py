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

from typing import Sequence

import numpy as np

from tt.sim.designs.base import ContinuousParam, Design, DesignSpace, DiscreteParam, FixedStructureSpace
from tt.sim.designs.servos import XM430_W350, XM540_W270, ServoJoint
from tt.sim.designs.mjcf import (
    JointSpec,
    Segment,
    actuators_xml,
    axis_angle_quat,
    chain_xml,
    fmt,
    header_xml,
    quat_mul,
)

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
    return JointSpec(name, _AXIS_VEC[axis], rng, kp=kp, kv=float(round(kv, 4)), force=servo.force, armature=armature,
                     damping=float(round(FRICTION_DAMPING + servo.damping, 4)))


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


def arm_parts(dof: str, axes: Sequence[str], dlens: Sequence[float], prefix_roles: bool = False) -> tuple[list[JointSpec], list[Segment]]:
    """Joints and segments of one ViperX-like arm.

    axes: axis name for every joint after the shoulder; dlens: length change [m] per segment.
    With a 7-DoF arm the shoulder segment shrinks to the part below the upper-arm roll.
    """
    names = _JOINTS[dof]
    upper = names[2:]
    if len(axes) != len(upper) or len(dlens) != len(names):
        raise ValueError(f"{dof}-DoF arm needs {len(upper)} axes and {len(names)} length changes")
    axis_of = dict(zip(upper, axes))
    joints, segments = [], []
    for name, dl in zip(names, dlens):
        nominal_axis, rng, kp, servo, armature = _ROLES[name]
        joints.append(_joint(name, axis_of.get(name, nominal_axis), rng, kp, servo, armature))
        direction, length, radius = _SEGMENTS[name]
        if name == "shoulder" and dof == "7":
            length = 0.10
        if name == "elbow" and dof in ("6", "7"):
            length = 0.10
        vec = tuple(float(c) * (length + dl) for c in direction)
        segments.append(Segment(vec, radius))
    return joints, segments


def segment_names(dof: str) -> tuple[str, ...]:
    """Names of the link-length parameters of a DoF variant."""
    return tuple(f"dlen_{n}" for n in _JOINTS[dof])


class ViperXSpace(DesignSpace):
    """The ViperX design space."""

    name = "viperx"
    ee_count = 1

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        params = [DiscreteParam("mount", MOUNTS), DiscreteParam("dof", DOFS)]
        if len(discrete) >= 2:
            dof = DOFS[discrete[1]] if 0 <= discrete[1] < len(DOFS) else "6"
            params += [DiscreteParam(f"axis_{j}", AXES) for j in _JOINTS[dof][2:]]
        return tuple(params)

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        dof = DOFS[discrete[1]]
        params = [ContinuousParam(k, -v, v) for k, v in MOUNT_RANGE.items()]
        params.append(ContinuousParam("mount_yaw", -np.pi / 2, np.pi / 2, "rad"))
        params += [ContinuousParam(n, *DLEN_RANGE) for n in segment_names(dof)]
        return tuple(params)

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
