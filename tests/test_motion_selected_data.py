"""Motion-selected training data (issue 51): every kept episode's design was chosen for that
episode's motion, the uniform share holds, and selected datasets resume bit for bit.

The reference for the selection is an independent rollout of the whole screen (the public
`rollout` with the same noise seed) scored by `tt.sim.rewards.metrics`, ranked here with
numpy, not with `select_episodes`."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch

from tt.generate import GenerateConfig, generate
from tt.sim.designs import get_space
from tt.sim.motions import augment_motion, for_space, motion_set
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardInputs, get_reward, metrics
from tt.sim.rollout import rollout
from tt.tokens.draws import select_episodes
from tt.tokens.store import TokenStore, shard_dirs

#: 2 shards of 8 designs, one rollout group each, 2 motions cut to 40 steps; each motion keeps 2 of 8.
CONFIG = GenerateConfig(
    space="viperx",
    designs=16,
    episodes_per_design=2,
    designs_per_shard=8,
    group_designs=8,
    min_steps=20,
    max_motion_steps=40,
    select=4,
)


def _rewards(designs, motions, config, noise_seed: int) -> np.ndarray:
    """(D, M) reward of every design on every motion: one independent rollout of the screen."""
    ep = rollout(designs, motions, device="cpu", action_noise=config.action_noise, noise_seed=noise_seed)
    steps = torch.tensor([m.steps for m in motions])[ep.motion_index]
    inputs = RewardInputs(
        ep.ee_pos.double(),
        ep.ee_quat.double(),
        ep.target_pos.double(),
        ep.target_quat.double(),
        act_force=ep.act_force.double(),
        act_vel=ep.act_vel.double(),
        alive=ep.alive,
        fallen=ep.fallen,
        motion_steps=steps,
    )
    return (
        metrics(inputs, get_reward(config.reward, config.space))["reward"].numpy().reshape(len(designs), len(motions))
    )


def test_select_episodes_keeps_each_motions_best_and_its_uniform_share():
    rng = np.random.default_rng(0)
    reward = rng.normal(size=40)
    motion = np.repeat(np.arange(4), 10)
    eligible = np.ones(40, bool)
    eligible[[3, 17]] = False
    best = select_episodes(reward, motion, eligible, 3, 0.0, None)
    for m in range(4):
        ok = np.nonzero((motion == m) & eligible)[0]
        want = set(ok[np.argsort(-reward[ok])[:3]].tolist())
        assert set(np.nonzero(best & (motion == m))[0].tolist()) == want
    mixed = select_episodes(reward, motion, eligible, 4, 0.5, np.random.default_rng(1))
    for m in range(4):
        kept = np.nonzero(mixed & (motion == m))[0]
        ok = np.nonzero((motion == m) & eligible)[0]
        top2 = set(ok[np.argsort(-reward[ok])[:2]].tolist())
        assert len(kept) == 4 and top2 <= set(kept.tolist()) and eligible[kept].all()
    with pytest.raises(ValueError, match="uniform share"):
        select_episodes(reward, motion, eligible, 3, 1.5, None)


@pytest.fixture(scope="module")
def selected(tmp_path_factory):
    path = tmp_path_factory.mktemp("sel") / "data"
    generate(CONFIG, path, device="cpu", progress=False)
    return path


def test_every_kept_episode_was_selected_on_its_own_motion(selected):
    from tt.tokens.draws import _STREAM_NOISE, _seed_int

    sp = get_space("viperx")
    base = motion_set("train", arms=1)
    store = TokenStore(selected)
    keep = CONFIG.group_keep(CONFIG.group_designs)
    assert keep == 2
    for shard, reader in enumerate(store.readers):
        designs = reader.designs(sp)
        block = reader.read_block(0, reader.episodes, fields=True)
        rows = reader.field("design")[: reader.episodes].astype(
            int
        )  # the shard's design rows (block.design is relative)
        K = CONFIG.episodes_per_design
        slot = (block.episode["episode_id"] - shard * CONFIG.designs_per_shard * K) % K
        motions = {}
        for e in range(len(block)):
            m = augment_motion(
                base[int(block.episode["motion"][e])],
                int(block.episode["augment_seed"][e]),
                max_yaw=CONFIG.max_yaw,
                max_shift=CONFIG.max_shift,
            )
            m = for_space([m], "viperx")[0]
            motions[int(slot[e])] = Motion(m.name, m.pos[:40], m.quat[:40], m.dt)
        assert sorted(motions) == list(range(K))
        reward = _rewards(
            designs, [motions[k] for k in range(K)], CONFIG, _seed_int(CONFIG.seed, shard, _STREAM_NOISE, 0)
        )
        for k in range(K):
            kept = sorted(int(d) for d in rows[slot == k])
            assert sorted(np.argsort(-reward[:, k], kind="stable")[:keep].tolist()) == kept, (
                f"shard {shard}, motion {k}"
            )
            np.testing.assert_allclose(np.sort(block.episode["reward"][slot == k]), np.sort(reward[kept, k]), rtol=1e-5)
        dropped = reader.attrs["dropped"]
        assert reader.episodes == K * keep and sum(dropped.values()) + reader.episodes == reader.attrs["generated"]


def test_a_selected_dataset_resumes_to_the_uninterrupted_one(selected, tmp_path):
    path = tmp_path / "again"
    shutil.copytree(selected, path)
    shutil.rmtree(shard_dirs(path)[1])
    generate(CONFIG, path, device="cpu", progress=False)
    a, b = TokenStore(selected, verify="full"), TokenStore(path, verify="full")
    assert a.episode_digests() == b.episode_digests()
    for i, folder in shard_dirs(selected).items():
        assert (folder / "manifest.json").read_bytes() == (shard_dirs(path)[i] / "manifest.json").read_bytes()


def test_the_uniform_share_holds_in_a_dataset(tmp_path):
    cfg = GenerateConfig(
        space="viperx",
        designs=8,
        episodes_per_design=2,
        designs_per_shard=8,
        group_designs=8,
        min_steps=20,
        max_motion_steps=40,
        select=2,
        uniform_share=0.5,
    )
    generate(cfg, tmp_path / "u", device="cpu", progress=False)
    reader = TokenStore(tmp_path / "u").readers[0]
    block = reader.read_block(0, reader.episodes, fields=True)
    slot = block.episode["episode_id"] % 2
    for k in range(2):
        # 4 kept per motion: 2 best, 2 drawn uniformly from the other 6.
        assert int((slot == k).sum()) == cfg.group_keep(8) == 4


def test_selection_settings_are_checked():
    with pytest.raises(ValueError, match=r"select= must be an integer >= 1"):
        GenerateConfig(space="viperx", designs=8, select=0)
    with pytest.raises(ValueError, match=r"uniform_share= applies only with select= above 1"):
        GenerateConfig(space="viperx", designs=8, uniform_share=0.2)
    assert "select" not in GenerateConfig(space="viperx", designs=8).to_dict()  # unselected roots unchanged


def test_online_refresh_keeps_each_motions_best_designs():
    from tt.dit.online import _STREAM_NOISE, OnlineConfig, OnlineTokenSource
    from tt.tokens.draws import _seed_int

    cfg = OnlineConfig(
        space="viperx", designs=2, motions=2, select=3, max_motion_steps=40, min_steps=20, absorbing=True
    )
    src = OnlineTokenSource(cfg, device="cpu")
    tokens = src._refresh(0)
    assert len(tokens) == cfg.designs * cfg.motions
    designs, motions = src.draw(0)
    assert len(designs) == 6
    reward = _rewards(designs, motions, cfg.generate_config(), _seed_int(cfg.seed, 0, _STREAM_NOISE))
    chosen = src.selected[0]  # (design, motion) pairs kept
    for m in range(cfg.motions):
        want = sorted(np.argsort(-reward[:, m], kind="stable")[: cfg.designs].tolist())
        assert sorted(d for d, mm in chosen if mm == m) == want
    assert math.isclose(src.stats["screened"], 12)
