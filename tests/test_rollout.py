"""`tt.sim.rollout.rollout`: the warp backend against the oracle, episode by episode, and its errors.

Closed loop, episode by episode: warp and the oracle (MuJoCo C + mink) run the same designs
on the same motions; every episode must have the same survival (whether it tracks its whole
motion), mean position error within 0.2 cm (over the steps both count) and tracking reward
within 2%.

Some random designs make that impossible for any implementation that is not bit-identical
to the oracle: their start posture (fifty IK steps toward a pose they cannot reach) or
their tracking (near a singularity, or while failing) is chaotic, so the oracle itself
lands elsewhere when its inputs change at round-off level. Such episodes are found by
running the oracle a second time on the inputs rounded to float32 (what the warp kernels
read); the comparison covers every episode the oracle reproduces, which must be most.
"""

import dataclasses

import numpy as np
import pytest
import torch

from tt.kernels.model import topology_of
from tt.sim.designs import get_space
from tt.sim.motions import Motion, for_space, motion_set
from tt.sim.rewards import RewardInputs, evaluate, get_reward
from tt.sim.rollout import rollout

POS_ERR_TOL = 0.2  # [cm]
REWARD_REL_TOL = 0.02


#: MjModel fields the kernels read, rounded to float32 for the second oracle run.
_ROUNDED_FIELDS = (
    "body_pos", "body_quat", "body_ipos", "body_iquat", "body_mass", "body_inertia",
    "jnt_axis", "jnt_pos", "jnt_range", "dof_armature", "dof_damping", "dof_invweight0",
    "actuator_gainprm", "actuator_biasprm", "actuator_ctrlrange", "actuator_forcerange",
    "site_pos", "site_quat",
)  # fmt: skip


def _rounded_oracle(space, designs, motions):
    """The oracle on the designs' models and the motions rounded to float32."""
    models = []
    for design in designs:
        model = get_space(space).model(design)
        for name in _ROUNDED_FIELDS:
            value = getattr(model, name)
            value[...] = value.astype(np.float32)
        models.append(model)
    rounded = [Motion(m.name, m.pos.astype(np.float32), m.quat.astype(np.float32), m.dt) for m in motions]
    return rollout(models, rounded, backend="mujoco")


def _on_cpu(ep):
    """The episode with its tensors copied to the host (where the oracle's live)."""
    return dataclasses.replace(
        ep,
        **{
            f.name: getattr(ep, f.name).cpu()
            for f in dataclasses.fields(ep)
            if isinstance(getattr(ep, f.name), torch.Tensor)
        },
    )


def _compare(space, designs, motions, min_reproducible, device="cpu"):
    warp_ep = _on_cpu(rollout(designs, motions, device=device))
    oracle_ep = rollout(designs, motions, backend="mujoco")
    again_ep = _rounded_oracle(space, designs, motions)

    # Same layout as the oracle: design-major worlds, joint fields padded to the widest design.
    for field in dataclasses.fields(oracle_ep):
        a, b = getattr(warp_ep, field.name), getattr(oracle_ep, field.name)
        if isinstance(b, torch.Tensor):
            assert a.shape == b.shape and a.dtype == b.dtype, field.name
    assert torch.equal(warp_ep.design_index, oracle_ep.design_index)
    assert torch.equal(warp_ep.motion_index, oracle_ep.motion_index)
    np.testing.assert_allclose(warp_ep.target_pos.numpy(), oracle_ep.target_pos.numpy(), atol=1e-6)

    cfg = get_reward("tracking", space)
    w, o, a = (evaluate(RewardInputs.from_episode(ep), cfg) for ep in (warp_ep, oracle_ep, again_ep))

    def pos_err_gap(x, y):
        """|mean position error [cm] of x - that of y| over the steps both count (NaN-free)."""
        common = x.counted & y.counted
        n = common.sum(1).clamp(min=1)
        mx = (x.pos_err.mean(-1) * common).sum(1) / n
        my = (y.pos_err.mean(-1) * common).sum(1) / n
        return 100.0 * (mx - my).abs()

    def reward_gap(x, y):
        return (x.reward - y.reward).abs() / y.reward.abs().clamp(min=1.0)

    start_moved = (oracle_ep.qpos[:, 0] - again_ep.qpos[:, 0]).abs().amax(dim=-1)
    reproducible = (
        (start_moved < 1e-4) & (a.survived == o.survived) & (pos_err_gap(a, o) <= 0.05) & (reward_gap(a, o) <= 0.005)
    )
    assert reproducible.float().mean() >= min_reproducible, reproducible.float().mean()
    r = reproducible
    assert torch.equal(w.survived[r], o.survived[r])
    assert bool((pos_err_gap(w, o)[r] <= POS_ERR_TOL).all()), pos_err_gap(w, o)[r].max()
    assert bool((reward_gap(w, o)[r] <= REWARD_REL_TOL).all()), reward_gap(w, o)[r].max()
    # Most reproducible episodes also end at the same step (a failing episode may cross the
    # termination threshold one step apart).
    same_length = (w.counted.sum(1) == o.counted.sum(1))[r]
    assert same_length.float().mean() >= 0.9
    return warp_ep, oracle_ep


def test_warp_matches_the_oracle_on_16_viperx_designs(device):
    space = get_space("viperx")
    designs = space.sample(16, seed=11)
    motions = motion_set("train", arms=1)[:2]
    _compare("viperx", designs, motions, min_reproducible=0.75, device=device)


@pytest.mark.slow
def test_warp_matches_the_oracle_on_64_viperx_designs():
    space = get_space("viperx")
    designs = space.sample(64, seed=0)
    motions = motion_set("train", arms=1)[:2]
    _compare("viperx", designs, motions, min_reproducible=0.75)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["aloha", "bimanual"])
def test_two_arm_designs_match_the_oracle(name):
    # Designs of the nominal topology only: each bimanual topology is a compile of minutes.
    space = get_space(name)
    sites = space.ee_sites()
    nominal = topology_of(space.model(space.nominal()), sites)
    designs = [d for d in space.sample(60, seed=2) if topology_of(space.model(d), sites) == nominal][:6]
    motions = for_space(motion_set("train", arms=2)[:2], name)
    _compare(name, designs, motions, min_reproducible=0.5)


def test_motions_of_different_lengths_pad_like_the_oracle(device):
    space = get_space("viperx")
    designs = [space.nominal()]
    long = motion_set("train", arms=1)[0]
    short = Motion("short", long.pos[:30], long.quat[:30])
    ep = _on_cpu(rollout(designs, [long, short], device=device))
    assert ep.qpos.shape[:2] == (2, long.steps)
    assert int(ep.alive[1].sum()) == 30 and not bool(ep.alive[1, 30:].any())
    # Past its motion's end a world repeats its last record; its target stays the last pose.
    assert torch.equal(ep.qpos[1, 30:], ep.qpos[1, 29:30].expand(long.steps - 30, -1))
    np.testing.assert_allclose(ep.target_pos[1, -1].numpy(), short.pos[-1], atol=1e-6)


def test_errors_name_the_problem():
    viperx, aloha = get_space("viperx"), get_space("aloha")
    motion = motion_set("train", arms=1)[0]
    with pytest.raises(ValueError, match="mix design spaces"):
        rollout([viperx.nominal(), aloha.nominal()], [motion], device="cpu")
    slow = Motion("slow", motion.pos, motion.quat, dt=0.04)
    with pytest.raises(ValueError, match="different dt"):
        rollout([viperx.nominal()], [motion, slow], device="cpu")
    with pytest.raises(ValueError, match="does not exist"):
        rollout([viperx.nominal()], [motion], device="cuda:7")
    with pytest.raises(ValueError, match="unknown rollout backend"):
        rollout([viperx.nominal()], [motion], backend="bullet", device="cpu")
    with pytest.raises(ValueError, match="end effector"):
        rollout([aloha.nominal()], [motion], device="cpu")
    quadruped = get_space("quadruped")
    with pytest.raises(ValueError, match="contacts"):
        rollout([quadruped.nominal()], [motion], device="cpu")


def test_every_backend_implements_the_interface_and_resolves_designs_like_their_space():
    """The registry's backends are `RolloutBackend`s; `resolve_designs` (the one design ->
    model resolver) compiles a Design to the model its space builds, keeps its MJCF, and
    raises for what a backend cannot run."""
    import mujoco

    from tt.sim.backends import BACKENDS, RolloutBackend, get_backend, resolve_designs

    assert BACKENDS == ("warp", "mjwarp", "newton", "mjbatch", "mujoco")
    for name in BACKENDS:
        impl = get_backend(name)
        assert isinstance(impl, RolloutBackend) and impl.name == name
        assert impl.perturbs == (name in ("warp", "mjbatch"))  # the two that add action noise (test_mjbatch.py)
    viperx, quadruped = get_space("viperx"), get_space("quadruped")
    designs = viperx.sample(3, seed=4)
    robots = resolve_designs(designs)
    for d, m, xml in zip(designs, robots.models, robots.mjcf):
        ref = viperx.model(d)
        assert xml == viperx.to_mjcf(d)
        for field in (
            "body_pos",
            "body_quat",
            "body_mass",
            "body_inertia",
            "jnt_axis",
            "jnt_range",
            "actuator_gainprm",
        ):
            np.testing.assert_array_equal(getattr(m, field), getattr(ref, field), err_msg=field)
    assert robots.ee_sites == ("ee_0",)
    raw = resolve_designs([viperx.model(designs[0])])
    assert raw.mjcf == (None,) and raw.sites == (("ee_0",),)
    with pytest.raises(ValueError, match="designs is empty; the 'warp' backend"):
        get_backend("warp").resolve([])
    with pytest.raises(ValueError, match="mix tt Designs and raw MjModels"):
        resolve_designs([designs[0], viperx.model(designs[1])])
    with pytest.raises(TypeError, match=r"designs\[1\] is a str"):
        resolve_designs([designs[0], "robot.xml"])
    with pytest.raises(ValueError, match="'quadruped' has contacts"):
        get_backend("newton").resolve([quadruped.nominal()])
    # The oracle runs any mix world by world; the batched backends need one set of end effectors.
    mixed = get_backend("mjwarp").resolve([designs[0], get_space("bimanual").nominal()])
    assert mixed.sites == (("ee_0",), ("ee_0", "ee_1"))
    with pytest.raises(ValueError, match=r"designs\[1\] .* has end effectors \['ee_0', 'ee_1'\]"):
        mixed.ee_sites
    assert isinstance(get_backend("mujoco").resolve([quadruped.nominal()]).models[0], mujoco.MjModel)


@pytest.mark.parametrize("space_name, backend, motion_steps", [("viperx", "warp", None), ("quadruped", "mjbatch", 20)])
def test_cli_rollout_reports_the_metrics_of_its_backend(tmp_path, space_name, backend, motion_steps, tt_cli):
    """`tt rollout` (warp by default, mjbatch for the quadruped's contacts) writes the
    metrics an evaluation of the same designs on the same backend gives, and counts world-steps."""
    import json

    from tt.baselines.evaluate import evaluate_designs
    from tt.sim.designs import load_designs
    from tt.sim.motions import get_motion, save_npz

    args = ["rollout", "--space", space_name, "--n", "3", "--seed", "5", "--out", str(tmp_path / "run")]
    toss = get_motion("toss")
    if motion_steps is None:
        args += ["--motion", "toss", "--motion", "scrub"]
        motions = for_space([toss, get_motion("scrub")], space_name)
    else:
        short = Motion("toss[:20]", toss.pos[:motion_steps], toss.quat[:motion_steps], toss.dt)
        save_npz(short, tmp_path / "short.npz")
        args += ["--motion", str(tmp_path / "short.npz")]
        motions = for_space([short], space_name)
    code, text = tt_cli(args)
    assert code == 0, text
    assert "world-steps/s" in text and f"backend {backend}" in text, text
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    designs = load_designs(tmp_path / "run" / "designs.json")
    assert designs == get_space(space_name).sample(3, 5)
    assert summary["backend"] == backend and summary["worlds"] == 3 * len(motions)
    assert summary["world_steps"] == 3 * 10 * sum(m.steps for m in motions)  # 0.002 s physics, 50 Hz control
    ref = evaluate_designs(designs, motions, "tracking", backend=backend, device="cpu")
    for key in ("pos_err", "survival", "reward"):
        # Strict JSON: a NaN (no step counted) is written as null.
        stored = np.array(
            [[np.nan if v is None else v for v in row] for row in summary["per_world"][key]], dtype=np.float64
        )
        np.testing.assert_allclose(stored, ref.metrics[key], rtol=1e-6, atol=1e-9)
    assert (tmp_path / "run" / "episode.npz").stat().st_size > 0


def test_cli_rollout_errors_name_the_problem(tmp_path, tt_cli):
    code, text = tt_cli(["rollout", "--space", "quadruped", "--n", "1", "--backend", "warp"])
    assert code != 0 and "has contacts" in text, text
    code, text = tt_cli(["rollout", "--space", "viperx", "--n", "1", "--device", "cuda:7"])
    assert code != 0 and "does not exist" in text, text
    code, text = tt_cli(["rollout", "--space", "viperx", "--n", "1", "--backend", "bullet"])
    assert code != 0 and "bullet" in text, text
    code, text = tt_cli(["rollout", "--space", "cheetah", "--n", "1"])
    assert code != 0 and "cheetah" in text, text
    code, text = tt_cli(["rollout", "--space", "viperx", "--n", "1", "--motion", "nope"])
    assert code != 0 and "nope" in text, text


@pytest.mark.parametrize("backend", ["warp", "mjwarp"])
def test_graph_replay_matches_plain_launches(backend, device):
    """The captured-graph path (the default on CUDA; forced on the CPU here, where Warp can
    replay a capture too) records exactly what plain launches record: one replay of a whole
    chunked, perturbed rollout ("warp"), or of each control step's physics ("mjwarp")."""
    space = get_space("viperx")
    designs = space.sample(2, seed=3)
    first = motion_set("train", arms=1)[0]
    motions = [Motion("short", first.pos[:12], first.quat[:12])]
    noise = dict(action_noise=0.05, noise_seed=7, chunk=5) if backend == "warp" else {}
    plain = _on_cpu(rollout(designs, motions, backend=backend, device=device, graph=False, **noise))
    graphed = _on_cpu(rollout(designs, motions, backend=backend, device=device, graph=True, **noise))
    default = _on_cpu(rollout(designs, motions, backend=backend, device=device, **noise))
    for field in dataclasses.fields(plain):
        a = getattr(plain, field.name)
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, getattr(graphed, field.name)), field.name
            assert torch.equal(a, getattr(default, field.name)), field.name
    assert bool(plain.alive.any()) and float(plain.qpos.abs().sum()) > 0
    with pytest.raises(ValueError, match="graph=True with differentiable"):
        from tt.kernels.model import build_tree_model
        from tt.kernels.rollout import motion_arrays, rollout_tree
        from tt.sim.controller import IKConfig

        tree = build_tree_model([space.model(designs[0])], space.ee_sites(), device=device)
        marrays = motion_arrays(first.pos[None, :4], first.quat[None, :4], [4], device=device)
        rollout_tree(tree, marrays, 1, 4, **IKConfig().rollout_args(), differentiable=True, graph=True)
