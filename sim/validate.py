"""The oracle: MuJoCo C + mink DiffIK, one robot at a time — the slow, trusted reference.

`oracle_rollout` runs every design on every motion with the controller of
`tt.sim.controller` and returns an `Episode`, the same record the batched backends fill.
It loops in Python over worlds and control steps on purpose: it is what the fast paths
are checked against, and what final designs are validated with.

Per control step ``k`` (50 Hz) of one world:

1. measured state: ``data.qpos``; at k = 0 the start posture ``controller.initial_q`` (IK
   toward the motion's first pose from ``qpos0``, see `IKConfig.init_iterations`), at rest;
2. IK target: motion pose ``min(k + lookahead_steps, T - 1)``; ``q_cmd = ik_step(...)``;
3. ``data.ctrl[i] = q_cmd[qpos address of the joint actuator i drives]``, clipped to the
   actuator's ctrlrange where it is limited (so ``ctrl`` is what MuJoCo executes);
4. ``substeps`` calls of ``mj_step`` with that command held, then one ``mj_forward`` so
   the recorded site poses and actuator forces/velocities belong to the recorded
   qpos/qvel (``mj_step`` leaves them at the state before its last integration);
5. record qpos, qvel, ctrl, action (= ctrl), act_force, act_vel, the site poses and the
   target at index ``k`` (not the look-ahead one: rewards score the current target);
6. termination: ``alive[k]`` is True while the position error summed over end effectors,
   ``sum_a |ee_pos[k, a] - target_pos[k, a]|``, has stayed within
   ``IKConfig.termination_pos_error`` at this and every earlier step. From the first step
   that exceeds it, the world stops: that step keeps its real record with alive False and
   every later step repeats it, alive False.

Padding, for batches that mix robots and motion lengths:
* designs with different DoF: qpos/qvel are padded to the widest nq/nv and
  ctrl/action/act_force/act_vel to the widest nu, with zeros;
* motions of different lengths: T is the longest; past the end of its motion a world
  repeats its last record with alive False, and its target stays the motion's last pose.
"""

from __future__ import annotations

import logging
from typing import Sequence

import mujoco
import numpy as np
import torch

from tt.sim.controller import (
    DiffIKController,
    IKConfig,
    actuated_qpos,
    check_fixed_base,
    ee_site_names,
    ik_step,
    model_name,
)
from tt.sim.designs import Design, get_space
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion

logger = logging.getLogger(__name__)

#: Episode fields recorded per step, and which model size pads each.
_JOINT_FIELDS = {"qpos": "nq", "qvel": "nv", "ctrl": "nu", "action": "nu", "act_force": "nu", "act_vel": "nu"}
_POSE_FIELDS = ("ee_pos", "ee_quat", "target_pos", "target_quat")


def _as_model(design: Design | mujoco.MjModel, index: int) -> tuple[mujoco.MjModel, tuple[str, ...]]:
    """Compiled model and end-effector site names of one input design."""
    if isinstance(design, mujoco.MjModel):
        return design, ee_site_names(design)
    if isinstance(design, Design):
        space = get_space(design.space)
        model = space.model(design)
        sites = space.ee_sites()
        for site in sites:
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site) < 0:
                raise ValueError(f"designs[{index}] of space {design.space!r} has no site {site!r}")
        return model, sites
    raise TypeError(f"designs[{index}] is a {type(design).__name__}; expected a tt Design or a mujoco.MjModel")


def _rollout_one(
    model: mujoco.MjModel,
    sites: tuple[str, ...],
    motion: Motion,
    steps: int,
    config: IKConfig,
    controller: DiffIKController,
) -> dict[str, np.ndarray]:
    """Roll one robot along one motion; arrays with leading dim `steps` (unpadded joints)."""
    substeps = config.substeps(model)
    lookahead = config.lookahead_steps
    qpos_of_actuator = actuated_qpos(model)
    ctrl_limited = model.actuator_ctrllimited.astype(bool)
    ctrl_range = model.actuator_ctrlrange
    site_ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in sites])
    A = len(sites)
    T_motion = motion.steps

    rec = {
        "qpos": np.zeros((steps, model.nq)),
        "qvel": np.zeros((steps, model.nv)),
        "ctrl": np.zeros((steps, model.nu)),
        "act_force": np.zeros((steps, model.nu)),
        "act_vel": np.zeros((steps, model.nu)),
        "ee_pos": np.zeros((steps, A, 3)),
        "ee_quat": np.zeros((steps, A, 4)),
        "target_pos": motion.pos[np.minimum(np.arange(steps), T_motion - 1)],
        "target_quat": motion.quat[np.minimum(np.arange(steps), T_motion - 1)],
        "alive": np.zeros(steps, dtype=bool),
    }

    data = mujoco.MjData(model)
    data.qpos[:] = controller.initial_q(motion.pos[0], motion.quat[0])
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)
    last = None
    for k in range(steps):
        if last is not None:
            for name in ("qpos", "qvel", "ctrl", "act_force", "act_vel", "ee_pos", "ee_quat"):
                rec[name][k] = rec[name][last]
            continue
        goal = min(k + lookahead, T_motion - 1)
        q_cmd = controller.step(data.qpos.copy(), motion.pos[goal], motion.quat[goal])
        ctrl = q_cmd[qpos_of_actuator]
        ctrl[ctrl_limited] = np.clip(ctrl[ctrl_limited], ctrl_range[ctrl_limited, 0], ctrl_range[ctrl_limited, 1])
        data.ctrl[:] = ctrl
        for _ in range(substeps):
            mujoco.mj_step(model, data)
        mujoco.mj_forward(model, data)

        rec["qpos"][k] = data.qpos
        rec["qvel"][k] = data.qvel
        rec["ctrl"][k] = ctrl
        rec["act_force"][k] = data.actuator_force
        rec["act_vel"][k] = data.actuator_velocity
        rec["ee_pos"][k] = data.site_xpos[site_ids]
        for a, sid in enumerate(site_ids):
            mujoco.mju_mat2Quat(rec["ee_quat"][k, a], data.site_xmat[sid])
        error = np.linalg.norm(rec["ee_pos"][k] - rec["target_pos"][k], axis=-1).sum()
        ended = k == T_motion - 1
        if not np.isfinite(error) or error > config.termination_pos_error:
            last = k
        else:
            rec["alive"][k] = True
            if ended:
                last = k
    rec["action"] = rec["ctrl"].copy()
    return rec


def oracle_rollout(
    designs: Sequence[Design | mujoco.MjModel],
    motions: Sequence[Motion],
    *,
    config: IKConfig = IKConfig(),
    progress: bool = False,
) -> Episode:
    """Run every design on every motion in MuJoCo C with the mink DiffIK controller.

    designs: D tt Designs (built with ``get_space(d.space).model(d)``) or MjModels with
        sites ``ee_0``, ``ee_1``, ...; fixed-base arms only (a free joint raises ValueError).
    motions: M motions, all sampled at ``config.control_dt``; each motion's arm count must
        equal each design's end-effector count.
    progress: show a tqdm bar over worlds.

    Returns an Episode of W = D * M worlds, design-major (world ``d * M + m`` runs design
    ``d`` on motion ``m``), T = the longest motion, float32/bool/long CPU tensors. Joint
    fields are zero-padded to the widest design, and worlds past their motion's end repeat
    their last record with alive False (see the module docstring).
    """
    if len(designs) == 0 or len(motions) == 0:
        raise ValueError(f"need at least one design and one motion, got {len(designs)} and {len(motions)}")
    for m, motion in enumerate(motions):
        if not isinstance(motion, Motion):
            raise TypeError(f"motions[{m}] is a {type(motion).__name__}; expected tt.sim.motions.base.Motion")
        if abs(motion.dt - config.control_dt) > 1e-9:
            raise ValueError(
                f"motions[{m}] ({motion.name!r}) has dt = {motion.dt} s; the oracle controls at "
                f"IKConfig.control_dt = {config.control_dt} s and needs motions sampled at that period"
            )

    built = [_as_model(d, i) for i, d in enumerate(designs)]
    for d, (model, sites) in enumerate(built):
        check_fixed_base(model)
        config.substeps(model)
        for m, motion in enumerate(motions):
            if motion.arms != len(sites):
                raise ValueError(
                    f"motions[{m}] ({motion.name!r}) has {motion.arms} arm(s) but designs[{d}] "
                    f"({model_name(model)!r}) has {len(sites)} end effector(s) {list(sites)}"
                )

    D, M = len(built), len(motions)
    T = max(motion.steps for motion in motions)
    A = len(built[0][1])
    sizes = {k: max(getattr(model, k) for model, _ in built) for k in ("nq", "nv", "nu")}
    out = {name: np.zeros((D * M, T, sizes[size])) for name, size in _JOINT_FIELDS.items()}
    out.update({name: np.zeros((D * M, T, A, 3 if name.endswith("pos") else 4)) for name in _POSE_FIELDS})
    alive = np.zeros((D * M, T), dtype=bool)

    worlds = [(d, m) for d in range(D) for m in range(M)]
    if progress:
        from tqdm import tqdm

        worlds = tqdm(worlds, desc="oracle", unit="world")
    controller, controller_design = None, -1
    for d, m in worlds:
        model, sites = built[d]
        if d != controller_design:  # worlds are design-major: one controller per design
            controller, controller_design = DiffIKController(model, config), d
        rec = _rollout_one(model, sites, motions[m], T, config, controller)
        w = d * M + m
        for name, size in _JOINT_FIELDS.items():
            out[name][w, :, : getattr(model, size)] = rec[name]
        for name in _POSE_FIELDS:
            out[name][w] = rec[name]
        alive[w] = rec["alive"]
        logger.debug("oracle world %d (design %d, motion %r): %d/%d steps alive", w, d, motions[m].name, alive[w].sum(), T)

    f32 = {name: torch.from_numpy(value).to(torch.float32) for name, value in out.items()}
    return Episode(
        **f32,
        alive=torch.from_numpy(alive),
        fallen=torch.zeros((D * M, T), dtype=torch.bool),
        design_index=torch.arange(D).repeat_interleave(M),
        motion_index=torch.arange(M).repeat(D),
        dt=config.control_dt,
    )


__all__ = ["IKConfig", "ik_step", "oracle_rollout"]
