"""Two-arm design spaces: ALOHA (fixed station) and the mobile bimanual robot."""

import importlib
import itertools
import json
import math
import re

import mujoco
import numpy as np
import pytest

from tt.sim.designs import Design, DesignError, get_space, load_designs, save_designs
from tt.sim.designs.bimanual import WORKSPACE_CENTER
from tt.sim.designs.mjcf import LINK_DENSITY

SPACES = ("aloha", "bimanual")
M = np.diag([1.0, -1.0, 1.0])  # reflection through the XZ plane

#: The two-arm target region the motions are written for (two arms standing at
#: y = +-0.3 m on a table at z = 0): per arm x 0.15..0.5, |y| 0.15..0.3, z 0.05..0.5.
REGION_CENTER = np.array([0.33, 0.0, 0.25])
REGION_GRID = list(itertools.product((0.15, 0.33, 0.5), (0.15, 0.3), (0.05, 0.25, 0.5)))


@pytest.fixture(scope="module", params=SPACES)
def space(request):
    return get_space(request.param)


def _ik(model, targets, sites, iters=300):
    """Damped least squares on positions (reference solver for reachability), limits clipped.

    Returns the remaining position error per site [m].
    """
    data = mujoco.MjData(model)
    q = model.qpos0.copy()
    limited = model.jnt_limited.astype(bool)
    lo, hi = model.jnt_range[limited].T
    for _ in range(iters):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        jac, err = [], []
        for site, target in zip(sites, targets):
            jacp = np.zeros((3, model.nv))
            mujoco.mj_jacSite(model, data, jacp, None, model.site(site).id)
            jac.append(jacp)
            err.append(target - data.site(site).xpos)
        jac, err = np.vstack(jac), np.concatenate(err)
        dq = jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(len(err)), err)
        q = q + np.clip(dq, -0.2, 0.2)
        q[limited] = np.clip(q[limited], lo, hi)
    return np.linalg.norm(err.reshape(-1, 3), axis=1)


def test_200_designs_load_and_step_without_nan(space):
    rng = np.random.default_rng(0)
    kinds = set()
    primitives = {
        int(t)
        for t in (
            mujoco.mjtGeom.mjGEOM_CAPSULE,
            mujoco.mjtGeom.mjGEOM_CYLINDER,
            mujoco.mjtGeom.mjGEOM_BOX,
            mujoco.mjtGeom.mjGEOM_SPHERE,
        )
    }
    for d in space.sample(200, seed=1):
        m = space.model(d)
        kinds.add(d.discrete)
        assert m.opt.timestep == 0.002 and m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
        assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
        assert {int(t) for t in m.geom_type} <= primitives
        # One position actuator per joint, in joint order.
        assert m.nu == m.njnt and np.array_equal(m.actuator_trnid[:, 0], np.arange(m.njnt))
        assert m.site("ee_0") and m.site("ee_1")
        data = mujoco.MjData(m)
        lo, hi = m.actuator_ctrlrange.T
        for k in range(int(round(1.0 / m.opt.timestep))):
            if k % 50 == 0:  # a new random target every 0.1 s
                data.ctrl[:] = rng.uniform(lo, hi)
            mujoco.mj_step(m, data)
        assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel)), space.to_dict(d)
    # Every discrete combination was drawn.
    n_combos = math.prod(len(p.options) for p in space.discrete_params(space.nominal().discrete))
    assert len(kinds) == n_combos


def test_masses_follow_geometry(space):
    for d in [space.nominal(), *space.sample(20, seed=2)]:
        xml = space.to_mjcf(d)
        assert not re.search(r'\b(mass|inertia|diaginertia|fullinertia)="', xml)
        m = mujoco.MjModel.from_xml_string(xml)
        assert np.all(m.body_mass[1:] > 0) and np.all(m.body_inertia[1:] > 0)
    # The upper-arm body by hand: a motor cylinder (radius r, half-length r) plus a capsule.
    if space.name == "aloha":
        body, r, length = "left_shoulder", 0.03, 0.05 + 0.25
    else:
        body, r, length = "left_shoulder_yaw", 0.025, 0.10 + 0.12
    cyl = math.pi * r**2 * 2 * r
    capsule = math.pi * r**2 * length + 4 / 3 * math.pi * r**3
    m = space.model(space.nominal())
    np.testing.assert_allclose(m.body(body).mass, LINK_DENSITY * (cyl + capsule), rtol=1e-9)


def test_json_round_trip_is_exact(space, tmp_path):
    designs = space.sample(50, seed=3)
    save_designs(designs, tmp_path / "designs.json")
    assert load_designs(tmp_path / "designs.json") == designs
    for d in designs:
        assert space.from_dict(json.loads(json.dumps(space.to_dict(d)))) == d
        assert space.to_mjcf(space.from_dict(space.to_dict(d))) == space.to_mjcf(d)
    assert space.sample(10, seed=5) == space.sample(10, seed=5)
    assert space.sample(10, seed=5) != space.sample(10, seed=6)


def _with(space, discrete, **values):
    """A design of `space` with the nominal continuous values replaced by `values`."""
    nominal = space.nominal()
    params = space.continuous_params(discrete)
    base = dict(zip((p.name for p in space.continuous_params(nominal.discrete)), nominal.continuous))
    base.update(values)
    return Design(space.name, discrete, tuple(base.get(p.name, (p.low + p.high) / 2) for p in params))


def test_aloha_invalid_designs_name_the_field():
    space = get_space("aloha")
    with pytest.raises(DesignError, match="interarm_distance"):
        space.validate(_with(space, (0,), interarm_distance=0.7))
    with pytest.raises(DesignError, match="mount_x"):
        space.validate(_with(space, (0,), mount_x=0.1))
    with pytest.raises(DesignError, match="mount_z"):
        space.to_mjcf(_with(space, (2,), mount_z=float("nan")))
    with pytest.raises(DesignError, match="forearm_extension"):
        space.validate(_with(space, (1,), forearm_extension=0.3))
    with pytest.raises(DesignError, match="mount"):
        space.validate(Design("aloha", (3,), space.nominal().continuous))
    with pytest.raises(DesignError, match="expects"):
        space.validate(Design("aloha", (0,), space.nominal().continuous[:-1]))
    good = space.to_dict(space.nominal())
    bad = json.loads(json.dumps(good))
    bad["discrete"]["mount"] = "ceiling"
    with pytest.raises(DesignError, match="'mount'.*ceiling"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    bad["continuous"]["mount_z"] = 0.7  # upright arms stand on the table: no height
    with pytest.raises(DesignError, match="mount_z"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    del bad["continuous"]["arm_extension"]
    with pytest.raises(DesignError, match="arm_extension"):
        space.from_dict(bad)


def test_bimanual_invalid_designs_name_the_field():
    space = get_space("bimanual")
    fixed, sliding = (0, 0), (1, 0)
    # 0.3 m is a valid sliding spine but too short for a fixed one.
    space.validate(_with(space, sliding, spine_length=0.3))
    with pytest.raises(DesignError, match="spine_length"):
        space.validate(_with(space, fixed, spine_length=0.3))
    with pytest.raises(DesignError, match="shoulder_y"):
        space.validate(_with(space, fixed, shoulder_y=0.2))
    with pytest.raises(DesignError, match="arm_link"):
        space.validate(_with(space, fixed, arm_link=-0.01))
    with pytest.raises(DesignError, match="forearm_link"):
        space.to_mjcf(_with(space, fixed, forearm_link=float("inf")))
    with pytest.raises(DesignError, match="torso_pitch"):
        space.validate(Design("bimanual", (0, 2), space.nominal().continuous))
    good = space.to_dict(space.nominal())
    bad = json.loads(json.dumps(good))
    bad["discrete"]["spine"] = "rubber"
    with pytest.raises(DesignError, match="'spine'.*rubber"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    bad["continuous"]["shoulder_z"] = "high"
    with pytest.raises(DesignError, match="shoulder_z"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    del bad["discrete"]["torso_pitch"]
    with pytest.raises(DesignError, match="torso_pitch"):
        space.from_dict(bad)


def test_parameter_lists_follow_the_discrete_choices():
    aloha = get_space("aloha")
    names = {i: [p.name for p in aloha.continuous_params((i,))] for i in range(3)}
    assert names[0] == ["mount_x", "interarm_distance", "arm_extension", "forearm_extension"]
    assert names[1] == names[2] == ["mount_x", "interarm_distance", "mount_z", "arm_extension", "forearm_extension"]
    bimanual = get_space("bimanual")
    bounds = {s: bimanual.continuous_params((s, 0))[0] for s in range(3)}
    assert [(b.low, b.high) for b in bounds.values()] == [(0.60, 1.40), (0.10, 0.50), (0.20, 0.80)]
    # DoF: 3 base + spine joint (sliding, bending) + torso pitch + 2 x 6 arm joints.
    dofs = {
        (s, t): bimanual.model(_with(bimanual, (s, t), spine_length=bounds[s].low)).nu
        for s in range(3)
        for t in range(2)
    }
    assert dofs == {(0, 0): 15, (0, 1): 16, (1, 0): 16, (1, 1): 17, (2, 0): 16, (2, 1): 17}
    assert [aloha.model(_with(aloha, (i,), mount_z=0.7)).nu for i in range(3)] == [12, 12, 12]


def _left_right_joints(m):
    names = [m.joint(j).name for j in range(m.njnt)]
    left = [j for j, n in enumerate(names) if n.startswith("left_")]
    right = [names.index("right_" + names[j][len("left_") :]) for j in left]
    return names, left, right


def test_equal_joint_angles_give_mirror_image_poses(space):
    rng = np.random.default_rng(4)
    for d in [space.nominal(), *space.sample(10, seed=5)]:
        m = space.model(d)
        data = mujoco.MjData(m)
        names, left, right = _left_right_joints(m)
        assert len(left) == 6
        # Both arms share ranges and gains.
        np.testing.assert_array_equal(m.jnt_range[left], m.jnt_range[right])
        np.testing.assert_array_equal(m.actuator_gainprm[left], m.actuator_gainprm[right])
        np.testing.assert_array_equal(m.actuator_biasprm[left], m.actuator_biasprm[right])
        for _ in range(5):
            lo, hi = m.jnt_range.T
            q = rng.uniform(lo, hi)
            q[right] = q[left]
            for trunk in ("base_y", "base_yaw"):  # antisymmetric under the reflection
                if trunk in names:
                    q[names.index(trunk)] = 0.0
            data.qpos[:] = q
            mujoco.mj_kinematics(m, data)
            p0, p1 = data.site("ee_0").xpos, data.site("ee_1").xpos
            r0, r1 = data.site("ee_0").xmat.reshape(3, 3), data.site("ee_1").xmat.reshape(3, 3)
            np.testing.assert_allclose(p1, M @ p0, atol=1e-12)
            np.testing.assert_allclose(r1, M @ r0 @ M, atol=1e-12)
            for j_left, j_right in zip(left, right):
                b_left, b_right = m.jnt_bodyid[j_left], m.jnt_bodyid[j_right]
                np.testing.assert_allclose(data.xpos[b_right], M @ data.xpos[b_left], atol=1e-12)
            # Negated angles on the right arm break the mirror: the check tells conventions apart.
            data.qpos[right] = -q[left]
            mujoco.mj_kinematics(m, data)
            assert np.linalg.norm(data.site("ee_1").xpos - M @ data.site("ee_0").xpos) > 1e-3


def test_nominal_home_poses():
    aloha = get_space("aloha")
    m = aloha.model(aloha.nominal())
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    # ViperX 300 S: 0.127 shoulder height + 0.30 upper arm; 0.30 forearm + 0.07 wrist + 0.10 gripper.
    np.testing.assert_allclose(d.site("ee_0").xpos, [0.47, 0.30, 0.427], atol=1e-12)
    np.testing.assert_allclose(d.site("ee_1").xpos, [0.47, -0.30, 0.427], atol=1e-12)
    np.testing.assert_allclose(d.site("ee_0").xmat.reshape(3, 3), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(d.site("ee_1").xmat.reshape(3, 3), np.eye(3), atol=1e-12)

    bimanual = get_space("bimanual")
    m = bimanual.model(bimanual.nominal())
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    # 0.20 base top + 0.80 spine + 0.04 shoulder height - 0.22 upper arm; 0.22 forearm + 0.10 hand;
    # y: 0.08 shoulder offset + 0.05 shoulder link.
    np.testing.assert_allclose(d.site("ee_0").xpos, [0.32, 0.13, 0.82], atol=1e-12)
    np.testing.assert_allclose(d.site("ee_1").xpos, [0.32, -0.13, 0.82], atol=1e-12)
    np.testing.assert_allclose((d.site("ee_0").xpos + d.site("ee_1").xpos) / 2, WORKSPACE_CENTER, atol=1e-12)


@pytest.mark.parametrize("name", SPACES)
def test_nominal_reaches_the_two_arm_region(name):
    """Both end effectors reach every grid point of the region at once (mirrored pairs);
    the bimanual robot gets the region moved to its `WORKSPACE_CENTER`."""
    space = get_space(name)
    m = space.model(space.nominal())
    shift = np.asarray(WORKSPACE_CENTER) - REGION_CENTER if name == "bimanual" else np.zeros(3)
    for x, y, z in REGION_GRID:
        targets = [np.array([x, y, z]) + shift, np.array([x, -y, z]) + shift]
        err = _ik(m, targets, space.ee_sites())
        assert err.max() < 1e-3, (name, (x, y, z), err)


def test_home_pose_holds_under_gravity(space):
    """Servos commanded to the home posture keep both end effectors within 1 cm for 2 s.

    The servos are sized for a static sag of `HOME_SAG` (4 mm); the transient may overshoot
    it by half. Role gains alone would let long ALOHA arms sag 7 mm and some bimanual
    robots over 1 cm, so this also checks that the sizing is applied.
    """
    limit = 1.5 * importlib.import_module(f"tt.sim.designs.{space.name}").HOME_SAG
    assert limit < 0.01
    for d in [space.nominal(), *space.sample(20, seed=11)]:
        m = space.model(d)
        data = mujoco.MjData(m)
        mujoco.mj_forward(m, data)
        home = np.stack([data.site("ee_0").xpos, data.site("ee_1").xpos])
        data.ctrl[:] = m.qpos0[m.jnt_qposadr[m.actuator_trnid[:, 0]]]
        drift = 0.0
        for _ in range(int(round(2.0 / m.opt.timestep))):
            mujoco.mj_step(m, data)
            now = np.stack([data.site("ee_0").xpos, data.site("ee_1").xpos])
            drift = max(drift, float(np.linalg.norm(now - home, axis=1).max()))
        assert drift < limit, (space.to_dict(d), drift)
        # Servos hold their share with margin: no actuator near its force limit.
        assert np.all(np.abs(data.actuator_force) < 0.5 * m.actuator_forcerange[:, 1])


def test_servo_sizing_meets_the_static_sag_budget(space):
    """Linearised home sag sum_j |tau_j| |J_j| / kp_j, recomputed from the final model, is
    within `HOME_SAG`, and equals it where role gains alone were too soft (stiffened)."""
    sag = importlib.import_module(f"tt.sim.designs.{space.name}").HOME_SAG
    totals = []
    for d in space.sample(30, seed=12):
        m = space.model(d)
        data = mujoco.MjData(m)
        mujoco.mj_forward(m, data)
        sites = ("ee_0",) if space.name == "aloha" else ("ee_0", "ee_1")
        jacs = []
        for site in sites:
            jacp = np.zeros((3, m.nv))
            mujoco.mj_jacSite(m, data, jacp, None, m.site(site).id)
            jacs.append(jacp)
        # The right arm mirrors the left: the budget covers the trunk and the left arm.
        joints = [j for j in range(m.njnt) if not m.joint(j).name.startswith("right_")]
        dofs = m.jnt_dofadr[joints]
        lever = np.max([np.linalg.norm(j[:, dofs], axis=0) for j in jacs], axis=0)
        kp = m.actuator_gainprm[joints, 0]
        totals.append(float(np.sum(np.abs(data.qfrc_bias[dofs]) * lever / kp)))
    totals = np.array(totals)
    assert np.all(totals <= sag * (1 + 1e-9))
    assert np.any(np.isclose(totals, sag, rtol=1e-9)) and np.any(totals < 0.99 * sag)
