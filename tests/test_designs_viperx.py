"""ViperX design space and the shared design machinery (sampling, validation, JSON)."""

import json

import mujoco
import numpy as np
import pytest

from tt.sim.designs import Design, DesignError, get_space, load_designs, save_designs


@pytest.fixture(scope="module")
def space():
    return get_space("viperx")


def test_200_designs_load_and_step_without_nan(space):
    rng = np.random.default_rng(0)
    dofs = set()
    for d in space.sample(200, seed=1):
        m = mujoco.MjModel.from_xml_string(space.to_mjcf(d))
        dofs.add(m.nu)
        data = mujoco.MjData(m)
        lo, hi = m.actuator_ctrlrange.T
        data.ctrl[:] = rng.uniform(lo, hi) * 0.5
        for _ in range(int(round(1.0 / m.opt.timestep))):
            mujoco.mj_step(m, data)
        assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
        # Geoms only: every moving body's mass and inertia come from its primitives.
        assert np.all(m.body_mass[1:] > 0) and np.all(m.body_inertia[1:] > 0)
        primitives = {
            int(t)
            for t in (
                mujoco.mjtGeom.mjGEOM_CAPSULE,
                mujoco.mjtGeom.mjGEOM_CYLINDER,
                mujoco.mjtGeom.mjGEOM_BOX,
                mujoco.mjtGeom.mjGEOM_SPHERE,
            )
        }
        assert {int(t) for t in m.geom_type} <= primitives
        assert m.site("ee_0") is not None
    assert dofs == {5, 6, 7}


def test_nominal_is_the_viperx_home_pose(space):
    m = space.model(space.nominal())
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    # 0.127 shoulder height + 0.30 upper arm; 0.30 forearm + 0.07 wrist + 0.10 gripper.
    np.testing.assert_allclose(d.site("ee_0").xpos, [0.47, 0.0, 0.427], atol=1e-9)
    np.testing.assert_allclose(d.site("ee_0").xmat.reshape(3, 3), np.eye(3), atol=1e-9)
    assert m.nu == 6


def test_json_round_trip_is_exact(space, tmp_path):
    designs = space.sample(50, seed=3)
    save_designs(designs, tmp_path / "designs.json")
    assert load_designs(tmp_path / "designs.json") == designs
    assert load_designs(f"{tmp_path / 'designs.json'}#7") == [designs[7]]
    for d in designs:
        assert space.from_dict(json.loads(json.dumps(space.to_dict(d)))) == d
        assert space.to_mjcf(space.from_dict(space.to_dict(d))) == space.to_mjcf(d)


def test_sampling_is_seeded(space):
    assert space.sample(10, seed=5) == space.sample(10, seed=5)
    assert space.sample(10, seed=5) != space.sample(10, seed=6)


def test_out_of_range_values_name_the_field(space):
    d = space.nominal()
    cont = list(d.continuous)
    cont[1] = 0.9  # mount_y beyond +-0.5
    with pytest.raises(DesignError, match="mount_y"):
        space.validate(Design("viperx", d.discrete, tuple(cont)))
    cont = list(d.continuous)
    cont[-1] = float("nan")
    with pytest.raises(DesignError, match="dlen_wrist_rotate"):
        space.to_mjcf(Design("viperx", d.discrete, tuple(cont)))
    with pytest.raises(DesignError, match="mount"):
        space.validate(Design("viperx", (7,) + d.discrete[1:], d.continuous))
    with pytest.raises(DesignError, match="expects"):
        space.validate(Design("viperx", d.discrete, d.continuous[:-1]))


def test_malformed_json_names_the_field(space):
    good = space.to_dict(space.nominal())
    bad = json.loads(json.dumps(good))
    bad["discrete"]["mount"] = "ceiling"
    with pytest.raises(DesignError, match="'mount'.*ceiling"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    del bad["continuous"]["mount_yaw"]
    with pytest.raises(DesignError, match="mount_yaw"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    bad["continuous"]["mount_x"] = "far"
    with pytest.raises(DesignError, match="mount_x"):
        space.from_dict(bad)
    bad = json.loads(json.dumps(good))
    bad["discrete"]["axis_elbow_extra"] = "x"
    with pytest.raises(DesignError, match="axis_elbow_extra"):
        space.from_dict(bad)


def test_unknown_space_lists_the_valid_ones():
    with pytest.raises(DesignError, match="viperx"):
        get_space("scara")


def test_dof_choice_changes_the_parameter_lists(space):
    counts = {}
    for dof in range(3):
        params = space.discrete_params((2, dof))
        discrete = (2, dof) + (0,) * (len(params) - 2)
        counts[dof] = (len(params), len(space.continuous_params(discrete)))
    # 4 mount params + one length per segment; one axis per joint after the shoulder.
    assert counts == {0: (5, 9), 1: (6, 10), 2: (7, 11)}


def test_nominal_sub_space_fixes_the_structure():
    """viperx-nominal: the nominal arm's discrete choices, continuous ones free; its designs build
    the same MJCF as the equal ViperX design, its rewards are ViperX's."""
    from tt.sim.designs import DesignError, FixedStructureSpace, get_space
    from tt.sim.rewards import get_reward

    full, sub = get_space("viperx"), get_space("viperx-nominal")
    assert isinstance(sub, FixedStructureSpace) and sub.family == "viperx" and full.family == "viperx"
    designs = sub.sample(20, seed=3)
    assert {d.discrete for d in designs} == {(0,) * len(full.nominal().discrete)}
    assert len({d.continuous for d in designs}) == 20
    for d in designs:
        base = sub.to_base(d)
        assert base.discrete == full.nominal().discrete
        assert full.to_mjcf(base) == sub.to_mjcf(d)
        assert sub.from_base(base) == d
        assert sub.to_dict(d)["discrete"] == full.to_dict(base)["discrete"]
        assert sub.from_dict(sub.to_dict(d)) == d
    assert full.to_mjcf(sub.to_base(sub.nominal())) == full.to_mjcf(full.nominal())
    with pytest.raises(DesignError, match="not sub-space"):
        sub.from_base(
            full.sample(50, seed=1)[
                [d.discrete != full.nominal().discrete for d in full.sample(50, seed=1)].index(True)
            ]
        )
    assert (
        get_reward("tracking_velocity", "viperx-nominal").velocity_alpha
        == get_reward("tracking_velocity", "viperx").velocity_alpha
    )


def test_servo_joints_follow_the_datasheets_torque_speed_line(space):
    """The nominal arm's MJCF is the servo model of tt.sim.designs.servos: force limit = stall
    torque, damping = friction + stall / no-load speed, so MuJoCo C, with a joint commanded far
    past its position, settles at the speed where the saturated torque is spent on
    back-EMF and friction: w = stall / (stall / w0 + friction)."""
    import mujoco

    from tt.sim.designs.servos import XM430_W350, XM540_W270
    from tt.sim.designs.viperx import FRICTION_DAMPING

    model = space.model(space.nominal())
    model.opt.gravity[:] = 0.0  # the waist turns about the vertical: gravity does no work on it anyway
    want = {
        "waist": (XM540_W270, 1),
        "shoulder": (XM540_W270, 2),
        "elbow": (XM540_W270, 2),
        "wrist_rotate": (XM430_W350, 1),
    }
    for name, (servo, count) in want.items():
        a = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, name)
        j = model.actuator_trnid[a, 0]
        assert model.actuator_forcerange[a, 1] == pytest.approx(servo.stall_torque * count, rel=1e-12)
        assert model.dof_damping[model.jnt_dofadr[j]] == pytest.approx(
            FRICTION_DAMPING + count * servo.stall_torque / servo.no_load_speed, abs=1e-4
        )
    data = mujoco.MjData(model)
    a = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "waist")
    dof = model.jnt_dofadr[model.actuator_trnid[a, 0]]
    data.ctrl[a] = model.actuator_ctrlrange[a, 1]  # pi: saturated for the whole run
    for _ in range(int(0.6 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    stall, damping = XM540_W270.stall_torque, model.dof_damping[dof]
    assert abs(data.actuator_force[a]) == pytest.approx(stall, rel=1e-9)  # still saturated
    assert data.qvel[dof] == pytest.approx(stall / damping, rel=2e-3)
    assert data.qvel[dof] < XM540_W270.no_load_speed
