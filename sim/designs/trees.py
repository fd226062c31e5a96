"""Designs compiled straight to tree-model fields, grouped by topology (`DesignTrees`).

A design space that can compute its designs' `tt.kernels.model.TreeFields` without
writing and compiling MJCF (`DesignSpace.trees`) hands the warp backend one of these: the
rollout uploads each group's fields as it would MuJoCo-built ones, and the reward reads
size and mass from here instead of from compiled models.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tt.kernels.model import TreeFields


@dataclass(frozen=True)
class DesignTrees:
    """D designs of one space as tree fields, one group per topology.

    space: the design space's name; ee_sites: end-effector site names, in motion order.
    groups: (members, fields) per topology: the design indices of the group, ascending,
        (k,) int64, and their `TreeFields`, one entry per member in that order.
    size: `tt.sim.rewards.robot_size` of each design [m], (D,).
    mass: `tt.sim.rewards.robot_mass` of each design [kg], (D,).
    """

    space: str
    ee_sites: tuple[str, ...]
    groups: tuple[tuple[np.ndarray, TreeFields], ...]
    size: np.ndarray
    mass: np.ndarray

    def __len__(self) -> int:
        return len(self.size)

    def max_dofs(self) -> int:
        """The widest design's joint count (the Episode's qpos width)."""
        return max(f.topology.dof_count for _, f in self.groups)

    def max_actuators(self) -> int:
        """The widest design's actuator count (the Episode's ctrl width)."""
        return max(f.topology.actuator_count for _, f in self.groups)


__all__ = ["DesignTrees"]
