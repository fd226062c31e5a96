"""The oracle: MuJoCo C + mink DiffIK, one robot at a time — the slow, trusted reference.

`oracle_rollout` runs every design on every motion with the controller of
`tt.sim.controller` (fixed-base arms) or the whole-body controller of `tt.sim.wbc`
(legged floating-base robots: the quadruped) and returns an `Episode`, the same record
the batched backends fill.
It loops in Python over worlds and control steps on purpose: it is what the fast paths
are checked against, and what final designs are validated with.

Per control step ``k`` (50 Hz) of one world:

1. measured state: ``data.qpos``; at k = 0 the start posture ``controller.initial_q`` (IK
   toward the motion's first pose from ``qpos0``, see `IKConfig.init_iterations`), at rest;
   a floating-base robot is first reset to its ``home`` keyframe (qpos and ctrl) and its
   start posture is the whole-body IK from ``home`` with the feet held at their stance
   points (`tt.sim.wbc.WholeBodyController.initial_q`), so it starts standing;
2. IK target: motion pose ``min(k + lookahead_steps, T - 1)``; ``q_cmd = ik_step(...)``;
3. ``data.ctrl[i] = q_cmd[qpos address of the joint actuator i drives]``, clipped to the
   actuator's ctrlrange where it is limited (so ``ctrl`` is what MuJoCo executes); the
   base (free joint) and passive joints of a whole-body ``q_cmd`` are not commanded;
4. ``substeps`` calls of ``mj_step`` with that command held, then one ``mj_forward`` so
   the recorded site poses and actuator forces/velocities belong to the recorded
   qpos/qvel (``mj_step`` leaves them at the state before its last integration);
5. record qpos, qvel, ctrl, action (= ctrl), act_force, act_vel, the site poses and the
   target at index ``k`` (not the look-ahead one: rewards score the current target);
6. termination: ``alive[k]`` is True while the position error summed over end effectors,
   ``sum_a |ee_pos[k, a] - target_pos[k, a]|``, has stayed within
   ``termination_pos_error`` of the controller's config (`IKConfig`: 0.5 m, `WBCConfig`:
   0.8 m) at this and every earlier step and, for a floating base, the robot has not
   fallen (`tt.sim.wbc.fallen`: base below half its standing height or tilted over
   45 deg); ``fallen[k]`` is True from the step it fell. From the first step that fails,
   the world stops: that step keeps its real record with alive False and every later
   step repeats it, alive False.

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

from tt.kernels.errors import TTError
from tt.sim.backends.base import Robots, resolve_designs
from tt.sim.controller import (
    DiffIKController,
    IKConfig,
    actuated_qpos,
    check_fixed_base,
    ik_step,
    model_name,
)
from tt.sim.designs import Design
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion
from tt.sim.wbc import HOME_KEY, WBCConfig, WholeBodyController, fallen, foot_site_names, free_joint, standing_height

logger = logging.getLogger(__name__)

#: Episode fields recorded per step, and which model size pads each.
_JOINT_FIELDS = {"qpos": "nq", "qvel": "nv", "ctrl": "nu", "action": "nu", "act_force": "nu", "act_vel": "nu"}
_POSE_FIELDS = ("ee_pos", "ee_quat", "target_pos", "target_quat")


def _rollout_one(
    model: mujoco.MjModel,
    sites: tuple[str, ...],
    motion: Motion,
    steps: int,
    config: IKConfig,
    controller: DiffIKController | WholeBodyController,
) -> dict[str, np.ndarray]:
    """Roll one robot along one motion; arrays with leading dim `steps` (unpadded joints).

    `config` is the controller's config (a `WBCConfig` for a `WholeBodyController`)."""
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
        "fallen": np.zeros(steps, dtype=bool),
    }

    data = mujoco.MjData(model)
    base = None
    if isinstance(controller, WholeBodyController):
        key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY)
        if key >= 0:
            mujoco.mj_resetDataKeyframe(model, data, key)
        base = int(model.jnt_qposadr[free_joint(model)])
        height = standing_height(model)
    data.qpos[:] = controller.initial_q(motion.pos[0], motion.quat[0])
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)
    last = None
    for k in range(steps):
        if last is not None:
            for name in ("qpos", "qvel", "ctrl", "act_force", "act_vel", "ee_pos", "ee_quat", "fallen"):
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
        if base is not None:
            rec["fallen"][k] = fallen(data.qpos[base : base + 3], data.qpos[base + 3 : base + 7], height, config)
        if not np.isfinite(error) or error > config.termination_pos_error or rec["fallen"][k]:
            last = k
        else:
            rec["alive"][k] = True
            if ended:
                last = k
    rec["action"] = rec["ctrl"].copy()
    return rec


def oracle_rollout(
    designs: Sequence[Design | mujoco.MjModel] | Robots,
    motions: Sequence[Motion],
    *,
    config: IKConfig = IKConfig(),
    wbc_config: WBCConfig = WBCConfig(),
    progress: bool = False,
) -> Episode:
    """Run every design on every motion in MuJoCo C with the mink controllers.

    designs: D tt Designs (of any spaces) or MjModels with sites ``ee_0``, ``ee_1``, ...
        (or their `Robots`, `tt.sim.backends.base.resolve_designs`): fixed-base arms run the DiffIK controller with
        `config`; floating-base robots (a free joint) with foot sites ``foot_*`` run the
        whole-body controller of `tt.sim.wbc` with `wbc_config` (a free joint without
        feet raises ValueError).
    motions: M motions, all sampled at ``config.control_dt`` (``wbc_config.control_dt`` for
        floating bases); each motion's arm count must
        equal each design's end-effector count.
    progress: show a tqdm bar over worlds.

    Returns an Episode of W = D * M worlds, design-major (world ``d * M + m`` runs design
    ``d`` on motion ``m``), T = the longest motion, float32/bool/long CPU tensors. Joint
    fields are zero-padded to the widest design, and worlds past their motion's end repeat
    their last record with alive False (see the module docstring); ``fallen`` is set for
    floating bases from the step they fell (always False for arms).
    """
    if len(designs) == 0 or len(motions) == 0:
        raise TTError(f"need at least one design and one motion, got {len(designs)} and {len(motions)}")
    robots = designs if isinstance(designs, Robots) else resolve_designs(designs, who="the oracle", one_space=False)
    for m, motion in enumerate(motions):
        if not isinstance(motion, Motion):
            raise TypeError(f"motions[{m}] is a {type(motion).__name__}; expected tt.sim.motions.base.Motion")

    built = list(zip(robots.models, robots.sites))
    floating = [free_joint(model) is not None for model, _ in built]
    used = {"IKConfig": config} if not all(floating) else {}
    if any(floating):
        used["WBCConfig"] = wbc_config
    for m, motion in enumerate(motions):
        for kind, cfg in used.items():
            if abs(motion.dt - cfg.control_dt) > 1e-9:
                raise TTError(
                    f"motions[{m}] ({motion.name!r}) has dt = {motion.dt} s; the oracle controls at "
                    f"{kind}.control_dt = {cfg.control_dt} s and needs motions sampled at that period"
                )
    configs: list[IKConfig] = []
    for d, (model, sites) in enumerate(built):
        if floating[d]:
            foot_site_names(model)  # a floating base without feet raises here
            configs.append(wbc_config)
        else:
            check_fixed_base(model)
            configs.append(config)
        configs[-1].substeps(model)
        for m, motion in enumerate(motions):
            if motion.arms != len(sites):
                raise TTError(
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
    fell = np.zeros((D * M, T), dtype=bool)

    worlds = [(d, m) for d in range(D) for m in range(M)]
    if progress:
        from tqdm import tqdm

        worlds = tqdm(worlds, desc="oracle", unit="world")
    controller, controller_design = None, -1
    for d, m in worlds:
        model, sites = built[d]
        if d != controller_design:  # worlds are design-major: one controller per design
            controller = (WholeBodyController if floating[d] else DiffIKController)(model, configs[d])
            controller_design = d
        rec = _rollout_one(model, sites, motions[m], T, configs[d], controller)
        w = d * M + m
        for name, size in _JOINT_FIELDS.items():
            out[name][w, :, : getattr(model, size)] = rec[name]
        for name in _POSE_FIELDS:
            out[name][w] = rec[name]
        alive[w] = rec["alive"]
        fell[w] = rec["fallen"]
        logger.debug(
            "oracle world %d (design %d, motion %r): %d/%d steps alive", w, d, motions[m].name, alive[w].sum(), T
        )

    f32 = {name: torch.from_numpy(value).to(torch.float32) for name, value in out.items()}
    return Episode(
        **f32,
        alive=torch.from_numpy(alive),
        fallen=torch.from_numpy(fell),
        design_index=torch.arange(D).repeat_interleave(M),
        motion_index=torch.arange(M).repeat(D),
        dt=configs[0].control_dt,
    )


__all__ = ["IKConfig", "WBCConfig", "ik_step", "oracle_rollout"]
