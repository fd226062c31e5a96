"""Killed and resumed runs lose no finished work and duplicate none (issue 22).

* ``tt train`` killed after a checkpoint is written (and fsync'ed) but before it is renamed
  into place: the resumed run starts from the checkpoint before, and its losses and
  weights equal an uninterrupted run's.
* ``tt generate`` killed with SIGKILL at 10 random points: no complete shard is ever lost
  or damaged, and the finished dataset equals an uninterrupted run's, every episode once.
* Parent kills (issue 50): SIGKILL of ``tt view --serve`` takes its meshcat server down, and
  SIGKILL of ``tt generate --workers 2`` its worker processes and queue server.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict

import numpy as np
import pytest
import torch

from tt.dit.checkpoint import list_checkpoints, load_checkpoint

_TRAIN_CHILD = """
import os, sys
from pathlib import Path
real = os.replace
def replace(src, dst):
    if Path(dst).name == "step_0000004.pt":
        os._exit(9)  # killed between writing the checkpoint and renaming it
    return real(src, dst)
os.replace = replace
from tt.cli import main
sys.argv = ["tt", *sys.argv[1:]]
main()
"""


def _train_args(data, out, steps: int) -> list[str]:
    return [
        "train",
        "--data",
        str(data),
        "--size",
        "tiny",
        "--batch-size",
        "4",
        "--device",
        "cpu",
        "--steps",
        str(steps),
        "--config",
        "checkpoint_every=2",
        "--out",
        str(out),
    ]


@pytest.mark.slow  # about a minute on a loaded 2-core box (a child process, three tiny trainings)
def test_train_killed_between_checkpoint_write_and_rename(tmp_path, tt_cli, single_thread):
    from tt.dit.toy import toy_episodes

    data = tmp_path / "episodes.npz"
    toy_episodes(episodes=6, steps=12, seed=0).save(data)
    run = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    child = subprocess.run(
        [sys.executable, "-c", _TRAIN_CHILD, *_train_args(data, run, 6)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=600,
    )
    assert child.returncode == 9, child.stdout[-2000:]
    folder = run / "checkpoints"
    assert [p.name for p in list_checkpoints(run)] == ["step_0000002.pt"]
    assert len(list(folder.glob(".step_0000004.pt.tmp-*"))) == 1  # the written, never renamed file

    code, out = tt_cli(_train_args(data, run, 6))
    assert code == 0, out
    assert not list(folder.glob(".step_*.tmp-*"))
    code, out = tt_cli(_train_args(data, tmp_path / "straight", 6))
    assert code == 0, out
    a, b = load_checkpoint(list_checkpoints(run)[-1]), load_checkpoint(list_checkpoints(tmp_path / "straight")[-1])
    assert a["step"] == b["step"] == 6 and len(a["losses"]) == 6
    torch.testing.assert_close(a["losses"], b["losses"], rtol=0, atol=0)
    for k in b["state_dict"]:
        assert torch.equal(a["state_dict"][k], b["state_dict"][k]), k


_GENERATE_CHILD = """
import json, sys
from tt.generate import GenerateConfig, generate
generate(GenerateConfig(**json.loads(sys.argv[2])), sys.argv[1], device="cpu", progress=False)
"""


@pytest.mark.slow
def test_generate_killed_at_ten_random_points(tmp_path):
    from tt.generate import GenerateConfig, generate
    from tt.tokens.store import TokenStore, read_manifest, read_root, shard_dirs, verify_shard

    config = GenerateConfig(
        space="viperx", designs=12, episodes_per_design=2, designs_per_shard=2, min_steps=20, max_motion_steps=40
    )
    reference = tmp_path / "reference"
    generate(config, reference, device="cpu", progress=False)
    path = tmp_path / "killed"
    rng = np.random.default_rng(22)
    kept: dict[str, bytes] = {}  # manifest of every shard seen complete
    mid_work = 0
    for kill in range(10):
        child = subprocess.Popen(
            [sys.executable, "-c", _GENERATE_CHILD, str(path), json.dumps(asdict(config))],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(float(rng.uniform(1.0, 15.0)))
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        shards = shard_dirs(path)
        mid_work += child.returncode == -signal.SIGKILL and len(shards) < config.shards
        for i, folder in shards.items():
            assert verify_shard(folder) is None, f"kill {kill}: shard {i} damaged"
            manifest = (folder / "manifest.json").read_bytes()
            assert kept.setdefault(folder.name, manifest) == manifest, f"kill {kill}: shard {i} was rewritten"
        assert set(kept) <= {f.name for f in shards.values()}, f"kill {kill}: a complete shard was lost"
    assert mid_work >= 3, f"only {mid_work} of 10 kills landed while shards were left to do"
    generate(config, path, device="cpu", progress=False)
    assert read_root(path)["complete"]
    a, b = TokenStore(path, verify="full"), TokenStore(reference, verify="full")
    ids = a.episode_table()["episode_id"]
    assert len(np.unique(ids)) == len(ids) == b.episodes  # every episode once
    assert a.episode_digests() == b.episode_digests()
    for i, folder in shard_dirs(reference).items():
        assert read_manifest(shard_dirs(path)[i]) == read_manifest(folder)


def test_view_serve_listens_on_the_loopback_and_its_server_dies_with_it(tmp_path):
    """``tt view --serve`` binds meshcat's web server and command socket to 127.0.0.1 (meshcat
    alone listens on every interface), and SIGKILL of tt view takes its server down: no
    orphan keeps the ports."""
    sys.path.insert(0, os.path.dirname(__file__))
    from listening import children, listening, running, wait_gone

    from tt.sim.designs import get_space, save_designs

    save_designs([get_space("viperx").nominal()], tmp_path / "designs.json")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tt.cli", "view", str(tmp_path / "designs.json"), "--serve"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
    )
    server = None
    try:
        lines = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if "serving" in line or not line:
                break
        url = next((x.split(": ", 1)[1].strip() for x in lines if x.startswith("meshcat viewer: ")), None)
        assert url and url.startswith("http://127.0.0.1:"), "".join(lines)
        (server,) = children(proc.pid)
        addresses = listening(server)
        assert len(addresses) == 2, addresses  # the web server and the command socket
        assert {host for host, _ in addresses} == {"127.0.0.1"}, addresses
        assert int(url.split(":")[2].split("/")[0]) in {port for _, port in addresses}, (url, addresses)

        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        assert wait_gone(server, timeout=10), f"meshcat server {server} outlived its killed tt view"
    finally:
        proc.kill()
        if server is not None and running(server):
            os.kill(server, signal.SIGKILL)


def test_generate_workers_die_with_a_killed_run(tmp_path):
    """SIGKILL of ``tt generate --workers 2`` takes its worker processes (and the progress
    queue's server) down with it: none is left writing shards."""
    sys.path.insert(0, os.path.dirname(__file__))
    from bad_input_cases import killed_generate_leaves_no_workers

    kind, why = killed_generate_leaves_no_workers(tmp_path)
    assert kind == "ok", f"{kind}: {why}"
