"""Target motions: the skill library, its splits, motion files, resampling and SE(2) augmentation.

References: scipy's Rotation / Slerp for the quaternion helpers and resampling, analytic
trajectories for the loaders, the skill scripts' own formulas (toss release direction,
screw axis) for the library.
"""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from scipy.spatial.transform import Rotation, Slerp

from tt.sim.motions import (
    BIMANUAL,
    MOTION_DT,
    SINGLE_ARM,
    SKILLS,
    TRAIN_SEEDS,
    UMI_TOOL_QUAT,
    VAL_SEEDS,
    Motion,
    MotionError,
    augment_motion,
    augment_se2,
    default_motion,
    for_space,
    get_motion,
    list_motions,
    load_motion_file,
    load_npz,
    load_umi_zarr,
    motion_set,
    place_at_base,
    recenter,
    resample,
    resolve_motion,
    save_npz,
    umi_episode_count,
    workspaces,
)
from tt.sim.motions.base import (
    quat_angle,
    quat_conj,
    quat_from_rotvec,
    quat_mul,
    quat_rotate,
    quat_slerp,
    quat_to_rotvec,
)
from tt.sim.motions.skills import TOSS

# Limits every library motion must respect. Speed and angular speed are what a
# ViperX-class arm can follow (its servos turn at ~5 rad/s); the acceleration and jerk
# bounds are well above the scripted values (<= 8 m/s^2, <= 130 m/s^3) but a junction
# between phases that is only C0 or C1 would exceed them by far (a velocity jump of
# 0.1 m/s reads as 5 m/s^2 ... per step; an acceleration jump of 4 m/s^2 as 200 m/s^3).
MAX_SPEED = 1.5  # m/s
MAX_ACCEL = 15.0  # m/s^2
MAX_JERK = 250.0  # m/s^3
MAX_ANG_SPEED = 5.0  # rad/s
MAX_ANG_ACCEL = 60.0  # rad/s^2
# Tosses and flings move at human speed (2-3 m/s peaks): an arm that cannot follow shows
# it in its error, which is the point. Their limits are those of a fast human hand.
DYNAMIC = {
    "toss": (3.0, 60.0, 2000.0, 12.0, 250.0),
    "fling": (3.0, 60.0, 2000.0, 12.0, 250.0),
    "bi_fling": (3.0, 60.0, 2000.0, 12.0, 250.0),
}

SPLIT_SEEDS = TRAIN_SEEDS + VAL_SEEDS


def _sq(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) -> scipy's (x, y, z, w)."""
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _angular_velocity(m: Motion) -> np.ndarray:
    """World-frame angular velocity [rad/s] between consecutive samples, (T-1, A, 3)."""
    return quat_to_rotvec(quat_mul(m.quat[1:], quat_conj(m.quat[:-1]))) / m.dt


# ------------------------------------------------------------------ quaternion helpers


def test_quaternion_helpers_match_scipy():
    rng = np.random.default_rng(0)
    a, b = Rotation.random(64, random_state=1), Rotation.random(64, random_state=2)
    qa, qb = a.as_quat(scalar_first=True), b.as_quat(scalar_first=True)
    v = rng.normal(size=(64, 3))
    np.testing.assert_allclose(quat_mul(qa, qb), (a * b).as_quat(scalar_first=True), atol=1e-12)
    np.testing.assert_allclose(quat_rotate(qa, v), a.apply(v), atol=1e-12)
    np.testing.assert_allclose(quat_from_rotvec(v), Rotation.from_rotvec(v).as_quat(scalar_first=True), atol=1e-12)
    np.testing.assert_allclose(quat_to_rotvec(qa), a.as_rotvec(), atol=1e-12)
    # Tiny rotations take the series branches.
    np.testing.assert_allclose(quat_to_rotvec(quat_from_rotvec(v * 1e-10)), v * 1e-10, rtol=1e-9, atol=0)
    s = rng.uniform(size=64)
    ref = np.array(
        [Slerp([0, 1], Rotation.concatenate([a[i], b[i]]))(s[i]).as_quat(scalar_first=True) for i in range(64)]
    )
    out = quat_slerp(qa, qb, s)
    np.testing.assert_allclose(np.abs(np.sum(out * ref, axis=-1)), 1.0, atol=1e-12)  # same rotation, either sign
    np.testing.assert_allclose(quat_angle(qa, qb), (a.inv() * b).magnitude(), atol=1e-7)


# ------------------------------------------------------------------ library


def test_library_covers_the_required_skills():
    single = [n for n, s in SKILLS.items() if s.arms == 1]
    bimanual = [n for n, s in SKILLS.items() if s.arms == 2]
    assert {"toss", "scrub", "drawer_open", "screw", "wipe", "pour", "reach_place", "fling"} <= set(single)
    assert len(single) >= 8 and len(bimanual) >= 4
    assert all(n.startswith("bi_") for n in bimanual)


def test_every_space_has_a_default_motion_it_can_run():
    """`tt rollout` and the API's functions without motions run `default_motion` of the
    space's end-effector count: it must exist for every space and place there."""
    from tt.sim.designs import SPACE_NAMES, get_space

    for name in SPACE_NAMES:
        sp = get_space(name)
        m = get_motion(default_motion(sp.ee_count))
        assert m.arms == sp.ee_count
        assert for_space([m], name)[0].arms == sp.ee_count
    with pytest.raises(MotionError, match="3 end effectors"):
        default_motion(3)


@pytest.mark.parametrize("name", list(SKILLS))
def test_split_motions_are_valid_smooth_and_reachable(name):
    skill = SKILLS[name]
    max_speed, max_accel, max_jerk, max_ang_speed, max_ang_accel = DYNAMIC.get(
        name, (MAX_SPEED, MAX_ACCEL, MAX_JERK, MAX_ANG_SPEED, MAX_ANG_ACCEL)
    )
    for seed in SPLIT_SEEDS:
        m = get_motion(name, seed)
        where = f"{m.name} ({m.meta['params']})"
        # Placed as the paper places demonstrations: the first pose over the base.
        np.testing.assert_allclose(m.pos[0, :, :2].mean(axis=0), 0.0, atol=1e-12)
        assert m.dt == MOTION_DT and m.arms == skill.arms, where
        assert 3.0 <= m.duration <= 8.0, where
        assert np.all(np.isfinite(m.pos)) and np.all(np.isfinite(m.quat)), where
        np.testing.assert_allclose(np.linalg.norm(m.quat, axis=-1), 1.0, atol=1e-12)
        v = np.diff(m.pos, axis=0) / m.dt
        acc = np.diff(m.pos, n=2, axis=0) / m.dt**2
        jerk = np.diff(m.pos, n=3, axis=0) / m.dt**3
        assert np.linalg.norm(v, axis=-1).max() < max_speed, where
        assert np.linalg.norm(acc, axis=-1).max() < max_accel, where
        assert np.linalg.norm(jerk, axis=-1).max() < max_jerk, where
        w = _angular_velocity(m)
        assert np.linalg.norm(w, axis=-1).max() < max_ang_speed, where
        assert np.linalg.norm(np.diff(w, axis=0), axis=-1).max() / m.dt < max_ang_accel, where
        # Quaternion sign stays continuous (a flip would look like a jump to a tokenizer).
        assert np.all(np.sum(m.quat[1:] * m.quat[:-1], axis=-1) > 0.99), where
        # Starts and ends at rest.
        assert np.linalg.norm(v[[0, -1]], axis=-1).max() < 1e-6, where
        # The skill as written (before placement) stays where the nominal arm can reach.
        authored = skill.motion(seed, placed=False)
        np.testing.assert_array_equal(authored.quat, m.quat)
        np.testing.assert_allclose(
            m.pos - authored.pos, np.broadcast_to(m.pos[:1] - authored.pos[:1], m.pos.shape), atol=1e-12
        )
        for a, ws in enumerate(workspaces(m.arms)):
            inside = ws.contains(authored.pos[:, a], authored.quat[:, a])
            assert inside.all(), f"{where}: arm {a} leaves its workspace at step {int(np.argmin(inside))}"


def test_workspace_check_rejects_unreachable_targets():
    down = np.array([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])  # pitch +90 deg: pointing down
    up = np.array([np.cos(np.pi / 4), 0.0, -np.sin(np.pi / 4), 0.0])
    level = np.array([1.0, 0.0, 0.0, 0.0])
    assert SINGLE_ARM.contains(np.array([0.35, 0.0, 0.2]), down)
    assert not SINGLE_ARM.contains(np.array([0.35, 0.0, 0.2]), up)  # gripper pointing up
    assert not SINGLE_ARM.contains(np.array([0.60, 0.0, 0.2]), level)  # outside the box
    # In the box but 0.75 m from the shoulder (beyond reach).
    assert not SINGLE_ARM.contains(np.array([0.55, 0.35, 0.55]), level)
    # Tip within reach (0.60 m), but pointing down puts the wrist 0.17 m higher, 0.62 m away.
    p = np.array([0.55, 0.20, 0.30])
    assert np.linalg.norm(p - np.array(SINGLE_ARM.shoulder)) < SINGLE_ARM.reach
    assert SINGLE_ARM.contains(p, level) and not SINGLE_ARM.contains(p, down)
    assert BIMANUAL[0].contains(np.array([0.3, 0.1, 0.2]), down)
    assert not BIMANUAL[0].contains(np.array([0.3, -0.1, 0.2]), down)  # arm 0 stays on +y
    assert BIMANUAL[1].contains(np.array([0.3, -0.1, 0.2]), down)
    with pytest.raises(MotionError, match="arms"):
        workspaces(3)


def test_canonical_toss_releases_forward_and_up_mid_swing():
    m = get_motion("toss")
    p = TOSS.draw(0)
    assert m.name == "toss" and m.meta["split"] == "train" and m.meta["params"] == p
    # Central differences: at the sample in the middle of a symmetric min-jerk swing the
    # chord (p[k+1] - p[k-1]) is parallel to the tangent.
    v = (m.pos[2:, 0] - m.pos[:-2, 0]) / (2 * m.dt)
    speed = np.linalg.norm(v, axis=-1)
    k = int(np.argmax(speed))
    # Min-jerk timing s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 on the arc: the peak is at the
    # arc's middle, moving along the tangent (cos psi, 0, sin psi) with psi = (forward -
    # back) / 2. The central difference there is the chord over the angle the swing covers
    # in +-1 sample, A (s(1/2 + h) - s(1/2 - h)) with h = dt / swing time; it tends to the
    # continuous peak 1.875 * arc / swing time as h -> 0.
    angle = np.radians(p["back"] + p["forward"])
    h = m.dt / p["swing_time"]
    s_ = lambda tau: 10 * tau**3 - 15 * tau**4 + 6 * tau**5  # noqa: E731
    swept = angle * (s_(0.5 + h) - s_(0.5 - h))
    assert speed[k] == pytest.approx(2 * p["radius"] * np.sin(swept / 2) / (2 * m.dt), rel=1e-9)
    assert speed[k] == pytest.approx(1.875 * p["radius"] * angle / p["swing_time"], rel=0.03)
    psi = np.radians(p["forward"] - p["back"]) / 2
    direction = v[k] / speed[k]
    np.testing.assert_allclose(direction, [np.cos(psi), 0.0, np.sin(psi)], atol=1e-6)
    # The wrist flicks: the approach tilts up by `flick` from its wind-up pitch (80 deg down).
    approach = quat_rotate(m.quat[:, 0], [1.0, 0.0, 0.0])
    pitch = np.degrees(np.arcsin(-approach[:, 2]))
    assert pitch.max() == pytest.approx(80.0, abs=1e-9)
    assert pitch.min() == pytest.approx(80.0 - p["flick"], abs=1e-9)


def test_screw_turns_about_the_downward_approach_axis():
    p = SKILLS["screw"].draw(0)
    m = get_motion("screw")
    q = m.quat[:, 0]
    approach = quat_rotate(q, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(approach, np.tile([0.0, 0.0, -1.0], (m.steps, 1)), atol=1e-12)
    # Angle about the approach axis relative to the start; it sweeps exactly `turn`.
    rel = quat_to_rotvec(quat_mul(quat_conj(q[:1]), q))
    roll = np.degrees(rel[:, 0])
    assert np.abs(rel[:, 1:]).max() < 1e-12
    assert roll.max() - roll.min() == pytest.approx(p["turn"], abs=1e-6)
    # Three turns, each advancing the hand `drop` along the thread.
    z = m.pos[:, 0, 2]
    assert z.min() == pytest.approx(p["sz"] - 3 * p["drop"], abs=1e-9)


def test_bimanual_mirrored_skills_are_symmetric():
    m = get_motion("bi_fling", 4)
    np.testing.assert_allclose(m.pos[:, 1], m.pos[:, 0] * [1, -1, 1], atol=1e-12)
    # Mirror through the xz plane: R' = M R M, i.e. (w, x, y, z) -> (w, -x, y, -z).
    np.testing.assert_allclose(m.quat[:, 1], m.quat[:, 0] * [1, -1, 1, -1], atol=1e-12)


# ------------------------------------------------------------------ registry and splits


def test_splits_are_disjoint_deterministic_and_complete():
    assert not set(TRAIN_SEEDS) & set(VAL_SEEDS)
    for arms in (1, 2):
        train, val = motion_set("train", arms=arms), motion_set("val", arms=arms)
        n_skills = sum(s.arms == arms for s in SKILLS.values())
        assert len(train) == n_skills * len(TRAIN_SEEDS) and len(val) == n_skills * len(VAL_SEEDS)
        assert all(m.arms == arms for m in train + val)
        assert {m.meta["split"] for m in train} == {"train"} and {m.meta["split"] for m in val} == {"val"}
        names_train, names_val = [m.name for m in train], [m.name for m in val]
        assert len(set(names_train)) == len(names_train) and not set(names_train) & set(names_val)
        again = motion_set("val", arms=arms)
        for a, b in zip(val, again):
            assert a.name == b.name
            np.testing.assert_array_equal(a.pos, b.pos)
            np.testing.assert_array_equal(a.quat, b.quat)
    assert len(motion_set("train")) == len(SKILLS) * len(TRAIN_SEEDS)
    # Different seeds give different motions.
    assert not np.allclose(get_motion("wipe", 1).pos[:50], get_motion("wipe", 2).pos[:50])
    with pytest.raises(MotionError, match="valid: \\['train', 'val'\\]"):
        motion_set("test")


def test_registry_names_and_errors():
    rows = list_motions()
    assert [r.name for r in rows] == list(SKILLS)
    for r in rows:
        m = get_motion(r.name)
        assert r.arms == m.arms and r.steps == m.steps and r.duration == pytest.approx(m.duration)
        row = r.row()
        assert set(row) == {"name", "arms", "duration_s", "steps", "train", "val", "params", "summary"}
        assert row["train"] == "seeds 0-9" and row["val"] == "seeds 100-102"
    assert [r.name for r in list_motions(arms=2)] == [n for n, s in SKILLS.items() if s.arms == 2]
    np.testing.assert_array_equal(get_motion("toss:7").pos, get_motion("toss", 7).pos)
    assert get_motion("toss:7").name == "toss:7"
    with pytest.raises(MotionError, match="valid: toss, scrub"):
        get_motion("juggle")
    with pytest.raises(MotionError, match="seed 7 but seed=8"):
        get_motion("toss:7", seed=8)
    with pytest.raises(MotionError, match="integer seed"):
        get_motion("toss:x")
    with pytest.raises(MotionError, match="seed must be an integer >= 0"):
        get_motion("toss", -1)
    with pytest.raises(MotionError, match="no parameter 'speed'; valid"):
        SKILLS["toss"].motion(0, speed=1.0)
    with pytest.raises(MotionError, match="radius = 0.5 is outside"):
        SKILLS["toss"].motion(0, radius=0.5)
    custom = SKILLS["toss"].motion(3, radius=0.22)
    assert custom.meta["params"]["radius"] == 0.22 and custom.meta["split"] == "custom"


# ------------------------------------------------------------------ npz


def test_place_at_base_moves_the_first_pose_over_the_base_and_keeps_the_rest(tmp_path):
    authored = SKILLS["bi_handover"].motion(101, placed=False)
    placed = place_at_base(authored, (0.1, -0.2))
    shift = np.array([0.1, -0.2]) - authored.pos[0, :, :2].mean(axis=0)
    np.testing.assert_allclose(placed.pos[..., :2], authored.pos[..., :2] + shift, atol=1e-15)
    np.testing.assert_array_equal(placed.pos[..., 2], authored.pos[..., 2])
    np.testing.assert_array_equal(placed.quat, authored.quat)
    np.testing.assert_allclose(placed.meta["placed_shift"], [*shift, 0.0], atol=1e-15)
    assert place_at_base(placed, (0.1, -0.2)) is placed  # already placed: returned as it is
    # Files are placed the same way on load unless asked not to be.
    path = tmp_path / "authored.npz"
    save_npz(authored, path)
    np.testing.assert_allclose(load_motion_file(path).pos[0, :, :2].mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_array_equal(load_motion_file(path, place=False).pos, authored.pos)


@pytest.mark.parametrize("name", ["pour:5", "bi_handover:101"])
def test_npz_round_trip_is_exact(tmp_path, name):
    m = get_motion(name)
    path = tmp_path / "m.npz"
    save_npz(m, path)
    back = load_npz(path)
    assert back.name == m.name and back.dt == m.dt and back.arms == m.arms
    np.testing.assert_array_equal(back.pos, m.pos)
    np.testing.assert_array_equal(back.quat, m.quat)
    assert load_motion_file(path).steps == m.steps
    assert resolve_motion(str(path)).name == m.name and resolve_motion(name).name == m.name


def _analytic(t: np.ndarray, phase: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A circle in a tilted plane and a constant-rate rotation about a fixed axis."""
    pos = np.stack([0.35 + 0.1 * np.cos(2 * t + phase), 0.1 * np.sin(2 * t + phase), 0.2 + 0.05 * t], axis=-1)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rot = quat_from_rotvec((0.4 + 1.3 * t)[:, None] * axis)
    return pos, rot


def test_npz_at_another_rate_is_resampled(tmp_path):
    src_dt = 1.0 / 30.0
    t_src = np.arange(91) * src_dt  # 3 s
    # A straight line and a constant-rate rotation: linear interpolation and slerp are exact.
    pos = np.stack([0.2 + 0.1 * t_src, -0.05 * t_src, 0.3 + 0 * t_src], axis=-1)
    axis = np.array([0.0, 0.6, 0.8])
    rot = quat_from_rotvec((0.2 + 0.9 * t_src)[:, None] * axis)
    np.savez(tmp_path / "slow.npz", pos=pos, quat=rot, dt=src_dt)
    m = load_npz(tmp_path / "slow.npz")
    t = np.arange(m.steps) * MOTION_DT
    assert m.dt == MOTION_DT and m.steps == 151 and m.name == "slow"  # 0 .. 3.0 s at 50 Hz
    np.testing.assert_allclose(m.pos[:, 0], np.stack([0.2 + 0.1 * t, -0.05 * t, 0.3 + 0 * t], -1), atol=1e-12)
    ref = quat_from_rotvec((0.2 + 0.9 * t)[:, None] * axis)
    np.testing.assert_allclose(quat_angle(m.quat[:, 0], ref), 0.0, atol=1e-7)


def test_resample_matches_scipy_slerp():
    rng = np.random.default_rng(3)
    n, src_dt = 40, 1.0 / 60.0
    rots = Rotation.random(n, random_state=4)
    pos = rng.normal(size=(n, 1, 3))
    p, q = resample(pos, rots.as_quat(scalar_first=True)[:, None], src_dt)
    t = np.arange(p.shape[0]) * MOTION_DT
    assert t[-1] <= (n - 1) * src_dt < t[-1] + MOTION_DT
    ref = Slerp(np.arange(n) * src_dt, rots)(t)
    np.testing.assert_allclose(quat_angle(q[:, 0], ref.as_quat(scalar_first=True)), 0.0, atol=1e-7)
    for k in range(3):
        np.testing.assert_allclose(p[:, 0, k], np.interp(t, np.arange(n) * src_dt, pos[:, 0, k]), atol=1e-12)


def _write_npz(path, **fields):
    np.savez(path, **fields)
    return path


def test_npz_errors_name_the_file_and_field(tmp_path):
    good_pos = np.tile([0.3, 0.0, 0.2], (10, 1))
    good_quat = np.tile([1.0, 0.0, 0.0, 0.0], (10, 1))
    nan_pos = good_pos.copy()
    nan_pos[4, 1] = np.nan
    bad_quat = good_quat.copy()
    bad_quat[6] = [0.5, 0.0, 0.0, 0.0]
    cases = {
        "nan.npz": (dict(pos=nan_pos, quat=good_quat, dt=0.02), "field 'pos' has NaN/inf \\(first at step 4\\)"),
        "norm.npz": (dict(pos=good_pos, quat=bad_quat, dt=0.02), "field 'quat' at step 6 has norm 0.5000"),
        "empty.npz": (dict(pos=np.zeros((0, 3)), quat=np.zeros((0, 4)), dt=0.02), "field 'pos' is empty"),
        "missing.npz": (dict(pos=good_pos, dt=0.02), "missing field 'quat'"),
        "shape.npz": (dict(pos=good_pos[:, :2], quat=good_quat, dt=0.02), "field 'pos' must have shape \\(T, 3\\)"),
        "dt.npz": (dict(pos=good_pos, quat=good_quat, dt=-1.0), "field 'dt' must be a positive"),
        "lengths.npz": (dict(pos=good_pos, quat=good_quat[:9], dt=0.02), "different lengths"),
        "half2.npz": (dict(pos=good_pos, quat=good_quat, dt=0.02, pos2=good_pos), "needs both 'pos2' and 'quat2'"),
        "inf2.npz": (
            dict(pos=good_pos, quat=good_quat, dt=0.02, pos2=np.full_like(good_pos, np.inf), quat2=good_quat),
            "field 'pos2'",
        ),
    }
    for fname, (fields, pattern) in cases.items():
        path = _write_npz(tmp_path / fname, **fields)
        with pytest.raises(MotionError, match=pattern) as info:
            load_npz(path)
        assert fname in str(info.value)
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(MotionError, match="junk.npz is not an .npz archive"):
        load_npz(tmp_path / "junk.npz")
    with pytest.raises(MotionError, match="unknown motion file type"):
        load_motion_file(_write_npz(tmp_path / "x.npz", pos=good_pos).rename(tmp_path / "x.csv"))
    with pytest.raises(MotionError, match="no such file"):
        load_motion_file(tmp_path / "absent.npz")
    with pytest.raises(MotionError, match="neither a motion name"):
        resolve_motion("juggle")


# ------------------------------------------------------------------ UMI zarr


def _write_umi(root, episodes: list[int], hz: float, two_arms: bool) -> np.ndarray:
    """A UMI-layout store whose sample k sits at time k / hz on the analytic trajectory."""
    n = sum(episodes)
    t = np.arange(n) / hz
    pos, rot = _analytic(t)
    root.create_array("data/robot0_eef_pos", data=pos.astype(np.float32))
    root.create_array("data/robot0_eef_rot_axis_angle", data=quat_to_rotvec(rot))
    if two_arms:
        pos1, rot1 = _analytic(t, phase=np.pi)
        root.create_array("data/robot1_eef_pos", data=pos1)
        root.create_array("data/robot1_eef_rot_axis_angle", data=quat_to_rotvec(rot1))
    root.create_array("meta/episode_ends", data=np.cumsum(episodes))
    return np.cumsum(episodes)


@pytest.mark.parametrize("zipped", [False, True])
def test_umi_zarr_loads_episodes_and_resamples(tmp_path, zipped):
    hz = 60.0
    episodes = [150, 200]
    if zipped:
        path = tmp_path / "umi.zarr.zip"
        store = zarr.storage.ZipStore(path, mode="w")
        ends = _write_umi(zarr.open_group(store, mode="w"), episodes, hz, two_arms=True)
        store.close()
    else:
        path = tmp_path / "umi.zarr"
        ends = _write_umi(zarr.open_group(str(path), mode="w"), episodes, hz, two_arms=True)
    assert umi_episode_count(path) == 2
    m = load_umi_zarr(path, episode=1, hz=hz, tool_quat=(1.0, 0.0, 0.0, 0.0))
    assert m.arms == 2 and m.dt == MOTION_DT and m.name == "umi:1" and m.meta["episode"] == 1
    # Episode 1 holds samples ends[0] .. ends[1]-1, i.e. (200 - 1) / 60 s = 3.3167 s -> 166 samples at 50 Hz.
    assert m.steps == int(np.floor((episodes[1] - 1) / hz / MOTION_DT)) + 1 == 166
    t = ends[0] / hz + np.arange(m.steps) * MOTION_DT
    for arm, phase in ((0, 0.0), (1, np.pi)):
        pos, rot = _analytic(t, phase)
        # Linear interpolation of the circle: error <= h^2/8 max|p''| = (1/60)^2/8 * 0.4 m/s^2,
        # plus float32 storage of arm 0 (~3e-8 m).
        np.testing.assert_allclose(m.pos[:, arm], pos, atol=(1 / hz) ** 2 / 8 * 0.4 + 1e-7)
        # A constant-rate rotation about a fixed axis: slerp is exact.
        np.testing.assert_allclose(quat_angle(m.quat[:, arm], rot), 0.0, atol=1e-7)
    # The default tool rotation turns UMI's approach axis (z) into tt's (x).
    d = load_motion_file(path, episode=0, hz=hz)
    t0 = np.arange(d.steps) * MOTION_DT
    _, rot0 = _analytic(t0)
    np.testing.assert_allclose(
        quat_rotate(d.quat[:, 0], [1.0, 0.0, 0.0]), quat_rotate(rot0, [0.0, 0.0, 1.0]), atol=1e-7
    )
    np.testing.assert_allclose(
        quat_rotate(d.quat[:, 0], [0.0, 0.0, 1.0]), quat_rotate(rot0, [0.0, -1.0, 0.0]), atol=1e-7
    )
    assert np.allclose(UMI_TOOL_QUAT, [0.5, 0.5, -0.5, 0.5])


def test_umi_zarr_errors(tmp_path):
    path = tmp_path / "bad.zarr"
    root = zarr.open_group(str(path), mode="w")
    _write_umi(root, [30, 40], 60.0, two_arms=False)
    with pytest.raises(MotionError, match="episode 2 does not exist; valid: 0..1"):
        load_umi_zarr(path, episode=2)
    with pytest.raises(MotionError, match="hz must be a positive"):
        load_umi_zarr(path, hz=0.0)
    rot = root["data/robot0_eef_rot_axis_angle"]
    rot[35] = [np.nan, 0.0, 0.0]
    with pytest.raises(
        MotionError, match="bad.zarr: field 'data/robot0_eef_rot_axis_angle' has NaN/inf \\(first at step 5\\)"
    ):
        load_umi_zarr(path, episode=1)
    load_umi_zarr(path, episode=0)  # the NaN is in episode 1 only

    short = zarr.open_group(str(tmp_path / "short.zarr"), mode="w")
    _write_umi(short, [30], 60.0, two_arms=False)
    short["meta/episode_ends"][0] = 50
    with pytest.raises(MotionError, match="has 30 samples, meta/episode_ends needs 50"):
        load_umi_zarr(tmp_path / "short.zarr")

    no_ends = zarr.open_group(str(tmp_path / "noends.zarr"), mode="w")
    no_ends.create_array("data/robot0_eef_pos", data=np.zeros((5, 3)))
    with pytest.raises(MotionError, match="noends.zarr: missing array 'meta/episode_ends'"):
        load_umi_zarr(tmp_path / "noends.zarr")
    no_ends.create_array("meta/episode_ends", data=np.array([5]))
    with pytest.raises(MotionError, match="missing array 'data/robot0_eef_rot_axis_angle'"):
        load_umi_zarr(tmp_path / "noends.zarr")
    with pytest.raises(MotionError, match="cannot open as a zarr store"):
        load_umi_zarr(tmp_path / "absent.zarr")


# ------------------------------------------------------------------ SE(2) augmentation


def test_augment_se2_matches_rotation_matrices_and_keeps_relative_geometry():
    motions = [get_motion("bi_fold", s) for s in (0, 1, 2)]
    steps = min(m.steps for m in motions)
    pos = np.stack([m.pos[:steps] for m in motions])  # (3, T, 2, 3)
    quat = np.stack([m.quat[:steps] for m in motions])
    yaw, dx, dy = np.array([0.3, -1.2, 2.5]), np.array([0.05, -0.1, 0.0]), np.array([0.0, 0.2, -0.07])
    p2, q2 = augment_se2(pos, quat, yaw, dx, dy)
    for b in range(3):
        rz = Rotation.from_euler("z", yaw[b])
        ref_p = rz.apply(pos[b].reshape(-1, 3)).reshape(pos[b].shape) + [dx[b], dy[b], 0.0]
        np.testing.assert_allclose(p2[b], ref_p, atol=1e-12)
        ref_q = (rz * Rotation.from_quat(_sq(quat[b].reshape(-1, 4)))).as_quat(scalar_first=True)
        np.testing.assert_allclose(np.abs(np.sum(q2[b].reshape(-1, 4) * ref_q, -1)), 1.0, atol=1e-12)
        # Relative geometry: distances between arms and along time, heights, relative rotations.
        np.testing.assert_allclose(
            np.linalg.norm(p2[b, :, 0] - p2[b, :, 1], axis=-1),
            np.linalg.norm(pos[b, :, 0] - pos[b, :, 1], axis=-1),
            atol=1e-12,
        )
        np.testing.assert_allclose(
            np.linalg.norm(np.diff(p2[b], axis=0), axis=-1),
            np.linalg.norm(np.diff(pos[b], axis=0), axis=-1),
            atol=1e-12,
        )
        np.testing.assert_allclose(p2[b, ..., 2], pos[b, ..., 2], atol=0)
        rel = quat_mul(quat_conj(quat[b, :, 0]), quat[b, :, 1])
        rel2 = quat_mul(quat_conj(q2[b, :, 0]), q2[b, :, 1])
        np.testing.assert_allclose(quat_angle(rel, rel2), 0.0, atol=1e-7)
    with pytest.raises(MotionError, match="yaw must be a scalar or shape \\(3,\\)"):
        augment_se2(pos, quat, np.zeros(2), 0.0, 0.0)


def test_augment_se2_torch_matches_numpy_and_is_differentiable():
    torch = pytest.importorskip("torch")
    m = get_motion("toss", 3)
    pos, quat = m.pos[None], m.quat[None]
    p_np, q_np = augment_se2(pos, quat, 0.7, 0.1, -0.2)
    yaw = torch.tensor([0.7], dtype=torch.float64, requires_grad=True)
    p_t, q_t = augment_se2(torch.from_numpy(pos), torch.from_numpy(quat), yaw, 0.1, -0.2)
    np.testing.assert_allclose(p_t.detach().numpy(), p_np, atol=1e-12)
    np.testing.assert_allclose(q_t.detach().numpy(), q_np, atol=1e-12)
    # d/dyaw of sum(x) = sum(-sin(yaw) x0 - cos(yaw) y0).
    p_t[..., 0].sum().backward()
    expected = np.sum(-np.sin(0.7) * pos[..., 0] - np.cos(0.7) * pos[..., 1])
    assert yaw.grad.item() == pytest.approx(expected, rel=1e-12)


def test_augment_motion_is_seeded_and_rotates_about_the_pivot():
    m = get_motion("scrub", 2)
    a, b = augment_motion(m, 5), augment_motion(m, 5)
    np.testing.assert_array_equal(a.pos, b.pos)
    assert a.meta["se2"]["seed"] == 5 and a.name == "scrub:2+se2:5"
    assert not np.allclose(augment_motion(m, 6).pos, a.pos)
    # No shift, default pivot (the arm's base): every target keeps its distance from the base's vertical.
    r = augment_motion(m, 1, max_yaw=0.5, max_shift=0.0)
    np.testing.assert_allclose(
        np.linalg.norm(r.pos[..., :2], axis=-1), np.linalg.norm(m.pos[..., :2], axis=-1), atol=1e-12
    )
    assert abs(r.meta["se2"]["yaw"]) <= 0.5
    # About another pivot: the pivot stays put.
    pivot = np.array(SINGLE_ARM.center[:2])
    c = augment_motion(m, 3, max_shift=0.0, pivot=tuple(pivot))
    yaw, dx, dy = c.meta["se2"]["yaw"], c.meta["se2"]["dx"], c.meta["se2"]["dy"]
    moved, _ = augment_se2(np.array([[*pivot, 0.1]]), np.array([[1.0, 0, 0, 0]]), yaw, dx, dy)
    np.testing.assert_allclose(moved[0, :2], pivot, atol=1e-12)


def test_recenter_moves_the_bounding_box_centre():
    m = get_motion("bi_lift", 1)
    c = recenter(m, (0.1, 0.2, 0.3))
    flat = c.pos.reshape(-1, 3)
    np.testing.assert_allclose(0.5 * (flat.min(0) + flat.max(0)), [0.1, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(c.pos - m.pos, np.broadcast_to(c.pos[0, 0] - m.pos[0, 0], m.pos.shape), atol=1e-12)
    np.testing.assert_array_equal(c.quat, m.quat)


# ------------------------------------------------------------------ reachability by the nominal robots


def _ik_errors(model, targets_pos, targets_quat, rng, restarts=20, iters=150):
    """Largest position [m] / orientation [rad] error of damped-least-squares IK over the targets.

    Each target pose (A end effectors) starts from the previous solution, then from random
    joint vectors until one converges; joint limits are enforced by clipping.
    """
    import mujoco

    data = mujoco.MjData(model)
    arms = targets_pos.shape[1]
    sites = [model.site(f"ee_{a}").id for a in range(arms)]
    lo, hi = model.jnt_range[:, 0], model.jnt_range[:, 1]
    jp, jr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    q_prev = np.zeros(model.nq)
    worst_p = worst_o = 0.0
    for tp, tq in zip(targets_pos, targets_quat):
        best = (np.inf, np.inf, q_prev)
        for r in range(restarts):
            q = q_prev.copy() if r == 0 else rng.uniform(lo, hi)
            for _ in range(iters):
                data.qpos[:] = q
                mujoco.mj_kinematics(model, data)
                mujoco.mj_comPos(model, data)
                J, e, ep_max, eo_max = [], [], 0.0, 0.0
                for a, s in enumerate(sites):
                    mujoco.mj_jacSite(model, data, jp, jr, s)
                    cur = np.empty(4)
                    mujoco.mju_mat2Quat(cur, data.site_xmat[s])
                    ep = tp[a] - data.site_xpos[s]
                    eo = quat_to_rotvec(quat_mul(tq[a], quat_conj(cur)))
                    ep_max, eo_max = max(ep_max, np.linalg.norm(ep)), max(eo_max, np.linalg.norm(eo))
                    J += [jp.copy(), 0.3 * jr.copy()]
                    e += [ep, 0.3 * eo]
                if ep_max < 1e-4 and eo_max < 1e-3:
                    break
                J, e = np.vstack(J), np.concatenate(e)
                dq = J.T @ np.linalg.solve(J @ J.T + 1e-3 * np.eye(e.size), e)
                q = np.clip(q + np.clip(dq, -0.3, 0.3), lo, hi)
            if ep_max + 0.1 * eo_max < best[0] + 0.1 * best[1]:
                best = (ep_max, eo_max, q)
            if ep_max < 2e-3 and eo_max < np.radians(1.0):
                break
        worst_p, worst_o = max(worst_p, best[0]), max(worst_o, best[1])
        q_prev = best[2]
    return worst_p, worst_o


@pytest.mark.parametrize("name", list(SKILLS))
def test_nominal_robot_reaches_every_pose(name):
    # The reference for the workspace envelope: the nominal ViperX (single arm) or ALOHA
    # (two arms at y = +-0.3 m) reaches sampled poses of the canonical and one validation
    # variant within 2 mm and 1 deg, respecting its joint limits.
    from tt.sim.designs import get_space

    space = get_space("viperx" if SKILLS[name].arms == 1 else "aloha")
    model = space.model(space.nominal())
    rng = np.random.default_rng(0)
    for seed in (0, VAL_SEEDS[1]):
        m = SKILLS[name].motion(seed, placed=False)  # as written, before placement at the base
        ep, eo = _ik_errors(model, m.pos[::12], m.quat[::12], rng)
        assert ep < 2e-3 and eo < np.radians(1.0), f"{m.name}: IK error {ep * 1000:.2f} mm, {np.degrees(eo):.2f} deg"
