"""tt.kernels: Warp kernels that batch-simulate procedural robots.

Contact-free kinematic trees of hinge and slide joints (tt's arm design spaces), W worlds
at a time, one thread per world, compiled once per topology:

* `model`: `TreeModel` (per-world model arrays built from MuJoCo models) and `Topology`.
* `fk`: forward kinematics and end-effector Jacobians (MuJoCo's conventions).
* `dynamics`: mass matrix, bias forces, actuators, joint limits, Euler step (MuJoCo's).
* `ik`: the oracle's damped-least-squares DiffIK step (mink's conventions).
* `rollout`: the fused closed-loop rollout (controller at 50 Hz, physics at the model's
  timestep), differentiable under `wp.Tape`.
* `pose`: pose errors and the tracking reward; `lie`, `ltdl`: their building blocks.
"""

from tt.kernels.dynamics import simulate
from tt.kernels.fk import forward_kinematics
from tt.kernels.ik import ik_step
from tt.kernels.model import Topology, TreeModel, build_tree_model, topology_key, topology_of
from tt.kernels.pose import tracking_reward
from tt.kernels.rollout import MotionArrays, RolloutArrays, motion_arrays, rollout_tree

__all__ = [
    "MotionArrays",
    "RolloutArrays",
    "Topology",
    "TreeModel",
    "build_tree_model",
    "forward_kinematics",
    "ik_step",
    "motion_arrays",
    "rollout_tree",
    "simulate",
    "topology_key",
    "topology_of",
    "tracking_reward",
]
