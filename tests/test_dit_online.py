"""``tt train --online``: the rollout's Warp arrays reach torch without a copy; the online
source's tokens equal the copying path's (`rollout` + `episode_tokens`) for the same
episodes; its layout is a dataset's; online training resumes exactly; the CLI refuses
ambiguous data sources."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from tt.dit.checkpoint import load_checkpoint
from tt.dit.layout import layout_from_schema
from tt.dit.online import _STREAM_DESIGNS, _STREAM_MOTIONS, _STREAM_NOISE, OnlineConfig, OnlineTokenSource
from tt.dit.train import TrainConfig, train
from tt.sim.designs import get_space
from tt.sim.rollout import _RECORDED, group_episode, rollout, rollout_records
from tt.tokens import episode_tokens, tokenize_models
from tt.tokens.draws import space_token_maxima

#: Small refreshes on motions cut to 40 steps (20 kept at least), 2 refreshes buffered.
CONFIG = OnlineConfig(
    space="viperx", designs=6, motions=2, refresh_every=2, buffer=2, min_steps=20, max_motion_steps=40
)


pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def source():
    src = OnlineTokenSource(CONFIG, device="cpu")
    src.start_step(0)
    return src


def _motions(n: int = 2):
    """The first n augmented motions of refresh 0, drawn as the source draws them."""
    from tt.tokens.draws import _rng, episode_motion, training_motions

    base = training_motions("viperx")
    rng = _rng(CONFIG.seed, 0, _STREAM_MOTIONS)
    ids = rng.choice(len(base), size=n, replace=False)
    return [episode_motion(CONFIG.generate_config(), base[m], s) for m, s in zip(ids, rng.integers(0, 2**31, size=n))]


def test_rollout_records_reach_torch_without_a_copy():
    space = get_space("viperx")
    designs = space.sample(4, seed=3)
    models = [space.model(d) for d in designs]
    motions = _motions()
    groups = rollout_records(models, space.ee_sites(), motions, device="cpu")
    assert sum(len(m) for m, _ in groups) == 4
    for members, records in groups:
        ep = group_episode(members, records, len(motions), models[members[0]].nu, perturbed=False, dt=0.02)
        for name in _RECORDED:
            assert getattr(ep, name).data_ptr() == getattr(records, name).ptr, name
        # A write through Warp is seen by the torch view.
        records.qpos.fill_(1.25)
        wp.synchronize()
        assert bool((ep.qpos == 1.25).all())
        assert ep.design_index.tolist() == [d for d in members for _ in motions]


def test_online_tokens_equal_the_copying_path(source):
    """Refresh 0's episodes, tokenized from zero-copy group views, equal the same designs and
    motions rolled out by `rollout` (one padded Episode, copied) and tokenized directly."""
    space = get_space("viperx")
    from tt.tokens.draws import _seed_int

    designs = space.sample(CONFIG.designs, seed=_seed_int(CONFIG.seed, 0, _STREAM_DESIGNS))
    motions = _motions(CONFIG.motions)
    ep = rollout(
        designs,
        motions,
        backend="warp",
        device="cpu",
        action_noise=CONFIG.action_noise,
        noise_seed=_seed_int(CONFIG.seed, 0, _STREAM_NOISE),
    )
    emb = tokenize_models([space.model(d) for d in designs])
    lengths = ep.lengths()
    refresh = source._refreshes[0]
    kept = [w for w in range(ep.worlds) if int(lengths[w]) >= CONFIG.min_steps]
    assert len(refresh) == len(kept) > 0
    # The online source orders episodes by topology group; match them by (design, motion).
    T = ep.steps
    dyn = episode_tokens(ep, emb.index, step_index=torch.arange(T).expand(ep.worlds, T))
    seen = 0
    track = refresh.step_values["track_link_obs"]  # (E, S, P, D)
    for w in kept:
        n = int(lengths[w])
        ref = dyn.values["track_link_obs"].reshape(ep.worlds, T, -1, track.shape[-1])[w, :n]
        hits = [
            e
            for e in range(len(refresh))
            if int(refresh.lengths[e]) == n and torch.equal(track[e, :n, : ref.shape[1]], ref.to(track.dtype))
        ]
        assert len(hits) == 1, f"world {w}: {len(hits)} matching online episodes"
        e = hits[0]
        for name in refresh.step_values:
            r = dyn.values[name].reshape(ep.worlds, T, -1, refresh.step_values[name].shape[-1])[w, :n]
            got = refresh.step_values[name][e, :n]
            torch.testing.assert_close(got[:, : r.shape[1]], r.to(got.dtype), rtol=0, atol=0, msg=name)
            assert not got[:, r.shape[1] :].any(), f"{name}: padding is not zero"
        d = int(ep.design_index[w])
        for name in refresh.static_values:
            r = torch.as_tensor(np.asarray(emb.tokens.values[name][d]))
            torch.testing.assert_close(
                refresh.static_values[name][e, : r.shape[0]], r.to(torch.float32), rtol=0, atol=0
            )
        seen += 1
    assert seen == len(kept)


def test_online_layout_is_the_datasets(source):
    maxima = {k: v for k, v in space_token_maxima("viperx")["maxima"].items() if v > 0}
    assert source.layout(8) == layout_from_schema(maxima, steps=8)
    windows = source.sample(5, 8, "consecutive", torch.Generator().manual_seed(0))
    source.layout(8).check(windows)
    assert source.stats["refreshes"] >= 1 and source.stats["world_steps"] > 0


def test_online_training_resumes_exactly(tmp_path):
    class Stop(Exception):
        pass

    def cfg(folder, **kw):
        return TrainConfig(
            out=str(tmp_path / folder),
            size="tiny",
            task="both",
            batch_size=4,
            steps=5,
            warmup_steps=2,
            lr=3e-3,
            device="cpu",
            window=4,
            checkpoint_every=1000,
            online=CONFIG,
            **kw,
        )

    straight = train(cfg("a"))

    def stop_at_3(step, loss):
        if step == 3:
            raise Stop

    interrupted = cfg("b", keep_checkpoints=3)
    interrupted.checkpoint_every = 3
    with pytest.raises(Stop):
        train(interrupted, on_step=stop_at_3)
    resumed = train(interrupted)
    torch.testing.assert_close(straight.losses, resumed.losses, rtol=1e-6, atol=0)
    a, b = load_checkpoint(straight.checkpoint), load_checkpoint(resumed.checkpoint)
    for k in a["state_dict"]:
        assert torch.equal(a["state_dict"][k], b["state_dict"][k]), k
    assert TrainConfig.from_dict(a["train_config"]).online == CONFIG


def test_cli_needs_exactly_one_data_source(tt_cli, tmp_path):
    code, out = tt_cli(["train", "--out", str(tmp_path / "r"), "--size", "tiny", "--steps", "1"])
    assert code != 0 and "--data DATASET or --online" in out
    code, out = tt_cli(["train", "--online", "--data", str(tmp_path), "--out", str(tmp_path / "r"), "--steps", "1"])
    assert code != 0 and "--data DATASET or --online" in out
    code, out = tt_cli(
        ["train", "--online", "--config", "online.action_noise=-1", "--out", str(tmp_path / "r"), "--steps", "1"]
    )
    assert code != 0 and "action_noise" in out, out


def test_cli_trains_online(tt_cli, tmp_path):
    code, out = tt_cli(
        [
            "train",
            "--online",
            "--config",
            "online.designs=4",
            "--config",
            "online.motions=2",
            "--config",
            "online.refresh_every=2",
            "--size",
            "tiny",
            "--task",
            "both",
            "--steps",
            "3",
            "--batch-size",
            "4",
            "--device",
            "cpu",
            "--out",
            str(tmp_path / "run"),
        ]
    )
    assert code == 0, out
    assert "trained to step 3" in out


def test_shipped_checkpoint_fine_tunes_online(source):
    # `tt train --online --init checkpoints/viperx_mini.pt` needs the online layout to be the
    # one the shipped model was trained on (from the 52k-episode dataset).
    from tt.dit.checkpoint import default_checkpoint, load_model

    trained = load_model(default_checkpoint("viperx"), device="cpu")
    assert source.layout(trained.layout.steps) == trained.layout


def test_absorbing_keeps_failures_to_the_motion_end():
    """absorbing: every episode runs to the motion's end; past a termination its state tokens
    repeat the terminal record (the end effector already past the threshold) while the target
    tokens follow the motion, so a window there shows the design failing."""
    from dataclasses import replace

    cfg = OnlineConfig(space="viperx", designs=8, motions=1, min_steps=8, action_noise=0.0, seed=3)
    plain = OnlineTokenSource(cfg, device="cpu")._refresh(0)
    absorbing = OnlineTokenSource(replace(cfg, absorbing=True), device="cpu")._refresh(0)
    _, motions = OnlineTokenSource(cfg, device="cpu").draw(0)
    T = motions[0].steps
    assert len(absorbing) == 8 and bool((absorbing.lengths == T).all())
    checked = 0
    for e in range(len(absorbing)):
        # The same design's episode in the plain data (none if it ended within min_steps).
        same = [
            p
            for p in range(len(plain))
            if torch.equal(plain.static_values["link"][p], absorbing.static_values["link"][e])
        ]
        n = int(plain.lengths[same[0]]) if same else None
        track = absorbing.step_values["track_link_obs"][e]  # (T, P, D)
        if same:
            assert torch.equal(track[:n], plain.step_values["track_link_obs"][same[0]][:n])
        if n is None or n == T:
            continue
        assert torch.equal(track[n:], track[n : n + 1].expand_as(track[n:]))
        target = absorbing.step_values["target_pose"][e]
        assert not torch.equal(target[n], target[-1])
        checked += 1
    assert checked, "no episode of these 8 random designs terminated past min_steps; pick another seed"
