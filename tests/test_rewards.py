"""Rewards and metrics against the paper's formulas, evaluated by hand with plain Python math.

Cases place the end effector at chosen position and orientation errors from random targets,
so the expected rewards are sums of exp(-e_p^2/sigma_p - e_o^2/sigma_o) written out here.
Orientation errors are checked against arccos((tr R - 1)/2) with MuJoCo's quaternion-to-
matrix, gradients against central finite differences (float64), size and mass against the
closed-form lengths and volumes of primitive geoms.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

from tt.sim.episode import Episode
from tt.sim.rewards import (
    METRIC_UNITS,
    REWARD_SPACES,
    REWARDS,
    RewardConfig,
    RewardInputs,
    evaluate,
    get_reward,
    metrics,
    orientation_error,
    reward,
    robot_mass,
    robot_size,
    summarize,
)

SIGMA_P, SIGMA_O = 0.01, 0.5
DT = torch.float64


def _random_unit_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _quat_from_axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def make_inputs(pos_err, orn_err, *, seed=0, nu=2, **kw) -> RewardInputs:
    """Episodes whose per-step errors are exactly the given ones.

    pos_err, orn_err: nested lists (W, T, A) of position [m] and orientation [rad] errors.
    The end effector sits at target + err * (random unit direction), rotated by err about a
    random axis from a random target orientation.
    """
    rng = np.random.default_rng(seed)
    pe = np.asarray(pos_err, dtype=np.float64)
    oe = np.asarray(orn_err, dtype=np.float64)
    W, T, A = pe.shape
    tpos = rng.uniform(-1, 1, size=(W, T, A, 3))
    tquat = _random_unit_quats(rng, W * T * A).reshape(W, T, A, 4)
    pos = np.empty_like(tpos)
    quat = np.empty_like(tquat)
    for idx in np.ndindex(W, T, A):
        d = rng.normal(size=3)
        pos[idx] = tpos[idx] + pe[idx] * d / np.linalg.norm(d)
        rel = _quat_from_axis_angle(rng.normal(size=3), oe[idx])
        mujoco.mju_mulQuat(quat[idx], tquat[idx], rel)
    kw.setdefault("act_force", torch.zeros(W, T, nu, dtype=DT))
    kw.setdefault("act_vel", torch.zeros(W, T, nu, dtype=DT))
    return RewardInputs(
        ee_pos=torch.tensor(pos),
        ee_quat=torch.tensor(quat),
        target_pos=torch.tensor(tpos),
        target_quat=torch.tensor(tquat),
        **kw,
    )


def track(ep: float, eo: float) -> float:
    return math.exp(-(ep**2) / SIGMA_P - eo**2 / SIGMA_O)


# ---------------------------------------------------------------- errors
def test_orientation_error_matches_trace_formula():
    rng = np.random.default_rng(1)
    q1 = _random_unit_quats(rng, 200)
    q2 = _random_unit_quats(rng, 200)
    expected = []
    for a, b in zip(q1, q2):
        r1 = np.empty(9)
        r2 = np.empty(9)
        mujoco.mju_quat2Mat(r1, a)
        mujoco.mju_quat2Mat(r2, b)
        rel = r1.reshape(3, 3).T @ r2.reshape(3, 3)
        expected.append(math.acos(min(1.0, max(-1.0, (np.trace(rel) - 1) / 2))))
    got = orientation_error(torch.tensor(q1), torch.tensor(q2)).numpy()
    # arccos loses ~sqrt(machine eps) near 0 and pi; random pairs keep away from both.
    np.testing.assert_allclose(got, expected, atol=1e-9)
    # Scale and sign of either quaternion do not matter (same rotations).
    got_scaled = orientation_error(torch.tensor(-2.5 * q1), torch.tensor(0.3 * q2)).numpy()
    np.testing.assert_allclose(got_scaled, expected, atol=1e-9)


def test_orientation_error_small_and_half_turn():
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=DT)
    small = torch.tensor(_quat_from_axis_angle([0, 1, 0], 1e-7)[None])
    half = torch.tensor(_quat_from_axis_angle([1, 1, 0], math.pi)[None])
    assert orientation_error(q, q).item() == 0.0
    # Exact at tiny angles, where the arccos form returns 0 or sqrt(eps)-sized noise.
    assert orientation_error(q, small).item() == pytest.approx(1e-7, rel=1e-9)
    assert orientation_error(q, half).item() == pytest.approx(math.pi, abs=1e-12)


# ---------------------------------------------------------------- rewards by hand
POS = [[[0.0], [0.05], [0.1], [0.2]], [[0.05], [0.3], [0.6], [0.1]]]
ORN = [[[0.0], [0.1], [0.2], [0.3]], [[0.4], [0.2], [0.1], [0.0]]]


def test_tracking_with_termination():
    inputs = make_inputs(POS, ORN)
    got = reward(inputs, get_reward("tracking", "viperx"))
    # World 1 exceeds 0.5 m at step 2: steps 2 and 3 do not count, step 3 despite 0.1 m.
    w0 = sum(track(p[0], o[0]) for p, o in zip(POS[0], ORN[0]))
    w1 = track(0.05, 0.4) + track(0.3, 0.2)
    torch.testing.assert_close(got, torch.tensor([w0, w1], dtype=DT), rtol=1e-12, atol=1e-12)
    # Quadruped threshold 0.8 m: world 1 runs through.
    got = reward(inputs, get_reward("tracking", "quadruped"))
    w1_full = sum(track(p[0], o[0]) for p, o in zip(POS[1], ORN[1]))
    torch.testing.assert_close(got, torch.tensor([w0, w1_full], dtype=DT), rtol=1e-12, atol=1e-12)


def test_fallen_and_alive_masks():
    alive = torch.tensor([[True, True, True, False], [True, True, True, True]])
    fallen = torch.tensor([[False, False, False, False], [False, True, False, False]])
    pos = [[[0.01]] * 4, [[0.02]] * 4]
    orn = [[[0.1]] * 4, [[0.05]] * 4]
    inputs = make_inputs(pos, orn, alive=alive, fallen=fallen)
    terms = evaluate(inputs, get_reward("tracking", "quadruped"))
    # A fall at step 1 ends world 1 there even though `fallen` clears later; the rollout of
    # world 0 stopped after step 2.
    expected = [3 * track(0.01, 0.1), 1 * track(0.02, 0.05)]
    torch.testing.assert_close(terms.reward, torch.tensor(expected, dtype=DT), rtol=1e-12, atol=0)
    assert terms.counted.tolist() == [[True, True, True, False], [True, False, False, False]]
    assert terms.survived.tolist() == [False, False]
    # A step the rollout skipped ends the episode: later alive steps do not count.
    gap = torch.tensor([[True, False, True, True], [True, True, True, True]])
    terms = evaluate(make_inputs(pos, orn, alive=gap), get_reward("tracking", "viperx"))
    assert terms.counted.sum(1).tolist() == [1, 4]
    assert terms.survived.tolist() == [False, True]


def test_tracking_torque_clips_each_step_at_zero():
    cfg = get_reward("tracking_torque", "viperx")
    pos = [[[0.0], [0.05], [0.1], [0.0]]]
    orn = [[[0.0], [0.1], [0.0], [0.2]]]
    tau = torch.tensor([[[100.0, 0.0], [30.0, 40.0], [200.0, 0.0], [0.0, 0.0]]], dtype=DT)
    inputs = make_inputs(pos, orn, act_force=tau)
    alpha = 5e-5
    norms2 = [100.0**2, 50.0**2, 200.0**2, 0.0]
    expected = sum(max(track(p[0], o[0]) - alpha * n2, 0.0) for p, o, n2 in zip(pos[0], orn[0], norms2))
    # Step 2 (track 0.37, penalty 2.0) is clipped, the others are not.
    assert track(0.1, 0.0) - alpha * 200.0**2 < 0
    torch.testing.assert_close(reward(inputs, cfg), torch.tensor([expected], dtype=DT), rtol=1e-12, atol=0)
    # Forces at steps that do not count cost nothing: terminate at step 1.
    inputs = make_inputs([[[0.0], [0.7], [0.0], [0.0]]], orn, act_force=tau)
    torch.testing.assert_close(reward(inputs, cfg), torch.tensor([1.0 - alpha * 1e4], dtype=DT), rtol=1e-12, atol=0)


@pytest.mark.parametrize("space,alpha", [("viperx", 0.1), ("aloha", 0.1), ("bimanual", 0.5), ("quadruped", 0.005)])
def test_tracking_velocity(space, alpha):
    cfg = get_reward("tracking_velocity", space)
    pos = [[[0.02], [0.04], [0.0]]]
    orn = [[[0.05], [0.0], [0.3]]]
    qdot = torch.tensor([[[1.0, 2.0, 0.5], [0.1, 0.0, 0.2], [3.0, 0.0, 0.0]]], dtype=DT)
    inputs = make_inputs(pos, orn, act_vel=qdot, nu=3)
    norms2 = [1 + 4 + 0.25, 0.01 + 0.04, 9.0]
    expected = sum(max(track(p[0], o[0]) - alpha * n2, 0.0) for p, o, n2 in zip(pos[0], orn[0], norms2))
    torch.testing.assert_close(reward(inputs, cfg), torch.tensor([expected], dtype=DT), rtol=1e-12, atol=0)
    # Torques do not enter the velocity reward.
    inputs2 = make_inputs(pos, orn, act_vel=qdot, nu=3, act_force=torch.full((1, 3, 3), 1e3, dtype=DT))
    torch.testing.assert_close(reward(inputs2, cfg), reward(inputs, cfg), rtol=0, atol=0)


@pytest.mark.parametrize("space,target", [("viperx", 2.0), ("aloha", 4.0), ("bimanual", 5.0), ("quadruped", 6.5)])
def test_tracking_size(space, target):
    cfg = get_reward("tracking_size", space)
    pos = [[[0.01], [0.02], [0.9], [0.0]]] * 2
    orn = [[[0.1], [0.0], [0.0], [0.0]]] * 2
    size = torch.tensor([target + 0.5, target - 0.3], dtype=DT)
    inputs = make_inputs(pos, orn, size=size)
    # Termination at step 2 does not shorten T = 4 in the penalty.
    base = track(0.01, 0.1) + track(0.02, 0.0)
    expected = [base - 4 * 0.1 * 0.5, base]
    torch.testing.assert_close(reward(inputs, cfg), torch.tensor(expected, dtype=DT), rtol=1e-12, atol=1e-12)
    guided = [base - 4 * 0.005 * 0.5, base]
    torch.testing.assert_close(
        reward(inputs, cfg, guidance=True), torch.tensor(guided, dtype=DT), rtol=1e-12, atol=1e-12
    )
    torch.testing.assert_close(cfg(inputs), reward(inputs, cfg), rtol=0, atol=0)


def test_tracking_weight():
    cfg = get_reward("tracking_weight", "viperx")
    pos = [[[0.03], [0.03], [0.03]]] * 3
    orn = [[[0.2], [0.2], [0.2]]] * 3
    mass = torch.tensor([3.7, 3.2, 2.0], dtype=DT)
    inputs = make_inputs(pos, orn, mass=mass, size=torch.full((3,), 100.0, dtype=DT))
    base = 3 * track(0.03, 0.2)
    expected = [base - 3 * 10 * 0.5, base, base]
    torch.testing.assert_close(reward(inputs, cfg), torch.tensor(expected, dtype=DT), rtol=1e-12, atol=1e-12)
    guided = [base - 3 * 0.005 * 0.5, base, base]
    torch.testing.assert_close(
        reward(inputs, cfg, guidance=True), torch.tensor(guided, dtype=DT), rtol=1e-12, atol=1e-12
    )


def test_bimanual_sums_errors_over_end_effectors():
    cfg = get_reward("tracking", "bimanual")
    # Step 2: each arm 0.3 m off (each under 0.5 m), the sum 0.6 m terminates.
    pos = [[[0.03, 0.04], [0.0, 0.1], [0.3, 0.3], [0.0, 0.0]]]
    orn = [[[0.1, 0.2], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]]
    inputs = make_inputs(pos, orn)
    expected = track(0.07, 0.3) + track(0.1, 0.0)
    torch.testing.assert_close(reward(inputs, cfg), torch.tensor([expected], dtype=DT), rtol=1e-12, atol=0)
    m = metrics(inputs, cfg)
    # Metrics average over end effectors and counted steps.
    assert m["pos_err"].item() == pytest.approx(100 * (0.03 + 0.04 + 0.0 + 0.1) / 4, rel=1e-12)
    assert m["orn_err"].item() == pytest.approx(math.degrees((0.1 + 0.2) / 4), rel=1e-12)
    assert m["length"].item() == 2 and m["survival"].item() == 0.0


def test_padded_motions():
    cfg = get_reward("tracking_size", "viperx")
    pos = [[[0.01], [0.02], [0.9], [0.9]], [[0.01], [0.02], [0.03], [0.04]]]
    orn = [[[0.0]] * 4] * 2
    inputs = make_inputs(pos, orn, size=torch.tensor([3.0, 3.0], dtype=DT), motion_steps=torch.tensor([2, 4]))
    terms = evaluate(inputs, cfg)
    # World 0's motion has 2 steps: the padding neither counts nor terminates, T = 2.
    expected = [
        track(0.01, 0) + track(0.02, 0) - 2 * 0.1 * 1.0,
        sum(track(p, 0) for p in (0.01, 0.02, 0.03, 0.04)) - 4 * 0.1 * 1.0,
    ]
    torch.testing.assert_close(terms.reward, torch.tensor(expected, dtype=DT), rtol=1e-12, atol=1e-12)
    assert terms.survived.tolist() == [True, True]


def test_values_after_termination_do_not_leak():
    cfg = get_reward("tracking_torque", "viperx")
    inputs = make_inputs([[[0.0], [0.6], [0.0]]], [[[0.0], [0.0], [0.0]]])
    inputs.ee_pos.data[0, 2] = float("nan")
    inputs.act_force.data[0, 1:] = float("inf")
    assert reward(inputs, cfg).tolist() == [1.0]
    # Non-finite error terminates like a large one.
    inputs = make_inputs([[[0.0], [0.0], [0.0]]], [[[0.0], [0.0], [0.0]]])
    inputs.ee_pos.data[0, 1] = float("nan")
    terms = evaluate(inputs, cfg)
    assert terms.counted.tolist() == [[True, False, False]] and terms.reward.tolist() == [1.0]


# ---------------------------------------------------------------- metrics
def test_metrics_by_hand():
    cfg = get_reward("tracking_velocity", "viperx")
    tau = torch.tensor([[[3.0, 4.0]] * 4, [[6.0, 8.0], [0.0, 1.0], [9.0, 9.0], [9.0, 9.0]]], dtype=DT)
    qdot = torch.tensor([[[0.0, 0.5]] * 4, [[0.3, 0.4], [0.0, 0.0], [5.0, 5.0], [5.0, 5.0]]], dtype=DT)
    inputs = make_inputs(
        POS,
        ORN,
        act_force=tau,
        act_vel=qdot,
        size=torch.tensor([2.1, 2.2], dtype=DT),
        mass=torch.tensor([3.0, 3.1], dtype=DT),
    )
    m = metrics(inputs, cfg)
    assert set(m) == set(METRIC_UNITS)
    assert all(v.shape == (2,) for v in m.values())
    torch.testing.assert_close(m["pos_err"], torch.tensor([100 * 0.35 / 4, 100 * 0.35 / 2], dtype=DT))
    torch.testing.assert_close(m["orn_err"], torch.tensor([math.degrees(0.6 / 4), math.degrees(0.6 / 2)], dtype=DT))
    torch.testing.assert_close(m["torque"], torch.tensor([5.0, 5.5], dtype=DT))
    torch.testing.assert_close(m["velocity"], torch.tensor([0.5, 0.25], dtype=DT))
    # The largest |qdot_i| at a counted step: world 1's 5.0 comes after its termination.
    torch.testing.assert_close(m["max_joint_speed"], torch.tensor([0.5, 0.4], dtype=DT))
    assert m["survival"].tolist() == [1.0, 0.0]
    assert m["length"].tolist() == [4, 2]
    torch.testing.assert_close(m["reward"], reward(inputs, cfg))
    assert m["size"].tolist() == [2.1, 2.2] and m["mass"].tolist() == [3.0, 3.1]
    s = summarize(m)
    assert s["survival_pct"] == pytest.approx(50.0)
    assert s["pos_err"] == pytest.approx(100 * 0.35 * 0.75 / 2)


def test_max_joint_speed_matches_numpy_on_a_recorded_episode():
    """The max joint speed of an oracle rollout (the nominal ALOHA and two sampled designs on a
    fling's first 40 steps, the target thrown 0.6 m away from step 25 on in the second motion so
    that the episodes terminate) is numpy's max of |act_vel| over actuators and the counted steps:
    those the rollout ran, before the summed position error first passed the threshold."""
    from tt.baselines.evaluate import evaluate_designs
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, get_motion
    from tt.sim.motions.base import Motion

    sp = get_space("aloha")
    fling = for_space([get_motion("bi_fling:100")], "aloha")[0]
    short = Motion(fling.name, fling.pos[:40], fling.quat[:40], fling.dt)
    thrown = short.pos.copy()
    thrown[25:, :, 0] += 0.6
    motions = [short, Motion("thrown", thrown, short.quat, short.dt)]
    ev = evaluate_designs([sp.nominal(), *sp.sample(2, 0)], motions, "tracking_velocity", backend="mujoco")
    ep = ev.episode
    vel = ep.act_vel.double().numpy()  # (W, T, nu)
    err = np.linalg.norm(ep.ee_pos.double().numpy() - ep.target_pos.double().numpy(), axis=-1).sum(-1)  # (W, T)
    ok = (err <= get_reward("tracking_velocity", "aloha").threshold) & ep.alive.numpy() & ~ep.fallen.numpy()
    counted = np.cumprod(ok, axis=1).astype(bool)
    assert counted[:, -1].any() and not counted[:, -1].all(), "want episodes that survive and ones that terminate"
    want = np.where(counted, np.abs(vel).max(-1), -np.inf).max(1)
    got = ev.metrics["max_joint_speed"].reshape(-1)  # (D, M) design-major, as the episode's worlds
    np.testing.assert_allclose(got, want, rtol=1e-6)
    mean = (np.linalg.norm(vel, axis=-1) * counted).sum(1) / counted.sum(1)
    np.testing.assert_allclose(ev.metrics["velocity"].reshape(-1), mean, rtol=1e-6)  # the mean's steps, too
    assert ev.metrics["length"].reshape(-1).tolist() == counted.sum(1).tolist()


def test_p95_and_within_2cm_by_hand():
    """pos_err_p95 is numpy's linear-interpolation percentile of the counted steps' errors;
    within_2cm counts the motion's steps that counted at <= 2 cm (a terminated step is not within)."""
    cfg = get_reward("tracking", "viperx")
    errors_cm = [[0.0, 1.0, 1.9, 3.0, 10.0], [1.0, 60.0, 0.0, 0.0, 0.0]]  # world 1 terminates at step 1
    inputs = make_inputs([[[e / 100.0] for e in w] for w in errors_cm], [[[0.0]] * 5] * 2)
    m = metrics(inputs, cfg)
    assert m["pos_err_p95"][0].item() == pytest.approx(np.percentile(errors_cm[0], 95), rel=1e-6)
    assert m["pos_err_p95"][1].item() == pytest.approx(1.0, rel=1e-6)
    assert m["within_2cm"].tolist() == pytest.approx([3 / 5, 1 / 5])
    s = summarize(m)
    assert s["within_2cm_pct"] == pytest.approx(100 * (3 / 5 + 1 / 5) / 2)
    assert "within_2cm" not in s


def test_metrics_without_counted_steps_are_nan_and_skipped_in_summary():
    cfg = get_reward("tracking", "viperx")
    inputs = make_inputs([[[0.7], [0.0]], [[0.02], [0.04]]], [[[0.0], [0.0]], [[0.0], [0.0]]])
    m = metrics(inputs, cfg)
    assert math.isnan(m["pos_err"][0].item()) and m["length"].tolist() == [0, 2]
    assert m["reward"][0].item() == 0.0
    assert summarize(m)["pos_err"] == pytest.approx(3.0)


def test_from_episode_reads_views():
    W, T, nq, nu = 2, 3, 4, 4
    inputs0 = make_inputs([[[0.01]] * T] * W, [[[0.0]] * T] * W, nu=nu)
    ep = Episode(
        qpos=torch.zeros(W, T, nq),
        qvel=torch.zeros(W, T, nq),
        ctrl=torch.zeros(W, T, nu),
        action=torch.zeros(W, T, nu),
        act_force=torch.randn(W, T, nu, dtype=DT),
        act_vel=torch.randn(W, T, nu, dtype=DT),
        ee_pos=inputs0.ee_pos,
        ee_quat=inputs0.ee_quat,
        target_pos=inputs0.target_pos,
        target_quat=inputs0.target_quat,
        alive=torch.ones(W, T, dtype=torch.bool),
        fallen=torch.zeros(W, T, dtype=torch.bool),
        design_index=torch.arange(W),
        motion_index=torch.zeros(W, dtype=torch.long),
        dt=0.02,
    )
    size = torch.tensor([1.0, 2.0], dtype=DT)
    inputs = RewardInputs.from_episode(ep, size=size)
    for name in ("ee_pos", "ee_quat", "target_pos", "target_quat", "act_force", "act_vel", "alive", "fallen"):
        assert getattr(inputs, name).data_ptr() == getattr(ep, name).data_ptr(), name
    assert inputs.size is size and inputs.mass is None
    expected = torch.full((W,), T * track(0.01, 0), dtype=DT)
    torch.testing.assert_close(reward(inputs, get_reward("tracking", "viperx")), expected)


# ---------------------------------------------------------------- gradients
def _gradcheck_inputs(seed: int, A: int):
    """Float64 inputs away from every kink: errors well inside the threshold, clips far from 0."""
    rng = np.random.default_rng(seed)
    W, T, nu = 2, 3, 3
    pe = rng.uniform(0.01, 0.08 if A == 1 else 0.04, size=(W, T, A))
    oe = rng.uniform(0.05, 0.3, size=(W, T, A))
    inputs = make_inputs(pe.tolist(), oe.tolist(), seed=seed, nu=nu)
    # Every other step has a large effort that the clip zeroes (alpha |x|^2 > 2 for the ViperX
    # and bimanual alphas), the others a small one that leaves the step positive.
    large = torch.tensor([[(w + t) % 2 == 0 for t in range(T)] for w in range(W)])[..., None]
    sign = torch.tensor(rng.choice([-1.0, 1.0], size=(W, T, nu)))

    def magnitudes(low_small, high_small, low_large, high_large):
        small = torch.tensor(rng.uniform(low_small, high_small, (W, T, nu)))
        return sign * torch.where(large, torch.tensor(rng.uniform(low_large, high_large, (W, T, nu))), small)

    force = magnitudes(0, 30, 150, 200)
    vel = magnitudes(0, 0.3, 3, 4)
    return inputs, force, vel


@pytest.mark.parametrize("name", REWARDS)
@pytest.mark.parametrize("space", ["viperx", "bimanual"])
def test_reward_gradients_match_finite_differences(name, space):
    A = 2 if space == "bimanual" else 1
    base, force, vel = _gradcheck_inputs(seed=3, A=A)
    cfg = get_reward(name, space)
    size = torch.tensor([cfg.size_target + 0.4, cfg.size_target + 1.1], dtype=DT)
    mass = torch.tensor([cfg.mass_target + 0.3, cfg.mass_target + 0.05], dtype=DT)

    def build(ee_pos, ee_quat, act_force, act_vel, size, mass):
        return RewardInputs(
            ee_pos=ee_pos,
            ee_quat=ee_quat,
            target_pos=base.target_pos,
            target_quat=base.target_quat,
            act_force=act_force,
            act_vel=act_vel,
            size=size,
            mass=mass,
        )

    args = [t.clone().requires_grad_(True) for t in (base.ee_pos, base.ee_quat, force, vel, size, mass)]
    terms = evaluate(build(*args), cfg)
    assert bool(terms.counted.all())
    # Keep the finite differences off the clip's kink.
    track = torch.exp(-(terms.pos_err.sum(-1) ** 2) / cfg.sigma_p - terms.orn_err.sum(-1) ** 2 / cfg.sigma_o)
    effort = cfg.torque_alpha * force.square().sum(-1) + cfg.velocity_alpha * vel.square().sum(-1)
    assert bool(((track - effort).abs() > 1e-3).all())
    if name in ("tracking_torque", "tracking_velocity"):
        assert bool((terms.step_reward == 0).any()) and bool((terms.step_reward > 0).any())
    for guidance in (False, True):
        assert torch.autograd.gradcheck(
            lambda *a: reward(build(*a), cfg, guidance=guidance), args, eps=1e-6, atol=1e-6, rtol=1e-5
        )


def test_gradient_finite_at_perfect_tracking_and_half_turn():
    cfg = get_reward("tracking", "viperx")
    inputs = make_inputs([[[0.0], [0.01]]], [[[0.0], [math.pi]]])
    ee_pos = inputs.ee_pos.clone().requires_grad_(True)
    ee_quat = inputs.ee_quat.clone().requires_grad_(True)
    r = reward(
        RewardInputs(ee_pos=ee_pos, ee_quat=ee_quat, target_pos=inputs.target_pos, target_quat=inputs.target_quat), cfg
    )
    r.sum().backward()
    assert torch.isfinite(ee_pos.grad).all() and torch.isfinite(ee_quat.grad).all()
    # Zero error is the maximum: zero gradient there.
    assert ee_pos.grad[0, 0].abs().max().item() < 1e-6
    assert ee_quat.grad[0, 0].abs().max().item() < 1e-6


def test_uncounted_steps_have_zero_gradient():
    cfg = get_reward("tracking_torque", "viperx")
    inputs = make_inputs([[[0.02], [0.7], [0.02]]], [[[0.1], [0.1], [0.1]]])
    ee_pos = inputs.ee_pos.clone().requires_grad_(True)
    force = torch.full((1, 3, 2), 20.0, dtype=DT, requires_grad=True)
    r = reward(
        RewardInputs(
            ee_pos=ee_pos,
            ee_quat=inputs.ee_quat,
            target_pos=inputs.target_pos,
            target_quat=inputs.target_quat,
            act_force=force,
        ),
        cfg,
    )
    r.sum().backward()
    assert ee_pos.grad[0, 1:].abs().max().item() == 0.0 and force.grad[0, 1:].abs().max().item() == 0.0
    assert ee_pos.grad[0, 0].abs().max().item() > 0 and force.grad[0, 0].abs().max().item() > 0


# ---------------------------------------------------------------- registry and validation
def test_registry():
    from tt.sim.designs import SPACE_NAMES

    assert set(REWARD_SPACES) == set(SPACE_NAMES)
    for space in REWARD_SPACES:
        for name in REWARDS:
            cfg = get_reward(name, space)
            assert isinstance(cfg, RewardConfig) and cfg.name == name and cfg.space == space
            assert (cfg.sigma_p, cfg.sigma_o) == (SIGMA_P, SIGMA_O)
    assert get_reward("tracking", "quadruped").threshold == 0.8
    assert get_reward("tracking", "bimanual").threshold == 0.5
    assert get_reward("tracking_torque", "quadruped").torque_alpha == 5e-5
    assert get_reward("tracking_weight", "viperx").mass_target == 3.2
    assert get_reward("tracking_weight", "viperx").mass_alpha_guidance == 0.005
    assert get_reward("tracking", "viperx").needs == ()
    assert get_reward("tracking_size", "viperx").needs == ("size",)


@pytest.mark.parametrize("space", ["viperx", "aloha", "bimanual", "quadruped"])
def test_mass_target_is_the_median_uniform_design(space):
    """Every space's mass target is the median mass of its uniform designs, the paper's ViperX
    rule (3.2 kg): within 3 % over 300 draws, strictly inside the 5th-95th percentile band, so
    the weight term neither always acts (a search would prefer designs that fail early) nor never."""
    from tt.sim.designs import get_space
    from tt.sim.rewards import robot_mass

    sp = get_space(space)
    masses = robot_mass([sp.model(d) for d in sp.sample(300, seed=1)], dtype=torch.float64).numpy()
    target = get_reward("tracking_weight", space).mass_target
    assert abs(target - np.median(masses)) <= 0.03 * np.median(masses)
    lo, hi = np.percentile(masses, [5, 95])
    assert lo < target < hi


def test_the_papers_reward_names_are_aliases():
    """Every alias names its reward in any case, with spaces, hyphens or underscores between words;
    tt's names stay; the paper's appendix sections ("Tracking Only" ... "Tracking Weight") are all there."""
    from tt.baselines import Problem
    from tt.sim.rewards import REWARD_ALIASES, reward_name

    for section in ("Tracking Only", "Tracking Torque", "Tracking Velocity", "Tracking Size", "Tracking Weight"):
        assert section in REWARD_ALIASES
    assert set(REWARD_ALIASES.values()) == set(REWARDS)
    for name in REWARDS:
        assert reward_name(name) == name and reward_name(name.upper().replace("_", " ")) == name
    for alias, name in REWARD_ALIASES.items():
        spellings = (
            alias,
            alias.lower(),
            alias.upper(),
            alias.replace(" ", "-"),
            alias.replace(" ", "_"),
            f" {alias} ",
        )
        for spelled in spellings:
            assert reward_name(spelled) == name, spelled
    assert reward_name("tracking-velocity") == reward_name("Tracking  Velocity") == "tracking_velocity"
    assert get_reward("Tracking Velocity", "aloha") == get_reward("tracking_velocity", "aloha")
    assert get_reward("tracking only", "viperx").name == "tracking"
    problem = Problem(space="viperx", motions=(_short_toss(),), reward="Tracking Weight", budget=5)
    assert problem.reward == "tracking_weight"
    for bad in ("speed", "tracking velocityy", "", "tracking_speed"):
        with pytest.raises(ValueError, match="unknown reward .*Tracking Velocity"):
            reward_name(bad)


def _short_toss(steps: int = 20):
    from tt.sim.motions import for_space, get_motion
    from tt.sim.motions.base import Motion

    m = for_space([get_motion("toss")], "viperx")[0]
    return Motion(f"{m.name}[:{steps}]", m.pos[:steps], m.quat[:steps], m.dt)


def test_cli_takes_the_papers_reward_names(tmp_path, tt_cli, monkeypatch):
    """tt validate --reward "Tracking Velocity" scores tt's tracking_velocity: its JSON names it,
    its table shows the velocity and the max joint speed; --help lists the paper's names."""
    import json

    from tt.sim.designs import get_space, save_designs
    from tt.sim.motions.io import save_npz

    monkeypatch.setenv("COLUMNS", "250")  # the table's headers in full
    save_designs([get_space("viperx").nominal()], tmp_path / "designs.json")
    save_npz(_short_toss(), tmp_path / "toss.npz")
    args = ["validate", "--design", str(tmp_path / "designs.json"), "--motion", str(tmp_path / "toss.npz")]
    outs = {}
    for spelled in ("Tracking Velocity", "tracking-velocity", "tracking_velocity"):
        code, text = tt_cli([*args, "--reward", spelled, "--json", str(tmp_path / "v.json")])
        assert code == 0, text
        assert "max joint speed" in text and "tracking_velocity" in text, text
        outs[spelled] = json.loads((tmp_path / "v.json").read_text())
    assert {o["reward"] for o in outs.values()} == {"tracking_velocity"}
    assert len({json.dumps(o["metrics"]) for o in outs.values()}) == 1
    assert outs["tracking_velocity"]["metrics"][0]["max_joint_speed"] > 0
    code, text = tt_cli([*args, "--reward", "speed"])
    assert code == 2 and "unknown reward 'speed'" in text
    code, text = tt_cli(["validate", "--help"])
    assert code == 0 and "Tracking Velocity" in text


def test_unknown_names_and_missing_inputs():
    with pytest.raises(ValueError, match="tracking_torque"):
        get_reward("tracking_speed", "viperx")
    with pytest.raises(ValueError, match="quadruped"):
        get_reward("tracking", "hexapod")
    with pytest.raises(ValueError, match="sigma_p"):
        RewardConfig(name="tracking", space="viperx", sigma_p=0.0)
    inputs = make_inputs([[[0.0]]], [[[0.0]]])
    with pytest.raises(ValueError, match="mass"):
        reward(inputs, get_reward("tracking_weight", "viperx"))
    with pytest.raises(ValueError, match=r"ee_quat.*\(1, 1, 1, 4\)"):
        RewardInputs(
            ee_pos=inputs.ee_pos,
            ee_quat=inputs.ee_quat[..., :3],
            target_pos=inputs.target_pos,
            target_quat=inputs.target_quat,
        )
    # Targets broadcast: one motion for all worlds.
    two = RewardInputs(
        ee_pos=inputs.ee_pos.expand(2, 1, 1, 3),
        ee_quat=inputs.ee_quat.expand(2, 1, 1, 4),
        target_pos=inputs.target_pos[0],
        target_quat=inputs.target_quat[0],
    )
    assert reward(two, get_reward("tracking", "viperx")).tolist() == [1.0, 1.0]
    # Targets that do not broadcast to (W, T, A, 3), e.g. three end effectors for two worlds' one.
    with pytest.raises(ValueError, match=r"target_pos has shape \(3, 3\); expected broadcastable to \(2, 1, 1, 3\)"):
        RewardInputs(
            ee_pos=two.ee_pos, ee_quat=two.ee_quat, target_pos=torch.zeros(3, 3, dtype=DT), target_quat=two.target_quat
        )


def test_reward_stays_on_its_device(device):
    cfg = get_reward("tracking_size", "viperx")
    inputs = make_inputs(POS, ORN, size=torch.tensor([2.5, 1.0], dtype=DT))
    moved = RewardInputs(**{k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in vars(inputs).items()})
    r = reward(moved, cfg)
    assert r.device == torch.device(device)
    torch.testing.assert_close(r.cpu(), reward(inputs, cfg), rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------- size and mass
ROBOT_A = """
<mujoco>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <geom type="box" size="1 1 1" pos="0 0 -3"/>
    <body name="base">
      <geom type="sphere" size="0.1"/>
      <body name="link1" pos="0 0 0.2">
        <joint type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.4" size="0.05"/>
        <geom type="cylinder" size="0.3 0.1" density="500"/>
        <body name="link2" pos="0 0 0.4">
          <joint type="hinge" axis="0 1 0"/>
          <geom type="box" size="0.1 0.2 0.3"/>
          <geom type="ellipsoid" size="0.1 0.2 0.15" mass="2"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

ROBOT_B = """
<mujoco>
  <worldbody>
    <body><freejoint/><geom type="box" size="0.5 0.05 0.05"/></body>
    <body pos="2 0 0"><geom type="capsule" size="0.02 0.3" density="2000"/></body>
  </worldbody>
</mujoco>
"""


def test_robot_size_and_mass_of_primitive_geoms():
    models = [mujoco.MjModel.from_xml_string(x) for x in (ROBOT_A, ROBOT_B)]
    # Longest dimensions: sphere 2r, capsule 2(h + r), cylinder max(2r, 2h), box 2 max, ellipsoid 2 max.
    size_a = 0.2 + (0.4 + 0.1) + max(0.6, 0.2) + 0.6 + 0.4
    size_b = 1.0 + 2 * (0.3 + 0.02)
    pi = math.pi
    mass_a = (
        1000 * 4 / 3 * pi * 0.1**3
        + 1000 * (pi * 0.05**2 * 0.4 + 4 / 3 * pi * 0.05**3)
        + 500 * pi * 0.3**2 * 0.2
        + 1000 * 8 * 0.1 * 0.2 * 0.3
        + 2.0
    )
    mass_b = 1000 * 1.0 * 0.1 * 0.1 + 2000 * (pi * 0.02**2 * 0.6 + 4 / 3 * pi * 0.02**3)
    size = robot_size(models, dtype=DT)
    mass = robot_mass(models, dtype=DT)
    assert size.shape == (2,) and size.dtype == DT
    torch.testing.assert_close(size, torch.tensor([size_a, size_b], dtype=DT), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(mass, torch.tensor([mass_a, mass_b], dtype=DT), rtol=1e-9, atol=0)
    assert robot_size([]).shape == (0,)
