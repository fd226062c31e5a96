"""The reference backends, MuJoCo-Warp (``mjwarp``) and Newton (``newton``), against MuJoCo C.

Open loop (the same actuator commands at every physics step, 2 s = 1000 steps): both
integrate in float32 while MuJoCo C runs in float64, and the servo dynamics amplify
round-off (a joint pushed into a limit, a target that flips). As in
`tests/test_kernels_dynamics.py` the tolerance is defended by measuring that
amplification on MuJoCo alone: each design also runs from a start perturbed by 1e-6 rad,
and a backend's error may not exceed 1e-3 rad or 10x that self-sensitivity, whichever is
larger. MuJoCo-Warp solves MuJoCo's joint-limit constraints, so its commands drive joints
into their limits; Newton's limits are penalty springs (an approximation, see
`tt.sim.newton_backend`), so its commands stay inside the joint ranges and the test
checks that MuJoCo's reference never activated a limit.

Closed loop (the oracle's controller, `tt.sim.validate.oracle_rollout`): on 4 ViperX
designs x 1.2 s of the toss, the same steps survive and each world's mean position error
is within 0.2 cm of the oracle's (mjwarp) or 0.5 cm (newton: limits differ, see above).
"""

import math

import mujoco
import numpy as np
import pytest
import torch
import warp as wp
from ctrl_targets import some_at_the_ends

from tt.kernels.records import mat2quat
from tt.sim.designs import get_space
from tt.sim.mjwarp_backend import batch_model, mjwarp_simulate, structure_key
from tt.sim.motions import for_space, get_motion
from tt.sim.motions.base import Motion
from tt.sim.newton_backend import newton_simulate
from tt.sim.rollout import rollout
from tt.sim.validate import oracle_rollout

HORIZON_STEPS = 1000  # 2 s at 0.002 s
HORIZON_TOL = 1e-3  # [rad]
CLOSED_LOOP_STEPS = 60  # 1.2 s at 50 Hz
MJWARP_POS_TOL = 0.2e-2  # [m], mean position error per world
NEWTON_POS_TOL = 0.5e-2  # [m]


def _same_structure(space, n, seed):
    """n designs of the most common MuJoCo-Warp structure among 40 samples."""
    designs = space.sample(40, seed=seed)
    keys = [structure_key(space.model(d)) for d in designs]
    best = max(set(keys), key=keys.count)
    chosen = [d for d, k in zip(designs, keys) if k == best][:n]
    assert len(chosen) == n
    return chosen


def _ctrl_sequence(models, steps, rng, fraction, ends=0.3):
    """Piecewise-constant targets (new every 0.1 s) within `fraction` of each ctrl range
    around its centre, (W, steps, max nu)."""
    nu = max(m.nu for m in models)
    ctrl = np.zeros((len(models), steps, nu))
    for i, m in enumerate(models):
        lo, hi = m.actuator_ctrlrange.T
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * fraction
        knots = rng.uniform(mid - half, mid + half, size=(steps // 50 + 1, m.nu))
        ctrl[i, :, : m.nu] = some_at_the_ends(np.repeat(knots, 50, axis=0)[:steps], lo, hi, rng, ends)
    return ctrl


def _mujoco_run(m, qpos0, ctrl):
    """qpos (S + 1, nq) of MuJoCo C and the number of steps with an active constraint."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    out = [d.qpos.copy()]
    limited = 0
    for c in ctrl:
        d.ctrl[:] = c[: m.nu]
        mujoco.mj_step(m, d)
        out.append(d.qpos.copy())
        limited += d.nefc > 0
    return np.array(out), limited


def _reference(models, ctrl, rng):
    """MuJoCo C trajectories, their self-sensitivity to a 1e-6 rad start perturbation and
    the count of constrained steps."""
    refs, sensitivity, limited = [], [], 0
    for i, m in enumerate(models):
        ref, lim = _mujoco_run(m, m.qpos0, ctrl[i])
        perturbed, _ = _mujoco_run(m, m.qpos0 + 1e-6 * rng.standard_normal(m.nq), ctrl[i])
        refs.append(ref)
        sensitivity.append(np.abs(perturbed - ref).max())
        limited += lim
    return refs, np.array(sensitivity), limited


# --------------------------------------------------------------------------- batched model


def test_batch_model_holds_one_entry_per_world_where_designs_differ():
    space = get_space("viperx")
    designs = _same_structure(space, 3, seed=11)
    models = [space.model(d) for d in designs]
    m = batch_model(models, device="cpu")
    assert m.body_pos.shape == (3, models[0].nbody) and m.body_mass.shape == (3, models[0].nbody)
    for name in (
        "body_pos",
        "body_quat",
        "body_mass",
        "body_inertia",
        "geom_size",
        "dof_invweight0",
        "actuator_gainprm",
    ):
        value = getattr(m, name).numpy()
        for i, mm in enumerate(models):
            # One entry per world where the designs differ, one shared entry where they agree.
            entry = value[i % value.shape[0]]
            np.testing.assert_allclose(
                entry, getattr(mm, name).reshape(entry.shape), rtol=1e-5, atol=1e-7, err_msg=name
            )
    assert m.actuator_gainprm.shape[0] == 1  # the gains of these designs are equal
    assert m.opt.timestep.shape == (1,) and m.opt.gravity.shape == (1,)
    other = next(d for d in space.sample(40, seed=12) if structure_key(space.model(d)) != structure_key(models[0]))
    with pytest.raises(ValueError, match="model 1 .* different structure"):
        batch_model([models[0], space.model(other)], device="cpu")


def test_mat2quat_follows_mujoco_sign_convention():
    rng = np.random.default_rng(0)
    quats = rng.standard_normal((300, 4))
    # Rotations near pi about each axis reach every branch of mju_mat2Quat.
    for axis in range(3):
        q = np.zeros(4)
        q[1 + axis] = 1.0
        quats = np.vstack([quats, q + 0.01 * rng.standard_normal((20, 4))])
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    mats = np.zeros((len(quats), 9))
    ref = np.zeros((len(quats), 4))
    for i, q in enumerate(quats):
        mujoco.mju_quat2Mat(mats[i], q)
        mujoco.mju_mat2Quat(ref[i], mats[i])

    @wp.kernel(module="unique")
    def _convert(m: wp.array(dtype=wp.mat33), q: wp.array(dtype=wp.vec4)):
        i = wp.tid()
        q[i] = mat2quat(m[i])

    out = wp.zeros(len(quats), dtype=wp.vec4, device="cpu")
    wp.launch(
        _convert,
        dim=len(quats),
        inputs=[wp.array(mats.reshape(-1, 3, 3).astype(np.float32), dtype=wp.mat33, device="cpu")],
        outputs=[out],
        device="cpu",
    )
    np.testing.assert_allclose(out.numpy(), ref, atol=2e-6)


# --------------------------------------------------------------------------- open loop


@pytest.fixture(scope="module")
def open_loop_designs():
    space = get_space("viperx")
    designs = _same_structure(space, 4, seed=21)
    return designs, [space.model(d) for d in designs]


def test_mjwarp_open_loop_matches_mujoco_through_joint_limits(open_loop_designs):
    _, models = open_loop_designs
    rng = np.random.default_rng(1)
    ctrl = _ctrl_sequence(models, HORIZON_STEPS, rng, fraction=0.8)
    refs, sensitivity, limited = _reference(models, ctrl, rng)
    qpos, _ = mjwarp_simulate(models, ctrl, device="cpu")
    errors = np.array([np.abs(qpos[i, :, : m.nq] - refs[i]).max() for i, m in enumerate(models)])
    assert limited > 0  # joint-limit constraints were exercised
    assert np.all(errors <= np.maximum(HORIZON_TOL, 10.0 * sensitivity)), (errors, sensitivity)


def test_newton_open_loop_matches_mujoco_inside_joint_ranges(open_loop_designs):
    designs, models = open_loop_designs
    rng = np.random.default_rng(2)
    ctrl = _ctrl_sequence(models, HORIZON_STEPS, rng, fraction=0.3, ends=0.0)
    refs, sensitivity, limited = _reference(models, ctrl, rng)
    assert limited == 0  # the commands keep MuJoCo away from its limits (see the module docstring)
    traj = newton_simulate(designs, ctrl, device="cpu")
    errors = np.array([np.abs(traj.qpos[i, :, : m.nq] - refs[i]).max() for i, m in enumerate(models)])
    assert np.all(errors <= np.maximum(HORIZON_TOL, 10.0 * sensitivity)), (errors, sensitivity)


# --------------------------------------------------------------------------- closed loop


@pytest.fixture(scope="module")
def closed_loop_case():
    space = get_space("viperx")
    designs = _same_structure(space, 4, seed=3)
    toss = for_space([get_motion("toss")], "viperx")[0]
    motion = Motion("toss_head", toss.pos[:CLOSED_LOOP_STEPS], toss.quat[:CLOSED_LOOP_STEPS])
    return designs, motion, oracle_rollout(designs, [motion])


def _mean_error(ep):
    # A world terminated at its first step (a random design that cannot reach the placed
    # motion) has no steps to average; both backends must agree that it terminated.
    err = (ep.ee_pos - ep.target_pos).norm(dim=-1).sum(-1)  # (W, T) [m]
    return torch.stack(
        [err[w][ep.alive[w]].mean() if ep.alive[w].any() else err.new_zeros(()) for w in range(ep.worlds)]
    )


def _check_episode_against_oracle(ep, ref, tol):
    assert ep.qpos.shape == ref.qpos.shape and ep.ee_quat.shape == ref.ee_quat.shape
    assert torch.equal(ep.alive.cpu(), ref.alive)
    assert torch.equal(ep.fallen.cpu(), ref.fallen)
    gap = (_mean_error(ep).cpu() - _mean_error(ref)).abs()
    assert torch.all(gap <= tol), gap
    torch.testing.assert_close(ep.target_pos.cpu(), ref.target_pos)
    # Orientations follow the oracle's quaternion sign (MuJoCo's mju_mat2Quat).
    assert float((ep.ee_quat.cpu() * ref.ee_quat).sum(-1).min()) > 0.99


def test_mjwarp_closed_loop_matches_the_oracle(closed_loop_case):
    designs, motion, ref = closed_loop_case
    ep = rollout(designs, [motion], backend="mjwarp", device="cpu")
    _check_episode_against_oracle(ep, ref, MJWARP_POS_TOL)
    # Same physics and controller: the joint trajectories agree to float32 round-off too.
    assert float((ep.qpos - ref.qpos).abs().max()) < 1e-3


def test_newton_closed_loop_matches_the_oracle(closed_loop_case):
    designs, motion, ref = closed_loop_case
    ep = rollout(designs, [motion], backend="newton", device="cpu")
    _check_episode_against_oracle(ep, ref, NEWTON_POS_TOL)


def test_newton_rejects_what_it_cannot_simulate():
    quadruped = get_space("quadruped")
    motion = for_space([get_motion("toss")], "quadruped")[0]
    from tt.sim.newton_backend import newton_rollout

    with pytest.raises(ValueError, match="contacts"):
        newton_rollout([quadruped.nominal()], [motion], device="cpu")
    viperx = get_space("viperx")
    with pytest.raises(TypeError, match="needs tt Designs"):
        newton_rollout([viperx.model(viperx.nominal())], [motion], device="cpu")


# --------------------------------------------------------------------------- slow


@pytest.mark.slow
def test_mjwarp_runs_the_quadruped_like_the_oracle():
    space = get_space("quadruped")
    designs = [space.nominal(), *space.sample(1, seed=3)]
    reach = for_space([get_motion("reach_place")], "quadruped")[0]
    motion = Motion("reach_head", reach.pos[:50], reach.quat[:50])
    ref = oracle_rollout(designs, [motion])
    ep = rollout(designs, [motion], backend="mjwarp", device="cpu")
    _check_episode_against_oracle(ep, ref, MJWARP_POS_TOL)


@pytest.mark.slow
def test_newton_gradients_match_finite_differences():
    space = get_space("viperx")
    design = space.nominal()
    m = space.model(design)
    steps = 30
    # Small targets around the home posture keep every servo below its force limit, where
    # the commanded force (and so the trajectory) is differentiable in the command.
    ctrl = np.tile(0.02 * np.array([1.0, 1.0, -1.0, 1.0, 1.0, 1.0])[: m.nu], (1, steps, 1))

    @wp.kernel(module="unique")
    def _sum(x: wp.array(dtype=float), out: wp.array(dtype=float)):
        wp.atomic_add(out, 0, x[wp.tid()])

    tape = wp.Tape()
    with tape:
        traj = newton_simulate([design], ctrl, device="cpu", requires_grad=True)
        loss = wp.zeros(1, dtype=float, requires_grad=True, device="cpu")
        final = traj.states[-1].joint_q
        wp.launch(_sum, dim=final.shape[0], inputs=[final], outputs=[loss], device="cpu")
    tape.backward(loss)
    grad = traj.ctrl[0][1].grad.numpy()[0]  # (steps, nu)
    eps = 1e-3
    for k, u in ((steps - 10, 1), (steps - 5, 2), (steps - 3, 4)):
        values = []
        for sign in (1.0, -1.0):
            c = ctrl.copy()
            c[0, k, u] += sign * eps
            values.append(newton_simulate([design], c, device="cpu").qpos[0, -1].sum())
        fd = (values[0] - values[1]) / (2 * eps)
        assert math.isclose(grad[k, u], fd, rel_tol=0.05, abs_tol=1e-4), (k, u, grad[k, u], fd)


@pytest.mark.slow
def test_warp_and_mjwarp_match_mujoco_on_200_random_arm_designs():
    """The issue's dynamics check: 2 s open loop on 200 random ViperX, ALOHA and bimanual
    designs, tt's Warp kernels and MuJoCo-Warp each against MuJoCo C."""
    from tt.kernels.dynamics import simulate
    from tt.kernels.model import build_tree_model, topology_key

    rng = np.random.default_rng(5)
    errors_warp, errors_mjwarp, sens = [], [], []
    warp_runs, mjwarp_runs = [], []
    for name, count in (("viperx", 120), ("aloha", 40), ("bimanual", 40)):
        space = get_space(name)
        models = [space.model(d) for d in space.sample(count, seed=17)]
        ctrl = _ctrl_sequence(models, HORIZON_STEPS, rng, fraction=0.8)
        refs, sensitivity, _ = _reference(models, ctrl, rng)
        qpos_mjwarp, _ = mjwarp_simulate(models, ctrl, device="cpu")
        groups: dict[tuple, list[int]] = {}
        for i, m in enumerate(models):
            groups.setdefault(topology_key(m, space.ee_sites()), []).append(i)
        qpos_warp = np.zeros_like(qpos_mjwarp)
        for members in groups.values():
            gm = [models[i] for i in members]
            tree = build_tree_model(gm, space.ee_sites(), device="cpu")
            q0 = np.stack([m.qpos0 for m in gm]).astype(np.float32)
            c = ctrl[members][:, :, : gm[0].nu].astype(np.float32)
            out = simulate(tree, wp.array(q0, dtype=float), wp.zeros(q0.shape, dtype=float), wp.array(c, dtype=float))
            qpos_warp[members, :, : gm[0].nq] = out.qpos.numpy()
        warp_runs.extend(qpos_warp[i, :, : m.nq] for i, m in enumerate(models))
        mjwarp_runs.extend(qpos_mjwarp[i, :, : m.nq] for i, m in enumerate(models))
        for i, m in enumerate(models):
            errors_warp.append(np.abs(qpos_warp[i, :, : m.nq] - refs[i]).max())
            errors_mjwarp.append(np.abs(qpos_mjwarp[i, :, : m.nq] - refs[i]).max())
        sens.extend(sensitivity)
    errors_warp, errors_mjwarp, sens = map(np.array, (errors_warp, errors_mjwarp, sens))
    assert len(sens) == 200
    bound = np.maximum(HORIZON_TOL, 10.0 * sens)
    assert np.all(errors_mjwarp <= bound), (errors_mjwarp.max(), sens[errors_mjwarp.argmax()])
    assert np.all(errors_warp <= bound), (errors_warp.max(), sens[errors_warp.argmax()])
    warp_vs_mjwarp = np.array([np.abs(a - b).max() for a, b in zip(warp_runs, mjwarp_runs)])
    assert np.all(warp_vs_mjwarp <= 2.0 * bound), warp_vs_mjwarp.max()
    assert np.median(errors_mjwarp) < 1e-4 and np.median(errors_warp) < 1e-4
