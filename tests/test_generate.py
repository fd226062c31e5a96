"""``tt generate``: a run killed with SIGKILL and resumed equals an uninterrupted one, byte
for byte; damaged shards are regenerated; stored episodes equal a direct (control-perturbed)
rollout + tokenization, with the clean commands as control tokens; CMA-ES biasing keeps
every sampled design; Ray and process workers give the same dataset."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from tt.sim.designs import get_space
from tt.sim.motions import augment_motion, for_space, motion_set
from tt.sim.motions.base import Motion
from tt.sim.rollout import rollout
from tt.tokens import episode_tokens, tokenize_models
from tt.generate import GenerateConfig, generate, shard_design_list
from tt.tokens.store import DatasetError, TokenStore, read_root, shard_dirs

#: 5 shards of 2 designs x 2 episodes on motions cut to 40 steps (20 kept at least).
CONFIG = GenerateConfig(space="viperx", designs=10, episodes_per_design=2, designs_per_shard=2, min_steps=20,
                        max_motion_steps=40)

_CHILD = """
import json, sys
from tt.generate import GenerateConfig, generate
generate(GenerateConfig(**json.loads(sys.argv[2])), sys.argv[1], device="cpu", progress=False)
"""


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run."""
    path = tmp_path_factory.mktemp("gen") / "reference"
    report = generate(CONFIG, path, device="cpu", progress=False)
    assert report.run["shards"] == CONFIG.shards
    return path


def _same_data(a, b, shards: int = CONFIG.shards) -> None:
    """Equal episodes (content digests) and byte-identical shard files (sizes and CRC-32)."""
    da, db = TokenStore(a, verify="full").episode_digests(), TokenStore(b, verify="full").episode_digests()
    assert len(da) > 0 and da == db
    sa, sb = shard_dirs(a), shard_dirs(b)
    assert sorted(sa) == sorted(sb) == list(range(shards))
    for i in sa:
        # Whole manifests: no timings in them, so they are byte-identical too.
        assert (sa[i] / "manifest.json").read_bytes() == (sb[i] / "manifest.json").read_bytes(), f"shard {i} differs"


def test_killed_run_resumes_to_the_uninterrupted_dataset(reference, tmp_path):
    path = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(path), json.dumps(asdict(CONFIG))],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 600
    try:
        while child.poll() is None and len(shard_dirs(path)) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.wait()
    assert child.returncode == -signal.SIGKILL
    complete = len(shard_dirs(path))
    assert 2 <= complete < CONFIG.shards, f"the child finished {complete} of {CONFIG.shards} shards before the kill"
    assert not read_root(path).get("complete")
    assert (path / ".lock").exists()  # left by the killed process; the resumed run takes it over

    report = generate(CONFIG, path, device="cpu", progress=False)
    assert report.run["shards"] == CONFIG.shards - complete
    assert read_root(path)["complete"] and not (path / ".lock").exists()
    assert list((path / ".partial").iterdir()) == []
    _same_data(path, reference)
    assert read_root(path)["normalizer"] == read_root(reference)["normalizer"]
    assert generate(CONFIG, path, device="cpu", progress=False).run["shards"] == 0  # nothing left to do


def test_truncated_shard_is_detected_and_regenerated(reference, tmp_path):
    path = tmp_path / "damaged"
    shutil.copytree(reference, path)
    chunk = max((p for p in (shard_dirs(path)[3] / "track_link_obs").rglob("*") if p.is_file() and "/c/" in str(p)),
                key=lambda p: p.stat().st_size)
    chunk.write_bytes(chunk.read_bytes()[:-5])
    leftover = path / ".partial" / "s000004-123-deadbeef"  # an interrupted write
    leftover.mkdir(parents=True)
    report = generate(CONFIG, path, device="cpu", progress=False)
    assert list(report.run["regenerated"]) == [3] and "truncated" in report.run["regenerated"][3]
    assert report.run["shards"] == 1 and not leftover.exists()
    _same_data(path, reference)


def test_other_arguments_or_foreign_folder_are_refused(reference, tmp_path):
    with pytest.raises(DatasetError, match="seed=0.*seed=1"):
        generate(replace(CONFIG, seed=1), reference, device="cpu", progress=False)
    with pytest.raises(DatasetError, match=f"action_noise={CONFIG.action_noise}.*action_noise=0.0"):
        generate(replace(CONFIG, action_noise=0.0), reference, device="cpu", progress=False)
    assert read_root(reference)["config"]["action_noise"] == CONFIG.action_noise
    (tmp_path / "notes.txt").write_text("not a dataset")
    with pytest.raises(DatasetError, match="not a tt dataset"):
        generate(CONFIG, tmp_path, device="cpu", progress=False)


def test_stored_episodes_equal_a_direct_rollout_and_tokenization(reference):
    """Reference: the designs re-sampled, the group's motions re-built from the stored motion
    indices and augmentation seeds with the public motion API, one perturbed rollout of the
    group (world d * K + slot, the shard's noise seed), the tokenizers. Control tokens hold
    the clean commands (``Episode.action``), not the executed ones."""
    from tt.tokens.draws import _STREAM_NOISE, _seed_int

    sp = get_space("viperx")
    K = CONFIG.episodes_per_design
    store = TokenStore(reference)
    reader = store.readers[2]
    designs = reader.designs(sp)
    assert designs == shard_design_list(CONFIG, 2)
    block = reader.read_block(0, reader.episodes, fields=True)
    base = motion_set("train", arms=1)
    assert (block.length >= CONFIG.min_steps).all()
    orders = [r.field("design") for r in store.readers]
    assert any((np.diff(d) < 0).any() for d in orders)  # episodes are stored shuffled, not design by design
    generated = int(reader.attrs["generated"])
    assert generated == 2 * CONFIG.episodes_per_design and reader.episodes + sum(reader.attrs["dropped"].values()) == generated
    # Episode ids are shard-major, then design, then motion slot.
    local = block.episode["episode_id"] - 2 * CONFIG.designs_per_shard * K
    np.testing.assert_array_equal(local // K, block.design)
    slots = {}
    for e in range(len(block)):
        slots[int(local[e] % K)] = (int(block.episode["motion"][e]), int(block.episode["augment_seed"][e]))
    assert sorted(slots) == list(range(K)), "every motion slot of the group has a kept episode"
    motions = []
    for slot in range(K):
        m = augment_motion(base[slots[slot][0]], slots[slot][1], max_yaw=CONFIG.max_yaw, max_shift=CONFIG.max_shift)
        m = for_space([m], "viperx")[0]
        motions.append(Motion(m.name, m.pos[:40], m.quat[:40], m.dt))
    assert CONFIG.action_noise > 0
    ep = rollout(designs, motions, device="cpu", action_noise=CONFIG.action_noise,
                 noise_seed=_seed_int(CONFIG.seed, 2, _STREAM_NOISE, 0))
    embs = [tokenize_models([sp.model(d)]) for d in designs]
    for e in range(len(block)):
        design, slot = int(block.design[e]), int(local[e] % K)
        w = design * K + slot
        m = augment_motion(base[slots[slot][0]], slots[slot][1], max_yaw=CONFIG.max_yaw, max_shift=CONFIG.max_shift)
        np.testing.assert_array_equal(block.episode["se2"][e], [m.meta["se2"][k] for k in ("yaw", "dx", "dy")])
        n = int(ep.lengths()[w])
        assert n == block.length[e]
        emb = embs[design]
        one = _select(ep, w)
        ref = episode_tokens(one, emb.index, step_index=torch.arange(n)[None])
        win = block.windows(np.array([e]), np.arange(n)[None])
        for name in ref.types:
            v = ref.values[name].numpy().reshape(n, -1, ref.values[name].shape[-1])
            p = v.shape[1]
            got = win["values"][name].reshape(n, -1, v.shape[-1])
            np.testing.assert_allclose(got[:, :p], v, rtol=1e-6, atol=1e-6, err_msg=name)
            assert (got[:, p:] == 0).all() and win["mask"][name].reshape(n, -1)[:, :p].all()
            assert not win["mask"][name].reshape(n, -1)[:, p:].any()
        nu = sp.model(designs[design]).nu
        control = win["values"]["control"].reshape(n, -1)[:, :nu]
        np.testing.assert_allclose(control, ep.action[w, :n, :nu].numpy(), rtol=1e-6, atol=1e-6)
        assert np.abs(control - ep.ctrl[w, :n, :nu].numpy()).max() > 0.5 * CONFIG.action_noise  # not the executed ones
        for name in emb.tokens.types:
            real = emb.tokens.values[name].shape[1]
            np.testing.assert_array_equal(win["values"][name][0, :real], emb.tokens.values[name][0], err_msg=name)


def _select(ep, w: int):
    """World w of an Episode as a one-world Episode of design 0 (for its robot's own token index)."""
    from dataclasses import fields as dc_fields

    from tt.sim.episode import Episode

    kw = {f.name: getattr(ep, f.name)[w:w + 1] for f in dc_fields(Episode) if f.name != "dt"}
    return Episode(**{**kw, "design_index": torch.zeros(1, dtype=torch.long)}, dt=ep.dt)


def test_cmaes_bias_keeps_every_design_cmaes_samples():
    """Shard 0 of 20 designs: two CMA-ES runs (population 5, 3 generations) on training
    motions 0 and 1; reference: `tt.baselines.CMAES` run directly on those problems."""
    from tt.baselines import CMAES, CMAESConfig, Problem
    from tt.tokens.draws import _seed_int, training_motions

    cfg = replace(CONFIG, designs=20, designs_per_shard=20, bias="cmaes")
    designs = shard_design_list(cfg, 0, device="cpu")
    assert len(designs) == 20
    reference = []
    for m in (0, 1):
        motion = for_space([training_motions("viperx")[m]], "viperx")[0]
        motion = Motion(motion.name, motion.pos[:40], motion.quat[:40], motion.dt)
        problem = Problem(space="viperx", motions=(motion,), reward="tracking", budget=15,
                          seed=_seed_int(cfg.seed, 0, 2, m, bits=21), backend="warp", device="cpu")
        reference += CMAES(CMAESConfig(popsize=5, generations=3)).optimize(problem).designs
    assert designs == reference[:20]
    assert len({d.discrete for d in designs[:15]}) == 1  # one run: one discrete choice, 15 samples
    assert designs[:5] != shard_design_list(replace(cfg, bias=None), 0)[:5]


def test_action_noise_is_checked_and_defaults_to_the_measured_value():
    from tt.tokens.draws import DEFAULT_ACTION_NOISE

    assert CONFIG.action_noise == DEFAULT_ACTION_NOISE > 0
    with pytest.raises(ValueError, match="action_noise = -0.01"):
        replace(CONFIG, action_noise=-0.01)
    with pytest.raises(ValueError, match="needs backend 'warp'"):
        replace(CONFIG, backend="mujoco")
    assert replace(CONFIG, backend="mujoco", action_noise=0.0).to_dict()["action_noise"] == 0.0
    # A dataset written before the option existed stored action_noise 0: it reads back unperturbed.
    assert GenerateConfig.from_dict({**CONFIG.to_dict(), "action_noise": 0.0}).action_noise == 0.0


def test_ray_and_process_workers_equal_one_process(reference, tmp_path):
    """A local Ray cluster of 2 workers, and 2 worker processes, write the same dataset.
    (Ray comes with the test extra, so CI runs this.)"""
    report = generate(CONFIG, tmp_path / "ray", device="cpu", workers=2, ray_address="local", progress=False)
    assert report.run["shards"] == CONFIG.shards
    _same_data(tmp_path / "ray", reference)
    report = generate(CONFIG, tmp_path / "pool", device="cpu", workers=2, progress=False)
    assert report.run["shards"] == CONFIG.shards
    _same_data(tmp_path / "pool", reference)


def test_one_rollout_thread_writes_the_dataset_of_every_core(reference, tmp_path):
    """`threads=1` (the reference ran on every core) writes the same shards, byte for byte."""
    report = generate(CONFIG, tmp_path / "one", device="cpu", progress=False, threads=1)
    assert report.run["shards"] == CONFIG.shards
    _same_data(tmp_path / "one", reference)


def test_groups_written_while_the_next_rolls_out_give_the_inline_dataset(tmp_path):
    """With more than one thread, each group is tokenized and written while the next group rolls
    out; the shard is byte for byte the one a single thread writes group after group."""
    config = replace(CONFIG, designs=3, designs_per_shard=3, group_designs=1)
    generate(config, tmp_path / "inline", device="cpu", progress=False, threads=1)
    generate(config, tmp_path / "overlapped", device="cpu", progress=False, threads=2)
    _same_data(tmp_path / "overlapped", tmp_path / "inline", shards=1)


def _ray_shard_tasks() -> list[int]:
    """Process ids of Ray workers executing a shard now (Ray titles them ``ray::<task>``)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                if (proc / "cmdline").read_bytes().startswith(b"ray::_shard_task"):
                    pids.append(int(proc.name))
            except OSError:
                continue  # ended meanwhile
    return pids


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds Ray's worker processes through /proc")
def test_a_ray_worker_killed_mid_shard_is_retried_and_the_dataset_verifies(reference, tmp_path):
    """SIGKILL a Ray worker while it generates a shard: Ray reruns the task (``max_retries``)
    on a fresh worker, the shard is written from scratch, and the dataset equals one process's."""
    import threading

    killed: list[int] = []
    done = threading.Event()

    def killer():
        while not done.is_set() and not killed:
            pids = _ray_shard_tasks()
            if pids:
                time.sleep(0.5)  # well inside the shard (it takes seconds), past its start
                if pids[0] in _ray_shard_tasks():
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])
            time.sleep(0.05)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    try:
        report = generate(CONFIG, tmp_path / "ray", device="cpu", workers=2, ray_address="local", progress=False)
    finally:
        done.set()
        thread.join()
    assert len(killed) == 1, "no Ray worker was caught mid-shard"
    assert report.run["shards"] == CONFIG.shards
    TokenStore(tmp_path / "ray", verify="full")  # every shard's checksums verify
    _same_data(tmp_path / "ray", reference)


@pytest.mark.parametrize("kind", ["random", "consecutive"])
def test_a_data_parallel_rank_reads_its_part_of_the_store_windows(reference, kind):
    """`StoreTokenSource.sample(part=(a, b))`: windows a .. b - 1 of what the same draw of all
    n gives (blocks, episodes, steps and the SE(2) augmentation), and the generator ends in
    the same state, so the ranks stay in step."""
    from tt.dit.loader import StoreTokenSource

    source = StoreTokenSource(reference, windows_per_block=3)
    g_all, g_part = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    whole = source.sample(8, 4, kind, g_all)
    part = source.sample(8, 4, kind, g_part, part=(3, 7))
    for field in ("values", "ids", "mask"):
        for name, x in getattr(whole, field).items():
            assert torch.equal(x[3:7], getattr(part, field)[name]), (field, name)
    assert torch.equal(g_all.get_state(), g_part.get_state())
