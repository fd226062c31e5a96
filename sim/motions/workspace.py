"""Where the skills write their end-effector targets: one `Workspace` per arm.

Single-arm skills are written for a ViperX-300S-like arm standing upright at the world origin
(`SINGLE_ARM`); bimanual skills for two such arms mounted at y = +-0.3 m (`BIMANUAL`), end
effector 0 on the +y arm. `Workspace.contains` is the reachability check the tests apply to
every skill as written (``Skill.motion(seed, placed=False)``). The library's motions are then
placed to start over the base (`tt.sim.motions.place_at_base`), as the paper places its
demonstrations, so where they lie relative to an arm is the design's problem. Positions in
the world frame [m], z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tt.sim.motions.base import MotionError, quat_rotate


@dataclass(frozen=True)
class Workspace:
    """Where one arm's end-effector targets may go.

    mount: arm base position [m]; shoulder: shoulder joint position [m] (the arm's centre
    of reach); low, high: axis-aligned box for target positions [m]; center: middle of
    the region the skills work in [m]; reach: largest target distance from the shoulder
    [m] (below the arm's full stretch, so the wrist keeps some bend); hand: wrist-centre to
    gripper-tip length [m]; wrist_reach: largest wrist-centre distance from the shoulder
    [m] (upper arm + forearm less a margin); max_approach_z: largest upward component of
    the approach axis (grippers point forward or down, not up).
    """

    mount: tuple[float, float, float]
    shoulder: tuple[float, float, float]
    low: tuple[float, float, float]
    high: tuple[float, float, float]
    center: tuple[float, float, float]
    reach: float = 0.62
    hand: float = 0.17
    wrist_reach: float = 0.58
    max_approach_z: float = 0.5

    def contains(self, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """Whether each target pose is inside this workspace.

        pos: positions [m], shape (..., 3); quat: (w, x, y, z), shape (..., 4).
        Returns a bool array of shape (...).
        """
        pos = np.asarray(pos, dtype=np.float64)
        approach = quat_rotate(quat, np.array([1.0, 0.0, 0.0]))
        in_box = np.all((pos >= np.array(self.low) - 1e-9) & (pos <= np.array(self.high) + 1e-9), axis=-1)
        tip = np.linalg.norm(pos - np.array(self.shoulder), axis=-1) <= self.reach
        wrist = np.linalg.norm(pos - self.hand * approach - np.array(self.shoulder), axis=-1) <= self.wrist_reach
        upright = approach[..., 2] <= self.max_approach_z
        return in_box & tip & wrist & upright


#: Height of the nominal ViperX shoulder joint above its mount [m].
SHOULDER_HEIGHT = 0.127

#: The single arm: upright at the world origin, working in front of it.
SINGLE_ARM = Workspace(
    mount=(0.0, 0.0, 0.0),
    shoulder=(0.0, 0.0, SHOULDER_HEIGHT),
    low=(0.15, -0.35, 0.05),
    high=(0.55, 0.35, 0.55),
    center=(0.35, 0.0, 0.25),
)

#: Middle of the single arm's working region [m].
SINGLE_ARM_CENTER = SINGLE_ARM.center

#: Lateral mount offset of the bimanual arms [m]: arm 0 at +y, arm 1 at -y.
BIMANUAL_MOUNT_Y = 0.3

#: The two arms of the bimanual robot; targets of arm 0 stay at y >= 0, of arm 1 at y <= 0.
BIMANUAL = (
    Workspace(
        mount=(0.0, BIMANUAL_MOUNT_Y, 0.0),
        shoulder=(0.0, BIMANUAL_MOUNT_Y, SHOULDER_HEIGHT),
        low=(0.15, 0.0, 0.05),
        high=(0.5, 0.55, 0.5),
        center=(0.33, 0.15, 0.25),
    ),
    Workspace(
        mount=(0.0, -BIMANUAL_MOUNT_Y, 0.0),
        shoulder=(0.0, -BIMANUAL_MOUNT_Y, SHOULDER_HEIGHT),
        low=(0.15, -0.55, 0.05),
        high=(0.5, 0.0, 0.5),
        center=(0.33, -0.15, 0.25),
    ),
)

#: Middle of the shared bimanual workspace [m] (between the arms).
BIMANUAL_CENTER = (0.33, 0.0, 0.25)


def workspaces(arms: int) -> tuple[Workspace, ...]:
    """The workspace of each end effector of a robot with `arms` (1 or 2) end effectors."""
    if arms == 1:
        return (SINGLE_ARM,)
    if arms == 2:
        return BIMANUAL
    raise MotionError(f"arms must be 1 or 2, got {arms}")


__all__ = [
    "BIMANUAL",
    "BIMANUAL_CENTER",
    "BIMANUAL_MOUNT_Y",
    "SHOULDER_HEIGHT",
    "SINGLE_ARM",
    "SINGLE_ARM_CENTER",
    "Workspace",
    "workspaces",
]
