"""The batched DiffIK step against the oracle's (`tt.sim.controller.ik_step`, mink in float64).

200 random states of random ViperX designs (all three topologies) with targets at the
current site pose (zero error: the small-angle series of the SE(3) Jacobians), near it
(a few cm / tenths of a radian) and far (tens of cm, the regime the look-ahead creates on
fast motions). The commands must agree to 1e-3 rad; float32 round-off in the normal
equations, amplified by their condition number (damping 1e-3), stays well below that.
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


def _run(space, cases, config):
    models = [c[0] for c in cases]
    tree = build_tree_model(models, space.ee_sites(), device="cpu")
    q = np.stack([c[1] for c in cases]).astype(np.float32)
    pos = np.stack([c[2] for c in cases])[:, None].astype(np.float32)
    quat = np.stack([c[3] for c in cases])[:, None].astype(np.float32)
    out = ik_step(
        tree, wp.array(q, dtype=float), wp.array(pos, dtype=wp.vec3), wp.array(quat, dtype=wp.vec4), config
    )
    return out.numpy(), np.stack([c[4] for c in cases])


def test_ik_step_matches_the_oracle_on_200_states():
    config = IKConfig()
    space, groups = _cases(config, seed=0)
    assert len(groups) == 3
    clipped = 0
    for cases in groups.values():
        q_cmd, ref = _run(space, cases, config)
        np.testing.assert_allclose(q_cmd, ref, atol=TOL, rtol=0)
        lo, hi = np.stack([c[0].jnt_range for c in cases]).transpose(2, 0, 1)
        clipped += int(np.sum((ref <= lo + 1e-9) | (ref >= hi - 1e-9)))
    assert clipped > 0  # some far targets drive joints into the clip


def test_ik_step_with_levenberg_marquardt_and_other_weights():
    # Every IKConfig weight reaches the kernel: lm_damping adds mu = lm |C e|^2 to the diagonal.
    config = IKConfig(position_cost=2.0, orientation_cost=0.3, posture_cost=0.05, lm_damping=0.1, damping=1e-2)
    space, groups = _cases(config, seed=1)
    for cases in groups.values():
        q_cmd, ref = _run(space, cases, config)
        np.testing.assert_allclose(q_cmd, ref, atol=TOL, rtol=0)
