"""The arm controller: mink differential IK with look-ahead, as one damped least squares step.

This module is the specification that tt's batched IK kernels (`tt.kernels.ik`) reproduce,
and the place where its settings become the numbers those kernels take
(`IKConfig.ik_weights`, `IKConfig.rollout_args`). The controller
runs at the motion rate (50 Hz); at control step ``k`` it reads the measured joint
positions ``q``, takes the motion pose at index ``min(k + lookahead_steps, T - 1)`` as the
target of every end-effector site, solves one mink IK step for a joint displacement
``dq`` and commands the position actuators to ``clip(q + dq, joint range)``, held for the
physics substeps of that control period. See `IKConfig` for the exact problem.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import mink
import mujoco
import numpy as np

from tt.kernels.errors import TTError


@dataclass(frozen=True)
class IKConfig:
    r"""Settings of the oracle arm controller (mink DiffIK with look-ahead).

    Timing
        control_dt: control period [s] (50 Hz, equal to the motion sample period).
        lookahead_time: how far ahead along the motion the IK target is taken [s]; it
            covers the lag of the position servos. The paper uses 80 ms. With tt's servo
            model (voltage limit and back-EMF, `tt.sim.designs.servos`) the closed loop with
            no look-ahead trails the motion by a median 40 ms over ViperX designs that can
            reach it, and 80 ms leads it by 40 ms; 40 ms leaves a median lag of 0 (10th-90th
            percentile -20..40 ms) and the lowest mean error (`benchmarks/controller_lag.py`).
        Physics runs at the model's own timestep: ``substeps(model) = round(control_dt /
        timestep)`` MuJoCo steps per control step (10 for tt's 0.002 s arms).

    Task weights (mink "costs"; each multiplies both its error and its Jacobian, so it
    enters the normal equations squared)
        position_cost: site translation cost [1/m] -> weight 1.0 on position errors.
        orientation_cost: site rotation cost [1/rad]; 0.5 -> weight 0.25, so 1 rad of
            orientation error trades like 0.5 m of position error. Rewards score
            position far above orientation (sigma_p = 0.01 vs sigma_o = 0.5), and a
            5-DoF design cannot reach every orientation; 0.5 keeps orientation in the
            solution without letting it pull the position off.
        posture_cost: cost [1/rad] toward the home posture ``model.qpos0`` (all zeros for
            tt's arms); 1e-2 -> weight 1e-4, small enough not to bias tracking, large
            enough to pick a posture in the redundant directions of 7-DoF arms.
        lm_damping: mink's per-task Levenberg-Marquardt term on the frame tasks. 0 keeps
            the problem a plain linear least squares (with lm_damping > 0 mink adds
            ``lm_damping * |C e|^2`` to the diagonal, an error-dependent damping a kernel
            would also have to replicate).
        damping: mink's global damping ``lambda`` added to the Hessian diagonal [unitless].
        solver: qpsolvers backend for mink; with no inequality limits ``daqp`` solves the
            unconstrained problem exactly (one Cholesky solve).
    Start
        init_iterations: before the episode the robot is placed, kinematically, where this
            many IK steps from the home posture ``qpos0`` toward the motion's first pose
            lead (`DiffIKController.initial_q`). A robot that starts at home 0.5 m from the
            first target would terminate at step 0; the paper's robots start at their
            motion. 0 starts at ``qpos0``.
        init_damping: the global damping of those start-posture steps (the control loop
            keeps ``damping``). 1e-2: with the loop's 1e-3 the fifty steps from ``qpos0``
            took near-Gauss-Newton jumps that landed in another IK branch for designs 0.3 %
            of a parameter's range apart (32 % of such neighbours started more than 0.05
            rad apart and 12 % flipped between surviving and terminating), so the tracking
            reward was close to noise in the design: its correlation between neighbours
            was 0.79 on viperx-nominal and 0.92 on viperx. Damped, the start follows the
            design (1.00 on both, to two decimals), reaches the first pose (median distance
            at the first record 3.6 cm -> 0.24 cm on viperx-nominal's validation motions) and random
            designs fail less (35 % -> 20 % of pairs below reward 50; mean reward 156 ->
            192; viperx 59 -> 69), `benchmarks/reward_reliability.py`. 3e-2 is as smooth
            but needs about 100 steps to converge; in the loop, 3e-2 lags the target (3.0 cm
            mean error on the nominal arm's reachable circle, against under 2 cm).
    Termination
        termination_pos_error: an arm episode ends at the first recorded step whose
            position error summed over end effectors exceeds this [m] (paper: 0.5 m).

    The IK step, exactly as mink 1.3 builds it (``solve_ik(..., limits=[])``):

    For each end-effector site ``i`` with world pose ``T_b = (R, p)`` (``site_xmat``,
    ``site_xpos``) and target ``T_t = (R_t, p_t)``:

    * error ``e_i = log(T_b^{-1} T_t)`` in se(3), ordered ``(v, w)`` (translation first),
      i.e. the target seen from the site frame (mink's ``target.minus(frame)``). With
      ``w = log(R^T R_t)`` (quaternion taken with ``w >= 0``, angle ``theta = |w|``) and
      ``dp = R^T (p_t - p)``: ``v = V^{-1}(w) dp``, ``V^{-1} = I - 1/2 [w] +
      (1 - theta/2 cot(theta/2)) / theta^2 [w]^2``.
    * Jacobian ``J_i = -Jl^{-1}(e_i) Jb_i`` (= d e_i / d q exactly), where ``Jb_i =
      blockdiag(R^T, R^T) [jacp; jacr]`` is the body Jacobian from ``mj_jacSite`` and
      ``Jl^{-1}(v, w) = [[Jl3^{-1}(w), -Jl3^{-1}(w) Q(v, w) Jl3^{-1}(w)], [0,
      Jl3^{-1}(w)]]`` is the SE(3) inverse left Jacobian (Sola et al. 2018, eqs. 146,
      179b, 180); ``Jl3^{-1}(w) = I - 1/2 [w] + (1/theta^2)(1 - theta sin(theta) /
      (2 (1 - cos(theta)))) [w]^2``. mink uses the identity for ``Jl^{-1}`` when
      ``theta^2 < 1e-10``.
    * weights ``C = diag(c_p, c_p, c_p, c_o, c_o, c_o)``.

    Posture task: error ``q - qpos0``, Jacobian ``I``, weight ``c_q``. Then

        H = sum_i J_i^T C^2 J_i + (c_q^2 + damping) I
        g = -sum_i J_i^T C^2 e_i - c_q^2 (q - qpos0)
        dq = H^{-1} g                       (mink returns v = dq / control_dt)
        q_cmd = clip(q + dq, jnt_range)     (limited joints only)

    The task gain is 1 (dead-beat: the step aims to close the whole error at once), and
    there are no inequality constraints (mink would add configuration limits unless
    given ``limits=[]``), so a kernel solves the same ``nv x nv`` SPD system.
    """

    control_dt: float = 0.02
    lookahead_time: float = 0.04
    position_cost: float = 1.0
    orientation_cost: float = 0.5
    posture_cost: float = 1e-2
    lm_damping: float = 0.0
    damping: float = 1e-3
    init_damping: float = 1e-2
    solver: str = "daqp"
    termination_pos_error: float = 0.5
    init_iterations: int = 50

    def __post_init__(self) -> None:
        if not isinstance(self.init_iterations, int) or self.init_iterations < 0:
            raise TTError(f"IKConfig.init_iterations = {self.init_iterations!r}; must be an integer >= 0")
        positive = {"control_dt": self.control_dt, "termination_pos_error": self.termination_pos_error}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise TTError(f"IKConfig.{name} = {value!r}; must be a positive number")
        nonneg = {
            "lookahead_time": self.lookahead_time,
            "position_cost": self.position_cost,
            "orientation_cost": self.orientation_cost,
            "posture_cost": self.posture_cost,
            "lm_damping": self.lm_damping,
            "damping": self.damping,
            "init_damping": self.init_damping,
        }
        for name, value in nonneg.items():
            if not (math.isfinite(value) and value >= 0):
                raise TTError(f"IKConfig.{name} = {value!r}; must be a finite number >= 0")

    @property
    def lookahead_steps(self) -> int:
        """Look-ahead in control steps, ``round(lookahead_time / control_dt)`` (2 at 50 Hz)."""
        return int(round(self.lookahead_time / self.control_dt))

    def ik_weights(self):
        """The task weights as the kernels' struct (`tt.kernels.ik.IKWeights`)."""
        from tt.kernels.ik import ik_weights

        return ik_weights(
            position_cost=self.position_cost,
            orientation_cost=self.orientation_cost,
            posture_cost=self.posture_cost,
            lm_damping=self.lm_damping,
            damping=self.damping,
        )

    def init_ik_weights(self):
        """The start posture's task weights (`ik_weights` with ``init_damping``)."""
        return replace(self, damping=self.init_damping).ik_weights()

    def rollout_args(self) -> dict:
        """The controller's numbers as keyword arguments of `tt.kernels.rollout.rollout_tree`:
        weights, init_weights, control_dt, lookahead_steps, termination_pos_error, init_iterations."""
        return dict(
            weights=self.ik_weights(),
            init_weights=self.init_ik_weights(),
            control_dt=float(self.control_dt),
            lookahead_steps=self.lookahead_steps,
            termination_pos_error=float(self.termination_pos_error),
            init_iterations=int(self.init_iterations),
        )

    def substeps(self, model: mujoco.MjModel) -> int:
        """Physics steps per control step; raises ValueError if the periods do not divide."""
        ratio = self.control_dt / model.opt.timestep
        n = int(round(ratio))
        if n < 1 or abs(ratio - n) > 1e-6 * ratio:
            raise TTError(
                f"model timestep {model.opt.timestep} s does not divide IKConfig.control_dt "
                f"{self.control_dt} s into a whole number of physics steps"
            )
        return n


#: Joint types the controller commands directly (one qpos per joint).
_HINGE_OR_SLIDE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


def ee_site_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """The end-effector sites of a model: ``ee_0``, ``ee_1``, ... while they exist."""
    names = []
    while mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"ee_{len(names)}") >= 0:
        names.append(f"ee_{len(names)}")
    if not names:
        raise TTError(f"model {model_name(model)!r} has no end-effector site 'ee_0'")
    return tuple(names)


def model_name(model: mujoco.MjModel) -> str:
    """The MJCF model name (``<mujoco model="...">``), for error messages."""
    # MuJoCo stores the model name first in its name buffer.
    return bytes(model.names).split(b"\0", 1)[0].decode() or "<unnamed>"


def check_fixed_base(model: mujoco.MjModel) -> None:
    """Raise ValueError for floating-base models, which this arm controller cannot drive."""
    free = np.flatnonzero(model.jnt_type == int(mujoco.mjtJoint.mjJNT_FREE))
    if free.size:
        joint = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(free[0]))
        raise TTError(
            f"model {model_name(model)!r} has a free joint ({joint!r}): a floating-base robot "
            "(the quadruped) needs the whole-body controller; the DiffIK arm controller "
            "drives fixed-base arms only"
        )


def actuated_qpos(model: mujoco.MjModel) -> np.ndarray:
    """qpos address of the joint each actuator drives, (nu,) int.

    Raises ValueError for actuators that do not act on a hinge or slide joint.
    """
    addr = np.empty(model.nu, dtype=np.int64)
    for i in range(model.nu):
        joint = int(model.actuator_trnid[i, 0])
        kind = int(model.jnt_type[joint]) if joint >= 0 else -1
        if int(model.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_JOINT) or kind not in _HINGE_OR_SLIDE:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i)
            raise TTError(
                f"actuator {i} ({name!r}) of model {model_name(model)!r} does not drive a hinge "
                "or slide joint; the DiffIK controller commands joint position actuators"
            )
        addr[i] = model.jnt_qposadr[joint]
    return addr


class DiffIKController:
    """mink DiffIK for one fixed-base model; `step` maps measured q and targets to q_cmd.

    Holds the mink `Configuration` and tasks so a rollout does not rebuild them at every
    control step. One instance per model; not thread-safe (it owns one MjData).
    """

    def __init__(self, model: mujoco.MjModel, config: IKConfig = IKConfig()):
        check_fixed_base(model)
        self.model = model
        self.config = config
        self.sites = ee_site_names(model)
        self.configuration = mink.Configuration(model)
        self.frame_tasks = [
            mink.FrameTask(
                frame_name=site,
                frame_type="site",
                position_cost=config.position_cost,
                orientation_cost=config.orientation_cost,
                lm_damping=config.lm_damping,
            )
            for site in self.sites
        ]
        self.posture_task = mink.PostureTask(model, cost=config.posture_cost)
        self.posture_task.set_target(model.qpos0)
        limited = model.jnt_limited.astype(bool)
        hinge_or_slide = np.isin(model.jnt_type, _HINGE_OR_SLIDE)
        self._limited_qpos = model.jnt_qposadr[limited & hinge_or_slide]
        self._limited_range = model.jnt_range[limited & hinge_or_slide]

    def step(
        self, q: np.ndarray, targets_pos: np.ndarray, targets_quat: np.ndarray, *, damping: float | None = None
    ) -> np.ndarray:
        """One control step.

        q: measured joint positions, (nq,). targets_pos: site targets [m], (A, 3);
        targets_quat: site target orientations (w, x, y, z), (A, 4); A = number of sites;
        damping: the global damping (None: ``IKConfig.damping``).
        Returns the joint position command q_cmd, (nq,) float64.
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
        tasks = [*self.frame_tasks, self.posture_task]
        dt = self.config.control_dt
        # limits=[]: mink would otherwise add joint-limit inequalities, turning the step into
        # a constrained QP that the batched kernels do not solve; limits are applied by clipping.
        damping = self.config.damping if damping is None else damping
        v = mink.solve_ik(self.configuration, tasks, dt, self.config.solver, damping=damping, limits=[])
        q_cmd = self.configuration.integrate(v, dt)
        q_cmd[self._limited_qpos] = np.clip(
            q_cmd[self._limited_qpos], self._limited_range[:, 0], self._limited_range[:, 1]
        )
        return q_cmd

    def initial_q(self, targets_pos: np.ndarray, targets_quat: np.ndarray) -> np.ndarray:
        """Start posture: `IKConfig.init_iterations` IK steps (damping ``init_damping``) from
        ``qpos0`` toward the targets, each applied kinematically (q <- q_cmd). Returns (nq,) float64."""
        q = self.model.qpos0.copy()
        for _ in range(self.config.init_iterations):
            q = self.step(q, targets_pos, targets_quat, damping=self.config.init_damping)
        return q


def ik_step(
    model: mujoco.MjModel,
    data_or_q: mujoco.MjData | np.ndarray,
    targets_pos: np.ndarray,
    targets_quat: np.ndarray,
    config: IKConfig = IKConfig(),
) -> np.ndarray:
    """One DiffIK control step of one robot (the reference for the batched IK kernels).

    data_or_q: an MjData (its ``qpos`` is the measured state) or joint positions (nq,).
    targets_pos: site targets [m], (A, 3); targets_quat: (w, x, y, z), (A, 4), in the
    order of sites ``ee_0``, ``ee_1``, ... (the caller applies the look-ahead).
    Returns q_cmd, (nq,) float64: ``clip(q + dq, joint range)`` as in `IKConfig`.
    """
    q = data_or_q.qpos.copy() if isinstance(data_or_q, mujoco.MjData) else np.asarray(data_or_q, dtype=np.float64)
    return DiffIKController(model, config).step(q, targets_pos, targets_quat)


__all__ = ["DiffIKController", "IKConfig", "actuated_qpos", "check_fixed_base", "ee_site_names", "ik_step"]
