"""RoboToken dataset store and loaders: shard integrity checks, statistics, windows,
SE(2) augmentation against a re-tokenized moved robot, DataLoader batches and the
``tt train`` token source."""

from __future__ import annotations

import json
import math
import shutil

import mujoco
import numpy as np
import pytest
import torch

from tt.dit.loader import SE2Augment, StoreTokenSource, augment_se2_tokens, make_loader, window_steps
from tt.generate import GenerateConfig, generate
from tt.kernels.rotations import quat_to_mat
from tt.sim.designs import get_space
from tt.sim.motions import augment_se2
from tt.tokens import SCHEMA, Normalizer, TokenBatch, tokenize_model
from tt.tokens.store import (
    ShardPart,
    ShardReader,
    ShardWriter,
    TokenStore,
    shard_dirs,
    verify_shard,
)

#: Small and fast: 2 shards of 3 designs x 2 episodes on 48-step motions.
CONFIG = GenerateConfig(
    space="viperx", designs=6, episodes_per_design=2, designs_per_shard=3, min_steps=20, max_motion_steps=48
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("store") / "ds"
    generate(CONFIG, path, device="cpu", progress=False)
    return path


@pytest.fixture
def copy(dataset, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    return out


def _chunk_file(shard):
    """A chunk file of the shard's largest per-step array."""
    files = sorted(
        (shard / "dyna_joint_obs" / "values" / "c").rglob("*"), key=lambda p: p.stat().st_size if p.is_file() else 0
    )
    return files[-1]


def test_verify_detects_truncation_corruption_and_missing_manifest(copy):
    shards = shard_dirs(copy)
    s0, s1 = shards[0], shards[1]
    assert verify_shard(s0) is None and verify_shard(s1) is None
    full = TokenStore(copy).episodes
    n1 = TokenStore(copy).readers[1].episodes

    chunk = _chunk_file(s1)
    data = chunk.read_bytes()
    chunk.write_bytes(data[:-7])
    why = verify_shard(s1, full=False)
    assert why is not None and "truncated" in why
    store = TokenStore(copy)
    assert 1 in store.damaged and store.episodes == full - n1

    # Same size, one byte changed: only the CRC check sees it.
    chunk.write_bytes(data[:100] + bytes([data[100] ^ 0xFF]) + data[101:])
    assert verify_shard(s1, full=False) is None
    assert "CRC-32" in verify_shard(s1, full=True)

    chunk.write_bytes(data)
    assert verify_shard(s1) is None
    (s0 / "manifest.json").unlink()
    assert "no manifest" in verify_shard(s0)


def test_writer_without_commit_leaves_no_shard(tmp_path):
    (tmp_path / "shards").mkdir()
    part = ShardPart(
        np.zeros((1, 2)),
        np.zeros((1, 3)),
        {},
        {"design": np.zeros(2, np.int64), "length": np.array([3, 2])},
        {"control": (np.ones((5, 4, 1), np.float32), np.zeros((2, 4, 2)), np.ones((2, 4), bool))},
    )
    with pytest.raises(RuntimeError):
        with ShardWriter(tmp_path, 0) as w:
            w.append(part)
            raise RuntimeError("killed")
    assert shard_dirs(tmp_path) == {} and list((tmp_path / ".partial").iterdir()) == []
    with ShardWriter(tmp_path, 0) as w:
        w.append(part)
        w.commit({"generated": 2})
    r = ShardReader(shard_dirs(tmp_path)[0])
    block = r.read_block(0, 2)
    np.testing.assert_array_equal(block.offset, [0, 3])
    np.testing.assert_array_equal(r.index["step_start"], [0, 3])
    assert (r.attrs["length_min"], r.attrs["length_max"]) == (2, 3)
    with pytest.raises(ValueError, match="past an episode's length"):
        block.windows(np.array([1]), np.array([[0, 2]]))


def _all_tokens(store: TokenStore) -> TokenBatch:
    """Every real token of the dataset (all steps of all episodes, all robots) as one batch."""
    values, ids, mask = {}, {}, {}
    for r in store.readers:
        for name, (v, i, m) in r.static.items():
            values.setdefault(name, []).append(v.reshape(-1, 1, v.shape[-1]))
            mask.setdefault(name, []).append(m.reshape(-1, 1))
        block = r.read_block(0, r.episodes)
        rows = np.repeat(np.arange(len(block)), block.length)
        for name, (v, i, m) in block.steps.items():
            values.setdefault(name, []).append(v.reshape(-1, 1, v.shape[-1]))
            mask.setdefault(name, []).append(m[rows].reshape(-1, 1))
    values = {k: np.concatenate(v) for k, v in values.items()}
    mask = {k: np.concatenate(v) for k, v in mask.items()}
    ids = {k: np.zeros((*v.shape[:2], len(SCHEMA[k].ids)), np.int64) for k, v in values.items()}
    return TokenBatch(values, ids, mask)


def test_stored_statistics_equal_a_fit_over_all_tokens(dataset):
    store = TokenStore(dataset)
    assert store.attrs["complete"]
    stored = store.normalizer()
    reference = Normalizer.fit(_all_tokens(store))
    assert sorted(stored.low) == sorted(reference.low)
    for name in reference.low:
        np.testing.assert_array_equal(stored.low[name], reference.low[name], err_msg=name)
        np.testing.assert_array_equal(stored.high[name], reference.high[name], err_msg=name)


def _pose_tokens(name: str, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    t = SCHEMA[name]
    v = np.zeros((*pos.shape[:-1], t.width))
    v[..., t.slice("pos")] = pos
    v[..., t.slice("rot")] = quat_to_mat(quat).reshape(*pos.shape[:-1], 9)
    return v


def test_se2_augmentation_equals_tokens_of_the_moved_scene():
    """Reference: the tokenizer on the robot with its mount moved by g, and the world poses
    moved by `tt.sim.motions.augment_se2` (an independent implementation of the transform)."""
    sp = get_space("viperx")
    design = sp.sample(4, seed=11)[3]
    yaw, dx, dy = 0.9, 0.12, -0.07
    model = sp.model(design)
    moved = sp.model(design)
    qg = np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])
    rg = quat_to_mat(qg)
    for b in range(1, moved.nbody):
        if moved.body_parentid[b] == 0:  # bodies on the world: the mount
            moved.body_pos[b] = rg @ moved.body_pos[b] + [dx, dy, 0]
            q = np.zeros(4)
            mujoco.mju_mulQuat(q, qg, moved.body_quat[b])
            moved.body_quat[b] = q
    emb, emb_moved = tokenize_model(model).tokens, tokenize_model(moved).tokens
    rng = np.random.default_rng(0)
    pos = rng.uniform(-0.5, 0.5, (1, 5, 3))
    quat = rng.normal(size=(1, 5, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    pos_m, quat_m = augment_se2(pos, quat, yaw, dx, dy)

    values = {n: torch.as_tensor(emb.values[n], dtype=torch.float32) for n in emb.types}
    mask = {n: torch.as_tensor(emb.mask[n]) for n in emb.types}
    for name in ("track_link_obs", "target_pose"):
        values[name] = torch.as_tensor(_pose_tokens(name, pos, quat), dtype=torch.float32)
        mask[name] = torch.ones(1, 5, dtype=torch.bool)
    out = augment_se2_tokens(
        values,
        mask,
        torch.tensor([yaw], dtype=torch.float64),
        torch.tensor([dx], dtype=torch.float64),
        torch.tensor([dy], dtype=torch.float64),
    )
    changed = 0
    for name in emb.types:
        ref = emb_moved.values[name]
        np.testing.assert_allclose(out[name].numpy(), ref, atol=2e-6, err_msg=name)
        changed += int((np.abs(emb.values[name] - ref) > 1e-4).any())
    assert changed >= 1  # the mount's joint token did move
    for name in ("track_link_obs", "target_pose"):
        np.testing.assert_allclose(out[name].numpy(), _pose_tokens(name, pos_m, quat_m), atol=2e-6, err_msg=name)


def test_window_steps():
    g = torch.Generator().manual_seed(0)
    lengths = torch.tensor([8, 9, 50, 300])
    st = window_steps(lengths, 8, "random", g)
    assert st.shape == (4, 8)
    assert (st.diff(dim=1) > 0).all() and (st < lengths[:, None]).all() and (st >= 0).all()
    np.testing.assert_array_equal(st[0], np.arange(8))
    ct = window_steps(lengths, 8, "consecutive", g)
    assert (ct.diff(dim=1) == 1).all() and (ct[:, -1] < lengths).all()
    with pytest.raises(ValueError, match="fewer than the window"):
        window_steps(torch.tensor([7]), 8, "random", g)


def test_loader_batches_have_layout_shapes_and_padding_masks(dataset):
    src = StoreTokenSource(dataset)
    layout = src.layout(8)
    store = TokenStore(dataset)
    assert {s.name: s.length for s in layout.specs}["dyna_joint_obs"] == 8 * store.maxima["dyna_joint_obs"]
    for workers in (0, 2):
        seen = 0
        for batch in make_loader(dataset, batch_size=5, steps=8, kind="consecutive", workers=workers, seed=1):
            layout.check(batch)
            seen += len(batch)
            nu = batch.mask["actuator"].sum(1)  # actuators of each window's robot
            assert (batch.mask["control"].sum(1) == 8 * nu).all()
            assert (batch.mask["dyna_joint_obs"].sum(1) == 8 * nu).all()  # one actuator per joint
            for name, m in batch.mask.items():
                assert (batch.values[name][~m] == 0).all(), name  # padding stays zero
            t = batch.ids["control"][..., 1].reshape(len(batch), 8, -1)[:, :, 0]
            assert (t.diff(dim=1) == 1).all()  # consecutive time IDs
        assert seen == store.episodes  # one window per episode per epoch, split over workers


def test_token_source_is_deterministic_and_trains(dataset, tmp_path):
    from tt.dit.train import TrainConfig, train

    src = StoreTokenSource(dataset, windows_per_block=4)
    a = src.sample(9, 8, "random", torch.Generator().manual_seed(3))
    b = src.sample(9, 8, "random", torch.Generator().manual_seed(3))
    for name in a.values:
        assert torch.equal(a.values[name], b.values[name]) and torch.equal(a.ids[name], b.ids[name])
    src.layout(8).check(a)
    plain = StoreTokenSource(dataset, augment=None, windows_per_block=4).sample(
        9, 8, "random", torch.Generator().manual_seed(3)
    )
    assert not torch.equal(plain.values["target_pose"], a.values["target_pose"])  # augmentation is on by default
    identity = StoreTokenSource(dataset, augment=SE2Augment(0.0, 0.0), windows_per_block=4)
    same = identity.sample(9, 8, "random", torch.Generator().manual_seed(3))
    assert all(torch.equal(same.values[n], plain.values[n]) for n in plain.values)  # g = identity changes nothing
    torch.set_num_threads(1)
    result = train(
        TrainConfig(out=str(tmp_path / "run"), size="tiny", steps=2, batch_size=4, warmup_steps=1, device="cpu"),
        episodes=src,
    )
    assert result.step == 2 and torch.isfinite(result.losses).all()


def test_dataset_info_command(dataset, tmp_path, tt_cli):
    png = tmp_path / "rewards.png"
    code, text = tt_cli(["dataset", "info", str(dataset), "--plot", str(png)])
    assert code == 0, text
    store = TokenStore(dataset)
    assert f"episodes {store.episodes:,} kept" in text and "shards 2/2" in text and "dyna_joint_obs 7" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, out = tt_cli(["dataset", "info", str(dataset), "--json"])
    assert code == 0, out
    info = json.loads(out)
    assert info["episodes"] == store.episodes and info["complete"]
    assert info["episodes"] + sum(info["dropped"].values()) == info["episodes_generated"] == 12
    assert info["reward"]["n"] == store.episodes
