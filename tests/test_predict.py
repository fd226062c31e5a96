"""`tt predict`: the model as a critic. JSON schema, clear errors for an unknown design space
or motion and for a checkpoint of another design space; the predicted reward is the reward of
the predicted dynamics with the design inpainted."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from tt.cli import app
from tt.sim.designs import get_space, save_designs

pytestmark = pytest.mark.usefixtures("single_thread")

SPACE = "viperx-nominal"


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny viperx-nominal model of the robot and dynamics tasks, two steps on one online
    refresh (4 designs x 1 motion)."""
    from tt.dit.online import OnlineConfig
    from tt.dit.train import TrainConfig, train

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("predict") / "run"
    cfg = TrainConfig(
        out=str(out),
        task="robot+dynamics",
        size="tiny",
        steps=2,
        batch_size=4,
        warmup_steps=1,
        device="cpu",
        checkpoint_every=2,
        online=OnlineConfig(space=SPACE, designs=4, motions=1, refresh_every=100, buffer=1, min_steps=8),
    )
    try:
        result = train(cfg)
    finally:
        torch.set_num_threads(threads)
    return result.checkpoint


@pytest.fixture(scope="module")
def designs_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("designs") / "designs.json"
    save_designs(get_space(SPACE).sample(3, seed=5), path)
    return path


def _invoke(*args):
    # Wide enough that the table's columns are not cut.
    return CliRunner().invoke(app, ["predict", *map(str, args)], env={"COLUMNS": "240"})


def test_checkpoint_records_its_design_space(checkpoint):
    from tt.dit.checkpoint import load_model

    assert load_model(checkpoint).space == SPACE


def test_json_schema(checkpoint, designs_file, tmp_path):
    out = tmp_path / "pred.json"
    r = _invoke(
        "--design",
        designs_file,
        "--motion",
        "toss",
        "--motion",
        "scrub",
        "--checkpoint",
        checkpoint,
        "--reward",
        "tracking_torque",
        "--samples",
        "2",
        "--json",
        out,
    )
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert d["reward"] == "tracking_torque" and d["motions"] == ["toss", "scrub"]
    assert {"reward", "motions", "predictions"} <= set(d)
    pairs = [(p["design"], p["motion"]) for p in d["predictions"]]
    assert pairs == [(i, m) for i in range(3) for m in ("toss", "scrub")]
    for p in d["predictions"]:
        assert set(p) == {"design", "motion", "reward", "metrics"}
        assert isinstance(p["reward"], float) and math.isfinite(p["reward"])
        assert {"pos_err", "orn_err", "survival", "torque", "reward", "length"} <= set(p["metrics"])
        assert p["metrics"]["reward"] == p["reward"]
        # Over all 8 query steps, counted or not: the counted mean's where every step counted.
        if p["metrics"]["length"] == 8:
            assert p["metrics"]["query_pos_err"] == pytest.approx(p["metrics"]["pos_err"], rel=1e-5)
        assert p["metrics"]["query_pos_err"] >= 0
    assert "design" in r.output and "toss" in r.output  # the table
    # Its percent columns hold the JSON's shares x 100 (within 2 cm used to show "-").
    header = next(line for line in r.output.splitlines() if "within 2 cm (%)" in line)
    col = [c.strip() for c in header.split("┃")].index("within 2 cm (%)")
    cells = [
        float(line.split("│")[col])
        for line in r.output.splitlines()
        if line.startswith("│") and line.split("│")[2].strip() in ("toss", "scrub")
    ]
    shares = [100.0 * p["metrics"]["within_2cm"] for p in d["predictions"]]
    assert cells == pytest.approx(shares, rel=5e-3, abs=0.05)
    # designs.json#i reports the index in the file.
    r = _invoke(
        "--design",
        f"{designs_file}#-1",
        "--motion",
        "toss",
        "--checkpoint",
        checkpoint,
        "--json",
        out,
    )
    assert r.exit_code == 0, r.output
    assert [p["design"] for p in json.loads(out.read_text())["predictions"]] == [2]


def test_default_ddim_steps_are_the_critics(checkpoint, designs_file, tmp_path):
    """tt predict samples CRITIC_DDIM_STEPS steps, not all 100."""
    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import CRITIC_DDIM_STEPS, predict_designs
    from tt.sim.designs import load_designs
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward

    out = tmp_path / "pred.json"
    r = _invoke(
        "--design",
        designs_file,
        "--motion",
        "toss",
        "--checkpoint",
        checkpoint,
        "--reward",
        "tracking",
        "--device",
        "cpu",
        "--json",
        out,
    )
    assert r.exit_code == 0, r.output
    got = [p["reward"] for p in json.loads(out.read_text())["predictions"]]
    trained, cfg = load_model(checkpoint), get_reward("tracking", SPACE)
    motion = for_space([resolve_motion("toss")], SPACE)
    designs = load_designs(designs_file)
    for steps, same in ((CRITIC_DDIM_STEPS, True), (None, False)):
        want = predict_designs(trained, designs, motion, cfg, num_steps=steps).reward[:, 0]
        assert np.allclose(got, want, rtol=1e-5) == same, steps


def test_unknown_space_or_motion_fails_clearly(checkpoint, designs_file, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"designs": [{"space": "hexapod", "discrete": {}, "continuous": {}}]}))
    r = _invoke("--design", bad, "--motion", "toss", "--checkpoint", checkpoint)
    assert r.exit_code == 2 and "unknown design space 'hexapod'" in r.output and "viperx-nominal" in r.output
    r = _invoke("--design", designs_file, "--motion", "moonwalk", "--checkpoint", checkpoint)
    assert r.exit_code == 2 and "moonwalk" in r.output and "toss" in r.output, r.output


def test_checkpoint_of_another_space_is_refused(checkpoint, designs_file, tmp_path):
    from tt.dit.checkpoint import load_checkpoint, save_checkpoint

    state = load_checkpoint(checkpoint)
    state.pop("format")
    state["space"] = "viperx"
    other = save_checkpoint(tmp_path / "viperx.pt", state)
    r = _invoke("--design", designs_file, "--motion", "toss", "--checkpoint", other)
    assert r.exit_code == 2, r.output
    assert "'viperx'" in r.output and "'viperx-nominal'" in r.output and "trained on design space" in r.output


def test_prediction_is_the_reward_of_the_inpainted_samples(checkpoint):
    """`predict_designs` = the mean over K samples of `PredictedReward` on `sample(known=...)`
    of `design_query`, the embodiment kept exactly; checked by redoing one pair by hand."""
    from tt.dit.checkpoint import load_model
    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import ROBOT
    from tt.guidance.predicted import PredictedReward, design_query, predict_designs
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward

    trained = load_model(checkpoint)
    sp = get_space(SPACE)
    design = sp.sample(1, seed=9)
    motion = for_space([resolve_motion("toss")], SPACE)[0]
    cfg = get_reward("tracking", SPACE)
    pred = predict_designs(trained, design, [motion], cfg, samples=3, num_steps=4, seed=11, via="inpaint")
    q, known = design_query(trained.layout, trained.normalizer, motion, [sp.model(design[0])] * 3)
    res = sample(
        trained.model,
        q.tokens,
        ROBOT,
        scheduler=CosineDDIM(100),
        num_steps=4,
        generator=torch.Generator().manual_seed(11),
        known=known,
    )
    for n, m in known.items():
        assert torch.equal(res.tokens.values[n][m], q.tokens.values[n][m])  # the design is kept exactly
    by_hand = PredictedReward(trained.layout, trained.normalizer, cfg, q)(res.tokens.values).double().mean()
    np.testing.assert_allclose(pred.reward[0, 0], float(by_hand), rtol=1e-5)


def test_prediction_is_the_reward_of_the_dynamics_task_samples(checkpoint):
    """With a model trained on the dynamics task, `predict_designs` defaults to it: the mean
    over K samples of `PredictedReward` on `sample(DYNAMICS)` of `design_query`, which keeps
    the embodiment (a condition there) exactly; checked by redoing one pair by hand."""
    from tt.dit.checkpoint import load_model
    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import DYNAMICS
    from tt.guidance.predicted import PredictedReward, design_query, predict_designs
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward

    trained = load_model(checkpoint)
    assert trained.tasks == ("robot", "dynamics") and trained.trained_on("dynamics")
    sp = get_space(SPACE)
    design = sp.sample(1, seed=9)
    motion = for_space([resolve_motion("toss")], SPACE)[0]
    cfg = get_reward("tracking", SPACE)
    pred = predict_designs(trained, design, [motion], cfg, samples=3, num_steps=4, seed=11)
    q, known = design_query(trained.layout, trained.normalizer, motion, [sp.model(design[0])] * 3)
    res = sample(
        trained.model,
        q.tokens,
        DYNAMICS,
        scheduler=CosineDDIM(100),
        num_steps=4,
        generator=torch.Generator().manual_seed(11),
    )
    for n, m in known.items():
        assert torch.equal(res.tokens.values[n][m], q.tokens.values[n][m])
    by_hand = PredictedReward(trained.layout, trained.normalizer, cfg, q)(res.tokens.values).double().mean()
    np.testing.assert_allclose(pred.reward[0, 0], float(by_hand), rtol=1e-5)
    inpainted = predict_designs(trained, design, [motion], cfg, samples=3, num_steps=4, seed=11, via="inpaint")
    assert inpainted.reward[0, 0] != pred.reward[0, 0]


def test_dynamics_needs_a_model_trained_on_it(checkpoint):
    import dataclasses

    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import predict_designs
    from tt.kernels.errors import TTError
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward

    robot_only = dataclasses.replace(load_model(checkpoint), tasks=("robot",))
    motion = for_space([resolve_motion("toss")], SPACE)
    cfg = get_reward("tracking", SPACE)
    with pytest.raises(TTError, match=r"trained on the tasks \['robot'\], not 'dynamics'"):
        predict_designs(robot_only, get_space(SPACE).sample(1, seed=9), motion, cfg, num_steps=2, via="dynamics")
    with pytest.raises(ValueError, match="via 'both' is not one of"):
        predict_designs(robot_only, get_space(SPACE).sample(1, seed=9), motion, cfg, num_steps=2, via="both")


def test_zeroth_order_dynamics_critic(checkpoint):
    """Zeroth-Order's "dynamics" critic (the default for a model trained on that task) scores
    each candidate by the dynamics task's prediction from its sampled embodiment: the same
    embodiment as the joint critic's run with that seed, other dynamics, and the reward equal
    to `PredictedReward` on a by-hand redo of the two sampling calls. A model without the
    dynamics task is refused."""
    import dataclasses

    from tt.baselines.problem import Problem
    from tt.dit.checkpoint import load_model
    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import DYNAMICS, ROBOT
    from tt.guidance.compose import ComposedModel, compose_tokens, split_tokens
    from tt.guidance.predicted import PredictedReward, build_query
    from tt.guidance.zeroth import CandidateSampler, SamplerConfig, ZerothOrder
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward
    from tt.tokens.schema import STEP_ROLES

    trained = load_model(checkpoint)
    motion = for_space([resolve_motion("toss")], SPACE)[0]
    cfg = get_reward("tracking", SPACE)
    sampler = CandidateSampler(trained, "cpu")
    joint = sampler.run([motion], cfg, 3, seed=4, num_steps=4, critic="joint")
    critic = sampler.run([motion], cfg, 3, seed=4, num_steps=4, critic="dynamics")
    steps = {s.name for s in joint.layout.specs if s.role in STEP_ROLES}
    assert steps and len(steps) < len(joint.layout.specs)
    for name, v in joint.tokens.values.items():
        if name not in steps:
            assert torch.equal(v, critic.tokens.values[name]), name
    assert any(not torch.equal(joint.tokens.values[n], critic.tokens.values[n]) for n in steps)
    # By hand: the robot task, then the dynamics task on its tokens, one generator.
    composed = ComposedModel(trained.model, 1)
    g = torch.Generator().manual_seed(4)
    q = build_query(trained.layout, trained.normalizer, motion, 3, generator=torch.Generator().manual_seed(4))
    robot = sample(
        composed, compose_tokens(trained.layout, [q.tokens]), ROBOT, scheduler=CosineDDIM(100), num_steps=4, generator=g
    )
    dyn = sample(composed, robot.tokens, DYNAMICS, scheduler=CosineDDIM(100), num_steps=4, generator=g)
    scored = split_tokens(trained.layout, dyn.tokens, 1)[0].values
    by_hand = PredictedReward(trained.layout, trained.normalizer, cfg, q)(scored).double().numpy()
    np.testing.assert_allclose(critic.reward[:, 0], by_hand, rtol=1e-5)
    # critic_samples 2: the mean of two dynamics draws from the same robot draw (one generator
    # again), the tokens those of the first.
    averaged = sampler.run([motion], cfg, 3, seed=4, num_steps=4, critic="dynamics", critic_samples=2)
    g = torch.Generator().manual_seed(4)
    robot = sample(
        composed, compose_tokens(trained.layout, [q.tokens]), ROBOT, scheduler=CosineDDIM(100), num_steps=4, generator=g
    )
    scorer = PredictedReward(trained.layout, trained.normalizer, cfg, q)
    draws = [
        sample(composed, robot.tokens, DYNAMICS, scheduler=CosineDDIM(100), num_steps=4, generator=g).tokens
        for _ in range(2)
    ]
    each = [scorer(split_tokens(trained.layout, d, 1)[0].values).double().numpy() for d in draws]
    assert not np.allclose(each[0], each[1])  # two draws, not one twice
    np.testing.assert_allclose(each[0], by_hand, rtol=1e-5)
    np.testing.assert_allclose(averaged.reward[:, 0], (each[0] + each[1]) / 2, rtol=1e-5)
    for name, v in critic.tokens.values.items():
        assert torch.equal(v, averaged.tokens.values[name]), name
    with pytest.raises(ValueError, match="critic_samples = 2: must be >= 1, and 1 for the joint critic"):
        sampler.run([motion], cfg, 3, seed=4, num_steps=4, critic="joint", critic_samples=2)
    with pytest.raises(ValueError, match="critic_samples = 3 needs the 'dynamics' critic"):
        SamplerConfig(critic="joint", critic_samples=3)

    problem = Problem(SPACE, (motion,), "tracking", 2, seed=0, backend="warp", device="cpu")
    zo = ZerothOrder(SamplerConfig(num_steps=2), model=trained)
    assert zo.generate(problem)[2]["critic"] == "dynamics"
    robot_only = dataclasses.replace(trained, tasks=("robot",))
    assert ZerothOrder(SamplerConfig(num_steps=2), model=robot_only).generate(problem)[2]["critic"] == "joint"
    with pytest.raises(ValueError, match=r"critic 'dynamics' needs a model trained on the dynamics task"):
        ZerothOrder(SamplerConfig(num_steps=2, critic="dynamics"), model=robot_only).generate(problem)
    with pytest.raises(ValueError, match="critic = 'both'"):
        SamplerConfig(critic="both")


def test_zeroth_order_with_a_critic_model(checkpoint):
    """A critic model (another checkpoint's dynamics task) scores the sampling model's robot
    draws: the embodiment is the sampling model's own draw, the reward that of the critic's
    dynamics on a by-hand redo of the two sampling calls (one generator). A critic with
    another normaliser gets the embodiment in its own units, and its dynamics are read in
    them. A critic without the dynamics task, of another space, or asked for the joint
    critic is refused."""
    import copy
    import dataclasses

    from tt.baselines.problem import Problem
    from tt.dit.checkpoint import load_model
    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import DYNAMICS, ROBOT
    from tt.guidance.compose import ComposedModel, compose_tokens, split_tokens
    from tt.guidance.predicted import CheckpointSpaceError, PredictedReward, build_query
    from tt.guidance.zeroth import CandidateSampler, SamplerConfig, ZerothOrder, renormalize
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward
    from tt.tokens.batch import TokenBatch
    from tt.tokens.normalize import Normalizer
    from tt.tokens.schema import STEP_ROLES

    trained = load_model(checkpoint)
    net = copy.deepcopy(trained.model)
    with torch.no_grad():  # another network: the critic must not be the sampling model in disguise
        for p in net.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    low = {k: np.asarray(v) for k, v in trained.normalizer.low.items()}
    high = {k: np.asarray(v) + (np.asarray(v) - low[k]) for k, v in trained.normalizer.high.items()}
    motion = for_space([resolve_motion("toss")], SPACE)[0]
    cfg = get_reward("tracking", SPACE)
    q = build_query(trained.layout, trained.normalizer, motion, 3, generator=torch.Generator().manual_seed(4))
    own = CandidateSampler(trained, "cpu").run([motion], cfg, 3, seed=4, num_steps=4, critic="dynamics")
    for units in ("same", "other"):
        norm = trained.normalizer if units == "same" else Normalizer(low, high, trained.normalizer.version)
        critic = dataclasses.replace(trained, model=net, normalizer=norm, tasks=("dynamics",), path=None)
        got = CandidateSampler(trained, "cpu", critic_model=critic).run(
            [motion], cfg, 3, seed=4, num_steps=4, critic="dynamics"
        )
        g = torch.Generator().manual_seed(4)
        robot = sample(
            ComposedModel(trained.model, 1),
            compose_tokens(trained.layout, [q.tokens]),
            ROBOT,
            scheduler=CosineDDIM(100),
            num_steps=4,
            generator=g,
        ).tokens
        given = (
            robot
            if units == "same"
            else TokenBatch(renormalize(robot.values, trained.normalizer, norm), robot.ids, robot.mask, robot.version)
        )
        dyn = sample(ComposedModel(net, 1), given, DYNAMICS, scheduler=CosineDDIM(100), num_steps=4, generator=g)
        by_hand = PredictedReward(trained.layout, norm, cfg, q)(split_tokens(trained.layout, dyn.tokens, 1)[0].values)
        np.testing.assert_allclose(got.reward[:, 0], by_hand.double().numpy(), rtol=1e-5)
        assert not np.allclose(got.reward, own.reward)  # the critic's dynamics, not the sampling model's
        for spec in trained.layout.specs:  # the candidates are the sampling model's draws, in its units
            if spec.role not in STEP_ROLES:
                assert torch.equal(got.tokens.values[spec.name], own.tokens.values[spec.name]), spec.name
    if units == "other":  # padding stays padding in the critic's units
        from tt.tokens.normalize import is_padding

        for name, v in robot.values.items():
            assert torch.equal(is_padding(v), is_padding(given.values[name])), name

    sampler = CandidateSampler(trained, "cpu", critic_model=critic)
    with pytest.raises(ValueError, match="critic 'joint' would ignore it"):
        sampler.run([motion], cfg, 3, seed=4, num_steps=4, critic="joint")
    with pytest.raises(ValueError, match=r"not the dynamics task a critic needs"):
        CandidateSampler(trained, "cpu", critic_model=dataclasses.replace(critic, tasks=("robot",)))
    with pytest.raises(CheckpointSpaceError, match="'viperx'.*'viperx-nominal'"):
        CandidateSampler(trained, "cpu", critic_model=dataclasses.replace(critic, space="viperx"))
    with pytest.raises(ValueError, match="does not go with critic = 'joint'"):
        SamplerConfig(critic="joint", critic_checkpoint=str(checkpoint))
    problem = Problem(SPACE, (motion,), "tracking", 2, seed=0, backend="warp", device="cpu")
    info = ZerothOrder(SamplerConfig(num_steps=2, critic_checkpoint=str(checkpoint)), model=trained).generate(problem)[
        2
    ]
    assert info["critic"] == "dynamics" and info["critic_checkpoint"] == str(checkpoint)


def test_optimize_refuses_a_joint_critic_checkpoint(checkpoint):
    result = CliRunner().invoke(
        app,
        [
            "optimize",
            "--space",
            SPACE,
            "--motion",
            "toss",
            "--method",
            "zeroth",
            "--checkpoint",
            str(checkpoint),
            "--config",
            "critic=joint",
            "--config",
            f"critic_checkpoint={str(checkpoint)!r}",
        ],
    )
    assert result.exit_code != 0 and "critic = 'joint'" in result.output, result.output
    result = CliRunner().invoke(
        app,
        [
            "optimize",
            "--space",
            SPACE,
            "--motion",
            "toss",
            "--method",
            "zeroth",
            "--checkpoint",
            str(checkpoint),
            "--config",
            "critic_checkpoint=missing.pt",
        ],
    )
    assert result.exit_code != 0 and "missing.pt" in result.output and "does not exist" in result.output, result.output


def test_shipped_dynamics_specialist_critics_the_shipped_generalist():
    """The shipped ViperX dynamics specialist (what `tt predict` uses by default) is a
    dynamics-task model of the generalist's space and layout, so it can be the generalist's
    Zeroth-Order critic (`tt optimize --config critic_checkpoint=...`)."""
    from tt.dit.checkpoint import default_checkpoint, load_model
    from tt.guidance.zeroth import check_critic

    generalist = load_model(default_checkpoint("viperx"))
    specialist = load_model(default_checkpoint("viperx", task="dynamics"))
    assert specialist.path.name == "viperx_mini_dynamics.pt" and specialist.tasks == ("dynamics",)
    check_critic(generalist, specialist)


def test_critic_on_designs_ranks_by_tt_predicts_reward_of_the_decoded_designs(checkpoint):
    """With critic_on="designs" every candidate is decoded and ranked by the critic's
    prediction for its design, exactly `predict_designs` on those designs (same DDIM steps,
    the problem's seed), from the sampling model's dynamics task or a critic model's; the
    joint critic and unknown inputs are refused (config and CLI)."""
    import copy
    import dataclasses

    from tt.baselines.problem import Problem
    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import predict_designs
    from tt.guidance.zeroth import SamplerConfig, ZerothOrder
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward

    trained = load_model(checkpoint)
    motion = for_space([resolve_motion("toss")], SPACE)[0]
    cfg = get_reward("tracking", SPACE)
    problem = Problem(SPACE, (motion,), "tracking", 4, seed=3, backend="warp", device="cpu")
    net = copy.deepcopy(trained.model)
    with torch.no_grad():  # another network, so a critic model that is ignored fails the comparison
        for p in net.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    other = dataclasses.replace(trained, model=net, tasks=("dynamics",), path=None)
    for critic in (None, other):
        res = ZerothOrder(
            SamplerConfig(num_steps=2, critic_on="designs", decode="all"), model=trained, critic_model=critic
        ).optimize(problem)
        order = res.info["ranking"]
        assert len(res.designs) == 4 and sorted(order) == [0, 1, 2, 3]  # projection decodes every candidate
        by_index = [res.designs[order.index(i)] for i in range(4)]
        pred = predict_designs(critic or trained, by_index, [motion], cfg, num_steps=2, seed=3)
        np.testing.assert_allclose(res.rewards, pred.reward[order, 0], rtol=1e-6)
        assert np.all(np.diff(res.rewards) <= 0) and res.best == res.designs[0]
        assert res.info["critic_on"] == "designs" and res.info["critic"] == "dynamics"
    with pytest.raises(ValueError, match="does not go with critic = 'joint'"):
        SamplerConfig(critic="joint", critic_on="designs")
    with pytest.raises(ValueError, match="critic_on = 'robots'"):
        SamplerConfig(critic_on="robots")
    result = CliRunner().invoke(
        app,
        [
            "optimize",
            "--space",
            SPACE,
            "--motion",
            "toss",
            "--method",
            "zeroth",
            "--checkpoint",
            str(checkpoint),
            "--config",
            "critic=joint",
            "--config",
            "critic_on=designs",
        ],
    )
    assert result.exit_code != 0 and "does not go with critic = 'joint'" in result.output, result.output
