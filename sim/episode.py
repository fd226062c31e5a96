"""Episode: the batched result of a rollout, the same for every backend."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Episode:
    """States, actions and end-effector poses of W worlds over T control steps (50 Hz).

    Every tensor has leading shape (W, T). Fast backends fill these as zero-copy torch
    views of Warp arrays; the oracle fills them from MuJoCo C. Steps after a world
    terminated hold the last state and have ``alive`` False.

    qpos: joint positions, (W, T, nq)
    qvel: joint velocities, (W, T, nv)
    ctrl: actuator commands executed (joint position targets [rad or m]), (W, T, nu): the
        clean command, or with control perturbation (`tt.sim.rollout.rollout`'s
        ``action_noise`` sigma > 0) clip(action + sigma n, ctrlrange), n ~ N(0, 1)
    action: the controller's clean command clip(q_cmd, ctrlrange), computed at the state
        the step started from (perturbed or not), logged for learning (RoboToken control
        tokens), (W, T, nu); the same tensor as ctrl without perturbation
    act_force: actuator forces [N m or N], (W, T, nu)
    act_vel: actuator velocities [rad/s or m/s], (W, T, nu)
    ee_pos: end-effector positions [m], (W, T, A, 3)
    ee_quat: end-effector orientations (w, x, y, z), (W, T, A, 4)
    target_pos: targets [m], (W, T, A, 3)
    target_quat: target orientations (w, x, y, z), (W, T, A, 4)
    alive: step executed before termination, (W, T) bool
    fallen: the robot fell at or before this step (floating bases), (W, T) bool
    design_index: which input design each world ran, (W,) long
    motion_index: which input motion each world ran, (W,) long
    dt: control period [s]
    """

    qpos: torch.Tensor
    qvel: torch.Tensor
    ctrl: torch.Tensor
    action: torch.Tensor
    act_force: torch.Tensor
    act_vel: torch.Tensor
    ee_pos: torch.Tensor
    ee_quat: torch.Tensor
    target_pos: torch.Tensor
    target_quat: torch.Tensor
    alive: torch.Tensor
    fallen: torch.Tensor
    design_index: torch.Tensor
    motion_index: torch.Tensor
    dt: float

    @property
    def worlds(self) -> int:
        return self.qpos.shape[0]

    @property
    def steps(self) -> int:
        return self.qpos.shape[1]

    def lengths(self) -> torch.Tensor:
        """Number of executed steps per world, (W,) long."""
        return self.alive.sum(dim=1)
