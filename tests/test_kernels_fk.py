"""Batched forward kinematics and site Jacobians against MuJoCo C (mj_kinematics, mj_jacSite).

Outputs are poisoned with inf before the kernel runs, so an entry the kernel forgets to
write fails the comparison. Tolerances are float32 round-off on ~1 m chains: 1e-5 m for
positions and Jacobian entries, 1e-4 rad for orientations.
"""

import mujoco
import numpy as np
import pytest
import warp as wp

from tt.kernels.fk import forward_kinematics, kinematics_outputs
from tt.kernels.model import ENTITY_FIELDS, TREE_FIELDS, build_tree_model, topology_key, topology_of, tree_arrays
from tt.sim.designs import get_space

POS_TOL = 1e-5  # [m]
ROT_TOL = 1e-4  # [rad]


def _angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle [rad] between (w, x, y, z) quaternions, (...,): 2 atan2(|v|, |w|) of
    the relative quaternion, exact near zero (arccos of a dot product is not)."""
    q1 = np.asarray(q1, dtype=np.float64)
    q2 = np.asarray(q2, dtype=np.float64)
    w = np.sum(q1 * q2, axis=-1)
    v = q1[..., :1] * q2[..., 1:] - q2[..., :1] * q1[..., 1:] - np.cross(q1[..., 1:], q2[..., 1:])
    return 2.0 * np.arctan2(np.linalg.norm(v, axis=-1), np.abs(w))


def _check_group(models, sites, rng, device):
    tree = build_tree_model(models, sites, device=device)
    q = np.stack([rng.uniform(*np.clip(m.jnt_range, -np.pi, np.pi).T) for m in models]).astype(np.float32)
    out = kinematics_outputs(tree, len(models), fill=np.inf)
    forward_kinematics(tree, wp.array(q, dtype=float, device=device), out)
    xpos, xquat = out.xpos.numpy(), out.xquat.numpy()
    site_pos, site_quat, site_jac = out.site_pos.numpy(), out.site_quat.numpy(), out.site_jac.numpy()
    assert np.all(np.isfinite(xpos)) and np.all(np.isfinite(site_jac))
    for i, m in enumerate(models):
        d = mujoco.MjData(m)
        d.qpos[:] = q[i]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        # tt's arms have one joint per body, so tree bodies are MuJoCo's bodies.
        np.testing.assert_allclose(xpos[i], d.xpos, atol=POS_TOL)
        assert _angle(xquat[i], d.xquat).max() < ROT_TOL
        for e, name in enumerate(sites):
            sid = m.site(name).id
            ref_quat = np.zeros(4)
            mujoco.mju_mat2Quat(ref_quat, d.site_xmat[sid])
            jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
            mujoco.mj_jacSite(m, d, jacp, jacr, sid)
            np.testing.assert_allclose(site_pos[i, e], d.site_xpos[sid], atol=POS_TOL)
            assert _angle(site_quat[i, e], ref_quat) < ROT_TOL
            np.testing.assert_allclose(site_jac[i, e, :3], jacp, atol=POS_TOL)
            np.testing.assert_allclose(site_jac[i, e, 3:], jacr, atol=ROT_TOL)


def test_1000_random_viperx_designs_match_mujoco(device):
    space = get_space("viperx")
    rng = np.random.default_rng(0)
    groups: dict[tuple, list] = {}
    for design in space.sample(1000, seed=7):
        m = space.model(design)
        groups.setdefault(topology_key(m, space.ee_sites()), []).append(m)
    assert len(groups) == 3  # the 5-, 6- and 7-DoF arms
    for models in groups.values():
        _check_group(models, space.ee_sites(), rng, device)


@pytest.mark.parametrize("name", ["aloha", "bimanual"])
def test_two_arm_designs_match_mujoco(name, device):
    # One topology per space (the nominal one) keeps this to one compile per space.
    space = get_space(name)
    sites = space.ee_sites()
    nominal = topology_of(space.model(space.nominal()), sites)
    models = [m for m in (space.model(d) for d in space.sample(60, seed=3)) if topology_of(m, sites) == nominal]
    assert len(models) >= 5
    _check_group(models, sites, np.random.default_rng(1), device)


def test_multi_joint_body_is_split_into_a_chain(device):
    # A body with two hinges and a slide: MuJoCo applies them in order, each in the frame
    # left by the previous one; the tree model gives each its own body.
    xml = """
    <mujoco>
      <option integrator="Euler"><flag contact="disable"/></option>
      <worldbody>
        <body name="a" pos="0.1 0.2 0.3" quat="0.9 0.1 0.3 0.2">
          <joint type="hinge" axis="0 0 1" pos="0.05 0 0"/>
          <joint type="hinge" axis="1 0 0" pos="0 0.1 0"/>
          <joint type="slide" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
          <body name="b" pos="0.3 0 0">
            <joint type="hinge" axis="0 1 0"/>
            <geom type="sphere" size="0.05"/>
            <site name="ee_0" pos="0.1 0.02 0" quat="0.7 0.7 0 0"/>
          </body>
        </body>
      </worldbody>
    </mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    tree = build_tree_model([m], ("ee_0",), device=device)
    assert tree.topology.body_parent == (0, 0, 1, 2, 3)
    assert tree.topology.body_dof == (-1, 0, 1, 2, 3)
    q = np.array([[0.4, -0.7, 0.12, 1.1]], dtype=np.float32)
    out = forward_kinematics(tree, wp.array(q, dtype=float, device=device), kinematics_outputs(tree, 1, fill=np.inf))
    d = mujoco.MjData(m)
    d.qpos[:] = q[0]
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    np.testing.assert_allclose(out.xpos.numpy()[0, [3, 4]], d.xpos[1:], atol=POS_TOL)
    jacp, jacr = np.zeros((3, 4)), np.zeros((3, 4))
    mujoco.mj_jacSite(m, d, jacp, jacr, 0)
    np.testing.assert_allclose(out.site_pos.numpy()[0, 0], d.site_xpos[0], atol=POS_TOL)
    np.testing.assert_allclose(out.site_jac.numpy()[0, 0], np.vstack([jacp, jacr]), atol=POS_TOL)


def test_tree_arrays_struct_holds_every_field_and_with_fields_replaces_only_the_named_ones():
    space = get_space("viperx")
    models = [space.model(d) for d in (space.nominal(), space.nominal())]
    tree = build_tree_model(models, space.ee_sites(), device="cpu", requires_grad=True)
    # Every struct member is an array of the model's world count, gradients allocated on
    # the float fields (the tape differentiates through them).
    for name in TREE_FIELDS:
        a = getattr(tree.arrays, name)
        assert a.shape[0] == (1 if name == "limit_sweeps" else 2), name
        if name in ENTITY_FIELDS:
            assert a.requires_grad, name
    assert set(ENTITY_FIELDS) < set(TREE_FIELDS)
    assert {"gravity", "timestep", "limit_enabled", "limit_sweeps"} == set(TREE_FIELDS) - set(ENTITY_FIELDS)
    np.testing.assert_allclose(tree.arrays.body_mass.numpy()[0, 1:], models[0].body_mass[1:], rtol=1e-6)
    np.testing.assert_array_equal(tree.kinematics64.dof_ref.numpy()[0], models[0].qpos0)
    moved = tree.arrays.body_pos.numpy() + 0.01
    other = tree.with_fields(
        {"body_pos": wp.array(moved, dtype=wp.vec3)},
        {"dof_ref": wp.array(np.ones((2, models[0].nv)), dtype=wp.float64)},
    )
    np.testing.assert_array_equal(other.arrays.body_pos.numpy(), moved)
    np.testing.assert_array_equal(other.kinematics64.dof_ref.numpy(), 1.0)
    assert other.arrays.body_quat is tree.arrays.body_quat  # the rest is shared
    assert not np.array_equal(tree.arrays.body_pos.numpy(), moved)  # the original is unchanged
    np.testing.assert_array_equal(tree.kinematics64.dof_ref.numpy()[0], models[0].qpos0)
    q = np.zeros((2, models[0].nv), np.float32)
    base = forward_kinematics(tree, wp.array(q, dtype=float)).site_pos.numpy()
    shifted = forward_kinematics(other, wp.array(q, dtype=float)).site_pos.numpy()
    assert np.abs(shifted - base).max() > 1e-3  # the kernels read the new struct
    with pytest.raises(ValueError, match="missing"):
        tree_arrays(body_pos=tree.arrays.body_pos)
