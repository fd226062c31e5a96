"""The oracle (MuJoCo C + mink DiffIK): tracking, the IK step against a hand-built DLS
solution, termination, padding of mixed batches, and argument errors."""

import dataclasses

import mujoco
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tt.sim.controller import DiffIKController, IKConfig, ik_step
from tt.sim.designs import Design, get_space
from tt.sim.motions.base import Motion
from tt.sim.validate import oracle_rollout

DT = 0.02


def circle(seconds: float, centre=(0.4, 0.0, 0.3), radius=0.08, pitch=0.3, name="circle") -> Motion:
    """A vertical circle in front of the nominal ViperX, gripper pitched `pitch` rad down."""
    T = int(round(seconds / DT))
    phase = 2 * np.pi * np.arange(T) / T
    pos = np.stack([np.full(T, centre[0]), centre[1] + radius * np.cos(phase), centre[2] + radius * np.sin(phase)], -1)
    quat = np.tile([np.cos(pitch / 2), 0.0, np.sin(pitch / 2), 0.0], (T, 1))  # about +y: x axis tips down
    return Motion(name, pos, quat)


def arms_mjcf(bases, links=(0.25, 0.25, 0.1), name="arms", free=False) -> str:
    """Hand-written arms: per base, a yaw-pitch-pitch-roll chain ending in site ee_<i>.

    At q = 0 each arm is an "L" (upper arm up, forearm forward along +x), away from the
    stretched-out singularity, like tt's ViperX."""
    bodies, actuators = [], []
    for i, base in enumerate(bases):
        l0, l1, l2 = links
        x, y, z = base
        bodies.append(f"""
    <body name="b{i}" pos="{x} {y} {z}">
      <joint name="yaw{i}" axis="0 0 1" range="-3 3"/>
      <geom type="capsule" fromto="0 0 0 0 0 0.1" size="0.03"/>
      <body pos="0 0 0.1">
        <joint name="pitch{i}" axis="0 1 0" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0 0 {l0}" size="0.025"/>
        <body pos="0 0 {l0}">
          <joint name="elbow{i}" axis="0 1 0" range="-2.5 2.5"/>
          <geom type="capsule" fromto="0 0 0 {l1} 0 0" size="0.02"/>
          <body pos="{l1} 0 0">
            <joint name="roll{i}" axis="1 0 0" range="-3 3"/>
            <geom type="capsule" fromto="0 0 0 {l2} 0 0" size="0.02"/>
            <site name="ee_{i}" pos="{l2} 0 0"/>
          </body>
        </body>
      </body>
    </body>""")
        for j in ("yaw", "pitch", "elbow", "roll"):
            actuators.append(f'<position joint="{j}{i}" kp="200" kv="5" ctrlrange="-3 3"/>')
    world = "".join(bodies)
    if free:
        world = f'<body name="trunk"><freejoint/><geom type="box" size="0.1 0.1 0.1"/>{world}</body>'
    return f"""<mujoco model="{name}">
  <compiler angle="radian"/>
  <option timestep="0.002" integrator="Euler"><flag contact="disable"/></option>
  <default><geom density="1000" contype="0" conaffinity="0"/><joint armature="0.02" damping="0.1"/></default>
  <worldbody>{world}
  </worldbody>
  <actuator>{"".join(actuators)}</actuator>
</mujoco>"""


@pytest.fixture(scope="module")
def viperx():
    return get_space("viperx")


@pytest.fixture(scope="module")
def tracked(viperx):
    motion = circle(4.0)
    return motion, oracle_rollout([viperx.nominal()], [motion])


# ------------------------------------------------------------------ tracking and records
def test_tracks_a_reachable_circle_on_the_nominal_viperx(tracked):
    motion, ep = tracked
    assert (ep.worlds, ep.steps) == (1, motion.steps)
    assert ep.alive.all() and not ep.fallen.any()
    err = (ep.ee_pos - ep.target_pos).norm(dim=-1)  # (W, T, A)
    assert err.mean() < 0.02, f"mean position error {err.mean():.4f} m"
    # Orientation follows too (geodesic angle between recorded and target quaternions).
    dot = (ep.ee_quat * ep.target_quat).sum(-1).abs().clamp(max=1.0)
    assert (2 * torch.arccos(dot)).mean() < 0.1
    np.testing.assert_allclose(ep.target_pos[0, :, 0].numpy(), motion.pos[:, 0], atol=1e-6)
    assert ep.dt == DT and torch.equal(ep.action, ep.ctrl)


def test_records_belong_to_the_recorded_state(tracked, viperx):
    """Site poses are FK of the recorded qpos; actuator force is the position-servo law."""
    _, ep = tracked
    model = viperx.model(viperx.nominal())
    data = mujoco.MjData(model)
    kp = model.actuator_gainprm[:, 0]
    kv = -model.actuator_biasprm[:, 2]
    lo, hi = model.actuator_forcerange.T
    for k in (0, 37, 150):
        data.qpos[:] = ep.qpos[0, k].double().numpy()
        data.qvel[:] = ep.qvel[0, k].double().numpy()
        mujoco.mj_kinematics(model, data)
        np.testing.assert_allclose(ep.ee_pos[0, k, 0].numpy(), data.site_xpos[0], atol=1e-5)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, data.site_xmat[0])
        np.testing.assert_allclose(ep.ee_quat[0, k, 0].numpy(), quat, atol=1e-5)
        force = np.clip(kp * (ep.ctrl[0, k].double().numpy() - data.qpos) - kv * data.qvel, lo, hi)
        np.testing.assert_allclose(ep.act_force[0, k].numpy(), force, atol=1e-3)
        np.testing.assert_allclose(ep.act_vel[0, k].numpy(), data.qvel, atol=1e-6)


def test_start_posture_is_ik_toward_the_first_pose(tracked, viperx):
    """The episode starts where init_iterations IK steps (with the start's damping) from qpos0
    lead, near the first target."""
    motion, ep = tracked
    model = viperx.model(viperx.nominal())
    q_start = DiffIKController(model).initial_q(motion.pos[0], motion.quat[0])
    q = model.qpos0.copy()
    start = dataclasses.replace(IKConfig(), damping=IKConfig().init_damping)
    for _ in range(IKConfig().init_iterations):
        q = ik_step(model, q, motion.pos[0], motion.quat[0], start)
    np.testing.assert_allclose(q_start, q, atol=1e-12)
    data = mujoco.MjData(model)
    data.qpos[:] = q_start
    mujoco.mj_kinematics(model, data)
    # The posture task (weight 1e-4 toward qpos0) leaves a fixed point a few mm off.
    assert np.linalg.norm(data.site_xpos[0] - motion.pos[0, 0]) < 5e-3
    assert np.abs(q_start - model.qpos0).max() > 0.05  # it really moved


def test_commands_come_from_ik_with_the_configured_look_ahead(tracked, viperx):
    motion, ep = tracked
    model = viperx.model(viperx.nominal())
    q_start = DiffIKController(model).initial_q(motion.pos[0], motion.quat[0])
    for k in (0, 60, motion.steps - 2):
        q = q_start if k == 0 else ep.qpos[0, k - 1].double().numpy()
        goal = min(k + IKConfig().lookahead_steps, motion.steps - 1)
        q_cmd = ik_step(model, q, motion.pos[goal], motion.quat[goal])
        np.testing.assert_allclose(ep.ctrl[0, k].numpy(), q_cmd, atol=1e-4)


# ------------------------------------------------------------------ the IK step itself
def _skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def _jl_so3(w):
    """Left Jacobian of SO(3)."""
    t = np.linalg.norm(w)
    S = _skew(w)
    if t < 1e-8:
        return np.eye(3) + 0.5 * S
    return np.eye(3) + (1 - np.cos(t)) / t**2 * S + (t - np.sin(t)) / t**3 * S @ S


def _q_se3(v, w):
    """The coupling block Q(v, w) of the SE(3) left Jacobian (Sola et al. 2018, eq. 180)."""
    t = np.linalg.norm(w)
    V, W = _skew(v), _skew(w)
    a = (t - np.sin(t)) / t**3
    b = (1 - t**2 / 2 - np.cos(t)) / t**4
    c = 0.5 * (b - 3 * (t - np.sin(t) - t**3 / 6) / t**5)
    return (
        0.5 * V
        + a * (W @ V + V @ W + W @ V @ W)
        - b * (W @ W @ V + V @ W @ W - 3 * W @ V @ W)
        - c * (W @ V @ W @ W + W @ W @ V @ W)
    )


def _site_error(model, data, sid, p_t, quat_t):
    """e = log(T_site^-1 T_target) as (v, w) in the site frame."""
    R = data.site_xmat[sid].reshape(3, 3)
    R_t = Rotation.from_quat(quat_t, scalar_first=True).as_matrix()
    w = Rotation.from_matrix(R.T @ R_t).as_rotvec()
    dp = R.T @ (p_t - data.site_xpos[sid])
    return np.concatenate([np.linalg.solve(_jl_so3(w), dp), w])  # V(w) = Jl(w) on SO(3)


def _reference_q_cmd(model, q, targets_pos, targets_quat, cfg):
    """The DLS step of IKConfig's docstring, built from mj_jacSite with numpy and scipy."""
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    C2 = np.diag([cfg.position_cost] * 3 + [cfg.orientation_cost] * 3) ** 2
    H = (cfg.posture_cost**2 + cfg.damping) * np.eye(model.nv)
    g = -(cfg.posture_cost**2) * (q - model.qpos0)
    jacobians = []
    for a, (p_t, quat_t) in enumerate(zip(targets_pos, targets_quat)):
        sid = model.site(f"ee_{a}").id
        jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        mujoco.mj_jacSite(model, data, jacp, jacr, sid)
        R = data.site_xmat[sid].reshape(3, 3)
        Jb = np.vstack([R.T @ jacp, R.T @ jacr])
        e = _site_error(model, data, sid, p_t, quat_t)
        Jl = np.block([[_jl_so3(e[3:]), _q_se3(e[:3], e[3:])], [np.zeros((3, 3)), _jl_so3(e[3:])]])
        J = -np.linalg.solve(Jl, Jb)
        jacobians.append((sid, p_t, quat_t, J))
        H += J.T @ C2 @ J
        g -= J.T @ C2 @ e
    q_cmd = q + np.linalg.solve(H, g)
    lo, hi = model.jnt_range.T
    return np.clip(q_cmd, lo, hi), jacobians


def _ik_cases(viperx):
    seven = viperx.nominal().discrete[:1] + (2, 2, 1, 0, 1, 0)
    seven_design = Design("viperx", seven, tuple(0.0 for _ in viperx.continuous_params(seven)))
    tilt = Rotation.from_rotvec([0.2, -0.5, 0.3])
    return [
        (
            "viperx",
            viperx.model(viperx.nominal()),
            [0.3, -0.4, 0.5, 0.2, 0.6, -0.3],
            [[0.42, 0.08, 0.33]],
            [tilt.as_quat(scalar_first=True)],
            IKConfig(),
        ),
        (
            "viperx-7dof",
            viperx.model(seven_design),
            [0.1, 0.2, -0.3, 0.4, 0.1, -0.2, 0.3],
            [[0.5, -0.1, 0.3]],
            [[1.0, 0.0, 0.0, 0.0]],
            IKConfig(position_cost=2.0, orientation_cost=0.3, posture_cost=0.1, damping=1e-2),
        ),
        (
            "two-arms",
            mujoco.MjModel.from_xml_string(arms_mjcf([(0, 0.3, 0), (0, -0.3, 0)])),
            [0.2, -0.3, 0.6, 0.1, -0.2, -0.5, 0.8, -0.1],
            [[0.35, 0.4, 0.2], [0.3, -0.2, 0.15]],
            [tilt.as_quat(scalar_first=True), [0.9238795, 0.0, 0.3826834, 0.0]],
            IKConfig(),
        ),
    ]


@pytest.mark.parametrize("case", range(3))
def test_ik_step_equals_closed_form_dls(viperx, case):
    name, model, q, pos, quat, cfg = _ik_cases(viperx)[case]
    q = np.asarray(q, dtype=np.float64)
    pos, quat = np.asarray(pos), np.asarray(quat)
    expected, _ = _reference_q_cmd(model, q, pos, quat, cfg)
    assert np.abs(expected - q).max() > 1e-2, "the step must move for the comparison to mean anything"
    data = mujoco.MjData(model)
    data.qpos[:] = q
    np.testing.assert_allclose(ik_step(model, data, pos, quat, cfg), expected, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(ik_step(model, q, pos, quat, cfg), expected, atol=1e-9, err_msg=name)


def test_ik_jacobian_is_the_derivative_of_the_error(viperx):
    """J = -Jl^-1(e) Jb is d e / d q (what a kernel must reproduce), by central differences."""
    _, model, q, pos, quat, cfg = _ik_cases(viperx)[2]
    q = np.asarray(q, dtype=np.float64)
    _, jacobians = _reference_q_cmd(model, q, np.asarray(pos), np.asarray(quat), cfg)
    data = mujoco.MjData(model)
    h = 1e-6
    for sid, p_t, quat_t, J in jacobians:
        fd = np.zeros_like(J)
        for i in range(model.nv):
            errs = []
            for s in (h, -h):
                data.qpos[:] = q
                data.qpos[i] += s
                mujoco.mj_kinematics(model, data)
                errs.append(_site_error(model, data, sid, p_t, quat_t))
            fd[:, i] = (errs[0] - errs[1]) / (2 * h)
        np.testing.assert_allclose(J, fd, atol=1e-7)


def test_ik_step_clips_to_joint_range(viperx):
    model = viperx.model(viperx.nominal())
    q = np.array([0.0, 1.9, 0.0, 0.0, 0.0, 0.0])  # shoulder near its 1.99 rad limit
    q_cmd = ik_step(model, q, [[0.6, 0.0, -0.2]], [[1.0, 0.0, 0.0, 0.0]])
    lo, hi = model.jnt_range.T
    assert np.all(q_cmd >= lo) and np.all(q_cmd <= hi)
    assert np.isclose(q_cmd[1], hi[1]), "the target below the base drives the shoulder into its limit"


# ------------------------------------------------------------------ termination
def test_unreachable_motion_terminates(viperx):
    T = 100
    pos = np.linspace([0.4, 0.0, 0.3], [2.5, 0.0, 0.3], T)  # out of reach (~0.9 m) by mid-motion
    motion = Motion("away", pos, np.tile([1.0, 0, 0, 0], (T, 1)))
    ep = oracle_rollout([viperx.nominal()], [motion])
    alive = ep.alive[0]
    n = int(alive.sum())
    assert 0 < n < T and alive[:n].all() and not alive[n:].any(), "alive must be a prefix"
    assert ep.lengths().tolist() == [n] and not ep.alive.all(dim=1).any()  # survival 0
    err = (ep.ee_pos - ep.target_pos).norm(dim=-1).sum(-1)[0]  # summed over arms, (T,)
    assert err[:n].max() <= 0.5 < err[n]
    for name in ("qpos", "qvel", "ctrl", "ee_pos", "act_force"):
        held = getattr(ep, name)[0, n:]
        assert torch.equal(held, held[:1].expand_as(held)), f"{name} must repeat the terminal record"


# ------------------------------------------------------------------ batches and padding
def test_mixed_designs_and_motion_lengths_pad(viperx):
    five = (viperx.nominal().discrete[0], 0, 1, 1, 0)
    five_design = Design("viperx", five, tuple(0.0 for _ in viperx.continuous_params(five)))
    small = mujoco.MjModel.from_xml_string(arms_mjcf([(0.0, 0.0, 0.2)]))
    designs = [viperx.nominal(), five_design, small]
    motions = [circle(0.5, name="short"), circle(1.0, radius=0.05, name="long")]
    ep = oracle_rollout(designs, motions)

    W, T = 6, 50
    assert (ep.worlds, ep.steps) == (W, T)
    assert ep.qpos.shape == (W, T, 6) and ep.qvel.shape == (W, T, 6)
    for name in ("ctrl", "action", "act_force", "act_vel"):
        assert getattr(ep, name).shape == (W, T, 6)
    for name in ("ee_pos", "target_pos"):
        assert getattr(ep, name).shape == (W, T, 1, 3)
    for name in ("ee_quat", "target_quat"):
        assert getattr(ep, name).shape == (W, T, 1, 4)
    assert ep.qpos.dtype == torch.float32 and ep.alive.dtype == torch.bool and ep.design_index.dtype == torch.long
    assert ep.design_index.tolist() == [0, 0, 1, 1, 2, 2] and ep.motion_index.tolist() == [0, 1, 0, 1, 0, 1]
    # Joint columns past a design's DoF are zero padding.
    assert ep.qpos[2:4, :, 5:].abs().max() == 0 and ep.ctrl[4:, :, 4:].abs().max() == 0
    assert ep.qpos[2:4, :, :5].abs().max() > 0.05
    # The short motion's worlds stop at its end and hold their last record and target.
    assert not ep.alive[0::2, 25:].any() and ep.alive[0, :25].all()
    assert torch.equal(ep.qpos[0, 25:], ep.qpos[0, 24:25].expand(25, -1))
    assert torch.equal(ep.target_pos[0, 25:], ep.target_pos[0, 24:25].expand(25, -1, -1))
    # World d * M + m ran design d on motion m: the same as running that pair alone.
    alone = oracle_rollout([five_design], [motions[1]])
    torch.testing.assert_close(ep.qpos[3, :, :5], alone.qpos[0], rtol=0, atol=0)
    torch.testing.assert_close(ep.ee_pos[3], alone.ee_pos[0], rtol=0, atol=0)


def test_two_arm_robot_records_both_end_effectors():
    model = mujoco.MjModel.from_xml_string(arms_mjcf([(0, 0.3, 0), (0, -0.3, 0)]))
    T = 25
    # Level-gripper poses the arms reach with the upper arm pitched 0.3 and -0.2 rad.
    pos = np.tile(
        [
            [0.35 + 0.25 * np.sin(0.3), 0.3, 0.1 + 0.25 * np.cos(0.3)],
            [0.35 - 0.25 * np.sin(0.2), -0.3, 0.1 + 0.25 * np.cos(0.2)],
        ],
        (T, 1, 1),
    )
    motion = Motion("hold", pos, np.tile([1.0, 0, 0, 0], (T, 2, 1)))
    ep = oracle_rollout([model], [motion])
    assert ep.ee_pos.shape == (1, T, 2, 3) and ep.qpos.shape == (1, T, 8)
    assert ep.alive.all()
    assert (ep.ee_pos[0, -1] - ep.target_pos[0, -1]).norm(dim=-1).max() < 0.02


# ------------------------------------------------------------------ argument errors
def test_wrong_arm_count_raises(viperx):
    two = Motion("two", np.tile([[0.4, 0.2, 0.3], [0.4, -0.2, 0.3]], (10, 1, 1)), np.tile([1.0, 0, 0, 0], (10, 2, 1)))
    with pytest.raises(ValueError, match=r"motions\[0\] \('two'\) has 2 arm\(s\) but designs\[0\] \('viperx'\) has 1"):
        oracle_rollout([viperx.nominal()], [two])


def test_floating_base_needs_the_whole_body_controller():
    model = mujoco.MjModel.from_xml_string(arms_mjcf([(0, 0, 0.1)], free=True, name="floating"))
    with pytest.raises(ValueError, match="whole-body controller"):
        oracle_rollout([model], [circle(0.2)])


def test_motion_at_another_rate_raises(viperx):
    m = circle(0.2)
    slow = Motion("slow", m.pos, m.quat, dt=0.04)
    with pytest.raises(ValueError, match="dt = 0.04"):
        oracle_rollout([viperx.nominal()], [slow])
