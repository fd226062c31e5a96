"""tt.kernels: Warp kernels that batch-simulate procedural robots, and their launch wrappers.

The bottom layer: it imports nothing of tt's above it, and it takes numbers, not
configs (the layers above turn their settings into the structs and arguments here, e.g.
`tt.sim.controller.IKConfig.ik_weights`). Contact-free kinematic trees of hinge and slide
joints (tt's arm design spaces), W worlds at a time, one thread per world, compiled once
per topology:

* `model`: `TreeModel` (a topology, the per-world model arrays as one flat `@wp.struct`,
  `TreeArrays`, that every tree kernel takes, and their float64 kinematic copies,
  `Kinematics64`), uploaded from host-side `TreeFields` (`tree_model`), which are read
  from MuJoCo models (`tree_fields`) or computed by a design space; `Topology`.
* `fk`: forward kinematics and end-effector Jacobians (MuJoCo's conventions).
* `dynamics`: mass matrix, bias forces, actuators, joint limits, Euler step (MuJoCo's).
* `ik`: the oracle's damped-least-squares DiffIK step (mink's conventions), `IKWeights`.
* `rollout`: the fused closed-loop rollout (controller at 50 Hz, physics at the model's
  timestep), differentiable under `wp.Tape`; the float64 start posture on its own.
* `control_step`: one control period of externally commanded worlds (the DiT controller's physics).
* `pose`: pose errors and the tracking reward; `lie`, `ltdl`: their building blocks.
* `rotations`: host-side (numpy) quaternion <-> matrix conversions every layer shares.

For the other simulators' backends (`tt.sim.mjwarp_backend`, `tt.sim.newton_backend`):

* `wbc`: the quadruped's batched whole-body IK step (float64, any mix of designs).
* `control`: IK targets from motions, actuator commands from joint commands.
* `records`: Episode-shaped records of a step, with the oracle's termination rules.
* `flat_joints`: MuJoCo's actuators, states and site poses on Newton's flat joint vectors.
"""

from tt.kernels.dynamics import simulate
from tt.kernels.fk import forward_kinematics
from tt.kernels.ik import IKWeights, ik_step, ik_weights
from tt.kernels.model import (
    Kinematics64,
    Topology,
    TreeArrays,
    TreeFields,
    TreeModel,
    build_tree_model,
    topology_key,
    topology_of,
    tree_fields,
    tree_model,
)
from tt.kernels.pose import tracking_reward
from tt.kernels.rollout import MotionArrays, RolloutArrays, motion_arrays, rollout_tree, start_postures

__all__ = [
    "IKWeights",
    "Kinematics64",
    "MotionArrays",
    "RolloutArrays",
    "Topology",
    "TreeArrays",
    "TreeFields",
    "TreeModel",
    "build_tree_model",
    "forward_kinematics",
    "ik_step",
    "ik_weights",
    "motion_arrays",
    "rollout_tree",
    "simulate",
    "start_postures",
    "topology_key",
    "topology_of",
    "tree_fields",
    "tree_model",
    "tracking_reward",
]
