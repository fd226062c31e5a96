"""Joint-space dynamics of the tree kernels against MuJoCo C's mj_step (Euler).

Two checks:

* one step from random states (some past their joint limits, so the soft limit
  constraints are active): the velocity update, i.e. h * qacc, must agree to float32
  round-off, relative 1e-4 of the largest acceleration;
* 2 s of open-loop control (1000 steps) on 200 random ViperX designs. Here float32 round-off
  (1e-7 relative per step) is amplified by the system itself: a position servo pushed
  into a joint limit, or a joint whose target flips, turns a 1e-7 difference into a
  visible one. The tolerance is defended by measuring that amplification on MuJoCo alone:
  each design also runs in MuJoCo from a start perturbed by 1e-6 rad, and a design's
  warp-vs-MuJoCo error may not exceed 1e-3 rad or 10x that self-sensitivity, whichever is
  larger; the median over designs must stay below 1e-4 rad.
"""

import mujoco
import numpy as np
import pytest
import warp as wp
from ctrl_targets import some_at_the_ends

from tt.kernels.dynamics import simulate
from tt.kernels.model import build_tree_model, topology_key, topology_of
from tt.sim.designs import get_space

STEP_REL_TOL = 1e-4
HORIZON_STEPS = 1000  # 2 s at 0.002 s
HORIZON_TOL = 1e-3  # [rad]
MEDIAN_TOL = 1e-4  # [rad]


def _groups(space, designs):
    groups: dict[tuple, list] = {}
    for design in designs:
        m = space.model(design)
        groups.setdefault(topology_key(m, space.ee_sites()), []).append(m)
    return list(groups.values())


def _ctrl_sequence(models, steps, rng, fraction=0.8):
    """Piecewise-constant targets (new every 0.1 s) within `fraction` of each ctrl range."""
    nu = models[0].nu
    ctrl = np.zeros((len(models), steps, nu), np.float32)
    for i, m in enumerate(models):
        lo, hi = m.actuator_ctrlrange.T
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * fraction
        knots = rng.uniform(mid - half, mid + half, size=(steps // 50 + 1, nu))
        ctrl[i] = some_at_the_ends(np.repeat(knots, 50, axis=0)[:steps], lo, hi, rng)
    return ctrl


def _mujoco_run(m, qpos0, ctrl):
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    out = [d.qpos.copy()]
    limited = 0
    for c in ctrl:
        d.ctrl[:] = c
        mujoco.mj_step(m, d)
        out.append(d.qpos.copy())
        limited += d.nefc > 0
    return np.array(out), limited


def test_one_step_matches_mujoco_including_active_limits(device):
    space = get_space("viperx")
    rng = np.random.default_rng(0)
    active_rows = 0
    for models in _groups(space, space.sample(60, seed=2)):
        W, nv = len(models), models[0].nv
        q = np.zeros((W, nv))
        qd = rng.normal(0.0, 1.0, (W, nv))
        ctrl = np.zeros((W, 1, nv))
        qd_next = np.zeros((W, nv))
        nefc = np.zeros(W, dtype=int)
        for i, m in enumerate(models):
            lo, hi = m.jnt_range.T
            q[i] = rng.uniform(lo - 0.05, hi + 0.05)  # some joints start past a limit
            ctrl[i, 0] = rng.uniform(lo, hi)
            d = mujoco.MjData(m)
            d.qpos[:], d.qvel[:], d.ctrl[:] = q[i], qd[i], ctrl[i, 0]
            mujoco.mj_step(m, d)
            qd_next[i] = d.qvel
            nefc[i] = d.nefc
        tree = build_tree_model(models, space.ee_sites(), device=device)
        f32 = lambda x: wp.array(np.asarray(x, np.float32), dtype=float, device=device)  # noqa: E731
        out = simulate(tree, f32(q), f32(qd), f32(ctrl))
        h = models[0].opt.timestep
        acc_warp = (out.qvel.numpy()[:, 1] - qd.astype(np.float32)) / h
        acc_ref = (qd_next - qd) / h
        scale = np.abs(acc_ref).max(axis=1, keepdims=True)
        assert np.abs(acc_warp - acc_ref).max() <= STEP_REL_TOL * scale.max()
        assert np.all(np.abs(acc_warp - acc_ref) <= STEP_REL_TOL * scale)
        # The same limit rows are active (tt's arms have no other constraints).
        np.testing.assert_array_equal(out.limit_count.numpy()[:, 0], nefc)
        active_rows += int(nefc.sum())
    assert active_rows > 5  # the limit constraint path was exercised


def test_two_seconds_open_loop_on_200_viperx_designs(device):
    space = get_space("viperx")
    rng = np.random.default_rng(1)
    errors, sensitivity, limited_warp, limited_ref = [], [], 0, 0
    for models in _groups(space, space.sample(200, seed=5)):
        ctrl = _ctrl_sequence(models, HORIZON_STEPS, rng)
        qpos0 = np.stack([m.qpos0 for m in models]).astype(np.float32)
        tree = build_tree_model(models, space.ee_sites(), device=device)
        out = simulate(tree, *(wp.array(a, dtype=float, device=device) for a in (qpos0, np.zeros_like(qpos0), ctrl)))
        qpos_warp = out.qpos.numpy()
        limited_warp += int((out.limit_count.numpy() > 0).sum())
        for i, m in enumerate(models):
            ref, limited = _mujoco_run(m, qpos0[i], ctrl[i])
            perturbed, _ = _mujoco_run(m, qpos0[i] + 1e-6 * rng.standard_normal(m.nq), ctrl[i])
            limited_ref += limited
            errors.append(np.abs(qpos_warp[i] - ref).max())
            sensitivity.append(np.abs(perturbed - ref).max())
    errors, sensitivity = np.array(errors), np.array(sensitivity)
    assert len(errors) == 200
    assert np.median(errors) < MEDIAN_TOL
    assert np.all(errors <= np.maximum(HORIZON_TOL, 10.0 * sensitivity)), (errors.max(), sensitivity[errors.argmax()])
    # Limits are active in a few percent of the steps, and at the same steps in both.
    assert limited_ref > 0 and abs(limited_warp - limited_ref) <= 0.01 * limited_ref


@pytest.mark.slow
@pytest.mark.parametrize("name", ["aloha", "bimanual"])
def test_two_arm_open_loop_matches_mujoco(name, device):
    space = get_space(name)
    sites = space.ee_sites()
    nominal = topology_of(space.model(space.nominal()), sites)
    models = [m for m in (space.model(d) for d in space.sample(60, seed=4)) if topology_of(m, sites) == nominal][:8]
    rng = np.random.default_rng(2)
    ctrl = _ctrl_sequence(models, HORIZON_STEPS, rng)
    qpos0 = np.stack([m.qpos0 for m in models]).astype(np.float32)
    tree = build_tree_model(models, sites, device=device)
    out = simulate(tree, *(wp.array(a, dtype=float, device=device) for a in (qpos0, np.zeros_like(qpos0), ctrl)))
    for i, m in enumerate(models):
        ref, _ = _mujoco_run(m, qpos0[i], ctrl[i])
        perturbed, _ = _mujoco_run(m, qpos0[i] + 1e-6 * rng.standard_normal(m.nq), ctrl[i])
        error = np.abs(out.qpos.numpy()[i] - ref).max()
        assert error <= max(HORIZON_TOL, 10.0 * np.abs(perturbed - ref).max()), (i, error)
