"""Quadruped manipulator design space: structure, standing, linkage legs, JSON, validation.

The reference throughout is MuJoCo C: models are compiled and stepped with `mj_step`, and
geometry claims (feet on the floor, closed linkages, knee directions) are read back from
`mj_kinematics` / `mj_forward` rather than recomputed with the module's own formulas.
"""

import itertools
import json

import mujoco
import numpy as np
import pytest

from tt.sim.designs import Design, DesignError, get_space, load_designs, save_designs
from tt.sim.designs import quadruped as q
from tt.sim.rewards import robot_mass, robot_size

LEGS = ("fl", "fr", "rl", "rr")
PRIMITIVES = {
    int(t)
    for t in (
        mujoco.mjtGeom.mjGEOM_CAPSULE,
        mujoco.mjtGeom.mjGEOM_CYLINDER,
        mujoco.mjtGeom.mjGEOM_BOX,
        mujoco.mjtGeom.mjGEOM_SPHERE,
    )
}


@pytest.fixture(scope="module")
def space():
    return get_space("quadruped")


def _with_discrete(space, discrete) -> Design:
    return Design(space.name, tuple(discrete), space.nominal().continuous)


def _home(model: mujoco.MjModel) -> mujoco.MjData:
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_forward(model, data)
    return data


def _tilt_deg(data: mujoco.MjData) -> float:
    """Angle [deg] between the torso's z axis and the world's."""
    return float(np.degrees(np.arccos(np.clip(data.body("torso").xmat[8], -1.0, 1.0))))


def _stands(model: mujoco.MjModel, seconds: float) -> tuple[float, float]:
    """Worst base-height change [m] and tilt [deg] over `seconds` with ctrl held at home."""
    data = _home(model)
    z0 = data.qpos[2]
    dz, tilt = 0.0, 0.0
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)
        dz = max(dz, abs(data.qpos[2] - z0))
        tilt = max(tilt, _tilt_deg(data))
    assert np.all(np.isfinite(data.qpos))
    return dz, tilt


def _passive_joint_ids(model: mujoco.MjModel) -> list[int]:
    """Joints no actuator drives (the free joint aside), in joint order."""
    driven = {int(model.actuator_trnid[a, 0]) for a in range(model.nu)}
    return [j for j in range(model.njnt) if j not in driven and model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE]


def _passive_joints(model: mujoco.MjModel) -> set[str]:
    return {model.joint(j).name for j in _passive_joint_ids(model)}


def test_space_has_the_papers_seven_binary_choices(space):
    nominal = space.nominal()
    params = space.discrete_params(nominal.discrete)
    assert [(p.name, p.options) for p in params] == [
        ("arm_mount", ("fixed", "rail")),
        ("leg_fl", ("serial", "linkage")),
        ("leg_fr", ("serial", "linkage")),
        ("leg_rl", ("serial", "linkage")),
        ("leg_rr", ("serial", "linkage")),
        ("knee_front", ("forward", "backward")),
        ("knee_back", ("forward", "backward")),
    ]
    bounds = {p.name: (p.low, p.high) for p in space.continuous_params(nominal.discrete)}
    assert bounds["arm_dlen_upper"] == bounds["arm_dlen_forearm"] == (-0.10, 0.40)
    assert bounds["arm_mount_x"] == bounds["battery_x"] == (-0.20, 0.20)
    assert bounds["body_length"] == (0.10, 0.50)
    assert all(bounds[f"leg_yaw_{leg}"] == (-0.7, 0.7) for leg in LEGS)
    # Thigh + calf spans the paper's 20-60 cm leg.
    assert bounds["thigh_length"][0] + bounds["calf_length"][0] == pytest.approx(0.20)
    assert bounds["thigh_length"][1] + bounds["calf_length"][1] == pytest.approx(0.60)
    assert space.has_contacts and space.ee_count == 1 and space.ee_sites() == ("ee_0",)


def test_nominal_robot_is_dog_sized_and_stands_on_its_feet(space):
    design = space.nominal()
    model = space.model(design)
    # 6 free + 4 legs x 3 + 6 arm; every actuator a position servo on its own joint.
    assert (model.nq, model.nv, model.nu, model.neq) == (25, 24, 18, 0)
    assert not _passive_joints(model)
    mass = float(robot_mass([model])[0])
    size = float(robot_size([model])[0])
    assert 10.0 <= mass <= 20.0, mass
    assert 4.0 <= size <= 6.5, size
    data = _home(model)
    # The home keyframe is the compiled default pose, standing at the space's own height.
    np.testing.assert_allclose(model.key("home").qpos, model.qpos0, atol=1e-12)
    assert data.qpos[2] == pytest.approx(space.standing_height(design), abs=1e-12)
    for leg in LEGS:
        foot = data.site(f"foot_{leg}").xpos
        hip = data.body(f"{leg}_thigh").xpos
        assert foot[2] == pytest.approx(q.FOOT_RADIUS, abs=1e-9)  # sphere resting on z = 0
        np.testing.assert_allclose(foot[:2], hip[:2], atol=1e-9)  # straight below the hip
    # The arm's zero pose: the gripper points forward, level, as on the ViperX.
    np.testing.assert_allclose(data.site("ee_0").xmat.reshape(3, 3), np.eye(3), atol=1e-9)
    dz, tilt = _stands(model, 3.0)
    assert dz < 0.05 and tilt < 10.0, (dz, tilt)


@pytest.mark.parametrize("arm_mount", [0, 1])
def test_all_128_discrete_combinations_build_and_hold_their_pose(space, arm_mount):
    for rest in itertools.product(range(2), repeat=6):
        discrete = (arm_mount, *rest)
        design = _with_discrete(space, discrete)
        model = space.model(design)
        options = {p.name: p.options[i] for p, i in zip(space.discrete_params(discrete), discrete)}
        linkage = [leg for leg in LEGS if options[f"leg_{leg}"] == "linkage"]
        rail = options["arm_mount"] == "rail"
        # 3 actuated joints per leg, 6 in the arm, the rail; 2 passive joints per linkage leg.
        assert model.nu == 18 + rail
        assert model.nv == 6 + model.nu + 2 * len(linkage)
        assert _passive_joints(model) == {f"{leg}_{j}" for leg in linkage for j in ("knee", "rod")}
        assert model.neq == len(linkage)
        assert all(model.eq_type[i] == mujoco.mjtEq.mjEQ_CONNECT for i in range(model.neq))
        # Actuators follow joint order.
        assert list(model.actuator_trnid[:, 0]) == sorted(model.actuator_trnid[:, 0])
        if rail:
            assert model.joint("arm_rail").type == mujoco.mjtJoint.mjJNT_SLIDE
        data = _home(model)
        # The home pose closes every linkage loop and puts all four feet on the floor.
        for leg in linkage:
            gap = data.site(f"{leg}_rod_pin").xpos - data.site(f"{leg}_calf_pin").xpos
            assert np.linalg.norm(gap) < 1e-9
        for leg in LEGS:
            assert data.site(f"foot_{leg}").xpos[2] == pytest.approx(q.FOOT_RADIUS, abs=1e-9)
            # Nominal legs have zero yaw: a forward knee lies ahead of its hip, a backward one behind.
            knee_dir = options["knee_front" if leg[0] == "f" else "knee_back"]
            ahead = data.body(f"{leg}_calf").xpos[0] - data.body(f"{leg}_thigh").xpos[0]
            assert ahead > 0.02 if knee_dir == "forward" else ahead < -0.02
            knee_home = data.joint(f"{leg}_knee").qpos[0]
            assert knee_home > 0 if knee_dir == "forward" else knee_home < 0
        z0 = data.qpos[2]
        for _ in range(250):
            mujoco.mj_step(model, data)
        assert abs(data.qpos[2] - z0) < 0.02 and _tilt_deg(data) < 5.0, (discrete, data.qpos[2] - z0)


def test_200_sampled_designs_load_and_step_1s_without_nan(space):
    rng = np.random.default_rng(0)
    models = []
    for design in space.sample(200, seed=11):
        model = space.model(design)
        models.append(model)
        assert {int(t) for t in model.geom_type[1:]} <= PRIMITIVES  # geom 0 is the floor plane
        assert np.all(model.body_mass[1:] > 0) and np.all(model.body_inertia[1:] > 0)
        assert model.opt.timestep == 0.002 and model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
        data = _home(model)
        # Anywhere in the control range: the robot collapses or kicks, and must stay finite.
        lo, hi = model.actuator_ctrlrange.T
        data.ctrl[:] = rng.uniform(lo, hi)
        for _ in range(500):
            mujoco.mj_step(model, data)
        assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel)), space.to_dict(design)
    # The paper's quadruped size target (6.5 m of geometry) sits mid-distribution; dog-sized masses.
    assert 6.0 <= float(robot_size(models).median()) <= 7.0
    assert 10.0 <= float(robot_mass(models).min()) and float(robot_mass(models).max()) <= 20.0


def test_random_designs_stand_from_home(space):
    results = [_stands(space.model(d), 3.0) for d in space.sample(50, seed=0)]
    standing = [dz < 0.05 and tilt < 10.0 for dz, tilt in results]
    # Measured: 49 of 50 (the fall: a 0.31 m hip base with the battery and a long arm forward).
    assert np.mean(standing) >= 0.9, f"{np.mean(standing):.2f} of random designs stand"


def test_only_feet_and_torso_touch_the_floor(space):
    model = space.model(_with_discrete(space, (1, 1, 1, 1, 1, 0, 0)))
    colliding = {model.geom(g).name for g in range(model.ngeom) if model.geom_contype[g] or model.geom_conaffinity[g]}
    assert colliding == {"floor", "torso", *(f"{leg}_foot" for leg in LEGS)}
    # Torso and feet collide with the floor only (contype 1 meets the floor's conaffinity 1).
    assert all(model.geom(f"{leg}_foot").conaffinity[0] == 0 for leg in LEGS)
    assert model.geom("torso").conaffinity[0] == 0
    data = _home(model)
    for _ in range(50):
        mujoco.mj_step(model, data)
    floor = model.geom("floor").id
    assert data.ncon == 4 and np.all(np.any(data.contact.geom[: data.ncon] == floor, axis=1))


def test_linkage_crank_drives_the_calf_through_the_parallelogram(space):
    model = space.model(_with_discrete(space, (0, 1, 1, 1, 1, 1, 1)))
    model.opt.gravity[:] = 0.0  # floating, so only the linkage moves the calf
    data = _home(model)
    data.qpos[2] += 0.3
    crank = model.actuator("fl_crank").id
    knee0 = data.joint("fl_knee").qpos[0]
    data.ctrl[crank] += 0.4
    for _ in range(500):
        mujoco.mj_step(model, data)
    flex, knee = data.joint("fl_hip_flex").qpos[0], data.joint("fl_knee").qpos[0]
    crank_q, rod = data.joint("fl_crank").qpos[0], data.joint("fl_rod").qpos[0]
    # The servo holds the knee spring's 0.4 rad x 30 N m/rad against kp 500: ~0.024 rad short.
    spring_lag = q.KNEE_SPRING * 0.4 / q.LEG_KP
    assert crank_q == pytest.approx(data.ctrl[crank] - spring_lag, abs=0.01)
    # Parallelogram: calf pitch = crank angle and the rod stays parallel to the thigh. The
    # loop's soft constraint gives under half a millimetre at the 4 cm lever: 0.012 rad.
    assert flex + knee == pytest.approx(crank_q, abs=0.012)
    assert rod == pytest.approx(-knee, abs=0.012)
    assert knee - knee0 > 0.3
    # The passive knee carries the spring, rest angle at the standing pose.
    j = model.joint("fl_knee")
    assert j.stiffness[0] > 0 and model.qpos_spring[j.qposadr[0]] == pytest.approx(knee0)


def test_rail_slides_the_arm_along_the_back(space):
    model = space.model(_with_discrete(space, (1, 0, 0, 0, 0, 1, 1)))
    data = _home(model)
    x0 = data.body("arm_mount").xpos[0] - data.body("torso").xpos[0]
    data.ctrl[model.actuator("arm_rail").id] = 0.1
    for _ in range(500):
        mujoco.mj_step(model, data)
    x1 = data.body("arm_mount").xpos[0] - data.body("torso").xpos[0]
    assert x1 - x0 == pytest.approx(0.1, abs=0.01)
    assert _tilt_deg(data) < 10.0


def test_json_round_trip_is_exact(space, tmp_path):
    designs = space.sample(50, seed=3)
    save_designs(designs, tmp_path / "designs.json")
    assert load_designs(tmp_path / "designs.json") == designs
    for d in designs:
        assert space.from_dict(json.loads(json.dumps(space.to_dict(d)))) == d
        assert space.to_mjcf(space.from_dict(space.to_dict(d))) == space.to_mjcf(d)
    assert space.sample(10, seed=5) == space.sample(10, seed=5)


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda d: Design("viperx", d.discrete, d.continuous), "space"),
        (lambda d: Design(d.space, (2, *d.discrete[1:]), d.continuous), "arm_mount"),
        (lambda d: Design(d.space, (*d.discrete[:5], -1, d.discrete[6]), d.continuous), "knee_front"),
        (lambda d: Design(d.space, d.discrete[:6], d.continuous), "discrete choices"),
        (lambda d: Design(d.space, d.discrete, d.continuous[:-1]), "continuous choices"),
        (lambda d: Design(d.space, d.discrete, (*d.continuous[:3], 0.6, *d.continuous[4:])), "body_length"),
        (lambda d: Design(d.space, d.discrete, (*d.continuous[:4], 0.05, *d.continuous[5:])), "thigh_length"),
        (lambda d: Design(d.space, d.discrete, (*d.continuous[:6], 0.8, *d.continuous[7:])), "leg_yaw_fl"),
        (lambda d: Design(d.space, d.discrete, (*d.continuous[:-1], float("nan"))), "battery_x"),
    ],
)
def test_invalid_designs_raise_naming_the_field(space, change, field):
    with pytest.raises(DesignError, match=field):
        space.to_mjcf(change(space.nominal()))


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d["discrete"].pop("leg_rr"), "leg_rr"),
        (lambda d: d["discrete"].update(knee_back="sideways"), "knee_back"),
        (lambda d: d["continuous"].pop("battery_x"), "battery_x"),
        (lambda d: d["continuous"].update(arm_mount_x=0.3), "arm_mount_x"),
        (lambda d: d["continuous"].update(arm_dlen_upper="long"), "arm_dlen_upper"),
        (lambda d: d["continuous"].update(tail_length=0.2), "tail_length"),
    ],
)
def test_malformed_json_raises_naming_the_field(space, edit, field):
    data = space.to_dict(space.nominal())
    edit(data)
    with pytest.raises(DesignError, match=field):
        space.from_dict(data)


@pytest.mark.parametrize("linkage_legs", [0, 2, 4])
def test_passive_linkage_joints_are_unactuated_joints_in_robotokens(space, linkage_legs):
    """RoboTokens of a quadruped with linkage legs, decoded back to MJCF, have the same joints,
    the same passive (unactuated) joints at the same places in joint order, and the linkage
    loops as equality constraints at the same bodies (an MJCF round trip through the tokens)."""
    import warnings

    from tt.tokens.detokenize import detokenize
    from tt.tokens.tokenize import tokenize_models

    legs = [1] * linkage_legs + [0] * (4 - linkage_legs)
    model = space.model(_with_discrete(space, (1, *legs, 0, 1)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tokens = tokenize_models([model]).tokens
    back = detokenize(tokens)[0].model
    assert back is not None

    assert (back.njnt, back.nu, back.neq) == (model.njnt, model.nu, model.neq)
    assert _passive_joint_ids(back) == _passive_joint_ids(model) and len(_passive_joint_ids(model)) == 2 * linkage_legs
    np.testing.assert_array_equal(back.jnt_type, model.jnt_type)
    np.testing.assert_array_equal(back.jnt_bodyid, model.jnt_bodyid)
    np.testing.assert_array_equal(back.eq_type, model.eq_type)

    def loops(m):
        """Each connect constraint as (sorted body pair, anchor in the torso's frame at qpos0);
        the detokenizer names its own sites and may list a pair's two sides the other way round
        (and places the floating base elsewhere in the world)."""
        data = mujoco.MjData(m)
        mujoco.mj_kinematics(m, data)
        out = []
        for i in range(m.neq):
            a, b = int(m.eq_obj1id[i]), int(m.eq_obj2id[i])
            if m.eq_objtype[i] == mujoco.mjtObj.mjOBJ_SITE:
                pair, anchor = (int(m.site_bodyid[a]), int(m.site_bodyid[b])), data.site_xpos[a].copy()
            else:
                pair, anchor = (a, b), data.xpos[a] + data.xmat[a].reshape(3, 3) @ m.eq_data[i, :3]
            local = data.xmat[1].reshape(3, 3).T @ (anchor - data.xpos[1])
            out.append((tuple(sorted(pair)), local))
        return sorted(out, key=lambda x: x[0])

    for (pair, anchor), (pair_back, anchor_back) in zip(loops(model), loops(back), strict=True):
        assert pair == pair_back
        np.testing.assert_allclose(anchor_back, anchor, atol=1e-5)
