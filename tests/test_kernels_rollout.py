"""The fused rollout's differentiability and the Warp tracking reward.

* The tracking reward kernel equals `tt.guidance.rewards` (the torch definition), value and
  gradient with respect to the poses.
* Gradients of the tracking reward of a rollout with respect to link offsets (body_pos)
  and the mount pose, taken with `wp.Tape` through the differentiable rollout kernel, equal
  central finite differences of the same rollout run in float64 by MuJoCo C with the
  oracle's mink controller (relative error <= 1e-2). The start posture is held fixed (the
  oracle's, passed to both): gradients flow through the controller and the physics.
"""

import mujoco
import numpy as np
import pytest
import torch
import warp as wp

from tt.guidance.rewards import RewardInputs, evaluate, get_reward
from tt.kernels.model import build_tree_model
from tt.kernels.pose import tracking_reward
from tt.kernels.rollout import motion_arrays, rollout_tree
from tt.sim.controller import DiffIKController, IKConfig
from tt.sim.designs import get_space
from tt.sim.motions import motion_set

GRAD_REL_TOL = 1e-2
STEPS = 20  # control steps of the differentiated rollouts (0.4 s, 200 physics steps)


def test_tracking_reward_kernel_matches_the_torch_reward():
    rng = np.random.default_rng(0)
    W, T, A = 5, 7, 2
    pos = rng.normal(0.0, 0.1, (W, T, A, 3))
    target_pos = pos + rng.normal(0.0, 0.05, (W, T, A, 3))
    quat = rng.normal(size=(W, T, A, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    target_quat = rng.normal(size=(W, T, A, 4))
    target_quat /= np.linalg.norm(target_quat, axis=-1, keepdims=True)
    target_quat[0, 0] = quat[0, 0]  # zero orientation error: the gradient must stay finite
    counted = np.ones((W, T), dtype=np.int32)
    counted[1, 3:] = 0

    arrays = {
        "pos": wp.array(pos.astype(np.float32), dtype=wp.vec3, requires_grad=True),
        "quat": wp.array(quat.astype(np.float32), dtype=wp.vec4, requires_grad=True),
        "tpos": wp.array(target_pos.astype(np.float32), dtype=wp.vec3),
        "tquat": wp.array(target_quat.astype(np.float32), dtype=wp.vec4),
    }
    reward = wp.zeros(W, dtype=float, requires_grad=True)
    tape = wp.Tape()
    with tape:
        tracking_reward(
            arrays["pos"], arrays["quat"], arrays["tpos"], arrays["tquat"], wp.array(counted, dtype=wp.int32), reward
        )
    tape.backward(grads={reward: wp.ones(W, dtype=float)})

    t = {k: torch.tensor(v, dtype=torch.float64) for k, v in dict(pos=pos, quat=quat, tpos=target_pos, tquat=target_quat).items()}
    t["pos"].requires_grad_(True)
    t["quat"].requires_grad_(True)
    alive = torch.tensor(counted.astype(bool))
    cfg = get_reward("tracking", "aloha")
    ref = evaluate(RewardInputs(t["pos"], t["quat"], t["tpos"], t["tquat"], alive=alive), cfg)
    # The torch reward also stops counting after termination (summed error > 0.5 m); the
    # poses here stay within it, so both count the same steps.
    assert bool(ref.counted.eq(alive).all())
    ref.reward.sum().backward()
    np.testing.assert_allclose(reward.numpy(), ref.reward.detach().numpy(), rtol=1e-5)
    np.testing.assert_allclose(arrays["pos"].grad.numpy(), t["pos"].grad.numpy(), rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(arrays["quat"].grad.numpy(), t["quat"].grad.numpy(), rtol=1e-3, atol=1e-4)


def _oracle_reward(model: mujoco.MjModel, motion, q0: np.ndarray, config: IKConfig) -> float:
    """Tracking reward of `STEPS` control steps in MuJoCo C + mink (float64) from posture q0."""
    controller = DiffIKController(model, config)
    data = mujoco.MjData(model)
    data.qpos[:] = q0
    mujoco.mj_forward(model, data)
    total = 0.0
    for k in range(STEPS):
        goal = min(k + config.lookahead_steps, STEPS - 1)
        data.ctrl[:] = controller.step(data.qpos.copy(), motion.pos[goal], motion.quat[goal])
        for _ in range(config.substeps(model)):
            mujoco.mj_step(model, data)
        mujoco.mj_forward(model, data)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, data.site_xmat[0])
        eps_p = np.linalg.norm(motion.pos[k, 0] - data.site_xpos[0])
        w = abs(float(np.dot(quat, motion.quat[k, 0])))
        eps_o = 2.0 * np.arctan2(np.sqrt(max(0.0, 1.0 - w * w)), w)
        total += np.exp(-eps_p**2 / 0.01 - eps_o**2 / 0.5)
    return total


def _quat_mul(a, b):
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


@pytest.mark.slow
def test_rollout_gradients_match_float64_finite_differences():
    space = get_space("viperx")
    motion = motion_set("train", arms=1)[0]
    config = IKConfig()
    # Two designs of one topology (one compile of the differentiable module).
    nominal = space.nominal()
    other = next(d for d in space.sample(50, seed=3) if d.discrete[1] == nominal.discrete[1])
    for design in (nominal, other):
        model = space.model(design)
        q0 = DiffIKController(model, config).initial_q(motion.pos[0], motion.quat[0])
        tree = build_tree_model([model], space.ee_sites(), device="cpu", requires_grad=True)
        motions = motion_arrays(motion.pos[None, :STEPS], motion.quat[None, :STEPS], [STEPS], device="cpu")
        tape = wp.Tape()
        reward = wp.zeros(1, dtype=float, requires_grad=True)
        with tape:
            out = rollout_tree(tree, motions, 1, STEPS, config=config, differentiable=True, initial_qpos=q0[None])
            counted = wp.array(out.alive.numpy().astype(np.int32), dtype=wp.int32)
            tracking_reward(out.ee_pos, out.ee_quat, out.target_pos, out.target_quat, counted, reward)
        assert out.alive.numpy().all()
        tape.backward(loss=reward)
        grad_pos = tree.body_pos.grad.numpy()[0].copy()
        grad_quat = tree.body_quat.grad.numpy()[0].copy()

        eps = 1e-5
        # Link offsets of every moving body and the mount position.
        for b in range(1, model.nbody):
            for c in range(3):
                if abs(model.body_pos[b, c]) < 1e-12 and b > 1:
                    continue  # offsets that are zero by construction stay so
                values = []
                for sign in (1.0, -1.0):
                    m = space.model(design)
                    m.body_pos[b, c] += sign * eps
                    values.append(_oracle_reward(m, motion, q0, config))
                fd = (values[0] - values[1]) / (2 * eps)
                assert abs(grad_pos[b, c] - fd) <= GRAD_REL_TOL * max(abs(fd), 1e-2), (b, c, grad_pos[b, c], fd)
        # Mount yaw: rotate the base about the world z axis; d/dyaw by the chain rule.
        base_quat = space.model(design).body_quat[1].copy()
        dq_dyaw = 0.5 * _quat_mul([0.0, 0.0, 0.0, 1.0], base_quat)
        adjoint = float(grad_quat[1] @ dq_dyaw)
        values = []
        for sign in (1.0, -1.0):
            m = space.model(design)
            m.body_quat[1] = _quat_mul([np.cos(sign * eps / 2), 0.0, 0.0, np.sin(sign * eps / 2)], base_quat)
            values.append(_oracle_reward(m, motion, q0, config))
        fd = (values[0] - values[1]) / (2 * eps)
        assert abs(adjoint - fd) <= GRAD_REL_TOL * max(abs(fd), 1e-2), (adjoint, fd)
