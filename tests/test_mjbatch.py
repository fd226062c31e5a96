"""The ``mjbatch`` backend (MuJoCo C on a thread pool, tt's batched whole-body controller)
against the oracle (`tt.sim.validate.oracle_rollout`) on random quadruped designs.

The physics is the oracle's own (MuJoCo C, float64, the solver's warm start carried from
step to step), so with the oracle's mink controller (``controller="mink"``) every field of
every episode equals the oracle's bit for bit, terminations and padding included, for any
thread count. With tt's whole-body kernel (the default) the commands differ from mink's by
round-off (about 1e-13 rad), which the contacts may amplify; the agreement measure is then
the issue's: each episode's mean position error within 0.3 cm of the oracle's, and the same
survived / fell outcome (a fast case here, 100 designs x 5 validation motions in the slow
test).
"""

import mujoco
import numpy as np
import pytest
import torch

from tt.baselines.evaluate import score_episode
from tt.kernels.errors import TTError
from tt.kernels.rollout import action_noise_draws
from tt.sim.backends import get_backend
from tt.sim.controller import actuated_qpos
from tt.sim.designs import get_space
from tt.sim.mjbatch_backend import actuator_forces, affine_actuators, layout_key, mat2quat, mjbatch_rollout
from tt.sim.motions import for_space, motion_set
from tt.sim.motions.base import Motion
from tt.sim.rollout import rollout
from tt.sim.validate import oracle_rollout
from tt.sim.wbc import HOME_KEY, WBCConfig, WholeBodyController, fallen, free_joint, standing_height

POS_TOL_CM = 0.3  # per-episode mean position error, the measure [cm]
FIELDS = (
    "qpos", "qvel", "ctrl", "action", "act_force", "act_vel", "ee_pos", "ee_quat",
    "target_pos", "target_quat", "alive", "fallen", "design_index", "motion_index",
)  # fmt: skip


def _val(steps: int | None = None, count: int | None = None) -> list[Motion]:
    motions = for_space(motion_set("val", arms=1), "quadruped")[:count]
    if steps is None:
        return motions
    return [Motion(f"{m.name}[:{steps}]", m.pos[:steps], m.quat[:steps], m.dt) for m in motions]


def _layout_mates(space, seed: int) -> list:
    """Two designs of different structures (discrete choices) with one MjData layout."""
    designs = space.sample(40, seed=seed)
    seen: dict[tuple, object] = {}
    for d in designs:
        key = layout_key(space.model(d))
        other = seen.get(key)
        if other is not None and tuple(other.discrete) != tuple(d.discrete):
            return [other, d]
        seen.setdefault(key, d)
    raise AssertionError("no two structures share a layout among 40 samples")


def _equal(ep, ref) -> None:
    for name in FIELDS:
        a, b = getattr(ep, name), getattr(ref, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert torch.equal(a, b), (name, float((a.double() - b.double()).abs().max()))
    assert ep.dt == ref.dt


def _agreement(ep, ref, designs, motions) -> tuple[np.ndarray, np.ndarray]:
    """Per-episode |mean position error - the oracle's| [cm] and whether the survived /
    fell outcome is the same, (D * M,) each."""
    _, mine = score_episode(ep, designs, motions, "tracking")
    _, theirs = score_episode(ref, designs, motions, "tracking")
    gap = np.abs(mine["pos_err"] - theirs["pos_err"]).ravel()
    same = (
        (ep.alive.sum(1) == ref.alive.sum(1)).numpy()
        & (ep.fallen.any(1) == ref.fallen.any(1)).numpy()
        & (mine["survival"] == theirs["survival"]).ravel()
    )
    return gap, same


def test_mink_controller_equals_the_oracle_bit_for_bit():
    """Mixed structures in one batch, motions of different lengths and one out of reach
    (its worlds stop at once): every field equals the oracle's, on 1 and 2 threads."""
    space = get_space("quadruped")
    designs = [*_layout_mates(space, seed=5), *space.sample(1, seed=11)]
    a, b = _val(16, 2)
    far = Motion("far", a.pos[:10] + np.array([1.5, 0.0, 0.0]), a.quat[:10], a.dt)
    motions = [a, Motion("b_short", b.pos[:9], b.quat[:9], b.dt), far]
    ref = oracle_rollout(designs, motions)
    assert not ref.alive[2::3].any() and ref.alive[0::3].all()  # the far motion stops its worlds at step 0
    robots = get_backend("mjbatch").resolve(designs)
    for threads in (1, 2):
        _equal(mjbatch_rollout(robots, motions, threads=threads, controller="mink"), ref)


def test_kernel_controller_agrees_with_the_oracle():
    """4 random designs x 1 validation motion (2 s): the issue's fast agreement case,
    through `rollout(backend="mjbatch")`; and the Episode does not depend on the threads."""
    space = get_space("quadruped")
    designs = space.sample(4, seed=2)
    motions = _val(100, 1)
    ref = oracle_rollout(designs, motions)
    ep = rollout(designs, motions, backend="mjbatch", threads=2)
    gap, same = _agreement(ep, ref, designs, motions)
    assert np.all(gap <= POS_TOL_CM), gap
    assert np.all(same)
    # Same physics, commands within round-off: the trajectories agree far inside the bound.
    assert float((ep.ee_pos - ref.ee_pos).abs().max()) < 1e-4
    _equal(rollout(designs, motions, backend="mjbatch", threads=1), ep)


def test_stance_points_from_the_batch_are_stance_points(monkeypatch):
    """The backend reads the stance points from its batches' home-pose kinematics; the
    controller they give is the one `tt.sim.wbc.stance_points` gives, bit for bit."""
    import tt.sim.wbc_model as wbc_model

    space = get_space("quadruped")
    robots = get_backend("mjbatch").resolve(_layout_mates(space, seed=5))
    motions = _val(8, 1)
    ep = mjbatch_rollout(robots, motions, threads=1)
    build = wbc_model.build_wbc_model
    monkeypatch.setattr(wbc_model, "build_wbc_model", lambda *a, stance=None, **k: build(*a, **k))
    _equal(mjbatch_rollout(robots, motions, threads=1), ep)


def test_mat2quat_is_mujocos():
    rng = np.random.default_rng(0)
    quats = rng.standard_normal((400, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # each branch of mju_mat2Quat
    mats = np.zeros((len(quats), 9))
    ref = np.zeros((len(quats), 4))
    for i, q in enumerate(quats):
        mujoco.mju_quat2Mat(mats[i], q)
        mujoco.mju_mat2Quat(ref[i], mats[i])
    np.testing.assert_allclose(mat2quat(mats), ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mat2quat(mats.reshape(100, 4, 9)), ref.reshape(100, 4, 4), rtol=0, atol=1e-15)


def test_actuator_forces_are_mujocos():
    """The forces the backend computes at stage VEL (no constraint solve) equal the ones
    MuJoCo's forward computes, bit for bit in float64, at random states and commands, some
    past the force range; a model with a stateful actuator is left to the forward."""
    space = get_space("quadruped")
    models = [space.model(d) for d in _layout_mates(space, seed=5)]
    force = affine_actuators(models)
    assert force is not None
    rng = np.random.default_rng(0)
    for i, m in enumerate(models):
        data = mujoco.MjData(m)
        for _ in range(20):
            mujoco.mj_resetDataKeyframe(m, data, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY))
            data.qpos[7:] += rng.normal(0.0, 0.3, m.nq - 7)
            data.qvel[:] = rng.normal(0.0, 3.0, m.nv)
            lo, hi = m.actuator_ctrlrange.T
            data.ctrl[:] = np.clip(data.qpos[actuated_qpos(m)] + rng.normal(0.0, 0.2, m.nu), lo, hi)
            mujoco.mj_forward(m, data)
            got = actuator_forces(
                tuple(p[i : i + 1] for p in force), data.ctrl[None], data.actuator_length[None],
                data.actuator_velocity[None],
            )[0]  # fmt: skip
            assert np.array_equal(got, data.actuator_force)
        assert np.any(np.abs(got) == m.actuator_forcerange[:, 1])  # the range clips some
    stateful = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body><joint name="j"/><geom size=".1"/></body></worldbody>'
        '<actuator><position joint="j" kp="10" timeconst="0.1"/></actuator></mujoco>'
    )
    assert affine_actuators([*models, stateful]) is None


def test_rejects_fixed_base_arms():
    arm = get_space("viperx").nominal()
    motion = for_space(motion_set("val", arms=1), "viperx")[0]
    with pytest.raises(TTError, match="no free joint.*'mjbatch' backend runs floating-base"):
        rollout([arm], [motion], backend="mjbatch")


def _perturbed_reference(model, sites, motion, steps, world, sigma, seed, config=WBCConfig()):
    """The oracle's loop (`tt.sim.validate`, MjData and mink) executing the "warp" backend's
    control perturbation: clip(ctrl + sigma n[world, t], ctrlrange), n of
    `action_noise_draws`; (qpos, executed ctrl, clean ctrl, alive), (steps, ...) float64."""
    controller = WholeBodyController(model, config)
    act = actuated_qpos(model)
    limited = model.actuator_ctrllimited.astype(bool)
    lo = np.where(limited, model.actuator_ctrlrange[:, 0], -np.inf)
    hi = np.where(limited, model.actuator_ctrlrange[:, 1], np.inf)
    noise = action_noise_draws(seed, [world], steps, model.nu)[0].astype(np.float64)
    site_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in sites]
    base, height = int(model.jnt_qposadr[free_joint(model)]), standing_height(model)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY))
    data.qpos[:] = controller.initial_q(motion.pos[0], motion.quat[0])
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)
    qpos, ctrl_out, action = np.zeros((steps, model.nq)), np.zeros((steps, model.nu)), np.zeros((steps, model.nu))
    alive, last = np.zeros(steps, bool), None
    for k in range(steps):
        if last is not None:
            qpos[k], ctrl_out[k], action[k] = qpos[last], ctrl_out[last], action[last]
            continue
        goal = min(k + config.lookahead_steps, motion.steps - 1)
        ctrl = np.clip(controller.step(data.qpos.copy(), motion.pos[goal], motion.quat[goal])[act], lo, hi)
        data.ctrl[:] = np.clip(ctrl + sigma * noise[k], lo, hi)
        for _ in range(config.substeps(model)):
            mujoco.mj_step(model, data)
        mujoco.mj_forward(model, data)
        qpos[k], ctrl_out[k], action[k] = data.qpos, data.ctrl, ctrl
        error = np.linalg.norm(data.site_xpos[site_ids] - motion.pos[min(k, motion.steps - 1)], axis=-1).sum()
        fell = fallen(data.qpos[base : base + 3], data.qpos[base + 3 : base + 7], height, config)
        alive[k] = np.isfinite(error) and error <= config.termination_pos_error and not fell
        if not alive[k] or k == motion.steps - 1:
            last = k
    return qpos, ctrl_out, action, alive


def test_control_perturbation_is_the_warp_backends_on_the_oracles_loop():
    """action_noise > 0: the actuators execute clip(ctrl + sigma n, ctrlrange) with the Warp
    rollout kernel's normals n (`action_noise_draws`, keyed by world index and step) and
    ``Episode.action`` holds the clean command. With the mink controller every world equals
    the oracle's loop perturbed that way, bit for bit (terminations and padding included), on
    1 and 2 threads; with the kernel the Episode does not depend on the threads; sigma = 0 is
    the unperturbed rollout."""
    space = get_space("quadruped")
    designs = [*_layout_mates(space, seed=5), *space.sample(1, seed=11)]
    a, b = _val(24, 2)
    motions = [a, Motion("b_short", b.pos[:15], b.quat[:15], b.dt)]
    sigma, seed = 0.05, 1234
    robots = get_backend("mjbatch").resolve(designs)
    M, T = len(motions), 24
    for threads in (1, 2):
        ep = mjbatch_rollout(robots, motions, threads=threads, controller="mink", action_noise=sigma, noise_seed=seed)
        for d, model in enumerate(robots.models):
            for m, motion in enumerate(motions):
                w = d * M + m
                qpos, ctrl, action, alive = _perturbed_reference(model, robots.ee_sites, motion, T, w, sigma, seed)
                assert torch.equal(ep.qpos[w, :, : model.nq], torch.from_numpy(qpos).float()), (threads, w)
                assert torch.equal(ep.ctrl[w, :, : model.nu], torch.from_numpy(ctrl).float()), (threads, w)
                assert torch.equal(ep.action[w, :, : model.nu], torch.from_numpy(action).float()), (threads, w)
                assert torch.equal(ep.alive[w], torch.from_numpy(alive)), (threads, w)
    clean = mjbatch_rollout(robots, motions, threads=1, controller="mink")
    assert not torch.equal(clean.qpos, ep.qpos) and not torch.equal(ep.ctrl, ep.action)
    # The kernel controller through rollout(): the same draws, every thread count.
    noisy = rollout(designs, motions, backend="mjbatch", threads=2, action_noise=sigma, noise_seed=seed)
    _equal(rollout(designs, motions, backend="mjbatch", threads=1, action_noise=sigma, noise_seed=seed), noisy)
    nu = max(m.nu for m in robots.models)
    n = torch.from_numpy(action_noise_draws(seed, np.arange(noisy.worlds), T, nu))
    # The stepped records: alive, or the step that failed (before the motion's end).
    alive_steps = noisy.alive.sum(1, keepdim=True)
    lengths = torch.tensor([m.steps for m in motions])[noisy.motion_index][:, None]
    stepped = noisy.alive | ((torch.arange(T) == alive_steps) & (alive_steps < lengths))
    expect = noisy.action.double() + sigma * n.double()
    for d, model in enumerate(robots.models):
        lim = model.actuator_ctrllimited.astype(bool)
        lo = torch.from_numpy(np.where(lim, model.actuator_ctrlrange[:, 0], -np.inf))
        hi = torch.from_numpy(np.where(lim, model.actuator_ctrlrange[:, 1], np.inf))
        rows = slice(d * M, (d + 1) * M)
        want = torch.clamp(expect[rows, :, : model.nu], lo, hi)[stepped[rows]]
        torch.testing.assert_close(noisy.ctrl[rows, :, : model.nu][stepped[rows]].double(), want, rtol=0, atol=1e-6)
    _equal(
        rollout(designs, motions, backend="mjbatch", action_noise=0.0, noise_seed=seed),
        rollout(designs, motions, backend="mjbatch"),
    )


@pytest.mark.slow
def test_agrees_with_the_oracle_on_100_random_designs_x_5_motions():
    """The issue's agreement bar: over 100 random designs x 5 validation motions, per-episode
    mean position error within 0.3 cm of the oracle's in >= 95 % of the episodes and the same
    survived / fell outcome in >= 97 % (several minutes: the oracle runs 500 episodes)."""
    space = get_space("quadruped")
    designs = space.sample(100, seed=7)
    all_val = _val()
    motions = [all_val[i] for i in (0, 7, 13, 20, 28)]
    ref = oracle_rollout(designs, motions)
    ep = rollout(designs, motions, backend="mjbatch")
    gap, same = _agreement(ep, ref, designs, motions)
    assert np.mean(gap <= POS_TOL_CM) >= 0.95, np.sort(gap)[-10:]
    assert np.mean(same) >= 0.97, np.flatnonzero(~same)


def test_evaluate_designs_defaults_to_the_spaces_backend():
    """Without a backend, evaluate_designs rolls the quadruped out on mjbatch (the space's
    default), the same rewards as naming it; naming "warp" is still refused for contacts."""
    from tt.baselines.evaluate import evaluate_designs

    space = get_space("quadruped")
    designs = space.sample(2, seed=4)
    placed = for_space(motion_set("val", arms=1)[:1], "quadruped")
    motions = [Motion(m.name, m.pos[:20], m.quat[:20], m.dt) for m in placed]
    default = evaluate_designs(designs, motions, "tracking", device="cpu")
    named = evaluate_designs(designs, motions, "tracking", backend="mjbatch", device="cpu")
    np.testing.assert_array_equal(default.reward, named.reward)
    with pytest.raises(TTError, match="has contacts; backend 'warp'"):
        evaluate_designs(designs, motions, "tracking", backend="warp", device="cpu")
