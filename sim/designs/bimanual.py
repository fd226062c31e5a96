"""Mobile bimanual robot: a holonomic base, a spine, an optional torso pitch and two small arms.

Discrete choices (paper, appendix "Procedural Generation"):
  spine: fixed | sliding | bending
  torso_pitch: no | yes  (a 45 degree pitch joint under the torso, leaning forward)
Continuous choices [m]:
  spine_length: fixed column 0.60-1.40; sliding: lower tube 0.10-0.50 (the upper tube has
      the same length and telescopes out by up to 0.9 of it); bending: column 0.20-0.80
      above a pitch hinge on the base
  shoulder_y: shoulder offset from the torso centre along y, 0.04-0.10 (the torso's
      half-width follows it, so the shoulders sit on its sides)
  shoulder_z: shoulder height above the top of the spine, -0.03-0.08
  shoulder_link: lateral link from the shoulder pitch to the shoulder roll, 0.02-0.08
  arm_link: upper-arm tube beyond the 0.10 m shoulder bracket, 0.01-0.18
  forearm_link: forearm tube beyond the 0.10 m elbow bracket, 0.01-0.18
  (The brackets keep the shortest arms useful: upper arm and forearm are 0.11-0.28 m,
  the hand another 0.10 m, a small humanoid's proportions.)

Kinematic tree (joint order = actuator order):
  base_x, base_y (slides along world x, y), base_yaw (hinge about z): a holonomic base,
      position-servoed with modest gains so it moves slowly; contacts are disabled, so it
      glides without wheels on the floor (z = 0), its top at `BASE_TOP`.
  spine_slide (sliding spine, along z) or spine_bend (bending spine, pitch about y).
  torso_pitch (if chosen, pitch about y at the top of the spine, 0 to pi/4 forward).
  left_* then right_*, six joints per arm: shoulder_pitch (y), shoulder_roll (x),
      shoulder_yaw (z), elbow (y), wrist_roll (x), wrist_pitch (y).

At zero joint angles (the home posture) each arm is an "L": the upper arm hangs down,
forearm and hand point forward (+x). A sliding spine's home is the middle of its travel.
The end-effector sites ``ee_0`` (left arm, +y) and ``ee_1`` (right arm, -y) have the hand's
frame: the identity orientation means "hand pointing forward, level" in the base frame.

Symmetry: the right arm is the mirror image of the left through the XZ plane, as in
`tt.sim.designs.aloha`: equal joint values on both arms give mirror-image poses
(``p_right = M p_left``, ``R_right = M R_left M``, ``M = diag(1, -1, 1)``) while the base,
spine and torso, which lie on the symmetry plane, keep base_y = base_yaw = 0.
"""

from __future__ import annotations

from typing import Sequence

import mujoco
import numpy as np

from tt.sim.designs.base import ContinuousParam, Design, DesignSpace, DiscreteParam
from tt.sim.designs.mjcf import (
    JointSpec,
    Segment,
    actuators_xml,
    chain_xml,
    fmt,
    header_xml,
    mirror_joint_xz,
    mirror_segment_xz,
    servo,
    stiffen_for_gravity,
)
from tt.sim.motions.workspace import BIMANUAL_CENTER

SPINES = ("fixed", "sliding", "bending")
TORSO_PITCH = ("no", "yes")

#: Spine length bounds [m] per spine kind.
SPINE_LENGTH = {"fixed": (0.60, 1.40), "sliding": (0.10, 0.50), "bending": (0.20, 0.80)}
#: Fraction of the sliding spine's length its upper tube travels (the rest stays nested).
SLIDE_TRAVEL = 0.9

#: Height of the base's top plate above the floor [m]; the spine starts there.
BASE_TOP = 0.20
#: Half-extents of the base's chassis box [m].
CHASSIS_HALF = (0.22, 0.20, 0.07)
#: Fixed parts of the arms [m]: brackets the link lengths add to, and the hand (wrist
#: pitch to end-effector site).
ARM_BRACKET = 0.10
FOREARM_BRACKET = 0.10
HAND = 0.10

#: Largest end-effector sag [m] of the home posture under gravity that the servo
#: stiffness is sized for (static, linearised); the test allows 1 cm with the transient.
HOME_SAG = 0.004

_PARAMS = {
    "shoulder_y": ContinuousParam("shoulder_y", 0.04, 0.10),
    "shoulder_z": ContinuousParam("shoulder_z", -0.03, 0.08),
    "shoulder_link": ContinuousParam("shoulder_link", 0.02, 0.08),
    "arm_link": ContinuousParam("arm_link", 0.01, 0.18),
    "forearm_link": ContinuousParam("forearm_link", 0.01, 0.18),
}

#: The nominal robot: a fixed 0.80 m spine, no torso pitch, mid-range arms.
_NOMINAL = {
    "spine": "fixed",
    "torso_pitch": "no",
    "spine_length": 0.80,
    "shoulder_y": 0.08,
    "shoulder_z": 0.04,
    "shoulder_link": 0.05,
    "arm_link": 0.12,
    "forearm_link": 0.12,
}

#: Centre of the nominal robot's two-arm workspace in the world frame [m]: the midpoint
#: of its two home end-effector positions, (0.32, +-0.13, 0.82): 0.22 m forearm and 0.10 m
#: hand in front of the shoulders, at 0.20 m base top + 0.80 m spine + 0.04 m shoulder
#: height - 0.22 m upper arm.
WORKSPACE_CENTER = (0.32, 0.0, 0.82)

#: Where this robot's motions go (`BimanualSpace.motion_offset`) [m]. Motions are placed as
#: for every robot, as the paper places its demonstrations (`tt.sim.motions.place_at_base`:
#: the first pose's mean (x, y) over both hands over the base's centre, heights kept), then
#: moved forward to where the nominal robot's hands rest, in front of its base, and up from
#: the library's table (two-arm skills written for two arms at y = +-0.3 m on a table top
#: z = 0, as in ``tt.sim.designs.aloha``, their region centred at `BIMANUAL_CENTER`) to its
#: hands' counter height. A demonstration starts with the hands in front of the robot at the
#: height it was recorded at; the base rolls and the spine carries the arms to it.
MOTION_OFFSET = (WORKSPACE_CENTER[0], 0.0, WORKSPACE_CENTER[2] - BIMANUAL_CENTER[2])

#: Base and trunk joints: (axis, range, kp, force, armature, damping), kind.
#: Base slides [m, N/m, N, kg, N s/m]; hinges [rad, N m/rad, N m, kg m^2, N m s/rad]. The
#: base's joint damping (implicit in MuJoCo's Euler step, so any value is stable) brings
#: the ~20-30 kg robot near critical damping at kp 1500 N/m: about 0.3 s to settle.
_TRUNK = {
    "base_x": ("slide", (1, 0, 0), (-3.0, 3.0), 1500.0, 300.0, 1.0, 200.0),
    "base_y": ("slide", (0, 1, 0), (-3.0, 3.0), 1500.0, 300.0, 1.0, 200.0),
    "base_yaw": ("hinge", (0, 0, 1), (-np.pi, np.pi), 400.0, 100.0, 0.5, 20.0),
    "spine_slide": ("slide", (0, 0, 1), None, 20000.0, 600.0, 2.0, 100.0),
    "spine_bend": ("hinge", (0, 1, 0), (-0.35, 1.2), 2000.0, 300.0, 0.5, 10.0),
    "torso_pitch": ("hinge", (0, 1, 0), (0.0, np.pi / 4), 800.0, 120.0, 0.2, 5.0),
}

#: Left-arm joints base to tip: (axis, range [rad], kp [N m/rad], force [N m], armature [kg m^2]).
_ARM = {
    "shoulder_pitch": ((0, 1, 0), (-np.pi, 1.0), 150.0, 30.0, 0.03),
    "shoulder_roll": ((1, 0, 0), (-0.6, 2.6), 150.0, 30.0, 0.03),
    "shoulder_yaw": ((0, 0, 1), (-2.0, 2.0), 80.0, 15.0, 0.02),
    "elbow": ((0, 1, 0), (-1.5, 1.6), 120.0, 20.0, 0.02),
    "wrist_roll": ((1, 0, 0), (-np.pi, np.pi), 40.0, 5.0, 0.01),
    "wrist_pitch": ((0, 1, 0), (-1.6, 1.6), 40.0, 5.0, 0.01),
}


def arm_chain(shoulder_link: float, arm_link: float, forearm_link: float) -> tuple[list[JointSpec], list[Segment]]:
    """Joints and segments of the left arm (role gains, before sizing for gravity)."""
    joints = [servo(n, axis, rng, kp, force, armature) for n, (axis, rng, kp, force, armature) in _ARM.items()]
    segments = [
        Segment((0.0, shoulder_link, 0.0), 0.025),
        Segment((0.0, 0.0, 0.0), 0.025),
        Segment((0.0, 0.0, -(ARM_BRACKET + arm_link)), 0.025),
        Segment((FOREARM_BRACKET + forearm_link, 0.0, 0.0), 0.022),
        Segment((0.0, 0.0, 0.0), 0.02),
        Segment((HAND, 0.0, 0.0), 0.02),
    ]
    return joints, segments


def trunk_joints(spine: str, torso_pitch: bool, spine_length: float) -> list[JointSpec]:
    """Base, spine and torso joints of a design, in tree order (role gains)."""
    names = ["base_x", "base_y", "base_yaw"]
    if spine == "sliding":
        names.append("spine_slide")
    elif spine == "bending":
        names.append("spine_bend")
    if torso_pitch:
        names.append("torso_pitch")
    joints = []
    for n in names:
        kind, axis, rng, kp, force, armature, damping = _TRUNK[n]
        if n == "spine_slide":
            half = SLIDE_TRAVEL * spine_length / 2
            rng = (-half, half)
        joints.append(servo(n, axis, rng, kp, force, armature, kind=kind, damping=damping))
    return joints


class BimanualSpace(DesignSpace):
    """The mobile bimanual design space."""

    name = "bimanual"
    ee_count = 2
    motion_offset = MOTION_OFFSET

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        return (DiscreteParam("spine", SPINES), DiscreteParam("torso_pitch", TORSO_PITCH))

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        low, high = SPINE_LENGTH[SPINES[discrete[0]]]
        return (ContinuousParam("spine_length", low, high), *_PARAMS.values())

    def nominal(self) -> Design:
        discrete = (SPINES.index(_NOMINAL["spine"]), TORSO_PITCH.index(_NOMINAL["torso_pitch"]))
        return Design(self.name, discrete, tuple(_NOMINAL[p.name] for p in self.continuous_params(discrete)))

    def _mjcf(self, discrete, values, options) -> str:
        trunk = trunk_joints(options["spine"], options["torso_pitch"] == "yes", values["spine_length"])
        arm, segments = arm_chain(values["shoulder_link"], values["arm_link"], values["forearm_link"])
        draft = _robot_xml(options["spine"], values, trunk, arm, segments)
        # Size the servos from the draft's gravity load at home. The right arm mirrors the
        # left, so the trunk and left-arm joints cover every load and lever.
        specs = {j.name: j for j in trunk} | {f"left_{j.name}": j for j in arm}
        sized = stiffen_for_gravity(mujoco.MjModel.from_xml_string(draft), specs, self.ee_sites(), HOME_SAG)
        trunk = [sized[j.name] for j in trunk]
        arm = [sized[f"left_{j.name}"] for j in arm]
        return _robot_xml(options["spine"], values, trunk, arm, segments)


def _joint_xml(j: JointSpec) -> str:
    return (
        f'<joint name="{j.name}" type="{j.kind}" axis="{fmt(j.axis)}" range="{fmt(j.range)}" '
        f'armature="{j.armature!r}" damping="{j.damping!r}"/>'
    )


class _Tree:
    """Indented MJCF lines with a stack of open bodies."""

    def __init__(self, depth: int):
        self.lines: list[str] = []
        self.depth = depth
        self.open_bodies = 0

    def add(self, text: str) -> None:
        self.lines.extend("  " * self.depth + line for line in text.splitlines())

    def open(self, attrs: str) -> None:
        self.add(f"<body {attrs}>")
        self.depth += 1
        self.open_bodies += 1

    def close(self) -> None:
        self.depth -= 1
        self.open_bodies -= 1
        self.add("</body>")

    def close_all(self) -> None:
        while self.open_bodies:
            self.close()


def _robot_xml(
    spine: str, values: dict[str, float], trunk: list[JointSpec], arm: list[JointSpec], segments: list[Segment]
) -> str:
    """MJCF of a design given its (sized) trunk joints and its left arm."""
    joint = {j.name: j for j in trunk}
    length = values["spine_length"]
    sy, sz = values["shoulder_y"], values["shoulder_z"]
    chassis_z = BASE_TOP - CHASSIS_HALF[2]
    dark = 'rgba="0.15 0.15 0.15 1"'
    metal = 'rgba="0.55 0.6 0.7 1"'
    t = _Tree(depth=2)
    # The slides' bodies carry small drive units (inside the chassis) so every moving
    # body has mass of its own.
    for axis in ("x", "y"):
        t.open(f'name="base_{axis}"')
        t.add(_joint_xml(joint[f"base_{axis}"]))
        t.add(f'<geom name="base_{axis}_drive" type="sphere" size="0.03" pos="0 0 {chassis_z!r}" {dark}/>')
    t.open('name="base"')
    t.add(_joint_xml(joint["base_yaw"]))
    t.add(f'<geom name="chassis" type="box" size="{fmt(CHASSIS_HALF)}" pos="0 0 {chassis_z!r}" rgba="0.3 0.3 0.32 1"/>')
    t.open(f'name="spine" pos="0 0 {BASE_TOP!r}"')
    torso_z = length
    if spine == "fixed":
        t.add(f'<geom name="spine_column" type="capsule" fromto="0 0 0 0 0 {length!r}" size="0.04" {metal}/>')
    elif spine == "bending":
        t.add(_joint_xml(joint["spine_bend"]))
        t.add(f'<geom name="spine_bend_motor" type="cylinder" size="0.05 0.05" zaxis="0 1 0" {dark}/>')
        t.add(f'<geom name="spine_column" type="capsule" fromto="0 0 0 0 0 {length!r}" size="0.04" {metal}/>')
    else:
        # Two tubes of equal length; at home the upper one is out by half its travel.
        t.add(f'<geom name="spine_outer" type="capsule" fromto="0 0 0 0 0 {length!r}" size="0.045" {metal}/>')
        t.open(f'name="spine_lift" pos="0 0 {length + SLIDE_TRAVEL * length / 2!r}"')
        t.add(_joint_xml(joint["spine_slide"]))
        t.add(f'<geom name="spine_inner" type="capsule" fromto="0 0 {-length!r} 0 0 0" size="0.035" {metal}/>')
        torso_z = 0.0
    t.open(f'name="torso" pos="0 0 {torso_z!r}"')
    if "torso_pitch" in joint:
        t.add(_joint_xml(joint["torso_pitch"]))
    # The torso box spans the shoulders (half-width = shoulder_y) and their height range.
    t.add(f'<geom name="torso" type="box" size="0.06 {sy!r} 0.1" rgba="0.45 0.5 0.6 1"/>')
    right = [mirror_joint_xz(j) for j in arm]
    right_segments = [mirror_segment_xz(s) for s in segments]
    for side, y, js, ss, site in (("left", sy, arm, segments, "ee_0"), ("right", -sy, right, right_segments, "ee_1")):
        t.open(f'name="{side}_shoulder" pos="0 {y!r} {sz!r}"')
        t.add(f'<geom name="{side}_shoulder_bracket" type="sphere" size="0.03" {dark}/>')
        t.depth -= 1  # chain_xml indents its first body by one level itself
        t.add(chain_xml(f"{side}_", js, ss, site, housing_radius=0.025, indent="  "))
        t.depth += 1
        t.close()
    t.close_all()
    body_text = "\n".join(t.lines)
    actuators = "\n".join([actuators_xml("", trunk), actuators_xml("left_", arm), actuators_xml("right_", right)])
    return f"""{header_xml("bimanual", contacts=False)}
  <worldbody>
{body_text}
  </worldbody>
  <actuator>
{actuators}
  </actuator>
</mujoco>
"""


SPACE = BimanualSpace()
