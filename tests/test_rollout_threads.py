"""Multi-threaded CPU rollouts (`threads=`): every thread count gives the same episodes, bit for bit.

The warp backend cuts each topology group's worlds into contiguous slices and launches
each slice from its own thread on views of the arrays (`tt.kernels.rollout`). A world's
arithmetic must not depend on which slice it lands in, so the records of 2 and 3 threads
(uneven slices) must equal one thread's exactly: np.array_equal, no tolerance.
"""

import dataclasses

import numpy as np
import pytest
import torch

from tt.kernels.model import build_tree_model
from tt.kernels.rollout import cpu_threads, motion_arrays, rollout_tree, world_slices
from tt.sim.controller import IKConfig
from tt.sim.designs import get_space
from tt.sim.motions import Motion, for_space, get_motion
from tt.sim.rollout import rollout

STEPS = 12  # control steps: enough for the controller, the physics and a termination to act


def _motions(steps: int = STEPS) -> list[Motion]:
    toss = for_space([get_motion("toss")], "viperx")[0]
    short = Motion("toss[:8]", toss.pos[:8], toss.quat[:8], toss.dt)  # pads past its end
    return [Motion(f"toss[:{steps}]", toss.pos[:steps], toss.quat[:steps], toss.dt), short]


def _tensor_fields(ep) -> dict[str, np.ndarray]:
    return {
        f.name: getattr(ep, f.name).numpy()
        for f in dataclasses.fields(ep)
        if isinstance(getattr(ep, f.name), torch.Tensor)
    }


@pytest.fixture
def small_slices(monkeypatch):
    """Slices of any size, so that the few worlds of a test are cut too."""
    import tt.kernels.rollout

    monkeypatch.setattr(tt.kernels.rollout, "MIN_SLICE_WORLDS", 1)


@pytest.mark.parametrize("action_noise", [0.0, 0.05])
def test_episodes_are_bit_identical_for_every_thread_count(action_noise, small_slices):
    # 9 designs of several topologies x 2 motions: groups of uneven size, slices of whole
    # motion blocks (2 worlds), so 3 threads cut a group unevenly.
    designs = get_space("viperx").sample(9, seed=3)
    motions = _motions()
    episodes = {
        k: _tensor_fields(rollout(designs, motions, device="cpu", threads=k, action_noise=action_noise, noise_seed=7))
        for k in (1, 2, 3)
    }
    names = sorted(episodes[1])
    assert {"qpos", "qvel", "ctrl", "action", "act_force", "act_vel", "ee_pos", "alive"} <= set(names)
    for k in (2, 3):
        for name in names:
            assert np.array_equal(episodes[k][name], episodes[1][name], equal_nan=True), (k, name)
    # Not vacuous: the robots moved and some world terminated or ran past its motion.
    assert np.abs(episodes[1]["qvel"]).max() > 1e-2
    assert not episodes[1]["alive"].all()


def test_shared_model_and_motion_entries_keep_their_world_indexing(small_slices):
    """A model of 2 entries and 3 motions read as ``world % 2`` and ``world % 3``: slices must
    start at multiples of 6, and each world must read the entries it reads in one launch."""
    space = get_space("viperx")
    designs = [d for d in space.sample(40, seed=1) if len(space.model(d).jnt_type) == 6][:2]
    assert len(designs) == 2
    sites = space.ee_sites()
    tree = build_tree_model([space.model(d) for d in designs], sites, device="cpu")
    toss = for_space([get_motion("toss")], "viperx")[0]
    pos = np.stack([toss.pos[k : k + STEPS] for k in (0, 5, 10)])
    quat = np.stack([toss.quat[k : k + STEPS] for k in (0, 5, 10)])
    marrays = motion_arrays(pos, quat, [STEPS] * 3, device="cpu")
    W = 18
    args = IKConfig().rollout_args()
    runs = {k: rollout_tree(tree, marrays, W, STEPS, **args, threads=k, device="cpu") for k in (1, 2, 3, 5)}
    for k in (2, 3, 5):
        for name in ("qpos", "qvel", "ctrl", "ee_pos", "target_pos", "alive"):
            assert np.array_equal(getattr(runs[k], name).numpy(), getattr(runs[1], name).numpy()), (k, name)
    # World w tracks motion w % 3 with design w % 2.
    q = runs[1].qpos.numpy()
    assert not np.array_equal(q[0], q[3]) and np.array_equal(q[0], q[6])


def test_world_slices_cover_the_worlds_in_aligned_near_equal_parts():
    assert world_slices(10, 3) == [(0, 3), (3, 6), (6, 10)]
    assert world_slices(14, 3, align=2) == [(0, 4), (4, 8), (8, 14)]
    assert world_slices(18, 5, align=6) == [(0, 6), (6, 12), (12, 18)]
    assert world_slices(5, 8) == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]
    assert world_slices(7, 4, align=8) == [(0, 7)]
    for W, k, a in ((4096, 2, 1), (1000, 7, 3), (31, 4, 5)):
        s = world_slices(W, k, a)
        assert s[0][0] == 0 and s[-1][1] == W and all(x[1] == y[0] for x, y in zip(s, s[1:]))
        assert all(lo % a == 0 for lo, _ in s)


def test_thread_counts_are_validated():
    assert cpu_threads(3) == 3 and cpu_threads(None) >= 1
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="threads"):
            cpu_threads(bad)
    with pytest.raises(ValueError, match="threads"):
        rollout(get_space("viperx").sample(1, seed=0), _motions(), device="cpu", threads=0)


def test_cli_rollout_threads_flag(tmp_path, tt_cli, small_slices):
    """`tt rollout --threads K` reports K threads and the same metrics for every K."""
    import json

    from tt.sim.motions import save_npz

    save_npz(_motions(40)[0], tmp_path / "short.npz")
    summaries = {}
    for k in (1, 2):
        code, text = tt_cli(
            [
                "rollout",
                "--n",
                "5",
                "--seed",
                "2",
                "--motion",
                str(tmp_path / "short.npz"),
                "--threads",
                str(k),
                "--device",
                "cpu",
                "--out",
                str(tmp_path / f"t{k}"),
            ]
        )
        assert code == 0, text
        assert f"{k} threads" in text, text
        summaries[k] = json.loads((tmp_path / f"t{k}" / "summary.json").read_text())
        assert summaries[k]["threads"] == k
    assert summaries[1]["per_world"] == summaries[2]["per_world"]
    code, text = tt_cli(["rollout", "--n", "1", "--threads", "0"])
    assert code != 0 and "threads" in text, text


def test_models_built_in_worker_processes_equal_the_serial_build(monkeypatch):
    """`DesignSpace.models(processes=2)` returns the serial build's models (MuJoCo's binary
    format through pickling), in order."""
    import tt.sim.designs.base as base

    space = get_space("viperx")
    designs = space.sample(6, seed=4)
    monkeypatch.setattr(base, "PARALLEL_MODELS_MIN", 1)
    parallel = space.models(designs, processes=2)
    serial = [space.model(d) for d in designs]
    assert len(parallel) == len(serial)
    for a, b in zip(parallel, serial):
        for name in (
            "body_pos",
            "body_quat",
            "body_mass",
            "body_inertia",
            "jnt_axis",
            "jnt_range",
            "actuator_gainprm",
            "site_pos",
            "qpos0",
            "dof_invweight0",
        ):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_problem_threads_are_validated():
    from tt.baselines.problem import Problem

    motion = _motions()[0]
    assert Problem(space="viperx", motions=(motion,), reward="tracking", budget=4, threads=2).threads == 2
    for bad in (0, -2, 1.5):
        with pytest.raises(ValueError, match="Problem.threads"):
            Problem(space="viperx", motions=(motion,), reward="tracking", budget=4, threads=bad)
