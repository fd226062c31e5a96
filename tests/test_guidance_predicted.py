"""Reward inputs from predicted tokens (`tt.guidance.predicted`).

References: MuJoCo's compiled models (`robot_size` / `robot_mass` of the real designs the
link tokens come from), scipy's rotation conversions, the reward definitions of
`tt.sim.rewards` evaluated on the ground-truth inputs the tokens were made from, the
paper's formula on a hand case (perfect tracking scores one per step), and finite
differences for the gradient guidance uses.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tt.dit.layout import layout_from_schema
from tt.guidance.predicted import (
    PredictedReward,
    build_query,
    matrix_to_quat,
    orthonormalize,
    query_steps,
)
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import RewardConfig, RewardInputs, evaluate, get_reward, orientation_error, robot_mass, robot_size
from tt.tokens.batch import TokenBatch
from tt.tokens.normalize import Normalizer
from tt.tokens.schema import PAD_VALUE
from tt.tokens.tokenize import tokenize_models

S = 8  # control steps per window (the layout's)


def _scipy_quat(rot: Rotation) -> np.ndarray:
    """(w, x, y, z) from scipy's scalar-last quaternions."""
    q = rot.as_quat()
    return np.concatenate([q[..., 3:], q[..., :3]], -1)


def test_query_steps_even_and_random():
    even = query_steps(223, S, 3)
    # Midpoints of 8 strata of 223 steps: floor((k + 1/2) 223 / 8).
    assert even[0].tolist() == [int((k + 0.5) * 223 / 8) for k in range(8)]
    assert torch.equal(even[0], even[2])
    rnd = query_steps(223, S, 50, placement="random", generator=torch.Generator().manual_seed(0))
    assert rnd.shape == (50, S)
    assert bool((rnd.diff(dim=1) > 0).all()) and int(rnd.min()) >= 0 and int(rnd.max()) < 223
    with pytest.raises(ValueError, match="placement"):
        query_steps(10, S, 1, placement="uniform")


def test_rotation_projection_and_quaternion_against_scipy():
    rng = np.random.default_rng(0)
    rots = Rotation.random(400, random_state=1)
    # Include rotations by ~pi about each axis, where each of the four formulas is needed.
    rots = Rotation.concatenate([rots, Rotation.from_rotvec(np.pi * np.eye(3)), Rotation.from_rotvec(3.1 * np.eye(3))])
    mats = torch.tensor(rots.as_matrix(), dtype=torch.float64)
    proj = orthonormalize(mats.reshape(-1, 9))
    torch.testing.assert_close(proj, mats, atol=1e-12, rtol=0)
    q = matrix_to_quat(mats).numpy()
    ref = _scipy_quat(rots)
    # q and -q are one rotation.
    assert np.abs(np.abs((q * ref).sum(-1)) - 1).max() < 1e-12
    # Noisy matrices (as a model predicts them) project to proper rotations near the truth.
    noisy = mats + 0.05 * torch.tensor(rng.standard_normal(mats.shape))
    r = orthonormalize(noisy.reshape(-1, 9))
    eye = torch.eye(3, dtype=torch.float64).expand_as(r)
    torch.testing.assert_close(r.transpose(-1, -2) @ r, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(len(r), dtype=torch.float64), atol=1e-12, rtol=0)
    angle = orientation_error(matrix_to_quat(r), torch.tensor(ref))
    assert float(angle.max()) < 0.25


@pytest.fixture(scope="module")
def truth():
    """Three ViperX designs, a motion, and ground-truth dynamics tokens made from known poses,
    forces and velocities, normalised with statistics fitted on them (as a dataset's are)."""
    space = get_space("viperx")
    designs = space.sample(3, seed=4)
    models = [space.model(d) for d in designs]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models(models).tokens
    motion = for_space([get_motion("toss")], "viperx")[0]
    B = len(designs)
    steps = query_steps(motion.steps, S, B)
    rng = np.random.default_rng(2)
    target_pos = motion.pos[steps.numpy()]  # (B, S, 1, 3)
    target_rot = Rotation.from_quat(np.roll(motion.quat[steps.numpy()].reshape(-1, 4), -1, axis=-1))
    ee_pos = target_pos + 0.03 * rng.standard_normal(target_pos.shape)
    ee_rot = target_rot * Rotation.from_rotvec(0.3 * rng.standard_normal((B * S, 3)))
    act_count = np.asarray(emb.mask["actuator"]).sum(1)  # (B,)
    P = emb.values["actuator"].shape[1]
    used = np.arange(P)[None, :] < act_count[:, None]  # (B, P)
    force = np.where(used[:, None], rng.uniform(-3, 3, (B, S, P)), 0.0)
    vel = np.where(used[:, None], rng.uniform(-2, 2, (B, S, P)), 0.0)
    track = np.concatenate([ee_pos, ee_rot.as_matrix().reshape(B, S, 1, 9)], -1).reshape(B, S, 12)
    act = np.stack([vel, force], -1).reshape(B, S * P, 2)
    step_mask = {
        "track_link_obs": np.ones((B, S), bool),
        "actuator_obs": np.repeat(used[:, None], S, 1).reshape(B, S * P),
    }
    dyn = TokenBatch(
        {"track_link_obs": track.astype(np.float32), "actuator_obs": act.astype(np.float32)},
        {"track_link_obs": np.zeros((B, S, 2), np.int64), "actuator_obs": np.zeros((B, S * P, 2), np.int64)},
        step_mask,
    )
    target_raw = np.concatenate([target_pos.reshape(B, S, 3), target_rot.as_matrix().reshape(B, S, 9)], -1)
    target = TokenBatch(
        {"target_pose": target_raw.astype(np.float32)},
        {"target_pose": np.zeros((B, S, 2), np.int64)},
        {"target_pose": np.ones((B, S), bool)},
    )
    norm = Normalizer.fit([emb, dyn, target])
    counts = {n: int(np.asarray(emb.mask[n]).sum(1).max()) for n in emb.types}
    counts.update(track_link_obs=1, target_pose=1, actuator_obs=P)
    layout = layout_from_schema(counts, steps=S)
    x0 = {}
    for name, batch in (("emb", emb), ("dyn", dyn)):
        normed = norm.normalize(batch.to_torch())
        for n in normed.types:
            x0[n] = normed.values[n]
    ee_quat = _scipy_quat(ee_rot).reshape(B, S, 1, 4)
    return dict(
        space=space,
        models=models,
        motion=motion,
        layout=layout,
        norm=norm,
        x0=x0,
        ee_pos=ee_pos,
        ee_quat=ee_quat,
        force=force,
        vel=vel,
        used=used,
    )


def test_predicted_inputs_recover_ground_truth(truth):
    t = truth
    B = len(t["models"])
    query = build_query(t["layout"], t["norm"], t["motion"], B)
    cfg = get_reward("tracking_size", "viperx")
    scorer = PredictedReward(t["layout"], t["norm"], cfg, query)
    inputs = scorer.inputs(t["x0"])
    torch.testing.assert_close(inputs.ee_pos, torch.tensor(t["ee_pos"], dtype=torch.float32), atol=2e-6, rtol=0)
    # float32 tokens: orientations come back within 1e-5 rad.
    assert float(orientation_error(inputs.ee_quat, torch.tensor(t["ee_quat"], dtype=torch.float32)).max()) < 1e-5
    torch.testing.assert_close(inputs.act_force, torch.tensor(t["force"], dtype=torch.float32), atol=2e-6, rtol=0)
    torch.testing.assert_close(inputs.act_vel, torch.tensor(t["vel"], dtype=torch.float32), atol=2e-6, rtol=0)
    # Size and mass: the formulas on token values against MuJoCo's compiled models.
    torch.testing.assert_close(inputs.size, robot_size(t["models"]), atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(inputs.mass, robot_mass(t["models"]), atol=1e-5, rtol=1e-6)
    # The query's targets are the motion's at the query's steps.
    torch.testing.assert_close(
        query.target_pos, torch.tensor(t["motion"].pos[query.steps.numpy()], dtype=torch.float32)
    )
    # The reward: (T / S) x the reward of the ground-truth inputs over the S steps.
    ref = RewardInputs(
        torch.tensor(t["ee_pos"]),
        torch.tensor(t["ee_quat"]),
        query.target_pos.double(),
        query.target_quat.double(),
        torch.tensor(t["force"]),
        torch.tensor(t["vel"]),
        robot_size(t["models"], dtype=torch.float64),
        robot_mass(t["models"], dtype=torch.float64),
    )
    for name in ("tracking", "tracking_torque", "tracking_velocity", "tracking_size", "tracking_weight"):
        cfg = get_reward(name, "viperx")
        got = PredictedReward(t["layout"], t["norm"], cfg, query)(t["x0"])
        want = t["motion"].steps / S * evaluate(ref, cfg).reward
        torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-3, msg=name)


def test_perfect_tracking_scores_the_motion_length(truth):
    """Predicted poses on the targets: every step scores 1, so tracking = T; the size penalty
    is T alpha max(size - target, 0) (the paper's formula, alpha 0.1, target 2.0 m)."""
    t = truth
    B = len(t["models"])
    query = build_query(t["layout"], t["norm"], t["motion"], B)
    raw = torch.cat([query.target_pos[:, :, 0], query.target_quat.new_zeros(B, S, 9)], -1)
    raw[..., 3:] = torch.tensor(
        Rotation.from_quat(np.roll(query.target_quat.reshape(-1, 4).numpy(), -1, axis=-1)).as_matrix().reshape(B, S, 9),
        dtype=torch.float32,
    )
    x0 = dict(t["x0"], track_link_obs=t["norm"].normalize_values("track_link_obs", raw))
    T = t["motion"].steps
    tracking = PredictedReward(t["layout"], t["norm"], get_reward("tracking", "viperx"), query)(x0)
    torch.testing.assert_close(tracking, torch.full((B,), float(T)), rtol=1e-5, atol=0)
    size = robot_size(t["models"])
    sized = PredictedReward(t["layout"], t["norm"], get_reward("tracking_size", "viperx"), query)(x0)
    torch.testing.assert_close(sized, T - T * 0.1 * (size - 2.0).clamp_min(0), rtol=1e-5, atol=1e-3)
    # The guidance alpha (0.005) replaces 0.1 when asked.
    guided = PredictedReward(t["layout"], t["norm"], get_reward("tracking_size", "viperx"), query)(x0, guidance=True)
    torch.testing.assert_close(guided, T - T * 0.005 * (size - 2.0).clamp_min(0), rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("T", [1, 2, 3])
def test_a_motion_shorter_than_the_window_scores_its_own_steps(truth, T):
    """A motion of T < S steps: the query takes its T steps, then the last repeated, and the
    reward scores the T steps alone, as `tt validate` scores the simulated episode: perfect
    tracking there scores T whatever the window's later slots hold, ``length`` is T and
    ``survival`` 1; a miss at step T - 1 terminates there; the size penalty is T alpha excess."""
    from tt.guidance.predicted import predicted_metrics, scored_steps
    from tt.sim.motions.base import Motion

    t = truth
    B = len(t["models"])
    full = t["motion"]
    motion = Motion(f"{full.name}_{T}", full.pos[:T], full.quat[:T], full.dt)
    assert scored_steps(T, S) == T and scored_steps(full.steps, S) == S
    for placement in ("even", "start", "random"):
        steps = query_steps(T, S, 1, placement=placement, generator=torch.Generator().manual_seed(0))[0]
        assert steps.tolist() == [min(k, T - 1) for k in range(S)], placement
    query = build_query(t["layout"], t["norm"], motion, B)
    assert query.scored == T
    rot = (
        Rotation.from_quat(np.roll(query.target_quat.reshape(-1, 4).numpy(), -1, axis=-1)).as_matrix().reshape(B, S, 9)
    )
    raw = torch.cat([query.target_pos[:, :, 0], torch.tensor(rot, dtype=torch.float32)], -1)
    raw[:, T:, :3] += 10.0  # the window's later slots far off: no step of the motion, not scored
    x0 = dict(t["x0"], track_link_obs=t["norm"].normalize_values("track_link_obs", raw))
    scorer = PredictedReward(t["layout"], t["norm"], get_reward("tracking", "viperx"), query)
    torch.testing.assert_close(scorer(x0), torch.full((B,), float(T)), rtol=1e-5, atol=0)
    m = predicted_metrics(scorer, x0)
    assert m["length"].tolist() == [T] * B and m["survival"].tolist() == [1.0] * B
    assert m["within_2cm"].tolist() == [1.0] * B and float(m["query_pos_err"].max()) < 1e-3
    size = robot_size(t["models"])
    sized = PredictedReward(t["layout"], t["norm"], get_reward("tracking_size", "viperx"), query)(x0)
    torch.testing.assert_close(sized, T - T * 0.1 * (size - 2.0).clamp_min(0), rtol=1e-5, atol=1e-3)
    # The reward of the same poses as `tt validate` scores them: T steps, no window.
    inputs = scorer.inputs(x0)
    sim = RewardInputs(
        inputs.ee_pos[:, :T].double(),
        inputs.ee_quat[:, :T].double(),
        torch.tensor(motion.pos, dtype=torch.float64),
        torch.tensor(motion.quat, dtype=torch.float64),
    )
    torch.testing.assert_close(
        scorer(x0).double(), evaluate(sim, get_reward("tracking", "viperx")).reward, rtol=1e-5, atol=1e-5
    )
    raw[:, T - 1, :3] += 10.0  # a miss at the motion's last step ends the count there
    x0 = dict(t["x0"], track_link_obs=t["norm"].normalize_values("track_link_obs", raw))
    m = predicted_metrics(scorer, x0)
    assert m["length"].tolist() == [T - 1] * B and m["survival"].tolist() == [0.0] * B


def test_padding_slots_do_not_count(truth):
    """Actuator slots the robot does not use are padding (PAD_VALUE) and contribute no torque,
    whatever their observation tokens hold."""
    t = truth
    B = len(t["models"])
    query = build_query(t["layout"], t["norm"], t["motion"], B)
    x0 = dict(t["x0"])
    noisy = x0["actuator_obs"].clone()
    P = x0["actuator"].shape[1]
    pad = ~torch.tensor(t["used"]).repeat_interleave(1, 0)[:, None, :].expand(B, S, P).reshape(B, S * P)
    noisy[pad] = 0.7  # a large value in unused slots
    x0["actuator_obs"] = noisy
    inputs = PredictedReward(t["layout"], t["norm"], get_reward("tracking_torque", "viperx"), query).inputs(x0)
    assert bool((inputs.act_force.reshape(B, S * P)[pad] == 0).all())
    assert bool((x0["actuator"][~torch.tensor(t["used"])] == PAD_VALUE).all())


def test_predicted_reward_gradient_matches_finite_differences(truth):
    """The gradient DGS follows, against central differences (float64, every term active)."""
    t = truth
    B = len(t["models"])
    query = build_query(t["layout"], t["norm"], t["motion"], B)
    cfg = RewardConfig(
        name="tracking",
        space="viperx",
        torque_alpha=5e-5,
        velocity_alpha=0.1,
        size_alpha=0.1,
        size_target=0.5,
        mass_alpha=10.0,
        mass_target=0.5,
    )
    scorer = PredictedReward(t["layout"], t["norm"], cfg, query)
    base = {k: v.double() for k, v in t["x0"].items()}
    # Real designs sit on kinks of the formulas: massless links (sites) decode to exactly
    # 0 kg, the decoder's clip, and the ViperX joint cylinders have radius = half-length, a
    # tie of max(r, h). A random nudge of 1e-3 to 2e-3 (normalised) moves every link value
    # off them (ties by ~3e-5 m, far beyond the 1e-6 difference step).
    g = torch.Generator().manual_seed(5)
    base["link"] = base["link"] + 1e-3 * (1 + torch.rand(base["link"].shape, generator=g, dtype=torch.float64))
    names = ("track_link_obs", "actuator_obs", "link")

    def f(track, act, link):
        return scorer(dict(base, track_link_obs=track, actuator_obs=act, link=link))

    args = tuple(base[n].clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_training_padding_carries_the_ids_a_generation_query_gives():
    # Three ViperX designs of 5, 6 and 7 DoF: the tokenizer pads the shorter ones with ID 0,
    # where a generation query (the robot does not exist yet) gives every slot its positional
    # ID. `with_slot_ids` (applied to every training batch) makes the two agree, so the IDs
    # cannot tell the model which slots are padding.
    from tt.dit.layout import with_slot_ids

    space = get_space("viperx")
    by_dof = {}
    for d in space.sample(60, seed=0):
        by_dof.setdefault(space.model(d).nu, d)
    assert sorted(by_dof) == [5, 6, 7]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models([space.model(by_dof[k]) for k in (5, 6, 7)]).tokens
    counts = {n: int(np.asarray(emb.mask[n]).sum(1).max()) for n in emb.types}
    counts.update(track_link_obs=1, target_pose=1, actuator_obs=7, dyna_joint_obs=7, control=7)
    layout = layout_from_schema(counts, steps=S)
    emb = emb.pad_to({n: layout[n].length for n in emb.types}).to_torch()
    motion = for_space([get_motion("toss")], "viperx")[0]
    target = TokenBatch(
        {"target_pose": np.random.default_rng(0).normal(size=(4, S, 12)).astype(np.float32)},
        {"target_pose": np.zeros((4, S, 2), np.int64)},
        {"target_pose": np.ones((4, S), bool)},
    )
    query = build_query(layout, Normalizer.fit([emb, target]), motion, 3).tokens
    train = query.clone()
    names = [s.name for s in layout.specs if not s.per_step]
    for n in names:
        train.ids[n], train.mask[n] = emb.ids[n].clone(), emb.mask[n].clone()
    padded = [n for n in names if not bool(train.mask[n].all())]
    assert set(padded) >= {"link", "dyna_joint", "actuator"}
    assert not all(torch.equal(train.ids[n], query.ids[n]) for n in padded)  # zero IDs in the padding

    fixed = with_slot_ids(layout, train)
    for n in names:
        assert torch.equal(fixed.ids[n], query.ids[n]), n
        real = train.mask[n]
        assert torch.equal(fixed.ids[n][real], train.ids[n][real]), n  # real tokens keep their IDs
    for n in layout.names:
        if layout[n].per_step:
            assert torch.equal(fixed.ids[n], train.ids[n]), n


def test_design_query_holds_the_tokens_training_gives_those_designs():
    # Inpainting asks the motion-to-robot model for the dynamics of given designs; their
    # embodiment slots must look exactly as in a training batch of those designs
    # (normalised values, PAD_VALUE and positional IDs in the padding), and be marked known.
    from tt.dit.layout import with_slot_ids
    from tt.guidance.predicted import design_query
    from tt.tokens.batch import TokenBatch

    space = get_space("viperx")
    by_dof = {}
    for d in space.sample(60, seed=1):
        by_dof.setdefault(space.model(d).nu, d)
    models = [space.model(by_dof[k]) for k in (7, 5, 6)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models(models).tokens
    counts = {n: int(np.asarray(emb.mask[n]).sum(1).max()) for n in emb.types}
    counts.update(track_link_obs=1, target_pose=1, actuator_obs=7, dyna_joint_obs=7, control=7)
    layout = layout_from_schema(counts, steps=S)
    emb = emb.pad_to({n: layout[n].length for n in emb.types}).to_torch()
    target = TokenBatch(
        {"target_pose": np.random.default_rng(0).normal(size=(4, S, 12)).astype(np.float32)},
        {"target_pose": np.zeros((4, S, 2), np.int64)},
        {"target_pose": np.ones((4, S), bool)},
    )
    norm = Normalizer.fit([emb, target])
    motion = for_space([get_motion("toss")], "viperx")[0]
    query, known = design_query(layout, norm, motion, models)
    plain = build_query(layout, norm, motion, 3)
    names = [s.name for s in layout.specs if not s.per_step]
    assert sorted(known) == sorted(names)
    training = norm.normalize(
        with_slot_ids(
            layout,
            TokenBatch(
                {n: emb.values[n] for n in names}, {n: emb.ids[n] for n in names}, {n: emb.mask[n] for n in names}
            ),
        )
    )
    for n in names:
        assert known[n].all()
        torch.testing.assert_close(query.tokens.values[n], training.values[n].float(), rtol=0, atol=0, msg=n)
        assert torch.equal(query.tokens.ids[n], training.ids[n]), n
        assert (query.tokens.values[n][~emb.mask[n]] == PAD_VALUE).all(), n
    for n in layout.names:  # everything else is the plain query's
        if n not in names:
            assert torch.equal(query.tokens.values[n], plain.tokens.values[n]) and torch.equal(
                query.tokens.ids[n], plain.tokens.ids[n]
            ), n
