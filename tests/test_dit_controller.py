"""The DiT as a closed-loop controller (`tt.dit.closed_loop`, `tt.dit.policies`).

References: the "warp" rollout backend (the DiffIK policy in the loop must reproduce it),
MuJoCo C (the commands recorded must be the ones physics ran: replaying them through
`mj_step` gives the recorded states), and the dataset's own tokenizer path
(`tt.tokens.episodes.episode_tokens` on a recorded episode: the control query must hold
exactly the tokens a training window of that episode holds). A stand-in network that
knows the DiffIK command checks the whole model path (query, DDIM, decoding, actuator
mapping): it must reproduce the DiffIK episode.
"""

from __future__ import annotations

import math
import warnings

import mujoco
import numpy as np
import pytest
import torch

from tt.dit.checkpoint import TrainedModel
from tt.dit.closed_loop import closed_loop_rollout
from tt.dit.ddim import CosineDDIM
from tt.dit.layout import layout_from_schema
from tt.dit.model import RoboDiT, get_config
from tt.dit.policies import ControllerConfig, IKPolicy, ModelPolicy
from tt.dit.tasks import CONTROL
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rollout import rollout
from tt.tokens.episodes import episode_tokens
from tt.tokens.normalize import Normalizer
from tt.tokens.tokenize import tokenize_models

STEPS = 12  # control steps per test rollout


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny model: a second thread only waits
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def problem():
    """Two 6-DoF ViperX designs (one kernel topology) that track toss and scrub under the
    DiffIK for the test's steps, and the DiffIK reference rollout of the warp backend."""
    space = get_space("viperx")
    motions = for_space([get_motion("toss"), get_motion("scrub")], "viperx")
    designs = []
    for d in space.sample(40, seed=11):
        if space.model(d).nu == 6:
            designs.append(d)
    designs = designs[:2]
    ref = rollout(designs, motions, backend="warp", device="cpu")
    assert bool(ref.alive[:, :STEPS].all()), "the fixture's designs should track the motions' first steps"
    return space, designs, motions, ref


@pytest.fixture(scope="module")
def trained(problem):
    """A tiny random DiT whose layout and normaliser fit the problem's robots (normaliser
    ranges from the reference episode, widened so the DiffIK commands lie inside +-1)."""
    space, designs, _, ref = problem
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models([space.model(d) for d in designs])
    T = ref.steps
    dyn = episode_tokens(ref, emb.index, step_index=torch.arange(T).expand(ref.worlds, T)).to_numpy()
    norm = Normalizer.fit([emb.tokens.to_numpy(), dyn])
    for k in norm.low:
        span = np.maximum(norm.high[k] - norm.low[k], 1e-3)
        norm.low[k] = norm.low[k] - 0.25 * span
        norm.high[k] = norm.high[k] + 0.25 * span
    counts = {n: int(np.asarray(emb.tokens.mask[n]).sum(1).max()) + 1 for n in emb.tokens.types}
    per_step = {n: int(np.asarray(dyn.mask[n]).reshape(ref.worlds, T, -1)[:, 0].sum(1).max()) + 1 for n in dyn.types}
    layout = layout_from_schema({**counts, **per_step}, steps=8)
    torch.manual_seed(0)
    model = RoboDiT(layout, get_config("tiny")).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return TrainedModel(model, norm, layout, 0)


def test_ik_policy_reproduces_the_warp_backend(problem):
    """The loop with the DiffIK as the policy is the warp backend's fused rollout, step by
    step: same start posture, same commands, same physics, same records."""
    _, designs, motions, ref = problem
    ep = closed_loop_rollout(designs, motions, IKPolicy(), device="cpu", steps=STEPS)
    assert ep.qpos.shape == (4, STEPS, 6) and ep.ee_pos.shape == (4, STEPS, 1, 3)
    assert ep.design_index.tolist() == [0, 0, 1, 1] and ep.motion_index.tolist() == [0, 1, 0, 1]
    for name in ("qpos", "qvel", "ctrl", "act_force", "act_vel", "ee_pos", "ee_quat", "target_pos", "target_quat"):
        torch.testing.assert_close(getattr(ep, name), getattr(ref, name)[:, :STEPS], atol=1e-5, rtol=0, msg=name)
    assert torch.equal(ep.alive, ref.alive[:, :STEPS])


def test_commands_are_what_physics_ran(problem, trained):
    """Replaying the recorded commands of a model-controlled episode in MuJoCo C (substeps
    of mj_step from the start posture) gives the recorded states, and each record's actuator
    forces, velocities and end-effector pose are MuJoCo's at the recorded state and command."""
    space, designs, motions, _ = problem
    from tt.dit.closed_loop import ArmWorlds

    ep = closed_loop_rollout(designs, motions, ModelPolicy(trained), device="cpu", steps=STEPS)
    models = [space.model(d) for d in designs]
    start = ArmWorlds(models, space.ee_sites(), motions, device="cpu").reset().qpos.clone()
    assert float((ep.ctrl[:, 1:] - ep.ctrl[:, :-1]).abs().max()) > 1e-2  # the random model does move the arm
    for w in range(ep.worlds):
        m = models[int(ep.design_index[w])]
        data, probe = mujoco.MjData(m), mujoco.MjData(m)
        data.qpos[:] = start[w, : m.nq].double().numpy()
        for k in range(int(ep.lengths()[w])):
            data.ctrl[:] = ep.ctrl[w, k].double().numpy()
            for _ in range(10):
                mujoco.mj_step(m, data)
            # float32 kernels vs float64 MuJoCo, with servos pushed into joint limits by the
            # random commands: the tolerance of the kernels' own MuJoCo test (1e-3 rad).
            np.testing.assert_allclose(ep.qpos[w, k].numpy(), data.qpos, atol=1e-3, err_msg=f"world {w} step {k}")
            probe.qpos[:], probe.qvel[:], probe.ctrl[:] = (
                ep.qpos[w, k].numpy(),
                ep.qvel[w, k].numpy(),
                ep.ctrl[w, k].numpy(),
            )
            mujoco.mj_forward(m, probe)
            scale = np.abs(probe.actuator_force).max()
            np.testing.assert_allclose(ep.act_force[w, k].numpy(), probe.actuator_force, atol=1e-5 * scale + 1e-4)
            np.testing.assert_allclose(ep.act_vel[w, k].numpy(), probe.actuator_velocity, atol=1e-5)
            np.testing.assert_allclose(ep.ee_pos[w, k, 0].numpy(), probe.site_xpos[0], atol=1e-5)


def test_query_holds_the_training_window_of_the_episode(problem, trained):
    """At control step k the query is the training window starting at record k - 1 of the
    episode being run (embodiment, clean state, targets; time IDs k - 1 .. k + 6)."""
    _, designs, motions, _ = problem
    k = 5
    seen = {}

    class Recording(IKPolicy):
        def __call__(self, step, worlds, state):
            if step == k:
                seen["worlds"], seen["state"] = worlds.clone(), {f: getattr(state, f).clone() for f in vars(state)}
            return super().__call__(step, worlds, state)

    rec_policy = Recording()
    ep = closed_loop_rollout(designs, motions, rec_policy, device="cpu", steps=STEPS)
    from tt.dit.closed_loop import StepState

    policy = ModelPolicy(trained)
    policy.reset(rec_policy.ctx)
    tokens, slot = policy.query(k, seen["worlds"], StepState(**seen["state"]))
    assert slot == 1
    layout, norm = trained.layout, trained.normalizer
    layout.check(tokens)
    window = torch.arange(k - 1, k + 7).expand(ep.worlds, 8)
    ref = episode_tokens(ep, policy.robots, step_index=window)
    for s in layout.specs:
        if s.role.value == "embodiment":
            continue
        P = s.per_step
        got_v = tokens.values[s.name].reshape(ep.worlds, 8, P, -1)
        got_i = tokens.ids[s.name].reshape(ep.worlds, 8, P, -1)
        got_m = tokens.mask[s.name].reshape(ep.worlds, 8, P)
        e = ref.values[s.name].shape[1] // 8
        want_m = ref.mask[s.name].reshape(ep.worlds, 8, e)
        want_v = norm.normalize_values(s.name, ref.values[s.name], ref.mask[s.name]).reshape(ep.worlds, 8, e, -1)
        assert torch.equal(got_m[:, :, :e], want_m) and not got_m[:, :, e:].any(), s.name
        assert torch.equal(got_i[:, :, :e][want_m], ref.ids[s.name].reshape(ep.worlds, 8, e, -1)[want_m]), s.name
        # Clean tokens: the current state (window step 0) and every target pose.
        clean = slice(None) if s.role.value == "condition" else slice(0, 1)
        if s.role.value != "action":
            torch.testing.assert_close(got_v[:, clean, :e], want_v[:, clean], atol=1e-6, rtol=0, msg=s.name)
        else:  # the last command, clean for a model trained told it (known_command)
            torch.testing.assert_close(got_v[:, 0, :e], want_v[:, 0], atol=1e-6, rtol=0, msg=s.name)
    # The model is told which tokens are clean and which it must denoise, as in training.
    import dataclasses

    from tt.dit.tasks import task_masks

    masks = task_masks(CONTROL, layout, tokens)
    dyn = masks.noised["dyna_joint_obs"].reshape(ep.worlds, 8, -1)
    assert not dyn[:, 0].any() and bool(
        dyn[:, 1:][tokens.mask["dyna_joint_obs"].reshape(ep.worlds, 8, -1)[:, 1:]].all()
    )
    assert bool(masks.noised["control"][tokens.mask["control"]].all())
    known = task_masks(dataclasses.replace(CONTROL, known_command=True), layout, tokens).noised["control"]
    real = tokens.mask["control"].reshape(ep.worlds, 8, -1)
    known = known.reshape(ep.worlds, 8, -1)
    assert not known[:, 0].any() and bool(known[:, 1:][real[:, 1:]].all())


def test_query_with_a_target_offset_gives_the_later_targets(problem, trained):
    """A model trained with control_target_offset L (`tt.dit.tasks.look_ahead`) is queried with
    the targets of steps k - 1 + L .. k + 6 + L, clamped at the motion's end, under the time
    IDs k - 1 .. k + 6; every other token is the query without the offset."""
    import dataclasses

    from tt.dit.closed_loop import ArmWorlds

    _, designs, motions, _ = problem
    plain = ModelPolicy(trained)
    ahead = ModelPolicy(trained, task=dataclasses.replace(plain.task, target_offset=2))
    space = problem[0]
    sim = ArmWorlds([space.model(d) for d in designs], space.ee_sites(), motions, device="cpu")
    state = sim.reset()
    ctx = None

    class Capture(IKPolicy):
        def reset(self, c):
            nonlocal ctx
            ctx = c
            super().reset(c)

    closed_loop_rollout(designs, motions, Capture(), device="cpu", steps=1)
    worlds = torch.arange(ctx.world_count)
    horizon = ctx.target_pos.shape[1]
    for policy in (plain, ahead):
        policy.reset(ctx)
    for k in (5, horizon - 3):
        a, _ = plain.query(k, worlds, state)
        b, _ = ahead.query(k, worlds, state)
        for name in a.values:
            if name != "target_pose":
                assert torch.equal(a.values[name], b.values[name]), name
            assert torch.equal(a.ids[name], b.ids[name]), name
        n, P = len(worlds), trained.layout["target_pose"].per_step
        got = b.values["target_pose"].reshape(n, 8, P, -1)
        plain_t = a.values["target_pose"].reshape(n, 8, P, -1)
        torch.testing.assert_close(got[:, :6], plain_t[:, 2:], atol=0, rtol=0)
        if k + 7 >= horizon:  # past the end both repeat the motion's last pose
            torch.testing.assert_close(got[:, 6:], plain_t[:, 7:].expand_as(got[:, 6:]), atol=0, rtol=0)


class IKEps(torch.nn.Module):
    """A stand-in network that knows the DiffIK command of the current step: its clean
    control tokens are that command at the token whose time ID is the current control step
    and +0.9 (a wrong command) everywhere else; eps follows (DDIM then ends at those tokens)."""

    def __init__(self, model: RoboDiT):
        super().__init__()
        self.layout = model.layout
        self.anchor = torch.nn.Parameter(torch.zeros(1))  # gives the policy a device
        self.scheduler = CosineDDIM(CONTROL.diffusion_steps)
        self.step = 0
        self.command = None  # (n, P) normalised command per control slot

    def forward(self, values, ids, noised, time, attend=None, outputs=None):
        t = int(round(float(time[0]) * self.scheduler.train_steps)) - 1
        ab = float(self.scheduler.alpha_bar(t))
        out = {}
        for n in outputs:
            if n != "control":
                out[n] = torch.zeros_like(values[n])
                continue
            spec = self.layout[n]
            b = values[n].shape[0]
            time_id = ids[n][..., spec.time_index].reshape(b, self.layout.steps, spec.per_step)
            x0 = torch.where(
                time_id == self.step, self.command[:, None, :], torch.full_like(self.command[:, None, :], 0.9)
            )
            x0 = x0.reshape(b, -1, 1)
            out[n] = (values[n] - ab**0.5 * x0) / (1 - ab) ** 0.5
        return out


def test_model_path_with_an_ik_network_reproduces_the_ik_episode(problem, trained):
    _, designs, motions, ref = problem
    stand_in = IKEps(trained.model)

    class Scripted(ModelPolicy):
        def reset(self, ctx):
            super().reset(ctx)
            self.ik = IKPolicy()
            self.ik.reset(ctx)

        def __call__(self, step, worlds, state):
            cmd = self.ik(step, worlds, state)  # (n, NU) per MuJoCo actuator
            act = self._actuator[self.ctx.design_index[worlds]]  # (n, P) actuator of each control slot
            slots = torch.gather(cmd, 1, act.clamp_min(0))
            stand_in.command = self.trained.normalizer.normalize_values("control", slots[..., None])[..., 0]
            stand_in.step = step
            return super().__call__(step, worlds, state)

    # One query per command: the stand-in knows only the current step's command.
    policy = Scripted(
        TrainedModel(stand_in, trained.normalizer, trained.layout, 0), config=ControllerConfig(ensemble=1)
    )
    ep = closed_loop_rollout(designs, motions, policy, device="cpu", steps=STEPS)
    # Normalising and denormalising the command rounds it by ~1e-7 rad per step.
    for name in ("qpos", "ctrl", "ee_pos"):
        torch.testing.assert_close(getattr(ep, name), getattr(ref, name)[:, :STEPS], atol=1e-4, rtol=0, msg=name)
    assert torch.equal(ep.alive, ref.alive[:, :STEPS])


class ChunkEps(torch.nn.Module):
    """A stand-in network whose clean control tokens, at every control slot, are
    `value(query, time ID)`: each query's chunk differs from the last one's at every step."""

    def __init__(self, model: RoboDiT):
        super().__init__()
        self.layout = model.layout
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.scheduler = CosineDDIM(CONTROL.diffusion_steps)
        self.query = 0

    @staticmethod
    def value(query: int, time_id):
        return 0.1 * math.sin(1.7 * query) + 0.01 * time_id - 0.1  # inside every joint's command range

    def forward(self, values, ids, noised, time, attend=None, outputs=None):
        t = int(round(float(time[0]) * self.scheduler.train_steps)) - 1
        ab = float(self.scheduler.alpha_bar(t))
        out = {n: torch.zeros_like(values[n]) for n in outputs if n != "control"}
        spec = self.layout["control"]
        x0 = self.value(self.query, ids["control"][..., spec.time_index].float())[..., None]
        out["control"] = (values["control"] - ab**0.5 * x0) / (1 - ab) ** 0.5
        return out


@pytest.mark.parametrize("ensemble,decay", [(1, 0.0), (3, 0.0), (7, 0.5), (4, -0.3), (None, 0.0)])
def test_temporal_ensembling_averages_the_recent_chunks(problem, trained, ensemble, decay):
    """With ``ensemble`` m, step k's command is the exp(-decay * age)-weighted mean of what
    the queries of steps k - m + 1 .. k predicted for step k (each from its own window)."""
    _, designs, motions, _ = problem
    stand_in = ChunkEps(trained.model)

    class Scripted(ModelPolicy):
        def __call__(self, step, worlds, state):
            stand_in.query = step
            return super().__call__(step, worlds, state)

    # 5 leading steps: the stand-in gives eps, and one step from pure noise divides its float32 rounding by
    # sqrt(alpha_bar) = 0.01, past this test's 1e-5 tolerance.
    config = ControllerConfig(num_steps=5, spacing="leading", ensemble=ensemble, ensemble_decay=decay)
    policy = Scripted(TrainedModel(stand_in, trained.normalizer, trained.layout, 0), config=config)
    ep = closed_loop_rollout(designs[:1], motions[:1], policy, device="cpu", steps=10)
    P = trained.layout["control"].per_step
    nu = ep.ctrl.shape[-1]
    m = trained.layout.steps - 1 if ensemble is None else ensemble  # None: all queries whose window holds the step
    for k in range(int(ep.lengths()[0])):
        queries = range(max(0, k - m + 1), k + 1)
        w = np.array([math.exp(-decay * (k - q)) for q in queries])
        mean = float(np.dot(w, [ChunkEps.value(q, k) for q in queries]) / w.sum())
        want = trained.normalizer.denormalize_values("control", torch.full((P, 1), mean))[:nu, 0]
        torch.testing.assert_close(ep.ctrl[0, k], want.float(), atol=1e-5, rtol=0, msg=f"step {k}")
    assert k == 9  # every step compared; the queries' chunks differ, so a wrong window or weight shows


def test_seeded_runs_repeat_and_seeds_differ(problem, trained):
    _, designs, motions, _ = problem

    def run(seed):
        policy = ModelPolicy(trained, config=ControllerConfig(seed=seed))
        return closed_loop_rollout(designs[:1], motions[:1], policy, device="cpu", steps=4)

    a, b, c = run(3), run(3), run(4)
    assert torch.equal(a.ctrl, b.ctrl) and torch.equal(a.qpos, b.qpos)
    assert not torch.equal(a.ctrl, c.ctrl)
    with pytest.raises(ValueError, match="num_steps"):
        ModelPolicy(trained, config=ControllerConfig(num_steps=6))
    with pytest.raises(ValueError, match="spacing"):
        ControllerConfig(spacing="middle")
    with pytest.raises(ValueError, match="ensemble"):
        ControllerConfig(ensemble=0)
    with pytest.raises(ValueError, match="ensemble_decay"):
        ControllerConfig(ensemble_decay=float("nan"))
    with pytest.raises(ValueError, match="8-step window"):
        ModelPolicy(trained, config=ControllerConfig(ensemble=8))


def test_validate_cli_runs_the_model_controller(problem, trained, tmp_path):
    """`tt validate --controller model --checkpoint CKPT` scores the model-controlled episode
    as `score_episode` does; a wrong controller name fails with a clear error."""
    import json

    from typer.testing import CliRunner

    from tt.baselines.evaluate import score_episode
    from tt.cli import app
    from tt.dit.checkpoint import save_checkpoint
    from tt.dit.ema import EMA
    from tt.dit.policies import model_rollout
    from tt.sim.designs import save_designs
    from tt.sim.motions import save_npz
    from tt.sim.motions.base import Motion

    _, designs, motions, _ = problem
    m = motions[0]
    short = Motion("toss_short", m.pos[:6], m.quat[:6], m.dt)
    save_npz(short, tmp_path / "toss_short.npz")
    save_designs(designs, tmp_path / "designs.json")
    ckpt = save_checkpoint(
        tmp_path / "run" / "checkpoints" / "step_0000001.pt",
        {
            "schema_version": trained.layout.schema_version,
            "model": trained.model.describe(),
            "state_dict": trained.model.state_dict(),
            "ema": EMA(trained.model).state_dict(),
            "normalizer": trained.normalizer.state_dict(),
            "train_config": {"task": "both", "control_diffusion_steps": 5},
            "step": 1,
        },
    )
    out = tmp_path / "val.json"
    args = [
        "validate",
        "--design",
        str(tmp_path / "designs.json"),
        "--motion",
        str(tmp_path / "toss_short.npz"),
        "--controller",
        str(ckpt),
        "--device",
        "cpu",
        "--json",
        str(out),
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["controller"] == "model" and "DiT controller" in res.output
    # The loop at the motion's placement in the workspace, as `tt validate` resolves it.
    placed = for_space([short], "viperx")
    ep = model_rollout(designs, placed, ckpt, device="cpu")
    _, metrics = score_episode(ep, designs, placed, "tracking")
    np.testing.assert_allclose(data["per_motion"]["reward"], metrics["reward"], rtol=1e-6)
    res = CliRunner().invoke(app, args[:-2] + ["--controller", "pid"])
    assert res.exit_code == 2 and "give ik, model, or a DiT checkpoint" in res.output
