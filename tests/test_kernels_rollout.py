"""The fused rollout's differentiability and the Warp tracking reward.

* The tracking reward kernel equals `tt.sim.rewards` (the torch definition), value and
  gradient with respect to the poses.
* Gradients of the tracking reward of a rollout with respect to link offsets (body_pos)
  and the mount pose, taken with `wp.Tape` through the differentiable rollout kernel, equal
  central finite differences of the same rollout run in float64 by MuJoCo C with the
  oracle's mink controller (relative error <= 1e-2), on ten ViperX designs of 5, 6 and 7
  DoF. The start posture is held fixed (the oracle's, passed to both): gradients flow
  through the controller and the physics.
"""

import mujoco
import numpy as np
import pytest
import torch
import warp as wp

from tt.kernels.model import build_tree_model
from tt.kernels.pose import tracking_reward
from tt.kernels.rollout import motion_arrays, rollout_tree
from tt.sim.controller import DiffIKController, IKConfig
from tt.sim.designs import get_space
from tt.sim.motions import motion_set
from tt.sim.rewards import RewardInputs, evaluate, get_reward

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

    t = {
        k: torch.tensor(v, dtype=torch.float64)
        for k, v in dict(pos=pos, quat=quat, tpos=target_pos, tquat=target_quat).items()
    }
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
        total += np.exp(-(eps_p**2) / 0.01 - eps_o**2 / 0.5)
    return total


def _quat_mul(a, b):
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def _check_design_gradients(space, design, motion, config: IKConfig) -> None:
    """Tape gradients of the tracking reward of `design` w.r.t. its link offsets and mount
    yaw against central finite differences of the float64 oracle rollout."""
    model = space.model(design)
    q0 = DiffIKController(model, config).initial_q(motion.pos[0], motion.quat[0])
    tree = build_tree_model([model], space.ee_sites(), device="cpu", requires_grad=True)
    motions = motion_arrays(motion.pos[None, :STEPS], motion.quat[None, :STEPS], [STEPS], device="cpu")
    tape = wp.Tape()
    reward = wp.zeros(1, dtype=float, requires_grad=True)
    with tape:
        out = rollout_tree(tree, motions, 1, STEPS, **config.rollout_args(), differentiable=True, initial_qpos=q0[None])
        counted = wp.array(out.alive.numpy().astype(np.int32), dtype=wp.int32)
        tracking_reward(out.ee_pos, out.ee_quat, out.target_pos, out.target_quat, counted, reward)
    assert out.alive.numpy().all()
    tape.backward(loss=reward)
    grad_pos = tree.arrays.body_pos.grad.numpy()[0].copy()
    grad_quat = tree.arrays.body_quat.grad.numpy()[0].copy()

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
            assert abs(grad_pos[b, c] - fd) <= GRAD_REL_TOL * max(abs(fd), 1e-2), (design, b, c, grad_pos[b, c], fd)
    # Mount yaw: rotate the base about the world z axis; d/dyaw by the chain rule.
    base_quat = model.body_quat[1].copy()
    dq_dyaw = 0.5 * _quat_mul([0.0, 0.0, 0.0, 1.0], base_quat)
    adjoint = float(grad_quat[1] @ dq_dyaw)
    values = []
    for sign in (1.0, -1.0):
        m = space.model(design)
        m.body_quat[1] = _quat_mul([np.cos(sign * eps / 2), 0.0, 0.0, np.sin(sign * eps / 2)], base_quat)
        values.append(_oracle_reward(m, motion, q0, config))
    fd = (values[0] - values[1]) / (2 * eps)
    assert abs(adjoint - fd) <= GRAD_REL_TOL * max(abs(fd), 1e-2), (design, adjoint, fd)


@pytest.mark.slow
def test_rollout_gradients_match_float64_finite_differences():
    # Ten designs: the nominal and, for each DoF count (5, 6, 7), the first three random ones
    # that track the motion's start (oracle reward above 1 of 20): a design whose end
    # effector stays far from the targets has a reward and gradients of 1e-10 or less, which
    # says nothing (5 of the first 10 random designs of seed 0; those pass too).
    space = get_space("viperx")
    motion = motion_set("train", arms=1)[0]
    config = IKConfig()
    chosen, per_dof = [space.nominal()], {5: 0, 6: 0, 7: 0}
    for design in space.sample(60, seed=0):
        model = space.model(design)
        if per_dof[model.nu] == 3:
            continue
        q0 = DiffIKController(model, config).initial_q(motion.pos[0], motion.quat[0])
        if _oracle_reward(model, motion, q0, config) > 1.0:
            chosen.append(design)
            per_dof[model.nu] += 1
    assert len(chosen) == 10, per_dof
    for design in chosen:
        _check_design_gradients(space, design, motion, config)


_LIMITED_ARM = """
<mujoco model="limited_arm">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.002" integrator="Euler"><flag contact="disable"/></option>
  <worldbody>
    <body name="b1" pos="0 0 0.1">
      <joint name="j1" type="hinge" axis="0 0 1" range="-0.06 0.06" damping="0.1" armature="0.01"/>
      <geom type="capsule" fromto="0 0 0 0.28 0 0" size="0.02" density="1000"/>
      <body name="b2" pos="0.28 0 0" euler="0 0 1.5708">
        <joint name="j2" type="hinge" axis="0 0 1" range="-0.05 0.05" damping="0.1" armature="0.01"/>
        <geom type="capsule" fromto="0 0 0 0.22 0 0" size="0.02" density="1000"/>
        <site name="ee_0" pos="0.22 0 0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="j1" kp="30" kv="2" ctrlrange="-0.06 0.06"/>
    <position joint="j2" kp="30" kv="2" ctrlrange="-0.05 0.05"/>
  </actuator>
</mujoco>
"""


@pytest.mark.slow
def test_gradients_through_active_joint_limits_match_float64_finite_differences():
    # A two-link arm with ranges of a few degrees, driven along a circle it cannot follow:
    # it presses into its joint limits, so the soft limit constraints act on most steps.
    model = mujoco.MjModel.from_xml_string(_LIMITED_ARM)
    t = np.arange(STEPS) * 0.02
    pos = np.stack([0.22 + 0.06 * np.cos(3 * t), 0.18 + 0.06 * np.sin(3 * t), np.full_like(t, 0.1)], -1)[:, None]
    yaw = np.pi / 2 + 0.3 * np.sin(3 * t)
    quat = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], -1)[:, None]
    from tt.sim.motions.base import Motion

    motion = Motion("circle", pos, quat)
    config = IKConfig()
    q0 = DiffIKController(model, config).initial_q(motion.pos[0], motion.quat[0])
    tree = build_tree_model([model], ("ee_0",), device="cpu", requires_grad=True)
    motions = motion_arrays(motion.pos[None], motion.quat[None], [STEPS], device="cpu")
    reward = wp.zeros(1, dtype=float, requires_grad=True)
    tape = wp.Tape()
    with tape:
        out = rollout_tree(tree, motions, 1, STEPS, **config.rollout_args(), differentiable=True, initial_qpos=q0[None])
        counted = wp.array(out.alive.numpy().astype(np.int32), dtype=wp.int32)
        tracking_reward(out.ee_pos, out.ee_quat, out.target_pos, out.target_quat, counted, reward)
    tape.backward(loss=reward)
    # The limits are active in the rollout (MuJoCo's constraint count on the recorded states).
    data = mujoco.MjData(model)
    active = 0
    for q, qd in zip(out.qpos.numpy()[0], out.qvel.numpy()[0]):
        data.qpos[:], data.qvel[:] = q, qd
        mujoco.mj_forward(model, data)
        active += data.nefc > 0
    assert active >= STEPS // 4
    checks = [("body_pos", (2, 0)), ("body_pos", (1, 2)), ("act_gain", (0,)), ("act_gain", (1,)), ("dof_damping", (1,))]
    for name, index in checks:
        adjoint = float(getattr(tree.arrays, name).grad.numpy()[0][index])
        values = []
        for sign in (1.0, -1.0):
            m = mujoco.MjModel.from_xml_string(_LIMITED_ARM)
            if name == "body_pos":
                m.body_pos[index] += sign * 1e-5
            elif name == "act_gain":
                m.actuator_gainprm[index[0], 0] += sign * 1e-3
                m.actuator_biasprm[index[0], 1] -= sign * 1e-3  # a position servo's kp is both
            else:
                m.dof_damping[index[0]] += sign * 1e-4
            values.append(_oracle_reward(m, motion, q0, config))
        step = {"body_pos": 1e-5, "act_gain": 1e-3, "dof_damping": 1e-4}[name]
        fd = (values[0] - values[1]) / (2 * step)
        if name == "act_gain":
            # kp enters as gain and as bias b1 = -kp: the chain rule adds the bias gradient.
            adjoint -= float(tree.arrays.act_bias.grad.numpy()[0][index[0]][1])
        assert abs(adjoint - fd) <= GRAD_REL_TOL * max(abs(fd), 1e-2), (name, index, adjoint, fd)


@pytest.mark.parametrize("space", ["viperx", "bimanual"])
def test_per_topology_modules_hash_without_code_generation(space):
    """tt's per-topology kernels write the topology in as constants (no `wp.static` that
    depends on a loop counter), so Warp hashes their modules from source and constants and
    a cached module loads without Python code generation (about a second per rollout
    module otherwise). This reads Warp's own flag for "needs codegen to hash" on every
    module the rollout kernels draw functions from."""
    from tt.kernels.control_step import control_step_kernel
    from tt.kernels.fk import fk_kernel
    from tt.kernels.model import module_name, topology_of
    from tt.kernels.rollout import grad_kernels, rollout_kernels

    sp = get_space(space)
    top = topology_of(sp.model(sp.nominal()), sp.ee_sites())
    kernels = rollout_kernels(top)
    grads = grad_kernels(top)
    fk_kernel(top)
    control_step_kernel(top)
    modules = {
        kernels.module,
        grads.module,
        module_name(top, "fk"),
        module_name(top, "control_step"),
        "tt.kernels.fk",
        "tt.kernels.dynamics",
        "tt.kernels.ik",
        "tt.kernels.ltdl",
    }
    for name in sorted(modules):
        assert not wp.get_module(name).has_unresolved_static_expressions, name
    for kernel in (kernels.rollout, kernels.initial_posture, grads.rollout):
        assert not kernel.adj.has_unresolved_static_expressions, kernel.key
