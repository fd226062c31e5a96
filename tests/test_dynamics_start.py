"""The critic told the episode's start (`tt train --dynamics-start`): windows that hold step 0,
step 0 a clean condition of the dynamics task, a one-step rollout that is the full rollout's
first step bit for bit, start tokens that carry the simulated start, and `predict_designs`
end to end on a model trained that way."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tt.dit.checkpoint import load_model
from tt.dit.data import EpisodeTokens
from tt.dit.layout import with_slot_ids
from tt.dit.loader import window_steps
from tt.dit.online import OnlineConfig, OnlineTokenSource
from tt.dit.tasks import TaskSpec, task_masks
from tt.dit.train import TrainConfig, train
from tt.guidance.predicted import predict_designs, query_steps, start_tokens
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import get_reward
from tt.sim.rollout import _RECORDED, rollout_records
from tt.tokens.schema import SCHEMA, STEP_ROLES, Role

CONFIG = OnlineConfig(
    space="viperx", designs=6, motions=2, refresh_every=2, buffer=2, min_steps=20, max_motion_steps=40
)

pytestmark = pytest.mark.usefixtures("single_thread")


def _toss(steps: int = 40):
    toss = for_space([get_motion("toss")], "viperx")[0]
    return type(toss)(f"toss[:{steps}]", toss.pos[:steps], toss.quat[:steps], toss.dt)


def test_start_windows_hold_step_0_and_distinct_others():
    lengths = torch.tensor([8, 9, 30, 200])
    gen = torch.Generator().manual_seed(0)
    for steps in (window_steps(lengths, 8, "start", gen),):
        assert (steps[:, 0] == 0).all()
        assert (steps.diff(dim=1) > 0).all() and (steps < lengths[:, None]).all()
    # The in-memory source draws the same way.
    src = OnlineTokenSource(CONFIG, device="cpu")
    src.start_step(0)
    data: EpisodeTokens = src._refresh(0)
    idx = data.window_steps(torch.arange(len(data)), 8, "start", torch.Generator().manual_seed(1))
    assert (idx[:, 0] == 0).all() and (idx.diff(dim=1) > 0).all()
    assert (idx[:, 1:] > 0).any(dim=0).all()  # the other steps are drawn, not fixed


def test_start_window_is_the_dynamics_tasks_only():
    with pytest.raises(ValueError, match="dynamics task's only"):
        TaskSpec("robot", 100, "start")
    with pytest.raises(ValueError, match="needs the dynamics task"):
        TrainConfig(out="x", task="robot", dynamics_start=True, online=CONFIG)


def test_step_0_is_a_clean_condition_of_the_start_task():
    src = OnlineTokenSource(CONFIG, device="cpu")
    src.start_step(0)
    layout = src.layout(8)
    raw = with_slot_ids(layout, src.sample(5, 8, "start", torch.Generator().manual_seed(2)))
    start = task_masks(TaskSpec("dynamics", 100, "start"), layout, raw)
    plain = task_masks(TaskSpec("dynamics", 100, "random"), layout, raw)
    for spec in layout.specs:
        if spec.role in STEP_ROLES and spec.role is not Role.CONDITION:
            at_0 = raw.ids[spec.name][..., spec.time_index] == 0
            assert at_0.sum(1).eq(spec.per_step).all()  # exactly step 0's slots
            assert not start.noised[spec.name][at_0].any() and start.noised[spec.name][~at_0].all()
            assert plain.noised[spec.name].all()
        else:
            assert torch.equal(start.noised[spec.name], plain.noised[spec.name])


def test_first_steps_of_a_rollout_are_the_full_rollouts_bit_for_bit():
    space = get_space("viperx")
    designs = space.sample(5, seed=4)  # several topologies
    motions = [_toss(40), _toss(30)]
    full = rollout_records(space.trees(designs), space.ee_sites(), motions, device="cpu")
    first = rollout_records(space.trees(designs), space.ee_sites(), motions, device="cpu", steps=3)
    assert [m for m, _ in full] == [m for m, _ in first]
    for (_, a), (_, b) in zip(full, first):
        for name in _RECORDED:
            x, y = getattr(a, name).numpy(), getattr(b, name).numpy()
            assert y.shape[1] == 3
            assert np.array_equal(x[:, :3], y, equal_nan=True), name
    with pytest.raises(ValueError, match="must be 1 .. 40"):
        rollout_records(space.trees(designs), space.ee_sites(), motions, device="cpu", steps=41)


@pytest.fixture(scope="module")
def start_model(tmp_path_factory):
    out = tmp_path_factory.mktemp("start")
    cfg = TrainConfig(
        out=str(out),
        size="tiny",
        task="dynamics",
        dynamics_start=True,
        prediction="x0",
        batch_size=4,
        steps=3,
        warmup_steps=1,
        lr=3e-3,
        device="cpu",
        checkpoint_every=1000,
        online=CONFIG,
    )
    train(cfg)
    return load_model(out)


def test_start_tokens_carry_the_simulated_start(start_model):
    space = get_space("viperx")
    designs = space.sample(4, seed=5)
    motion = _toss(40)
    layout, norm = start_model.layout, start_model.normalizer
    motions = [motion, _toss(30)]
    tokens = start_tokens(layout, norm, designs, motions)
    assert set(tokens) == {s.name for s in layout.specs if s.role in STEP_ROLES and s.role is not Role.CONDITION}
    # Reference: the end effector at step 0 of the full rollout, design by design, motion by motion.
    full = rollout_records(space.trees(designs), space.ee_sites(), motions, device="cpu")
    ee = np.zeros((len(motions), len(designs), 3))
    for members, arrays in full:
        ee[:, members] = arrays.ee_pos.numpy()[:, 0, 0].reshape(len(members), len(motions), 3).transpose(1, 0, 2)
    track = norm.denormalize_values("track_link_obs", tokens["track_link_obs"])[:, :, 0]  # (M, D, dim): slot 0
    pos = track[..., SCHEMA["track_link_obs"].slice("pos")].numpy()
    # float32 tokens of metre-scale positions through min-max normalisation and back.
    np.testing.assert_allclose(pos, ee, atol=1e-5)


def test_predict_designs_from_the_start(start_model):
    assert start_model.dynamics_start
    steps = query_steps(100, 8, 2, placement="start")
    assert (steps[:, 0] == 0).all() and torch.equal(steps[0, 1:], query_steps(100, 8, 1)[0, 1:])
    space = get_space("viperx")
    designs = space.sample(3, seed=6)
    pred = predict_designs(start_model, designs, [_toss(40)], get_reward("tracking", "viperx"), num_steps=2, samples=2)
    assert pred.reward.shape == (3, 1) and np.isfinite(pred.reward).all()


_FRESH_PROCESS = """
import sys
from tt.dit.checkpoint import load_model
from tt.guidance.predicted import predict_designs
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import get_reward
toss = for_space([get_motion("toss")], "viperx")[0]
toss = type(toss)("toss[:20]", toss.pos[:20], toss.quat[:20], toss.dt)
pred = predict_designs(load_model(sys.argv[1]), get_space("viperx").sample(2, seed=6), [toss],
                       get_reward("tracking", "viperx"), num_steps=2)
print(pred.reward.shape)
"""


def test_predict_designs_from_the_start_in_a_fresh_process(start_model):
    """A start-aware prediction is the first Warp use of a process (as in
    benchmarks/dit_ladder.py): it initialises Warp itself before mapping the torch device."""
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-c", _FRESH_PROCESS, str(start_model.path)], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "(2, 1)"


def test_zeroth_order_asks_a_start_aware_critic_about_decoded_designs(start_model):
    """A critic trained told the start is, by default, asked about the decoded designs
    (the only candidates whose first step can be simulated) and ranks them by exactly
    `predict_designs`' reward; asking it about sampled tokens is refused."""
    import dataclasses

    from tt.baselines.problem import Problem
    from tt.guidance.zeroth import SamplerConfig, ZerothOrder

    # The sampling model: the same network retitled as trained on the robot task too, so it
    # samples embodiments; the critic is the start-aware model itself.
    sampler = dataclasses.replace(start_model, tasks=("robot", "dynamics"), dynamics_start=False, path=None)
    motion = _toss(40)
    problem = Problem("viperx", (motion,), "tracking", 3, seed=2, backend="warp", device="cpu")
    res = ZerothOrder(SamplerConfig(num_steps=2, decode="all"), model=sampler, critic_model=start_model).optimize(
        problem
    )
    assert res.info["critic_on"] == "designs" and res.info["critic"] == "dynamics"
    order = res.info["ranking"]
    by_index = [res.designs[order.index(i)] for i in range(len(order))]
    pred = predict_designs(start_model, by_index, [motion], get_reward("tracking", "viperx"), num_steps=2, seed=2)
    np.testing.assert_allclose(res.rewards, pred.reward[order, 0], rtol=1e-6)
    with pytest.raises(ValueError, match="trained told the episode's start"):
        ZerothOrder(SamplerConfig(num_steps=2, critic_on="tokens"), model=sampler, critic_model=start_model).optimize(
            problem
        )
    # A critic not told the start keeps the tokens default.
    plain = dataclasses.replace(start_model, dynamics_start=False)
    assert ZerothOrder(SamplerConfig(), model=sampler, critic_model=plain).critic_input() == "tokens"


def test_quadruped_start_is_the_full_mjbatch_episodes_first_step():
    """A space with contacts takes its start from mjbatch on motions cut after the first
    look-ahead target; step 0 of every recorded field equals the full episode's."""
    from tt.guidance.predicted import _mjbatch_first_step
    from tt.sim.motions import motion_set
    from tt.sim.rollout import rollout

    space = get_space("quadruped")
    designs = space.sample(3, seed=2)  # three structures
    models = [space.model(d) for d in designs]
    placed = for_space(motion_set("val", arms=1)[:2], "quadruped")
    motions = [type(m)(m.name, m.pos[:30], m.quat[:30], m.dt) for m in placed]
    full = rollout(models, motions, backend="mjbatch", device="cpu")
    first = _mjbatch_first_step(models, motions)
    assert first.qpos.shape[1] < 10
    for name in ("qpos", "qvel", "ctrl", "action", "act_force", "ee_pos", "ee_quat", "target_pos", "alive"):
        x, y = getattr(full, name)[:, 0], getattr(first, name)[:, 0]
        assert torch.equal(x, y), name
