"""The quadruped's whole-body controller on the oracle (MuJoCo C + mink): the IK step against
normal equations built from MuJoCo's Jacobians, standing, tracking with the feet planted,
linkage loops, the fall test, and the oracle's records for floating bases.

References: MuJoCo C (``mj_jacSite``, ``mj_jacSubtreeCom``, ``mj_makeConstraint``,
``mju_quat2Mat``, ``mj_kinematics``) for every quantity the controller reads, and the rollouts
of `tt.sim.validate.oracle_rollout` with contact physics for the closed-loop claims.
"""

import math

import mink
import mujoco
import numpy as np
import pytest
import torch

from tt.sim.controller import IKConfig
from tt.sim.designs import Design, get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardInputs, get_reward, metrics
from tt.sim.validate import oracle_rollout
from tt.sim.wbc import (
    WBCConfig,
    WholeBodyController,
    base_tilt,
    fallen,
    foot_site_names,
    standing_height,
)

DT = 0.02


@pytest.fixture(scope="module")
def space():
    return get_space("quadruped")


@pytest.fixture(scope="module")
def nominal(space):
    return space.nominal()


@pytest.fixture(scope="module")
def linkage(space):
    """Every leg a linkage, the arm on its rail, front knees forward: 4 loops, the most DoF."""
    names = [p.name for p in space.discrete_params(space.nominal().discrete)]
    picks = {"arm_mount": 1, "leg_fl": 1, "leg_fr": 1, "leg_rl": 1, "leg_rr": 1, "knee_front": 0, "knee_back": 1}
    discrete = tuple(picks[n] for n in names)
    return Design(space.name, discrete, space.nominal().continuous)


def home_ee(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """ee_0 position [m] and orientation (w, x, y, z) in the home keyframe."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_kinematics(model, data)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, data.site("ee_0").xmat)
    return data.site("ee_0").xpos.copy(), quat


def hold(model: mujoco.MjModel, seconds: float) -> Motion:
    pos, quat = home_ee(model)
    T = int(round(seconds / DT))
    return Motion("hold", np.tile(pos, (T, 1)), np.tile(quat, (T, 1)))


def circle(model: mujoco.MjModel, seconds: float, radius: float = 0.08) -> Motion:
    """A vertical circle (y-z plane) through the home ee pose, orientation held."""
    pos, quat = home_ee(model)
    T = int(round(seconds / DT))
    phase = 2 * np.pi * np.arange(T) / T
    path = pos + radius * np.stack([np.zeros(T), np.sin(phase), np.cos(phase) - 1.0], -1)
    return Motion("circle", path, np.tile(quat, (T, 1)))


def foot_drift(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """Largest distance [m] of each foot site from its stance point over the states, (F,)."""
    ctl = WholeBodyController(model)
    data = mujoco.MjData(model)
    worst = np.zeros(len(ctl.feet))
    for q in qpos:
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        feet = np.array([data.site(f).xpos for f in ctl.feet])
        worst = np.maximum(worst, np.linalg.norm(feet - ctl.stance, axis=1))
    return worst


def pos_error(ep, w: int) -> np.ndarray:
    return (ep.ee_pos[w, :, 0] - ep.target_pos[w, :, 0]).norm(dim=-1).numpy()


def loop_residual(model: mujoco.MjModel, data: mujoco.MjData) -> float:
    """Largest |connect residual| [m] of the equality constraints at data.qpos."""
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_makeConstraint(model, data)
    rows = data.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    return float(np.abs(data.efc_pos[rows]).max())


# ------------------------------------------------------------------ the IK step
def reference_step(model: mujoco.MjModel, ctl: WholeBodyController, q: np.ndarray, pos, quat) -> np.ndarray:
    """`WBCConfig`'s normal equations assembled from MuJoCo's Jacobians and residuals.

    The end-effector rows are mink's FrameTask (checked against the SE(3) formulas in
    test_oracle); the feet, centre of mass, posture and equality rows are built here."""
    cfg = ctl.config
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_makeConstraint(model, data)
    nv = model.nv
    rows = []  # (weights (k,), error (k,), jacobian (k, nv))

    ctl.configuration.update(q)
    ee = ctl.frame_tasks[0]
    ee.set_target(mink.SE3(wxyz_xyz=np.concatenate([quat, pos])))
    c_ee = np.array([cfg.position_cost] * 3 + [cfg.orientation_cost] * 3)
    e_ee = ee.compute_error(ctl.configuration)
    rows.append((c_ee, e_ee, ee.compute_jacobian(ctl.configuration)))

    for foot, point in zip(ctl.feet, ctl.stance):
        jacp = np.zeros((3, nv))
        mujoco.mj_jacSite(model, data, jacp, None, model.site(foot).id)
        rows.append((np.full(3, cfg.foot_cost), data.site(foot).xpos - point, jacp))

    jcom = np.zeros((3, nv))
    mujoco.mj_jacSubtreeCom(model, data, jcom, 1)
    centre = ctl.stance.mean(axis=0)
    rows.append((np.array([cfg.com_cost, cfg.com_cost, 0.0]), data.subtree_com[1] - [centre[0], centre[1], 0.0], jcom))

    e_post = np.zeros(nv)
    mujoco.mj_differentiatePos(model, e_post, 1.0, ctl.q_home, q)
    e_post[:6] = 0.0
    j_post = np.eye(nv)
    j_post[:, :6] = 0.0
    c_post = np.zeros(nv)
    for a in range(model.nu):
        dof = model.jnt_dofadr[model.actuator_trnid[a, 0]]
        c_post[dof] = cfg.posture_cost if model.actuator(a).name.startswith("arm_") else cfg.leg_posture_cost
    rows.append((c_post, e_post, j_post))

    if model.neq:
        eq = data.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
        efc_J = data.efc_J.reshape(data.nefc, nv)
        rows.append((np.full(eq.sum(), cfg.equality_cost), data.efc_pos[eq], efc_J[eq]))

    H = cfg.damping * np.eye(nv) + cfg.lm_damping * np.sum((c_ee * e_ee) ** 2) * np.eye(nv)
    g = np.zeros(nv)
    for c, e, J in rows:
        H += J.T @ (c[:, None] ** 2 * J)
        g += J.T @ (c**2 * e)
    dq = -np.linalg.solve(H, g)
    q_cmd = q.copy()
    mujoco.mj_integratePos(model, q_cmd, dq, 1.0)
    limited = model.jnt_limited.astype(bool) & (model.jnt_type != mujoco.mjtJoint.mjJNT_FREE)
    adr = model.jnt_qposadr[limited]
    q_cmd[adr] = np.clip(q_cmd[adr], model.jnt_range[limited, 0], model.jnt_range[limited, 1])
    return q_cmd


@pytest.mark.parametrize("which", ["nominal", "linkage"])
def test_ik_step_is_the_documented_least_squares(space, nominal, linkage, which):
    design = nominal if which == "nominal" else linkage
    model = space.model(design)
    ctl = WholeBodyController(model)
    rng = np.random.default_rng(3)
    # Away from home: feet off their stance points, loops open, CoM off centre, base tilted.
    q = ctl.q_home.copy()
    q[:3] += rng.normal(0, 0.01, 3)
    q[3:7] += rng.normal(0, 0.03, 4)
    q[3:7] /= np.linalg.norm(q[3:7])
    q[7:] += rng.normal(0, 0.05, model.nq - 7)
    pos, quat = home_ee(model)
    pos = pos + np.array([0.05, -0.04, -0.06])
    quat = np.array([math.cos(0.2), 0.0, math.sin(0.2), 0.0])
    expected = reference_step(model, ctl, q, pos, quat)
    np.testing.assert_allclose(ctl.step(q, pos, quat), expected, atol=1e-9)
    # The posture rows reach the arm (and rail) joints with the arm cost: the reference picks
    # them by name, the controller by the kinematic path to ee_0.
    arm = {
        model.jnt_dofadr[model.actuator_trnid[a, 0]]
        for a in range(model.nu)
        if model.actuator(a).name.startswith("arm_")
    }
    assert set(ctl.arm_dofs.tolist()) == arm


def test_start_posture_keeps_the_feet_planted_and_the_com_centred(space, nominal, linkage):
    """The start posture reaches the first target of a library motion standing on the home
    stance points; the CoM task holds the centre of mass over the support polygon's centre
    (at least twice as close as without it)."""
    motion = for_space([get_motion("reach_place")], "quadruped")[0]
    for design in (nominal, linkage):
        model = space.model(design)
        offset = {}
        for com_cost in (WBCConfig().com_cost, 0.0):
            ctl = WholeBodyController(model, WBCConfig(com_cost=com_cost))
            q = ctl.initial_q(motion.pos[0], motion.quat[0])
            data = mujoco.MjData(model)
            data.qpos[:] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            assert np.linalg.norm(data.site("ee_0").xpos - motion.pos[0, 0]) < 0.01
            assert foot_drift(model, q[None]).max() < 1e-3
            if model.neq:
                assert loop_residual(model, data) < 1e-3
            offset[com_cost] = np.linalg.norm(data.subtree_com[1, :2] - ctl.stance[:, :2].mean(0))
        assert offset[WBCConfig().com_cost] < 0.02
        assert offset[WBCConfig().com_cost] < 0.5 * offset[0.0]


def test_equality_task_keeps_linkage_loops_closed(space, linkage):
    """Kinematic IK steps toward a target 20 cm away: with the equality rows the passive joints
    follow the loops; without them (cost 0) the loops open."""
    model = space.model(linkage)
    pos, _ = home_ee(model)
    target = pos + np.array([0.1, 0.1, -0.15])
    worst = {}
    for cost in (WBCConfig().equality_cost, 0.0):
        ctl = WholeBodyController(model, WBCConfig(equality_cost=cost))
        data = mujoco.MjData(model)
        q = ctl.q_home.copy()
        worst[cost] = 0.0
        for _ in range(60):
            q = ctl.step(q, target, np.array([1.0, 0.0, 0.0, 0.0]))
            data.qpos[:] = q
            worst[cost] = max(worst[cost], loop_residual(model, data))
        assert np.linalg.norm(data.site("ee_0").xpos - target) < 0.01
    assert worst[WBCConfig().equality_cost] < 1e-3
    assert worst[0.0] > 0.01


# ------------------------------------------------------------------ closed loop on contact physics
@pytest.fixture(scope="module")
def nominal_runs(space, nominal):
    model = space.model(nominal)
    library = for_space([get_motion("wipe")], "quadruped")[0]
    motions = [hold(model, 5.0), circle(model, 5.0), library]
    return model, motions, oracle_rollout([nominal], motions)


def test_stands_for_five_seconds_holding_the_home_pose(nominal_runs):
    model, motions, ep = nominal_runs
    T = motions[0].steps
    assert bool(ep.alive[0, :T].all()) and not bool(ep.fallen[0].any())
    qpos = ep.qpos[0, :T, : model.nq].numpy().astype(np.float64)
    h = standing_height(model)
    # Servo sag under the robot's weight: a few mm, and no drift over the 5 s.
    assert np.abs(qpos[:, 2] - h).max() < 0.02
    assert np.abs(qpos[-50:, 2] - qpos[-1, 2]).max() < 1e-3
    assert np.degrees(base_tilt(qpos[:, 3:7])).max() < 2.0
    err = pos_error(ep, 0)[:T]
    assert err.mean() < 0.01 and err[-1] < 0.01
    assert foot_drift(model, qpos).max() < 0.005


def test_tracks_a_circle_with_the_feet_planted(nominal_runs):
    model, motions, ep = nominal_runs
    T = motions[1].steps
    assert bool(ep.alive[1, :T].all()) and not bool(ep.fallen[1].any())
    assert pos_error(ep, 1)[:T].mean() < 0.03
    assert foot_drift(model, ep.qpos[1, :T, : model.nq].numpy().astype(np.float64)).max() < 0.015


def test_tracks_a_library_motion_at_the_space_offset(space, nominal_runs):
    """The library's wipe, moved by QuadrupedSpace.motion_offset, is within the nominal robot's
    whole-body reach: tracked to 3 cm with the feet planted and the body level."""
    model, motions, ep = nominal_runs
    assert space.motion_offset == pytest.approx((0.0, 0.0, 0.39))
    T = motions[2].steps
    assert bool(ep.alive[2, :T].all()) and not bool(ep.fallen[2].any())
    assert pos_error(ep, 2)[:T].mean() < 0.03
    qpos = ep.qpos[2, :T, : model.nq].numpy().astype(np.float64)
    assert foot_drift(model, qpos).max() < 0.015
    assert np.degrees(base_tilt(qpos[:, 3:7])).max() < 10.0


def test_linkage_design_tracks_with_loops_closed(space, linkage):
    model = space.model(linkage)
    motion = circle(model, 3.0)
    ep = oracle_rollout([linkage], [motion])
    assert bool(ep.alive[0].all()) and not bool(ep.fallen[0].any())
    assert pos_error(ep, 0).mean() < 0.03
    qpos = ep.qpos[0, :, : model.nq].numpy().astype(np.float64)
    assert foot_drift(model, qpos).max() < 0.015
    data = mujoco.MjData(model)
    for q in qpos[::10]:
        data.qpos[:] = q
        assert loop_residual(model, data) < 2e-3


# ------------------------------------------------------------------ falls
def test_fall_predicate_on_states():
    cfg = WBCConfig()
    h = 0.3
    up = [1.0, 0.0, 0.0, 0.0]

    def about(axis, deg):
        axis = np.asarray(axis, float) / np.linalg.norm(axis)
        return np.concatenate([[math.cos(math.radians(deg) / 2)], math.sin(math.radians(deg) / 2) * axis])

    pos = np.array([[0, 0, 0.51 * h], [0, 0, 0.49 * h], [0, 0, h], [0, 0, h], [0, 0, h], [0, 0, h], [0, 0, np.nan]])
    quat = np.array(
        [up, up, about([1, 0, 0], 44), about([1, 0, 0], 46), about([1, 1, 0], 46), 2.0 * about([0, 0, 1], 170), up]
    )
    np.testing.assert_array_equal(fallen(pos, quat, h, cfg), [False, True, False, True, True, False, True])
    # Tilt against MuJoCo's rotation matrix: the angle between the body z axis and the world's.
    rng = np.random.default_rng(0)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    mat = np.zeros(9)
    for qi, tilt in zip(q, base_tilt(q)):
        mujoco.mju_quat2Mat(mat, qi)
        assert tilt == pytest.approx(math.acos(np.clip(mat[8], -1, 1)), abs=1e-9)


def test_collapsing_robot_is_detected_as_fallen(space, nominal):
    """Leg servos at 2 % stiffness cannot carry the robot: it sinks, the oracle flags the fall
    at the first step the base is below half its standing height, and the episode ends there."""
    model = space.model(nominal)
    for a in range(model.nu):
        if not model.actuator(a).name.startswith("arm_"):
            model.actuator_gainprm[a, 0] *= 0.02
            model.actuator_biasprm[a, 1:3] *= 0.02
    motion = hold(model, 2.0)
    ep = oracle_rollout([model], [motion])
    fell = ep.fallen[0].numpy()
    assert fell.any()
    k = int(np.argmax(fell))
    assert fell[k:].all() and not fell[:k].any()
    assert ep.alive[0, :k].all() and not ep.alive[0, k:].any()
    z = ep.qpos[0, :, 2].numpy()
    h = standing_height(model)
    assert z[k] < 0.5 * h <= z[k - 1]
    # The quaternion recorded with the fall is MuJoCo's torso orientation at that state.
    data = mujoco.MjData(model)
    data.qpos[:] = ep.qpos[0, k].numpy()
    mujoco.mj_kinematics(model, data)
    assert base_tilt(ep.qpos[0, k, 3:7].numpy()) == pytest.approx(math.acos(data.body("torso").xmat[8]), abs=1e-4)
    # The reward stops counting at the fall.
    inputs = RewardInputs.from_episode(ep)
    assert int(metrics(inputs, get_reward("tracking", "quadruped"))["length"][0]) == k


# ------------------------------------------------------------------ oracle plumbing and arguments
def test_mixed_batch_runs_each_robot_with_its_controller(space, nominal):
    viperx = get_space("viperx").nominal()
    qmodel = space.model(nominal)
    arm_only = oracle_rollout([viperx], [circle(qmodel, 0.4)])
    ep = oracle_rollout([viperx, nominal], [circle(qmodel, 0.4)])
    for name in ("qpos", "ctrl", "ee_pos", "alive"):
        ref = getattr(arm_only, name)[0]
        got = getattr(ep, name)[0]
        assert torch.equal(got[..., : ref.shape[-1]] if got.ndim > 1 else got, ref)
    assert not bool(ep.fallen.any())
    assert ep.qpos.shape[-1] == qmodel.nq
    assert bool(ep.alive[1].all())


def test_arguments_are_checked(space, nominal):
    with pytest.raises(ValueError, match="foot_cost"):
        WBCConfig(foot_cost=-1.0)
    with pytest.raises(ValueError, match="fall_height_fraction"):
        WBCConfig(fall_height_fraction=1.5)
    with pytest.raises(ValueError, match="fall_tilt"):
        WBCConfig(fall_tilt=4.0)
    with pytest.raises(ValueError, match="no free joint"):
        WholeBodyController(get_space("viperx").model(get_space("viperx").nominal()))
    model = space.model(nominal)
    assert foot_site_names(model) == ("foot_fl", "foot_fr", "foot_rl", "foot_rr")
    m = circle(model, 0.2)
    with pytest.raises(ValueError, match="WBCConfig.control_dt"):
        oracle_rollout([nominal], [Motion("slow", m.pos, m.quat, dt=0.04)])
    with pytest.raises(ValueError, match="IKConfig.control_dt"):
        oracle_rollout([get_space("viperx").nominal()], [m], config=IKConfig(control_dt=0.04))
