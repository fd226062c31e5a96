"""Quadruped manipulator: a dog-sized four-legged base with a 6-DoF arm on its back.

Discrete choices (paper, appendix "Procedural Generation"; 7 binary choices, 128 combinations):
  arm_mount: fixed | rail  (rail: the arm base slides along the back on an actuated slide joint)
  leg_fl, leg_fr, leg_rl, leg_rr: serial | linkage  (each leg independently)
  knee_front, knee_back: forward | backward  (shared within the front and within the back pair)
Continuous choices (the same for every discrete choice):
  arm_dlen_upper, arm_dlen_forearm: length change [m] of the arm's upper arm (nominal 0.25 m)
      and forearm (nominal 0.25 m: 0.10 m before the forearm roll + 0.15 m after it; the change
      goes to the part after the roll) in [-0.10, +0.40]
  arm_mount_x: x of the arm base on the back, from the torso centre [m] in [-0.20, +0.20]
  body_length: length [m] of the torso's middle section, between the two hip blocks, in
      [0.10, 0.50]. Each hip block is HIP_BLOCK_LENGTH long with its pair of hips at its centre,
      so the torso is body_length + 2 HIP_BLOCK_LENGTH long and the hips stand
      body_length + HIP_BLOCK_LENGTH apart.
  thigh_length, calf_length: leg link lengths [m] in [0.10, 0.30] each, so the leg (thigh +
      calf) spans the paper's 20-60 cm with a Go2-sized 0.40 m leg at the nominal design. Read
      per link, 20-60 cm would make 1.2 m legs and put the paper's quadruped size target
      (6.5 m of geometry) below almost every design; with these ranges it sits near the
      median. Both are shared by all four legs so every leg reaches the same standing height
      (the paper constrains left and right links equal; sharing front and back too keeps every
      design able to stand level).
  leg_yaw_fl, leg_yaw_fr, leg_yaw_rl, leg_yaw_rr: rotation [rad] of each hip mount, and with
      it the whole leg (abduction axis, sagittal plane, lateral hip offset), about the vertical
      in [-0.7, 0.7]
  battery_x: x of the battery box's centre from the torso centre [m] in [-0.20, +0.20]

Legs have three actuated joints each: hip abduction (about the leg frame's x), hip flexion and a
knee drive (about its y). A serial leg carries its knee motor at the knee. A linkage leg moves
the knee motor to the hip: a crank coaxial with the hip flexion drives the calf through a
parallelogram (crank, coupler rod, calf lever, thigh), so the crank angle is the calf's pitch
in the hip frame. The knee and rod hinges are passive; the knee hinge holds the spring
(stiffness with its rest angle at the standing pose), and a MuJoCo `connect` equality between
the rod's end and the calf lever closes the loop.

Joint angles are absolute pitches in the leg's sagittal plane: hip flexion is the thigh's pitch
and 0 points it straight down; the knee is the calf's pitch relative to the thigh; positive
pitch turns "down" towards -x (backwards). Bodies are written in the standing pose with each
joint's `ref` at its standing angle, so the model's qpos0 is the standing pose; the keyframe
``home`` holds the same qpos and the matching ctrl. Only the feet and the torso collide, and
only with the floor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from tt.sim.designs.base import ContinuousParam, Design, DesignSpace, DiscreteParam
from tt.sim.designs.mjcf import JointSpec, actuators_xml, axis_angle_quat, chain_xml, fmt, header_xml
from tt.sim.designs.viperx import _JOINTS as _ARM_JOINTS
from tt.sim.designs.viperx import _ROLES as _ARM_ROLES
from tt.sim.designs.viperx import arm_parts

ARM_MOUNTS = ("fixed", "rail")
LEG_TYPES = ("serial", "linkage")
KNEE_DIRECTIONS = ("forward", "backward")
#: Legs in body order: front left, front right, rear left, rear right.
LEGS = ("fl", "fr", "rl", "rr")

ARM_DLEN_RANGE = (-0.10, 0.40)
ARM_MOUNT_RANGE = (-0.20, 0.20)
BODY_LENGTH_RANGE = (0.10, 0.50)
LEG_LINK_RANGE = (0.10, 0.30)
LEG_YAW_RANGE = (-0.7, 0.7)
BATTERY_RANGE = (-0.20, 0.20)

# ---------------------------------------------------------------- geometry [m], densities [kg/m^3]
#: Length of the front and rear torso blocks that hold the hips; with the battery box's half
#: length it keeps the battery inside the torso over the whole battery_x range.
HIP_BLOCK_LENGTH = 0.18
TORSO_WIDTH = 0.20
TORSO_HEIGHT = 0.10
#: A hollow shell with electronics: ~3.9 kg for the nominal 0.56 m torso.
TORSO_DENSITY = 350.0
#: Battery box half sizes and the density of a lithium pack (~2.2 kg), laid across the torso.
BATTERY_HALF = (0.03, 0.08, 0.045)
BATTERY_DENSITY = 2500.0
#: Lateral offset from the abduction axis to the leg's sagittal plane (outboard).
HIP_OFFSET = 0.08
#: Hip motor housings (cylinders: radius, half length) and the smaller knee motor of a serial leg.
MOTOR_RADIUS = 0.04
MOTOR_HALF_LENGTH = 0.03
KNEE_MOTOR = (0.035, 0.025)
THIGH_RADIUS = 0.02
CALF_RADIUS = 0.015
FOOT_RADIUS = 0.02
#: Linkage: crank and calf-lever length (the crank is the knee motor's output disc, the rod
#: pinned at its rim), and the outboard offset of the linkage plane from the thigh so the rod
#: runs beside the thigh.
LEVER_LENGTH = 0.04
LINKAGE_OFFSET = 0.05
ROD_RADIUS = 0.01
LEVER_RADIUS = 0.012
#: Arm base plate (cylinder radius, half height); the rail (half width, half height), which
#: stops RAIL_END short of the torso's ends, and the carriage's end clearance on it.
ARM_PLATE = (0.06, 0.02)
RAIL_HALF = (0.02, 0.01)
RAIL_END = 0.02
RAIL_MARGIN = 0.06

#: Standing pose: hip-to-foot depth = |l1 - l2| + STANCE_FRACTION * (reachable span), which
#: bends the knee about 90 degrees when thigh and calf are equal (a dog's stance).
STANCE_FRACTION = 0.7

# ---------------------------------------------------------------- joints and actuators
#: Leg actuators: stiff position servos so a 10-17 kg robot stands with a few mm of sag; force
#: limits [N m] a little above a Unitree Go2's (23.7 hip, 45 knee) for the arm's extra load.
LEG_KP = 500.0
LEG_FORCE = {"hip_abd": 40.0, "hip_flex": 40.0, "knee": 60.0, "crank": 60.0}
LEG_ARMATURE = 0.03
LEG_DAMPING = 1.0
#: Typical inertia [kg m^2] of a leg link about its joint, for the actuator damping.
LEG_LINK_INERTIA = 0.02
HIP_ABD_RANGE = (-0.8, 0.8)
HIP_FLEX_RANGE = (-2.4, 2.4)
CRANK_RANGE = (-2.6, 2.6)
#: Knee range for the knee bending forward (positive pitch); backward knees mirror it. The
#: straight leg is excluded: the parallelogram is singular there.
KNEE_RANGE_FORWARD = (0.1, 2.8)
#: Spring of the linkage's passive knee [N m/rad]; the equality's solref [s, -] and solimp are
#: stiffer than MuJoCo's defaults so the loop stretches well under a millimetre standing.
KNEE_SPRING = 30.0
PASSIVE_DAMPING = 0.2
LINKAGE_SOLREF = (0.004, 1.0)
LINKAGE_SOLIMP = (0.99, 0.999, 0.001)
RAIL_KP, RAIL_FORCE, RAIL_ARMATURE = 3000.0, 300.0, 0.5
#: The arm's nominal upper arm and forearm [m] (a WidowX-250-sized arm; the forearm is 0.10 m
#: before the forearm roll and the rest after it). Its force limits scale with their sum
#: squared: holding torque grows with link mass times lever arm.
ARM_UPPER = 0.25
ARM_FOREARM = 0.25
FOOT_FRICTION = (1.0, 0.02, 0.01)


@dataclass(frozen=True)
class LegPose:
    """Standing pose of one leg in its sagittal plane, foot straight below the hip flexion axis.

    depth: hip-to-foot-centre depth [m]; hip_flex: thigh pitch [rad]; knee: calf pitch relative
    to the thigh [rad]; calf_pitch: calf pitch in the hip frame [rad] (= hip_flex + knee, the
    crank angle of a linkage leg).
    """

    depth: float
    hip_flex: float
    knee: float

    @property
    def calf_pitch(self) -> float:
        return self.hip_flex + self.knee


def stance_depth(thigh: float, calf: float) -> float:
    """Hip-to-foot-centre depth [m] of the standing pose for link lengths `thigh`, `calf` [m]."""
    short = abs(thigh - calf)
    return short + STANCE_FRACTION * (thigh + calf - short)


def leg_pose(thigh: float, calf: float, knee: str) -> LegPose:
    """Standing pose of a leg with the knee ahead of ("forward") or behind ("backward") the
    hip-foot line; the foot lies straight below the hip flexion axis."""
    depth = stance_depth(thigh, calf)
    # Law of cosines: angle at the hip between the thigh and the hip-foot line.
    alpha = math.acos(np.clip((thigh**2 + depth**2 - calf**2) / (2 * thigh * depth), -1.0, 1.0))
    # Calf pitch from the knee position (thigh pitched by -alpha puts the knee at +x).
    beta = math.atan2(thigh * math.sin(alpha), depth - thigh * math.cos(alpha))
    sign = 1.0 if knee == "forward" else -1.0
    return LegPose(depth, -sign * alpha, sign * (alpha + beta))


def _pitch(angle: float) -> np.ndarray:
    return axis_angle_quat((0, 1, 0), angle)


def _joint_xml(
    pad: str,
    name: str,
    axis,
    rng: tuple[float, float] | None,
    ref: float,
    *,
    armature: float,
    damping: float,
    stiffness: float = 0.0,
    kind: str = "hinge",
) -> str:
    """A joint element; `ref` is its angle in the pose the bodies are written in, and the rest
    angle of its spring when `stiffness` [N m/rad] is set; `rng` None leaves it unlimited."""
    rng_attr = f' range="{fmt(rng)}"' if rng is not None else ' limited="false"'
    spring = f' stiffness="{stiffness!r}" springref="{ref!r}"' if stiffness else ""
    ref_attr = f' ref="{ref!r}"' if ref else ""
    return (
        f'{pad}<joint name="{name}" type="{kind}" axis="{fmt(axis)}"{rng_attr}{ref_attr}{spring} '
        f'armature="{armature!r}" damping="{damping!r}"/>'
    )


def _leg_joint(leg: str, role: str, axis, rng) -> JointSpec:
    """The actuated joint `role` (hip_abd | hip_flex | knee | crank) of leg `leg`."""
    # kv near critical damping of the servo on its armature plus a light link, kept low enough
    # for the explicit Euler step (actuator damping is not integrated implicitly).
    kv = 2.0 * math.sqrt(LEG_KP * (LEG_ARMATURE + LEG_LINK_INERTIA))
    return JointSpec(
        f"{leg}_{role}",
        axis,
        rng,
        kp=LEG_KP,
        kv=round(kv, 4),
        force=LEG_FORCE[role],
        armature=LEG_ARMATURE,
        damping=LEG_DAMPING,
    )


@dataclass(frozen=True)
class _Leg:
    """XML of one leg and what the actuator/keyframe sections need from it."""

    body: str
    actuated: list[JointSpec]
    home_qpos: list[float]
    home_ctrl: list[float]
    equality: str


def _leg(name: str, kind: str, knee: str, hip_pos, yaw: float, thigh: float, calf: float) -> _Leg:
    side = 1.0 if name[1] == "l" else -1.0
    pose = leg_pose(thigh, calf, knee)
    knee_range = KNEE_RANGE_FORWARD if knee == "forward" else (-KNEE_RANGE_FORWARD[1], -KNEE_RANGE_FORWARD[0])
    abd = _leg_joint(name, "hip_abd", (1.0, 0.0, 0.0), HIP_ABD_RANGE)
    flex = _leg_joint(name, "hip_flex", (0.0, 1.0, 0.0), HIP_FLEX_RANGE)
    p = "      "
    lines = [
        f'{p}<body name="{name}_hip" pos="{fmt(hip_pos)}" quat="{fmt(axis_angle_quat((0, 0, 1), yaw))}">',
        _joint_xml(p + "  ", abd.name, abd.axis, abd.range, 0.0, armature=abd.armature, damping=abd.damping),
        f'{p}  <geom name="{name}_hip_motor" type="cylinder" size="{MOTOR_RADIUS!r} {MOTOR_HALF_LENGTH!r}" '
        'zaxis="1 0 0" rgba="0.15 0.15 0.15 1"/>',
        f'{p}  <body name="{name}_thigh" pos="0 {side * HIP_OFFSET!r} 0" quat="{fmt(_pitch(pose.hip_flex))}">',
        _joint_xml(
            p + "    ", flex.name, flex.axis, flex.range, pose.hip_flex, armature=flex.armature, damping=flex.damping
        ),
        f'{p}    <geom name="{name}_thigh_motor" type="cylinder" size="{MOTOR_RADIUS!r} '
        f'{MOTOR_HALF_LENGTH!r}" zaxis="0 1 0" rgba="0.15 0.15 0.15 1"/>',
        f'{p}    <geom name="{name}_thigh" type="capsule" fromto="0 0 0 0 0 {-thigh!r}" '
        f'size="{THIGH_RADIUS!r}" rgba="0.55 0.6 0.7 1"/>',
        f'{p}    <body name="{name}_calf" pos="0 0 {-thigh!r}" quat="{fmt(_pitch(pose.knee))}">',
    ]
    q = p + "      "
    actuated = [abd, flex]
    home_qpos = [0.0, pose.hip_flex, pose.knee]
    home_ctrl = [0.0, pose.hip_flex]
    if kind == "serial":
        knee_joint = _leg_joint(name, "knee", (0.0, 1.0, 0.0), knee_range)
        actuated.append(knee_joint)
        home_ctrl.append(pose.knee)
        lines += [
            _joint_xml(
                q,
                knee_joint.name,
                knee_joint.axis,
                knee_range,
                pose.knee,
                armature=knee_joint.armature,
                damping=knee_joint.damping,
            ),
            f'{q}<geom name="{name}_knee_motor" type="cylinder" size="{KNEE_MOTOR[0]!r} {KNEE_MOTOR[1]!r}" '
            'zaxis="0 1 0" rgba="0.15 0.15 0.15 1"/>',
        ]
    else:
        lever_end = (0.0, side * LINKAGE_OFFSET, LEVER_LENGTH)
        lines += [
            _joint_xml(
                q,
                f"{name}_knee",
                (0.0, 1.0, 0.0),
                knee_range,
                pose.knee,
                armature=0.0,
                damping=PASSIVE_DAMPING,
                stiffness=KNEE_SPRING,
            ),
            f'{q}<geom name="{name}_calf_lever" type="capsule" fromto="0 0 0 {fmt(lever_end)}" '
            f'size="{LEVER_RADIUS!r}" rgba="0.8 0.6 0.2 1"/>',
            f'{q}<site name="{name}_calf_pin" pos="{fmt(lever_end)}" size="0.01"/>',
        ]
    lines += [
        f'{q}<geom name="{name}_calf" type="capsule" fromto="0 0 0 0 0 {-calf!r}" size="{CALF_RADIUS!r}" '
        'rgba="0.55 0.6 0.7 1"/>',
        f'{q}<geom name="{name}_foot" type="sphere" pos="0 0 {-calf!r}" size="{FOOT_RADIUS!r}" contype="1" '
        f'friction="{fmt(FOOT_FRICTION)}" rgba="0.1 0.1 0.1 1"/>',
        f'{q}<site name="foot_{name}" pos="0 0 {-calf!r}" size="0.01"/>',
        f"{p}    </body>",
        f"{p}  </body>",
    ]
    equality = ""
    if kind == "linkage":
        crank = _leg_joint(name, "crank", (0.0, 1.0, 0.0), CRANK_RANGE)
        actuated.append(crank)
        rod_ref = -pose.knee  # keeps the rod parallel to the thigh
        home_qpos += [pose.calf_pitch, rod_ref]
        home_ctrl.append(pose.calf_pitch)
        y = side * (HIP_OFFSET + LINKAGE_OFFSET)
        lines += [
            f'{p}  <body name="{name}_crank" pos="0 {y!r} 0" quat="{fmt(_pitch(pose.calf_pitch))}">',
            _joint_xml(
                p + "    ",
                crank.name,
                crank.axis,
                crank.range,
                pose.calf_pitch,
                armature=crank.armature,
                damping=crank.damping,
            ),
            f'{p}    <geom name="{name}_crank_motor" type="cylinder" size="{MOTOR_RADIUS!r} '
            f'{MOTOR_HALF_LENGTH!r}" zaxis="0 1 0" rgba="0.15 0.15 0.15 1"/>',
            f'{p}    <body name="{name}_rod" pos="0 0 {LEVER_LENGTH!r}" quat="{fmt(_pitch(rod_ref))}">',
            _joint_xml(
                p + "      ", f"{name}_rod", (0.0, 1.0, 0.0), None, rod_ref, armature=0.0, damping=PASSIVE_DAMPING
            ),
            f'{p}      <geom name="{name}_rod" type="capsule" fromto="0 0 0 0 0 {-thigh!r}" '
            f'size="{ROD_RADIUS!r}" rgba="0.8 0.6 0.2 1"/>',
            f'{p}      <site name="{name}_rod_pin" pos="0 0 {-thigh!r}" size="0.01"/>',
            f"{p}    </body>",
            f"{p}  </body>",
        ]
        equality = (
            f'    <connect name="{name}_linkage" site1="{name}_rod_pin" site2="{name}_calf_pin" '
            f'solref="{fmt(LINKAGE_SOLREF)}" solimp="{fmt(LINKAGE_SOLIMP)}"/>'
        )
    lines.append(f"{p}</body>")
    return _Leg("\n".join(lines), actuated, home_qpos, home_ctrl, equality)


def _arm(dlen_upper: float, dlen_forearm: float) -> tuple[list[JointSpec], list]:
    """The 6-DoF arm (ViperX joints, WidowX-250 link lengths) with the upper arm and forearm
    changed by `dlen_upper`, `dlen_forearm` [m]; force limits scale with reach squared so longer
    arms can still hold themselves up."""
    names = _ARM_JOINTS["6"]
    axes = [_ARM_ROLES[n][0] for n in names[2:]]
    # arm_parts lengthens the ViperX's segments; shift them to this arm's nominal lengths.
    _, viperx = arm_parts("6", axes, [0.0] * len(names))
    length = {n: float(np.linalg.norm(s.vector)) for n, s in zip(names, viperx)}
    upper = ARM_UPPER - length["shoulder"] + dlen_upper
    fore = ARM_FOREARM - length["elbow"] - length["forearm_roll"] + dlen_forearm
    dlens = [upper if n == "shoulder" else fore if n == "forearm_roll" else 0.0 for n in names]
    joints, segments = arm_parts("6", axes, dlens)
    reach = ARM_UPPER + ARM_FOREARM
    scale = max(1.0, ((reach + dlen_upper + dlen_forearm) / reach) ** 2)
    joints = [replace(j, name=f"arm_{j.name}", force=j.force * scale) for j in joints]
    return joints, segments


#: Height [m] of the nominal design's arm mount (the top of its arm plate) above the floor when
#: standing: torso centre at the standing height of 0.20 m legs, plus half the torso, plus the plate.
NOMINAL_ARM_MOUNT_Z = round(stance_depth(0.20, 0.20) + FOOT_RADIUS + 0.5 * TORSO_HEIGHT + 2 * ARM_PLATE[1], 9)


class QuadrupedSpace(DesignSpace):
    """The quadruped manipulator design space."""

    name = "quadruped"
    has_contacts = True
    ee_count = 1
    # Library single-arm motions are authored for an arm standing at the world origin; lifted by
    # the nominal arm mount's height (0.39 m) they put that mount where the nominal quadruped's
    # is, so they run in front of and above the body at standing height. The quadruped's arm is
    # 0.1 m shorter than the library's ViperX; its base (moved by the legs) covers the difference.
    motion_offset = (0.0, 0.0, NOMINAL_ARM_MOUNT_Z)
    places_motions = False

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        return (
            DiscreteParam("arm_mount", ARM_MOUNTS),
            *(DiscreteParam(f"leg_{leg}", LEG_TYPES) for leg in LEGS),
            DiscreteParam("knee_front", KNEE_DIRECTIONS),
            DiscreteParam("knee_back", KNEE_DIRECTIONS),
        )

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        return (
            ContinuousParam("arm_dlen_upper", *ARM_DLEN_RANGE),
            ContinuousParam("arm_dlen_forearm", *ARM_DLEN_RANGE),
            ContinuousParam("arm_mount_x", *ARM_MOUNT_RANGE),
            ContinuousParam("body_length", *BODY_LENGTH_RANGE),
            ContinuousParam("thigh_length", *LEG_LINK_RANGE),
            ContinuousParam("calf_length", *LEG_LINK_RANGE),
            *(ContinuousParam(f"leg_yaw_{leg}", *LEG_YAW_RANGE, "rad") for leg in LEGS),
            ContinuousParam("battery_x", *BATTERY_RANGE),
        )

    def nominal(self) -> Design:
        """Fixed arm, serial legs with backward knees: a Go2-sized dog with a WidowX-sized arm."""
        discrete = (0, 0, 0, 0, 0, KNEE_DIRECTIONS.index("backward"), KNEE_DIRECTIONS.index("backward"))
        values = {"body_length": 0.20, "thigh_length": 0.20, "calf_length": 0.20}
        return Design(self.name, discrete, tuple(values.get(p.name, 0.0) for p in self.continuous_params(discrete)))

    def standing_height(self, design: Design) -> float:
        """Height [m] of the torso centre above the floor in the ``home`` pose (feet touching z=0)."""
        self.validate(design)
        names = [p.name for p in self.continuous_params(design.discrete)]
        values = dict(zip(names, design.continuous))
        return stance_depth(values["thigh_length"], values["calf_length"]) + FOOT_RADIUS

    def _mjcf(self, discrete, values, options) -> str:
        body_length = values["body_length"]
        torso_length = body_length + 2 * HIP_BLOCK_LENGTH
        hip_x = 0.5 * (body_length + HIP_BLOCK_LENGTH)
        thigh, calf = values["thigh_length"], values["calf_length"]
        legs = []
        for leg in LEGS:
            knee = options["knee_front"] if leg[0] == "f" else options["knee_back"]
            hip_pos = (hip_x if leg[0] == "f" else -hip_x, (0.5 if leg[1] == "l" else -0.5) * TORSO_WIDTH, 0.0)
            legs.append(_leg(leg, options[f"leg_{leg}"], knee, hip_pos, values[f"leg_yaw_{leg}"], thigh, calf))

        arm_joints, arm_segments = _arm(values["arm_dlen_upper"], values["arm_dlen_forearm"])
        arm_actuated = list(arm_joints)
        mount_x = values["arm_mount_x"]
        plate_r, plate_h = ARM_PLATE
        top = 0.5 * TORSO_HEIGHT
        chain = chain_xml("", arm_joints, arm_segments, "ee_0", indent="  ")
        chain = "\n".join("      " + line for line in chain.splitlines())
        if options["arm_mount"] == "rail":
            # The carriage may travel the whole back, whatever its home position.
            travel = 0.5 * torso_length - RAIL_MARGIN
            rail = JointSpec(
                "arm_rail",
                (1.0, 0.0, 0.0),
                (-travel - mount_x, travel - mount_x),
                kp=RAIL_KP,
                kv=round(2.0 * math.sqrt(RAIL_KP * 5.0), 4),
                force=RAIL_FORCE,
                armature=RAIL_ARMATURE,
                damping=5.0,
                kind="slide",
            )
            arm_actuated.insert(0, rail)
            rail_size = (0.5 * torso_length - RAIL_END, *RAIL_HALF)
            rail_geom = (
                f'\n      <geom name="rail" type="box" size="{fmt(rail_size)}" '
                f'pos="0 0 {top + RAIL_HALF[1]!r}" rgba="0.3 0.3 0.3 1"/>'
            )
            mount_z = top + 2 * RAIL_HALF[1] + 2 * plate_h
            mount_open = (
                f'      <body name="arm_mount" pos="{mount_x!r} 0 {mount_z!r}">\n'
                + _joint_xml(
                    "        ",
                    rail.name,
                    rail.axis,
                    rail.range,
                    0.0,
                    armature=rail.armature,
                    damping=rail.damping,
                    kind="slide",
                )
                + "\n"
            )
        else:
            rail_geom = ""
            mount_z = top + 2 * plate_h
            mount_open = f'      <body name="arm_mount" pos="{mount_x!r} 0 {mount_z!r}">\n'
        arm_xml = (
            mount_open
            + f'        <geom name="arm_plate" type="cylinder" size="{plate_r!r} {plate_h!r}" pos="0 0 {-plate_h!r}" '
            f'rgba="0.2 0.2 0.2 1"/>\n' + chain + "\n      </body>"
        )

        height = stance_depth(thigh, calf) + FOOT_RADIUS
        qpos = [0.0, 0.0, height, 1.0, 0.0, 0.0, 0.0]
        ctrl: list[float] = []
        actuated: list[JointSpec] = []
        for leg in legs:
            qpos += leg.home_qpos
            ctrl += leg.home_ctrl
            actuated += leg.actuated
        qpos += [0.0] * len(arm_actuated)
        ctrl += [0.0] * len(arm_actuated)
        actuated += arm_actuated
        equalities = [leg.equality for leg in legs if leg.equality]
        equality_xml = "\n  <equality>\n" + "\n".join(equalities) + "\n  </equality>" if equalities else ""
        torso = (torso_length, TORSO_WIDTH, TORSO_HEIGHT)
        return f"""{header_xml("quadruped", contacts=True)}
  <default>
    <default class="robot">
      <geom contype="0" conaffinity="0"/>
    </default>
  </default>
  <worldbody>
    <light name="sun" pos="0 0 3" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="0 0 0.05" contype="0" conaffinity="1" rgba="0.85 0.85 0.8 1"/>
    <body name="torso" pos="0 0 {height!r}" childclass="robot">
      <freejoint name="root"/>
      <geom name="torso" type="box" size="{fmt(0.5 * np.array(torso))}" density="{TORSO_DENSITY!r}" contype="1" rgba="0.9 0.9 0.92 1"/>
      <geom name="battery" type="box" size="{fmt(BATTERY_HALF)}" pos="{values["battery_x"]!r} 0 0" density="{BATTERY_DENSITY!r}" rgba="0.2 0.7 0.3 1"/>{rail_geom}
      <site name="imu" pos="0 0 0" size="0.01"/>
{chr(10).join(leg.body for leg in legs)}
{arm_xml}
    </body>
  </worldbody>{equality_xml}
  <actuator>
{actuators_xml("", actuated)}
  </actuator>
  <keyframe>
    <key name="home" qpos="{fmt(qpos)}" ctrl="{fmt(ctrl)}"/>
  </keyframe>
</mujoco>
"""  # noqa: E501 (MJCF lines of the template: the model text stays as MuJoCo reads it)


SPACE = QuadrupedSpace()
