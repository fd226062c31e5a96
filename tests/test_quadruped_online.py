"""``tt train --online --space quadruped``: online training rolls a space with contacts out on
the ``mjbatch`` backend, as `tt generate` does. A refresh's episodes equal, byte for byte,
the ones `tt generate` stores for the same designs and motions; online selection picks what
`select_episodes` picks from an independent mjbatch rollout; a tiny run trains, refreshes and
checkpoints."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from tt.dit.online import OnlineConfig, OnlineTokenSource
from tt.tokens.draws import DEFAULT_ACTION_NOISE, GenerateConfig, _rng, _seed_int, episode_motion, training_motions

#: 4 designs x 2 augmented training motions cut to 40 control steps, 20 kept at least.
CONFIG = OnlineConfig(
    space="quadruped", designs=4, motions=2, refresh_every=2, buffer=2, min_steps=20, max_motion_steps=40
)

pytestmark = pytest.mark.usefixtures("single_thread")


def test_contact_spaces_roll_out_on_mjbatch_unperturbed_by_default():
    """The backend and the default control perturbation are `tt generate`'s for the space."""
    assert CONFIG.backend == "mjbatch" and CONFIG.action_noise == 0.0
    assert CONFIG.generate_config().backend == "mjbatch"
    viperx = OnlineConfig(space="viperx")
    assert viperx.backend == "warp" and viperx.action_noise == DEFAULT_ACTION_NOISE
    assert replace(CONFIG, action_noise=0.01).generate_config().action_noise == 0.01  # mjbatch perturbs too


def _shard(tmp_path, cfg: GenerateConfig):
    """Shard 0 of a `tt generate` dataset of `cfg` (one group): its designs, motions and reader."""
    from tt.generate import generate, shard_design_list
    from tt.tokens.store import ShardReader, shard_dirs

    generate(cfg, tmp_path / "data", device="cpu", progress=False, threads=2)
    rng = _rng(cfg.seed, 0, 1, 0)  # tt generate's episode stream of shard 0, group 0
    base = training_motions(cfg.space)
    ids = rng.choice(len(base), size=cfg.episodes_per_design, replace=cfg.episodes_per_design > len(base))
    motions = [episode_motion(cfg, base[m], s) for m, s in zip(ids, rng.integers(0, 2**31, size=len(ids)))]
    return shard_design_list(cfg, 0), motions, ShardReader(shard_dirs(tmp_path / "data")[0])


@pytest.mark.parametrize("action_noise", [0.0, 0.02])
def test_refresh_equals_what_tt_generate_stores(tmp_path, monkeypatch, action_noise):
    """A refresh of the designs and motions of a `tt generate` shard (its noise seed too)
    stores the same tokens, byte for byte: every kept episode's length, embodiment tokens
    and every step's values, IDs and masks."""
    cfg = GenerateConfig(
        space="quadruped", designs=4, episodes_per_design=2, designs_per_shard=4, group_designs=4, min_steps=20,
        max_motion_steps=40, backend="mjbatch", action_noise=action_noise, seed=3,
    )  # fmt: skip
    designs, motions, shard = _shard(tmp_path, cfg)
    source = OnlineTokenSource(replace(CONFIG, action_noise=action_noise), device="cpu", threads=1)
    # The shard's designs, motions and noise seed (tt generate's stream 3 of shard 0, group 0)
    # in place of the refresh's own draws.
    monkeypatch.setattr(source, "draw", lambda k: (designs, motions))
    monkeypatch.setattr(source, "noise_seed", lambda k: _seed_int(cfg.seed, 0, 3, 0))
    refresh = source._refresh(0)

    block = shard.read_block(0, shard.episodes, fields=True)
    order = np.argsort(block.episode["episode_id"])  # world index: the online refresh's order
    assert len(refresh) == shard.episodes > 0
    assert refresh.lengths.tolist() == block.length[order].tolist()
    for e, s in enumerate(order):
        o, n = block.offset[s], block.length[s]
        for name, (v, i, m) in block.steps.items():
            assert np.array_equal(refresh.step_values[name][e, :n].numpy(), v[o : o + n]), (name, e)
            assert np.array_equal(refresh.step_ids[name][e].numpy(), i[s]), (name, e)
            assert np.array_equal(refresh.step_mask[name][e].numpy(), m[s]), (name, e)
        for name, (v, i, m) in block.static.items():
            d = block.design[s]
            assert np.array_equal(refresh.static_values[name][e].numpy(), v[d]), (name, e)
            assert np.array_equal(refresh.static_ids[name][e].numpy(), i[d]), (name, e)
            assert np.array_equal(refresh.static_mask[name][e].numpy(), m[d]), (name, e)
    assert set(refresh.step_values) == set(block.steps)


def test_online_selection_picks_from_the_mjbatch_episodes():
    """select 2: the refresh screens 8 designs on every motion and keeps, per motion, the 4
    best by reward of an independent mjbatch rollout of its designs and motions."""
    from tt.sim.rewards import RewardInputs, get_reward, metrics
    from tt.sim.rollout import rollout

    cfg = replace(CONFIG, select=2)
    source = OnlineTokenSource(cfg, device="cpu")
    refresh = source._refresh(0)
    designs, motions = source.draw(0)
    assert len(designs) == 8
    ep = rollout(designs, motions, backend="mjbatch", threads=2)
    steps = torch.tensor([m.steps for m in motions])[ep.motion_index]
    reward = metrics(
        RewardInputs.from_episode(ep, motion_steps=steps, double=True), get_reward("tracking", "quadruped")
    )["reward"]
    eligible = ep.lengths() >= cfg.min_steps
    want = []
    for m in range(len(motions)):
        worlds = [w for w in range(ep.worlds) if int(ep.motion_index[w]) == m and bool(eligible[w])]
        best = sorted(worlds, key=lambda w: (-float(reward[w]), w))[: cfg.designs]
        want += [(int(ep.design_index[w]), m) for w in best]
    assert sorted(source.selected[0]) == sorted(want)
    assert len(refresh) == len(want) and source.stats["screened"] == 16


def test_tiny_online_run_trains_refreshes_and_checkpoints(tmp_path):
    from tt.dit.checkpoint import load_checkpoint
    from tt.dit.train import TrainConfig, train

    config = TrainConfig(
        out=str(tmp_path / "run"), size="tiny", task="both", batch_size=4, steps=5, warmup_steps=2, lr=3e-3,
        device="cpu", window=4, checkpoint_every=2, online=CONFIG,
    )  # fmt: skip
    result = train(config)
    assert result.step == 5 and bool(torch.isfinite(result.losses).all())
    state = load_checkpoint(result.checkpoint)
    assert int(state["step"]) == 5
    assert TrainConfig.from_dict(state["train_config"]).online == CONFIG
    # Steps 0-1 read refresh 0, 2-3 refresh 1, 4 refresh 2: three refreshes were generated.
    source = OnlineTokenSource(CONFIG, device="cpu")
    source.start_step(4)
    assert sorted(source._refreshes) == [1, 2]


def test_tt_train_online_space_quadruped(tmp_path):
    """The command the issue names, `tt train --online --space quadruped`, trains on quadruped
    episodes (the flag wins over --config's online.space); --space without --online is refused."""
    from typer.testing import CliRunner

    from tt.cli import app
    from tt.dit.checkpoint import load_checkpoint
    from tt.dit.train import TrainConfig

    small = [
        f"online.{k}={v}"
        for k, v in dict(designs=2, motions=1, refresh_every=2, min_steps=20, max_motion_steps=40).items()
    ]
    args = ["train", "--online", "--space", "quadruped", "--size", "tiny", "--steps", "2", "--batch-size", "4"]
    args += ["--device", "cpu", "--out", str(tmp_path / "run"), "--config", "online.space=viperx"]
    args += [x for item in small for x in ("--config", item)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    state = load_checkpoint(tmp_path / "run" / "checkpoints" / "step_0000002.pt")
    assert state["space"] == "quadruped"
    assert TrainConfig.from_dict(state["train_config"]).online.space == "quadruped"
    r = CliRunner().invoke(app, ["train", "--space", "quadruped", "--out", str(tmp_path / "other")])
    assert r.exit_code != 0 and "--space picks the design space of online training" in r.output
