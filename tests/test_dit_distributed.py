"""Data-parallel training: ``torchrun --nproc-per-node 2 tt train`` on the CPU (gloo) takes
the same steps as one process at the same global batch, and a resume restores both ranks.

Two ranks at B/2 windows each see the windows and the noise one process at batch B sees
(`tt.dit.train`: shared generators, each rank its share) and normalise each type's loss by
the whole batch's token count, so the gradients differ only by the order of float32 sums:
the Adam moments (which hold the first step's gradient) agree to 1e-4 relative, and the
parameters to 1e-3 of the first step's size (Adam's first step is lr * g / (|g| + eps):
entries with |g| near eps amplify round-off, but not beyond that).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch

from tt.dit.checkpoint import checkpoint_path, list_checkpoints, load_checkpoint
from tt.dit.toy import toy_episodes

LR = 3e-3
ARGS = [
    "--size",
    "tiny",
    "--task",
    "both",
    "--batch-size",
    "8",
    "--device",
    "cpu",
    "--seed",
    "3",
    "--config",
    f"lr={LR}",
    "--config",
    "checkpoint_every=1",
]


def _tt(args: list[str], processes: int = 1) -> None:
    # The tt of this interpreter's environment (a `tt` earlier on PATH may be another install).
    tt = os.path.join(os.path.dirname(sys.executable), "tt")
    tt = tt if os.path.exists(tt) else shutil.which("tt")
    launcher = (
        [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(processes), "--master-port", "29517"]
        if processes > 1
        else []
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = subprocess.run([*launcher, tt, "train", *args], capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


def _assert_close(single: dict, parallel: dict, step: int) -> None:
    for name, p in single["state_dict"].items():
        q = parallel["state_dict"][name]
        torch.testing.assert_close(q, p, rtol=0, atol=1e-3 * LR * step, msg=lambda m: f"step {step} {name}: {m}")
    for key, s in single["optimizer"]["state"].items():
        d = parallel["optimizer"]["state"][key]
        scale = float(s["exp_avg"].abs().max()) + 1e-12
        torch.testing.assert_close(d["exp_avg"], s["exp_avg"], rtol=1e-4, atol=1e-5 * scale)
    assert abs(float(single["losses"][-1]) - float(parallel["losses"][-1])) <= 1e-5 * abs(float(single["losses"][-1]))


@pytest.mark.usefixtures("single_thread")
def test_two_ranks_at_half_batch_take_the_steps_of_one_process(tmp_path):
    data = tmp_path / "toy.npz"
    toy_episodes(episodes=12, steps=20, seed=0).save(data)
    _tt(["--data", str(data), "--out", str(tmp_path / "one"), "--steps", "2", *ARGS])
    _tt(["--data", str(data), "--out", str(tmp_path / "two"), "--steps", "1", *ARGS], processes=2)
    # Only rank 0 writes: one checkpoint, one loss curve.
    assert list_checkpoints(tmp_path / "two") == [checkpoint_path(tmp_path / "two", 1)]
    assert (tmp_path / "two" / "loss.csv").read_text().count("\n") == 2
    first = load_checkpoint(checkpoint_path(tmp_path / "one", 1))
    assert first["step"] == 1
    _assert_close(first, load_checkpoint(checkpoint_path(tmp_path / "two", 1)), 1)
    # The steps move the weights.
    later = load_checkpoint(checkpoint_path(tmp_path / "one", 2))
    assert any(not torch.equal(later["state_dict"][k], v) for k, v in first["state_dict"].items())
    # Resume: both ranks load step 1 (model, optimizer, EMA, generators) and take step 2.
    _tt(["--data", str(data), "--out", str(tmp_path / "two"), "--steps", "2", *ARGS], processes=2)
    second = load_checkpoint(checkpoint_path(tmp_path / "two", 2))
    assert second["step"] == 2 and len(second["losses"]) == 2
    _assert_close(later, second, 2)


def test_a_batch_that_does_not_split_over_the_ranks_is_refused(monkeypatch, tmp_path):
    from tt.dit.train import DataParallel

    monkeypatch.setenv("WORLD_SIZE", "3")
    monkeypatch.setenv("RANK", "1")
    dp = DataParallel.from_env()
    assert dp == DataParallel(rank=1, world_size=3, local_rank=1)
    assert dp.share(12, "robot") == (4, 8)
    with pytest.raises(ValueError, match="does not split over 3"):
        dp.share(8, "task robot's batch")


def test_episode_tokens_part_is_the_slice_of_the_whole_draw():
    episodes = toy_episodes(episodes=12, steps=20, seed=0)
    for kind in ("random", "consecutive"):
        g_all, g_part = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
        whole = episodes.sample(8, 4, kind, g_all)
        part = episodes.sample(8, 4, kind, g_part, part=(4, 8))
        for name, x in whole.values.items():
            assert torch.equal(x[4:8], part.values[name]) and torch.equal(whole.ids[name][4:8], part.ids[name])
        assert torch.equal(g_all.get_state(), g_part.get_state())
