"""The quadruped's whole-body controller: stance-constrained mink differential IK, and the fall test.

The robot never steps: its feet stay at their stance points (the foot sites of the
``home`` keyframe, on the floor) for the whole episode, and the end effector is tracked
by the base (6 unactuated DoF, moved through the legs) and the arm together. Like the arm
controller of `tt.sim.controller` it runs at the motion rate (50 Hz) with the same 80 ms
look-ahead and returns joint position targets ``clip(q + dq, joint range)``; only the
actuated joints' entries reach the actuators (through ``actuator_trnid``). See
`WBCConfig` for the exact problem, which is again one unconstrained linear least squares
(``solve_ik(..., limits=[])``) that a batched kernel can reproduce (`tt.kernels.wbc`;
`tt.sim.wbc_model.build_wbc_model` gives it these settings as numbers and arrays).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mink
import mujoco
import numpy as np

from tt.kernels.errors import TTError
from tt.sim.controller import IKConfig, actuated_qpos, ee_site_names, model_name

#: Prefix of the foot site names (``foot_fl``, ...); a floating-base model needs at least one.
FOOT_SITE_PREFIX = "foot_"
#: Keyframe with the standing pose (qpos and ctrl) that episodes start from.
HOME_KEY = "home"

_HINGE_OR_SLIDE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


@dataclass(frozen=True)
class WBCConfig(IKConfig):
    r"""Settings of the oracle whole-body controller; extends the arm's `IKConfig`.

    Inherited and used as for the arm: ``control_dt``, ``lookahead_time`` (80 ms here, the
    paper's: the arm's 40 ms was measured on the fixed-base arms only),
    ``position_cost`` / ``orientation_cost`` of the end-effector frame task, ``damping``
    (1e-3 on every DoF, base included), ``solver``, ``init_iterations``. ``posture_cost``
    is the arm joints' posture cost [1/rad or 1/m] (1e-2 as on the arms).
    ``termination_pos_error`` defaults to the paper's 0.8 m for the quadruped, and
    ``lm_damping`` to 1.0 instead of the arm's 0.

    The weights were chosen on 8 designs (the nominal one and 7 random ones) x 3
    validation motions (reach_place:100, wipe:101, hammer:102, moved by the space's
    ``motion_offset``) on the oracle; the numbers quoted below are from that set. With
    these defaults: mean position error 2.2 cm (nominal design 1.2 cm), no fall, feet
    within 15 mm of their stance points, base tilt within 10 deg. The nominal design
    gets about 1.2 cm whatever the weights; they matter for designs that reach the edge
    of their workspace, where the base has to help and the feet can slip.

        lm_damping: Levenberg-Marquardt term of the end-effector task: mink adds
            ``lm_damping * |C e_ee|^2`` (the task's weighted squared error, one scalar)
            to the diagonal of ``H``. It vanishes while the target is tracked (1 cm of
            error adds 1e-4) and grows for targets out of reach (10 cm adds 1e-2). There,
            a dead-beat step with joints clipped at their limits alternates between two
            postures every control step; on an arm that is a local jitter, on the
            quadruped the whole body shakes with it. With 0: mean error 4.0 cm, and one
            robot skated 43 cm across the floor.

    Task weights (mink "costs": each scales its error and Jacobian, so it enters the
    normal equations squared)
        foot_cost: position cost [1/m] of each foot site toward its stance point.
            10 -> weight 100 against the end effector's 1: a foot gives way by about 1 %
            of what the end effector asks of it, so the stance acts as a near-hard
            constraint while the problem stays one least squares (no equality block).
            Weights up to 100 against the damping's 1e-3 keep ``H``'s condition number
            near 1e5, which a float32 kernel still solves to about 1e-2 relative. 30
            changed nothing measurable: feet that move do so by slipping on the floor,
            not because the IK lets them.
        com_cost: cost [1/m] of the horizontal (x, y) whole-body centre of mass toward
            the centre of the support polygon (the mean of the stance points); the
            vertical is free. It makes the base lean away from a reaching arm and keeps
            every foot loaded, which is what keeps feet from slipping: the largest slip
            was 35 / 22 / 15 / 14 mm at 0.3 / 1 / 2 / 3, the mean error 2.05 / 1.99 /
            2.16 / 2.22 cm. 2 holds the feet within the 1-2 cm the controller is meant
            to keep for little tracking.
        leg_posture_cost: posture cost [1/rad] of the actuated leg joints toward
            ``home``. With the feet held, the leg angles fix the base pose, so this is the
            base's pull back to its standing height and attitude; it is what the base
            trades against the arm when both could reach a target. 0.1: at 0.03 the base
            tilted up to 26 deg and feet slipped 45 mm, at 0.3 it stayed within 4 deg but
            tracking degraded (mean 2.7 cm) where the base has to help the arm reach.
        equality_cost: cost [1/m] of the model's equality constraints (the linkage legs'
            ``connect`` loops), entered as mink's `EqualityConstraintTask` on MuJoCo's
            constraint residual ``efc_pos`` and Jacobian ``efc_J``. The passive knee and
            rod joints are free variables of the IK; this task keeps their velocities on
            the loop's tangent space (to 1/cost^2 against the other tasks), so the crank
            command the actuator receives is consistent with the calf motion the IK
            wants. It is a weighted row block like the other tasks, rather than an
            elimination of the passive joints through the constraint Jacobian's null
            space, so that a kernel solves the same ``nv x nv`` normal equations. 10
            (weight 100, as the feet) holds the loop to under 1 mm over 60 kinematic
            steps toward a target 20 cm away. With 0 the loops open by 2 cm in those
            steps, and on the oracle the linkage designs' feet slipped by 2-9 cm.
    Fall
        fall_height_fraction: the robot has fallen when its base (free joint) height is
            below this fraction of its standing height (the ``home`` keyframe's base z).
        fall_tilt: ... or when the base's z axis is tilted more than this from the
            vertical [rad] (45 deg).

    The IK step (mink 1.3, ``solve_ik(configuration, tasks, dt, damping=damping,
    limits=[])``) over the model's full tangent space ``v`` (free joint first, then every
    hinge/slide, passive ones included), with the residual rows ``C_i (J_i dq + e_i)``:

    * end effector ``ee_0``: the arm's SE(3) frame task (see `IKConfig`);
    * each foot site: world-frame position error ``p_foot - p_stance``, Jacobian ``jacp``
      (`SitePositionTask`), cost ``foot_cost``;
    * centre of mass: ``c(q) - c*`` with ``c*`` the stance centre, Jacobian
      ``mj_jacSubtreeCom`` of the robot's root body, costs ``(com_cost, com_cost, 0)``;
    * posture: ``q (-) q_home`` with Jacobian ``I`` on the hinge/slide DoF and zero on the
      free joint, costs ``posture_cost`` on arm joints (those on the path to ``ee_0``),
      ``leg_posture_cost`` on the other actuated joints and 0 on passive joints;
    * equality: ``efc_pos`` / ``efc_J`` rows of the equality constraints, ``equality_cost``.

    ``H = sum_i J_i^T C_i^2 J_i + (damping + lm_damping |C_ee e_ee|^2) I``,
    ``dq = -H^{-1} sum_i J_i^T C_i^2 e_i``; ``q_cmd = q (+) dq`` (``mj_integratePos``),
    hinge/slide joints clipped to their ranges.
    """

    lookahead_time: float = 0.08
    termination_pos_error: float = 0.8
    lm_damping: float = 1.0
    foot_cost: float = 10.0
    com_cost: float = 2.0
    leg_posture_cost: float = 0.1
    equality_cost: float = 10.0
    fall_height_fraction: float = 0.5
    fall_tilt: float = math.radians(45.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        nonneg = {
            "foot_cost": self.foot_cost,
            "com_cost": self.com_cost,
            "leg_posture_cost": self.leg_posture_cost,
            "equality_cost": self.equality_cost,
        }
        for name, value in nonneg.items():
            if not (math.isfinite(value) and value >= 0):
                raise TTError(f"WBCConfig.{name} = {value!r}; must be a finite number >= 0")
        if not 0.0 < self.fall_height_fraction < 1.0:
            raise TTError(f"WBCConfig.fall_height_fraction = {self.fall_height_fraction!r}; must be in (0, 1)")
        if not 0.0 < self.fall_tilt < math.pi:
            raise TTError(f"WBCConfig.fall_tilt = {self.fall_tilt!r} rad; must be in (0, pi)")

    def wbc_weights(self):
        """The task weights as the whole-body kernels' struct (`tt.kernels.wbc.WBCWeights`)."""
        from tt.kernels.wbc import wbc_weights

        return wbc_weights(
            position_cost=self.position_cost,
            orientation_cost=self.orientation_cost,
            lm_damping=self.lm_damping,
            damping=self.damping,
            foot_cost=self.foot_cost,
            com_cost=self.com_cost,
            equality_cost=self.equality_cost,
        )


def free_joint(model: mujoco.MjModel) -> int | None:
    """Id of the model's free joint, or None for a fixed-base model; raises for several."""
    free = np.flatnonzero(model.jnt_type == int(mujoco.mjtJoint.mjJNT_FREE))
    if free.size > 1:
        raise TTError(f"model {model_name(model)!r} has {free.size} free joints; tt's robots have at most one")
    return int(free[0]) if free.size else None


def foot_site_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """Sites named ``foot_*`` in site order; raises ValueError when there are none."""
    sites = (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, i) or "" for i in range(model.nsite))
    names = tuple(name for name in sites if name.startswith(FOOT_SITE_PREFIX))
    if not names:
        raise TTError(
            f"model {model_name(model)!r} has a free joint but no foot sites '{FOOT_SITE_PREFIX}*': the "
            "whole-body controller holds a legged robot's feet at their stance points and cannot drive "
            "a floating base without them"
        )
    return names


def home_qpos(model: mujoco.MjModel) -> np.ndarray:
    """qpos of the ``home`` keyframe (the standing pose), (nq,); ``qpos0`` if there is none."""
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY)
    return model.key_qpos[key].copy() if key >= 0 else model.qpos0.copy()


def standing_height(model: mujoco.MjModel) -> float:
    """Base height [m] in the ``home`` pose: the free joint's z there."""
    joint = free_joint(model)
    if joint is None:
        raise TTError(f"model {model_name(model)!r} has no free joint, so no base height")
    return float(home_qpos(model)[model.jnt_qposadr[joint] + 2])


def base_tilt(quat: np.ndarray) -> np.ndarray:
    """Angle [rad] between the base's z axis and the world's, from (w, x, y, z) quaternions
    (..., 4) (need not be unit); shape (...)."""
    quat = np.asarray(quat, dtype=np.float64)
    w, x, y, z = np.moveaxis(quat, -1, 0)
    # R_zz of the rotation, 1 - 2 (x^2 + y^2) for a unit quaternion, normalised here.
    cos = (w * w - x * x - y * y + z * z) / np.maximum(np.sum(quat * quat, axis=-1), 1e-300)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def fallen(
    base_pos: np.ndarray,
    base_quat: np.ndarray,
    standing_height: np.ndarray | float,
    config: WBCConfig = WBCConfig(),
) -> np.ndarray:
    """Whether each robot has fallen: base lower than ``config.fall_height_fraction`` of its
    standing height, or tilted more than ``config.fall_tilt``, or a non-finite state.

    base_pos: base (free joint) positions [m], (..., 3); base_quat: (w, x, y, z), (..., 4);
    standing_height: [m], broadcastable to (...). Returns bool (...).
    """
    base_pos = np.asarray(base_pos, dtype=np.float64)
    base_quat = np.asarray(base_quat, dtype=np.float64)
    finite = np.all(np.isfinite(base_pos), axis=-1) & np.all(np.isfinite(base_quat), axis=-1)
    with np.errstate(invalid="ignore"):
        low = base_pos[..., 2] < config.fall_height_fraction * np.asarray(standing_height, dtype=np.float64)
        tilted = base_tilt(base_quat) > config.fall_tilt
    return ~finite | low | tilted


class SitePositionTask(mink.Task):
    """World-frame position of one site toward a fixed point (a foot on its stance point).

    error ``e = site_xpos - target`` [m], (3,); Jacobian ``d e / d v = jacp`` of
    ``mj_jacSite``, (3, nv); cost [1/m], one for all three axes. mink's `FrameTask` with a
    zero orientation cost is not this: its position rows are the translation of the SE(3)
    log in the site frame, coupled to the site's rotation error, and a point contact has no
    orientation to hold.
    """

    k: int = 3

    def __init__(self, model: mujoco.MjModel, site: str, target: np.ndarray, cost: float):
        super().__init__(cost=np.full(self.k, float(cost)))
        self.site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        if self.site_id < 0:
            raise TTError(f"model {model_name(model)!r} has no site {site!r}")
        self.target = np.asarray(target, dtype=np.float64).reshape(3).copy()

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        return configuration.data.site_xpos[self.site_id] - self.target

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        jac = np.empty((3, configuration.model.nv))
        mujoco.mj_jacSite(configuration.model, configuration.data, jac, None, self.site_id)
        return jac


def _ancestor_dofs(model: mujoco.MjModel, body: int) -> set[int]:
    """DoF indices of the joints on the path from the world to `body`."""
    dofs: set[int] = set()
    while body > 0:
        for j in range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body]):
            if int(model.jnt_type[j]) in _HINGE_OR_SLIDE:
                dofs.add(int(model.jnt_dofadr[j]))
        body = int(model.body_parentid[body])
    return dofs


def stance_points(model: mujoco.MjModel, feet: tuple[str, ...] | None = None) -> np.ndarray:
    """Positions [m] of the foot sites `feet` (default: `foot_site_names`) in the ``home``
    pose, (F, 3) float64: the points the controller holds the feet at."""
    feet = foot_site_names(model) if feet is None else feet
    data = mujoco.MjData(model)
    data.qpos[:] = home_qpos(model)
    mujoco.mj_kinematics(model, data)
    return np.array([data.site(f).xpos for f in feet])


def posture_costs(model: mujoco.MjModel, config: WBCConfig = WBCConfig()) -> np.ndarray:
    """Cost [1/rad or 1/m] of each DoF's posture row, (nv,) float64: ``config.posture_cost``
    on the actuated joints on the path to ``ee_0`` (the arm, rail included),
    ``config.leg_posture_cost`` on the other actuated joints, 0 on passive joints and on
    the free joint."""
    return _posture_dofs(model, config)[2]


def _posture_dofs(model: mujoco.MjModel, config: WBCConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(actuated DoFs (nu,), arm DoFs, posture costs (nv,)); see `posture_costs`."""
    actuated_qpos(model)  # every actuator must drive a hinge or slide joint
    actuated = model.jnt_dofadr[model.actuator_trnid[:, 0]].astype(np.int64)
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ee_site_names(model)[0])
    arm = np.array(sorted(_ancestor_dofs(model, int(model.site_bodyid[site]))), dtype=np.int64)
    cost = np.zeros(model.nv)
    cost[actuated] = config.leg_posture_cost
    cost[np.intersect1d(arm, actuated)] = config.posture_cost
    return actuated, arm, cost


class WholeBodyController:
    """mink whole-body IK for one legged floating-base model (see `WBCConfig`).

    `step` maps the measured qpos and the end-effector targets to q_cmd with the feet held
    at `stance` (the ``home`` foot positions). Same interface as
    `tt.sim.controller.DiffIKController`. One instance per model; not thread-safe.

    Attributes:
        stance: stance points of the foot sites [m], (F, 3), in `feet` order.
        feet: the foot site names, (F,).
        arm_dofs: DoF indices of the joints on the path to ``ee_0`` (the arm, rail included).
        actuated_dofs: DoF index of the joint each actuator drives, (nu,).
    """

    def __init__(self, model: mujoco.MjModel, config: WBCConfig = WBCConfig()):
        joint = free_joint(model)
        if joint is None:
            raise TTError(
                f"model {model_name(model)!r} has no free joint; fixed-base arms use tt.sim.controller.DiffIKController"
            )
        if int(model.jnt_bodyid[joint]) != 1:
            # mink's ComTask reads the subtree of body 1, which must then be the whole robot.
            raise TTError(
                f"model {model_name(model)!r}: the free joint {model.joint(joint).name!r} is on body "
                f"{model.body(model.jnt_bodyid[joint]).name!r}; the whole-body controller needs it on "
                "the first body under the world (the robot's root)"
            )
        self.model = model
        self.config = config
        self.sites = ee_site_names(model)
        self.feet = foot_site_names(model)
        self.q_home = home_qpos(model)
        self.configuration = mink.Configuration(model, self.q_home)
        self.stance = stance_points(model, self.feet)

        self.frame_tasks = [
            mink.FrameTask(
                site,
                "site",
                position_cost=config.position_cost,
                orientation_cost=config.orientation_cost,
                lm_damping=config.lm_damping,
            )
            for site in self.sites
        ]
        self.foot_tasks = [
            SitePositionTask(model, foot, point, config.foot_cost) for foot, point in zip(self.feet, self.stance)
        ]
        self.com_task = mink.ComTask(cost=[config.com_cost, config.com_cost, 0.0])
        centre = self.stance.mean(axis=0)
        self.com_task.set_target(np.array([centre[0], centre[1], 0.0]))

        self.actuated_dofs, self.arm_dofs, posture_cost = _posture_dofs(model, config)
        self.posture_task = mink.PostureTask(model, cost=posture_cost)
        self.posture_task.set_target(self.q_home)
        self.equality_tasks = [mink.EqualityConstraintTask(model, cost=config.equality_cost)] if model.neq > 0 else []
        limited = model.jnt_limited.astype(bool) & np.isin(model.jnt_type, _HINGE_OR_SLIDE)
        self._limited_qpos = model.jnt_qposadr[limited]
        self._limited_range = model.jnt_range[limited]

    @property
    def tasks(self) -> list:
        """The mink tasks of one step, in the order their rows are stacked."""
        return [*self.frame_tasks, *self.foot_tasks, self.com_task, self.posture_task, *self.equality_tasks]

    def step(self, q: np.ndarray, targets_pos: np.ndarray, targets_quat: np.ndarray) -> np.ndarray:
        """One control step.

        q: measured qpos (free joint included), (nq,). targets_pos: end-effector targets
        [m], (A, 3); targets_quat: (w, x, y, z), (A, 4). Returns q_cmd, (nq,) float64: the
        whole-body IK solution, base included; the actuators take ``q_cmd`` at the qpos
        address of their joints (`tt.sim.controller.actuated_qpos`), so the base and the
        passive joints are not commanded.
        """
        q = np.asarray(q, dtype=np.float64)
        targets_pos = np.asarray(targets_pos, dtype=np.float64).reshape(-1, 3)
        targets_quat = np.asarray(targets_quat, dtype=np.float64).reshape(-1, 4)
        if q.shape != (self.model.nq,):
            raise TTError(f"q has shape {q.shape}; model {model_name(self.model)!r} needs ({self.model.nq},)")
        if len(targets_pos) != len(self.sites) or len(targets_quat) != len(self.sites):
            raise TTError(
                f"got {len(targets_pos)} target positions and {len(targets_quat)} orientations; "
                f"model {model_name(self.model)!r} has {len(self.sites)} end effectors {list(self.sites)}"
            )
        self.configuration.update(q)
        for task, pos, quat in zip(self.frame_tasks, targets_pos, targets_quat):
            task.set_target(mink.SE3(wxyz_xyz=np.concatenate([quat, pos])))
        dt = self.config.control_dt
        # limits=[]: the step stays an unconstrained least squares (see WBCConfig); joint
        # ranges are applied by clipping, and the free joint has none.
        v = mink.solve_ik(
            self.configuration, self.tasks, dt, self.config.solver, damping=self.config.damping, limits=[]
        )
        q_cmd = self.configuration.integrate(v, dt)
        q_cmd[self._limited_qpos] = np.clip(
            q_cmd[self._limited_qpos], self._limited_range[:, 0], self._limited_range[:, 1]
        )
        return q_cmd

    def initial_q(self, targets_pos: np.ndarray, targets_quat: np.ndarray) -> np.ndarray:
        """Start posture: `WBCConfig.init_iterations` IK steps from ``home`` toward the targets,
        applied kinematically (q <- q_cmd) with the feet held at their stance points, so the
        robot starts standing, leaning toward its first target. Returns (nq,) float64."""
        q = self.q_home.copy()
        for _ in range(self.config.init_iterations):
            q = self.step(q, targets_pos, targets_quat)
        return q


__all__ = [
    "FOOT_SITE_PREFIX",
    "HOME_KEY",
    "SitePositionTask",
    "WBCConfig",
    "WholeBodyController",
    "base_tilt",
    "fallen",
    "foot_site_names",
    "free_joint",
    "home_qpos",
    "posture_costs",
    "stance_points",
    "standing_height",
]
