"""The batched DiffIK step against the oracle's (`tt.sim.controller.ik_step`, mink in float64).

200 random states of random ViperX designs (all three topologies) with targets at the
current site pose (zero error: the small-angle series of the SE(3) Jacobians), near it
(a few cm / tenths of a radian) and far (tens of cm, the regime the look-ahead creates on
fast motions). The commands must agree to 1e-3 rad; float32 round-off in the normal
equations, amplified by their condition number (bounded by the damping), stays well below that.
A last set puts targets off the site in position only, exactly on its orientation and just
past it, the two sides of mink's switch to the identity Jacobian at zero rotation error.
"""

import mujoco
import numpy as np
import warp as wp

from tt.kernels.ik import ik_step
from tt.kernels.model import build_tree_model, topology_key
from tt.sim.controller import IKConfig
from tt.sim.controller import ik_step as oracle_ik_step
from tt.sim.designs import get_space

TOL = 1e-3  # [rad]
TOL_SWITCH = 2e-4  # [rad]: float32 arithmetic on float32 inputs, up to 4e-5 seen (see its test)


def _f32(x):
    """x rounded to float32, as float64 (so the oracle sees the kernel's inputs)."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def _random_quat(rng, angle):
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def _site_pose(m, q):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, d.site_xmat[0])
    return d.site_xpos[0].copy(), quat


def _cases(config: IKConfig, seed: int):
    space = get_space("viperx")
    rng = np.random.default_rng(seed)
    groups: dict[tuple, list] = {}
    for n, design in enumerate(space.sample(200, seed=seed)):
        m = space.model(design)
        q = rng.uniform(*m.jnt_range.T) * 0.8
        pos, quat = _site_pose(m, q)
        kind = n % 3  # 0: at the target, 1: near, 2: far
        if kind == 1:
            pos = pos + rng.normal(0.0, 0.03, 3)
            mujoco.mju_mulQuat(quat, quat.copy(), _random_quat(rng, rng.uniform(0.0, 0.4)))
        elif kind == 2:
            pos = pos + rng.normal(0.0, 0.2, 3)
            mujoco.mju_mulQuat(quat, quat.copy(), _random_quat(rng, rng.uniform(0.5, 2.5)))
        ref = oracle_ik_step(m, q, pos[None], quat[None], config)
        groups.setdefault(topology_key(m, space.ee_sites()), []).append((m, q, pos, quat, ref))
    return space, groups


def _run(space, cases, config, device):
    models = [c[0] for c in cases]
    tree = build_tree_model(models, space.ee_sites(), device=device)
    q = np.stack([c[1] for c in cases]).astype(np.float32)
    pos = np.stack([c[2] for c in cases])[:, None].astype(np.float32)
    quat = np.stack([c[3] for c in cases])[:, None].astype(np.float32)
    out = ik_step(
        tree,
        *(wp.array(a, dtype=t, device=device) for a, t in ((q, float), (pos, wp.vec3), (quat, wp.vec4))),
        config.ik_weights(),
    )
    return out.numpy(), np.stack([c[4] for c in cases])


def test_ik_step_matches_the_oracle_on_200_states(device):
    config = IKConfig()
    space, groups = _cases(config, seed=0)
    assert len(groups) == 3
    clipped = 0
    for cases in groups.values():
        q_cmd, ref = _run(space, cases, config, device)
        np.testing.assert_allclose(q_cmd, ref, atol=TOL, rtol=0)
        lo, hi = np.stack([c[0].jnt_range for c in cases]).transpose(2, 0, 1)
        clipped += int(np.sum((ref <= lo + 1e-9) | (ref >= hi - 1e-9)))
    assert clipped > 0  # some far targets drive joints into the clip


def test_ik_step_with_levenberg_marquardt_and_other_weights(device):
    # Every IKConfig weight reaches the kernel: lm_damping adds mu = lm |C e|^2 to the diagonal.
    config = IKConfig(position_cost=2.0, orientation_cost=0.3, posture_cost=0.05, lm_damping=0.1, damping=1e-2)
    space, groups = _cases(config, seed=1)
    for cases in groups.values():
        q_cmd, ref = _run(space, cases, config, device)
        np.testing.assert_allclose(q_cmd, ref, atol=TOL, rtol=0)


def test_ik_step_follows_minks_jacobian_switch_at_zero_rotation_error(device):
    """mink's SE(3) jlog is the identity below `MINK_JLOG_EPS` [rad^2] of rotation error.
    Targets ~10 cm off the site with its orientation exactly (below the switch) and
    turned by 1.5e-5 rad (2.25e-10 rad^2, above it): the oracle's steps on the two sides
    differ by about |v|/2 on rotational joints, and the kernel follows both. Inputs are
    rounded to float32 for both sides (the kernel's float32 rotation error, ~1e-7 rad,
    stays far from the switch on either side), so what separates them is the kernel's
    float32 arithmetic: held to TOL_SWITCH."""
    space = get_space("viperx")
    config = IKConfig()
    rng = np.random.default_rng(3)
    groups: dict[tuple, list] = {}
    jump = []
    for design in space.sample(30, seed=3):
        m = space.model(design)
        q = _f32(rng.uniform(*m.jnt_range.T) * 0.8)
        pos, quat = _site_pose(m, q)
        pos = _f32(pos + rng.normal(0.0, 0.1, 3))
        turned = quat.copy()
        mujoco.mju_mulQuat(turned, quat, _random_quat(rng, 1.5e-5))
        on, off = (oracle_ik_step(m, q, pos[None], _f32(x)[None], config) for x in (quat, turned))
        jump.append(np.abs(on - off).max())
        cases = groups.setdefault(topology_key(m, space.ee_sites()), [])
        cases += [(m, q, pos, _f32(quat), on), (m, q, pos, _f32(turned), off)]
    assert np.median(jump) > 5 * TOL  # the oracle's discontinuity
    for cases in groups.values():
        q_cmd, ref = _run(space, cases, config, device)
        np.testing.assert_allclose(q_cmd, ref, atol=TOL_SWITCH, rtol=0)
