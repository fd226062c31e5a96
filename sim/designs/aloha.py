"""ALOHA-like bimanual station: two ViperX-like 6-DoF arms on a shared, mirror-symmetric mount.

Discrete choice (paper, appendix "Procedural Generation"):
  mount: upright_facing | vertical_sides | upside_down
Continuous choices:
  mount_x: position of both bases along x [m] in [-0.40, 0]
  interarm_distance: distance between the two bases along y [m] in [0.40, 0.60]
  mount_z: height of the mounting frame above the table [m] in [0.60, 0.90]
      (side and hanging mounts only; upright arms stand on the table)
  arm_extension: upper-arm length beyond the 0.05 m shoulder bracket [m] in [0.10, 0.50]
  forearm_extension: forearm tube beyond the 0.10 m elbow bracket [m] in [0.05, 0.25]

World frame: the table top is z = 0, x points away from the operator into the workspace,
the left arm (site ``ee_0``) is at +y and the right arm (``ee_1``) at -y. Base positions
(left arm; the right one is its mirror image) and what z means for each mount:

  upright_facing: base on the table at (mount_x, +d/2, 0). The arms face the workspace
      in front of them: at zero waist angle each arm reaches along +x, and the waist
      (range +-pi) turns it toward the other arm. ALOHA's arms face each other across the
      shared workspace; with 0.4-0.6 m between bases, shorter than two arm reaches, that
      workspace lies in front of the pair.
  vertical_sides: base on a side wall of the frame at (mount_x, +d/2, mount_z), its axis
      horizontal, pointing at the other arm (-y); the forearm points along +x.
  upside_down: base hanging from the top bar of the frame at (mount_x, +d/2, mount_z),
      its axis pointing down; the forearm points along +x.

Symmetry: the right arm is the mirror image of the left through the XZ plane
(`tt.sim.designs.mjcf.mirror_joint_xz`): its base pose is mirrored, its link offsets are
mirrored, and its hinge axes are mirrored as pseudovectors (roll and yaw axes flip sign,
pitch axes stay). Equal joint values on both arms therefore give mirror-image poses:
``p_right = M p_left`` and ``R_right = M R_left M`` with ``M = diag(1, -1, 1)``, and the
site quaternion ``(w, x, y, z)`` of the right arm is ``(w, -x, y, -z)`` of the left.
Both arms share the joint ranges and gains.

The nominal design is the ALOHA follower arm (ViperX 300 S: 0.30 m upper arm, 0.30 m
forearm) upright at (0, +-0.30, 0); at zero joint angles its end effectors sit at
(0.47, +-0.30, 0.427) with the identity orientation (gripper forward, level).
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
    axis_angle_quat,
    chain_xml,
    fmt,
    header_xml,
    mirror_joint_xz,
    mirror_quat_xz,
    mirror_segment_xz,
    stiffen_for_gravity,
)
from tt.sim.designs.viperx import _ROLES, arm_parts, mount_pose

MOUNTS = ("upright_facing", "vertical_sides", "upside_down")

#: Orientation (w, x, y, z) of the left base for each mount; positions come from the
#: continuous choices. Side: base z axis toward the right arm (-y), x forward.
#: Hanging: base z axis down, x forward.
MOUNT_POSES = {
    "upright_facing": ((0.0, 0.0, 0.0), axis_angle_quat((1, 0, 0), 0.0)),
    "vertical_sides": ((0.0, 0.0, 0.0), axis_angle_quat((1, 0, 0), np.pi / 2)),
    "upside_down": ((0.0, 0.0, 0.0), axis_angle_quat((1, 0, 0), np.pi)),
}

#: Minimal link lengths [m] that the extensions add to: the shoulder bracket below the
#: upper-arm tube and the elbow bracket before the forearm roll (the ViperX 6-DoF split).
SHOULDER_BRACKET = 0.05
ELBOW_BRACKET = 0.10

#: ViperX 300 S link lengths the nominal design reproduces [m].
_VIPERX_UPPER_ARM = 0.30
_VIPERX_FOREARM_TUBE = 0.20

#: Largest end-effector sag [m] of the home posture under gravity that the servo
#: stiffness is sized for (static, linearised); the test allows 1 cm with the transient.
HOME_SAG = 0.004

_ARM_DOF = "6"
#: Axes of the joints after the shoulder (elbow, forearm roll, wrist angle, wrist rotate):
#: the nominal ViperX axes.
_UPPER_AXES = tuple(_ROLES[j][0] for j in ("elbow", "forearm_roll", "wrist_angle", "wrist_rotate"))

_PARAMS = {
    "mount_x": ContinuousParam("mount_x", -0.40, 0.0),
    "interarm_distance": ContinuousParam("interarm_distance", 0.40, 0.60),
    "mount_z": ContinuousParam("mount_z", 0.60, 0.90),
    "arm_extension": ContinuousParam("arm_extension", 0.10, 0.50),
    "forearm_extension": ContinuousParam("forearm_extension", 0.05, 0.25),
}

_NOMINAL = {
    "mount_x": 0.0,
    "interarm_distance": 0.60,
    "mount_z": 0.75,
    "arm_extension": _VIPERX_UPPER_ARM - SHOULDER_BRACKET,
    "forearm_extension": _VIPERX_FOREARM_TUBE,
}


def aloha_arm(arm_extension: float, forearm_extension: float) -> tuple[list[JointSpec], list[Segment]]:
    """Joints and segments of the left arm (role gains, before sizing for gravity).

    The shoulder segment is ``SHOULDER_BRACKET + arm_extension`` long and the forearm
    roll segment ``forearm_extension``; the elbow bracket (0.10 m), waist (0.127 m) and
    wrist and gripper segments keep their ViperX lengths.
    """
    upper = SHOULDER_BRACKET + arm_extension
    # arm_parts takes length changes relative to the ViperX segment lengths.
    dlens = [0.0, upper - _VIPERX_UPPER_ARM, 0.0, forearm_extension - _VIPERX_FOREARM_TUBE, 0.0, 0.0]
    return arm_parts(_ARM_DOF, _UPPER_AXES, dlens)


class AlohaSpace(DesignSpace):
    """The ALOHA design space (two mirrored ViperX-like arms)."""

    name = "aloha"
    ee_count = 2

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        return (DiscreteParam("mount", MOUNTS),)

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        names = ["mount_x", "interarm_distance", "mount_z", "arm_extension", "forearm_extension"]
        if MOUNTS[discrete[0]] == "upright_facing":
            names.remove("mount_z")
        return tuple(_PARAMS[n] for n in names)

    def nominal(self) -> Design:
        discrete = (MOUNTS.index("upright_facing"),)
        return Design(self.name, discrete, tuple(_NOMINAL[p.name] for p in self.continuous_params(discrete)))

    def _mjcf(self, discrete, values, options) -> str:
        joints, segments = aloha_arm(values["arm_extension"], values["forearm_extension"])
        mount = options["mount"]
        pose = {
            "mount_x": values["mount_x"],
            "mount_y": values["interarm_distance"] / 2,
            "mount_z": values.get("mount_z", 0.0),
            "mount_yaw": 0.0,
        }
        pos, quat = mount_pose(mount, pose, MOUNT_POSES)
        draft = _station_xml(pos, quat, joints, segments)
        # Longer arms carry more: size the servos from the draft's gravity load (the right
        # arm mirrors the left, so the left arm's loads and levers are both arms').
        sized = stiffen_for_gravity(
            mujoco.MjModel.from_xml_string(draft), {f"left_{j.name}": j for j in joints}, ("ee_0",), HOME_SAG
        )
        joints = [sized[f"left_{j.name}"] for j in joints]
        return _station_xml(pos, quat, joints, segments)


def _station_xml(pos: np.ndarray, quat: np.ndarray, joints: list[JointSpec], segments: list[Segment]) -> str:
    """MJCF of the two arms: the left one at `pos`, `quat`, the right one its mirror image."""
    right_joints = [mirror_joint_xz(j) for j in joints]
    right_segments = [mirror_segment_xz(s) for s in segments]
    mirrored_pos = pos * np.array([1.0, -1.0, 1.0]) + 0.0
    bodies = []
    for side, p, q, js, ss, site in (
        ("left", pos, quat, joints, segments, "ee_0"),
        ("right", mirrored_pos, mirror_quat_xz(quat), right_joints, right_segments, "ee_1"),
    ):
        chain = chain_xml(f"{side}_", js, ss, site, indent="  ")
        chain = "\n".join("    " + line for line in chain.splitlines())
        bodies.append(
            f"""    <body name="{side}_base" pos="{fmt(p)}" quat="{fmt(q)}">
      <geom name="{side}_base_plate" type="cylinder" size="0.06 0.02" pos="0 0 -0.02" rgba="0.2 0.2 0.2 1"/>
{chain}
    </body>"""
        )
    actuators = actuators_xml("left_", joints) + "\n" + actuators_xml("right_", right_joints)
    body_text = "\n".join(bodies)
    return f"""{header_xml("aloha", contacts=False)}
  <worldbody>
{body_text}
  </worldbody>
  <actuator>
{actuators}
  </actuator>
</mujoco>
"""


SPACE = AlohaSpace()
