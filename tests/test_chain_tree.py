"""Designs compiled straight to tree fields (`DesignSpace.trees`, `tt.sim.designs.chain_tree`)
against MuJoCo's compile of the same designs' MJCF, field by field, and in a rollout."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tt.kernels.model import FIELD_NAMES, dof_invweight0, topology_key, tree_fields
from tt.kernels.rotations import mat_to_quat, quat_to_mat
from tt.sim.designs import Design, DesignError, get_space
from tt.sim.designs.chain_tree import principal_frames
from tt.sim.rewards import robot_mass, robot_size


def _tensor(fields):
    """Inertia tensors in the body frame, from the principal moments and frames, (n, NB, 3, 3)."""
    rot = quat_to_mat(fields.values["body_iquat"])
    return np.einsum("...ij,...j,...kj->...ik", rot, fields.values["body_inertia"], rot)


@pytest.mark.parametrize("space", ["viperx", "viperx-nominal"])
def test_trees_match_mujoco_compile(space):
    """Every field of 120 random designs (all mounts and DoF variants) equals what
    `tree_fields` reads from MuJoCo's compile of their MJCF, to float64 round-off; inertias
    as tensors (a principal frame of a symmetric body is not unique)."""
    sp = get_space(space)
    designs = sp.sample(120, seed=11)
    trees = sp.trees(designs)
    assert sum(len(m) for m, _ in trees.groups) == len(designs)
    for members, fields in trees.groups:
        models = [sp.model(designs[i]) for i in members]
        ref = tree_fields(models, sp.ee_sites())
        assert fields.topology == ref.topology
        assert len({topology_key(m, sp.ee_sites()) for m in models}) == 1
        for name in FIELD_NAMES:
            if name in ("body_iquat", "body_inertia"):
                continue
            np.testing.assert_allclose(fields.values[name], ref.values[name], rtol=1e-12, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(_tensor(fields), _tensor(ref), rtol=1e-10, atol=1e-14)
        size = robot_size(models, dtype=torch.float64).numpy()
        mass = robot_mass(models, dtype=torch.float64).numpy()
        np.testing.assert_allclose(trees.size[members], size, rtol=1e-12)
        np.testing.assert_allclose(trees.mass[members], mass, rtol=1e-12)


@pytest.mark.parametrize("space", ["viperx", "aloha", "bimanual"])
def test_dof_invweight0_matches_mujoco(space):
    """`dof_invweight0` from the fields equals MuJoCo's set-constant pass, on every arm space."""
    sp = get_space(space)
    for d in sp.sample(6, seed=2):
        fields = tree_fields([sp.model(d)], sp.ee_sites())
        np.testing.assert_allclose(dof_invweight0(fields), fields.values["dof_invweight0"], rtol=1e-10)


def test_principal_frames_rebuild_tensor():
    """Random symmetric positive tensors: moments and frames rebuild them; frames are proper."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3, 3))
    tensor = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3)
    moments, quat = principal_frames(tensor.copy())
    rot = quat_to_mat(quat)
    np.testing.assert_allclose(np.einsum("nij,nj,nkj->nik", rot, moments, rot), tensor, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    # Rotations near each of Shepperd's branches (w, x, y, z largest) round-trip.
    for q in np.eye(4) + 0.01:
        q = q / np.linalg.norm(q)
        back = mat_to_quat(quat_to_mat(q[None]))[0]
        np.testing.assert_allclose(back, q * np.sign(q[0]), atol=1e-12)


def test_trees_rollout_matches_mujoco_built():
    """The warp rollout of designs given as tree fields equals the one of the same designs'
    MuJoCo models (the fields agree to round-off; float32 kernels may differ in the last
    bits, so the check is a tolerance on the end-effector trajectory)."""
    from tt.sim.motions import get_motion
    from tt.sim.rollout import rollout

    sp = get_space("viperx")
    designs = sp.sample(6, seed=5)
    motion = get_motion("toss")
    short = type(motion)(motion.name, motion.pos[:30], motion.quat[:30], motion.dt)
    a = rollout(sp.trees(designs), [short], device="cpu")
    b = rollout([sp.model(d) for d in designs], [short], device="cpu")
    assert a.qpos.shape == b.qpos.shape
    assert float((a.ee_pos - b.ee_pos).abs().max()) < 1e-4
    assert torch.equal(a.alive, b.alive)


def test_trees_reject_invalid_designs():
    """An out-of-range or malformed design raises the same DesignError as `validate`."""
    sp = get_space("viperx")
    good = sp.sample(3, seed=0)
    bad = Design("viperx", good[1].discrete, (9.0,) + tuple(good[1].continuous[1:]))
    with pytest.raises(DesignError, match="outside"):
        sp.trees([good[0], bad])
    flag = Design("viperx", (True,) + tuple(good[0].discrete[1:]), good[0].continuous)
    with pytest.raises(DesignError, match="discrete"):
        sp.trees([good[0], flag])
    assert get_space("aloha").trees(get_space("aloha").sample(2, seed=0)) is None
