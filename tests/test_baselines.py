"""Random and CMA-ES design optimizers: budgets, seeds, batched vs sequential, bad input, `tt optimize`.

References: the sequential mode's oracle (MuJoCo C + mink, one rollout at a time) for the
batched Warp evaluation; a synthetic objective with a known optimum for the CMA-ES update;
Random at the same number of candidates for the CMA-ES search. Problems use ViperX and
validation motions, cut short where a test needs speed only.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from tt.baselines import CMAES, CMAESConfig, CMAESPlan, Problem, RandomSearch, evaluate_designs
from tt.optimizers import get_optimizer
from tt.sim.designs import Design, get_space
from tt.sim.motions import Motion, for_space, get_motion, save_npz


def _motion(skill: str, seed: int = 100, steps: int | None = None) -> Motion:
    m = for_space([get_motion(skill, seed)], "viperx")[0]
    if steps is not None:
        m = Motion(f"{m.name}[:{steps}]", m.pos[:steps], m.quat[:steps], m.dt)
    return m


def _problem(motions, reward="tracking", budget=20, seed=0, **kw) -> Problem:
    return Problem(space="viperx", motions=tuple(motions), reward=reward, budget=budget, seed=seed, **kw)


# ------------------------------------------------------------------------------ search quality
def test_cmaes_beats_random_at_equal_budget():
    """Same problem, same seed, 30 candidates each. tracking_weight on the full toss: the mass
    penalty (10 per kg above 3.2 kg per step) rewards shrinking links, which random sampling
    cannot refine. (Over seeds 0-5 CMA-ES won 4, tied 1 and lost 1 to a lucky random design.)"""
    p = _problem([_motion("toss")], reward="tracking_weight", budget=30, seed=0)
    rnd = RandomSearch().optimize(p)
    cma = CMAES().optimize(p)
    assert len(rnd.designs) == len(cma.designs) == 30
    assert rnd.rollouts == cma.rollouts == 30
    assert cma.best_reward > rnd.best_reward + 1.0
    # The winner came from the CMA-ES generations, not from the screening batch.
    assert int(np.argmax(cma.rewards)) >= cma.info["screen"]
    # The history is the running best: never decreasing, ending at the best reward.
    assert np.all(np.diff(cma.history) >= 0) and cma.history[-1] == pytest.approx(cma.best_reward)


def test_cmaes_update_moves_to_a_known_optimum(monkeypatch):
    """With a synthetic objective (minus the squared distance of the normalised continuous
    values to a target) the restart's mean converges to the target: the sign of the update,
    the [0, 1] normalisation and the decoding are right."""
    monkeypatch.setattr("tt.baselines.cmaes.warm_up_problem", lambda *a, **k: 0.0)
    space = get_space("viperx")
    start = space.sample(1, seed=3)[0]
    lo = np.array([q.low for q in space.continuous_params(start.discrete)])
    hi = np.array([q.high for q in space.continuous_params(start.discrete)])
    target = np.linspace(0.2, 0.8, len(lo))

    class Synthetic(CMAES):
        def evaluate(self, problem, designs):
            x = np.array([(np.array(d.continuous) - lo) / (hi - lo) for d in designs])
            return -np.sum((x - target) ** 2, axis=1)

    p = _problem([_motion("toss", steps=10)], budget=600, seed=3)
    res = Synthetic(CMAESConfig(popsize=10, generations=60)).optimize(p)
    assert res.info["restarts"] == 1 and res.info["screen"] == 0
    assert all(d.discrete == start.discrete for d in res.designs)
    x = np.array([d.continuous for d in res.designs])
    assert np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12)
    assert res.rewards[:10].max() < -0.1  # the first generation is far from the target ...
    assert res.best_reward > -1e-3  # ... the search ends within ~0.01 of it per parameter


def test_plan_spends_the_budget():
    cfg = CMAESConfig()
    p = _problem([_motion("toss", steps=10)], budget=60)
    assert CMAES(cfg).plan(p) == CMAESPlan(restarts=2, generations=3, screen=30)
    assert CMAES(CMAESConfig(screen=0.0)).plan(p) == CMAESPlan(restarts=4, generations=3, screen=0)
    # A budget of one population: one generation, no screening.
    assert CMAES(cfg).plan(_problem(p.motions, budget=5)) == CMAESPlan(restarts=1, generations=1, screen=0)
    # Left-over candidates go to the screening batch; nothing exceeds the budget.
    plan = CMAES(cfg).plan(_problem(p.motions, budget=47))
    assert plan.screen + plan.restarts * plan.generations * cfg.popsize == 47


def test_budget_below_one_restart_warns(caplog):
    """Below popsize x generations CMA-ES runs a cut-short restart, close to a random search:
    the run says so and names the budget that buys a whole one; a whole restart runs silent."""

    class Synthetic(CMAES):
        def evaluate(self, problem, designs):
            return -np.array([np.sum(np.square(d.continuous)) for d in designs])

    motions = [_motion("toss", steps=10)]
    with caplog.at_level(logging.WARNING, logger="tt.baselines.cmaes"):
        res = Synthetic().optimize(_problem(motions, budget=10))
    assert res.info["generations"] == 2
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "budget 10 is below one CMA-ES restart" in caplog.text and "at least 15" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="tt.baselines.cmaes"):
        Synthetic().optimize(_problem(motions, budget=15))
    assert not caplog.records


# ------------------------------------------------------------------------------ determinism
def test_same_seed_same_result():
    motions = [_motion("scrub", steps=60)]
    state = np.random.get_state()
    a = CMAES().optimize(_problem(motions, budget=20, seed=4))
    b = CMAES().optimize(_problem(motions, budget=20, seed=4))
    c = CMAES().optimize(_problem(motions, budget=20, seed=5))
    assert a.designs == b.designs and np.array_equal(a.rewards, b.rewards) and a.best == b.best
    assert a.designs != c.designs
    r1 = RandomSearch().optimize(_problem(motions, budget=8, seed=4))
    r2 = RandomSearch().optimize(_problem(motions, budget=8, seed=4))
    assert r1.designs == r2.designs and np.array_equal(r1.rewards, r2.rewards)
    # pycma runs on private streams: numpy's global generator is left as it was.
    after = np.random.get_state()
    assert state[0] == after[0] and np.array_equal(state[1], after[1]) and state[2:] == after[2:]


# ------------------------------------------------------------------------------ batched vs sequential
REWARDS = ("tracking", "tracking_torque", "tracking_velocity", "tracking_size", "tracking_weight")


def test_batched_and_sequential_agree_on_fixed_candidates():
    """A candidate's objective from the batched Warp rollout and from the oracle (one rollout
    at a time) agree within 2% for every reward, on two motions (the multi-trajectory mean).
    Both integrate the same MJCF with the same controller; they differ by float32 vs
    float64 arithmetic, about 1e-5 relative here."""
    space = get_space("viperx")
    candidates = [space.nominal()] + space.sample(2, seed=11)
    motions = [_motion("toss", steps=100), _motion("pour", steps=100)]
    for reward in REWARDS:
        p = _problem(motions, reward=reward, budget=5)
        batched = CMAES().evaluate(p, candidates)
        sequential = CMAES(CMAESConfig(sequential=True)).evaluate(p, candidates)
        np.testing.assert_allclose(batched, sequential, rtol=0.02, err_msg=reward)


def test_sequential_run_proposes_the_batched_candidates():
    """The two modes run the same search: identical first generation, same best within 2%."""
    p = _problem([_motion("wipe", steps=75)], budget=10, seed=2)
    cfg = dict(popsize=5, generations=2, screen=0.0)
    batched = CMAES(CMAESConfig(**cfg)).optimize(p)
    sequential = CMAES(CMAESConfig(**cfg, sequential=True)).optimize(p)
    assert (batched.method, sequential.method) == ("cmaes", "cmaes-sequential")
    assert sequential.info["backend"] == "mujoco"
    assert batched.designs[:5] == sequential.designs[:5]
    assert sequential.best_reward == pytest.approx(batched.best_reward, rel=0.02)


def test_multi_trajectory_objective_is_the_mean_over_motions():
    space = get_space("viperx")
    designs = space.sample(3, seed=21)
    motions = [_motion("toss", steps=80), _motion("screw", steps=60)]
    both = evaluate_designs(designs, motions, "tracking")
    assert both.reward.shape == (3, 2)
    np.testing.assert_allclose(both.objective, both.reward.mean(axis=1))
    for j, m in enumerate(motions):
        alone = evaluate_designs(designs, [m], "tracking")
        np.testing.assert_allclose(both.reward[:, j], alone.reward[:, 0], rtol=1e-5)
    res = CMAES(CMAESConfig(screen=0.0)).optimize(_problem(motions, budget=10, seed=1))
    assert res.rollouts == len(res.designs) * 2 == 20


def test_large_batch_preloads_kernels_and_scores_as_one_thread(monkeypatch):
    """From PARALLEL_MODELS_MIN designs on 2 threads, a space without a tree-field builder
    (ALOHA) builds its models in worker processes while this process loads the rollout
    kernels; the scores equal a one-thread run's. ViperX builds tree fields instead, with
    no worker and no MuJoCo model per design."""
    import tt.kernels.rollout as kr
    import tt.sim.designs.base as base
    from tt.sim.designs.base import PARALLEL_MODELS_MIN

    loaded = []
    real = kr.preload_rollout_kernels

    def counted(*args, **kwargs):
        loaded.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(kr, "preload_rollout_kernels", counted)
    viperx = get_space("viperx").sample(PARALLEL_MODELS_MIN, seed=5)
    monkeypatch.setattr(base.DesignSpace, "models", lambda *a, **k: pytest.fail("viperx built MuJoCo models"))
    evaluate_designs(viperx, [_motion("toss", steps=4)], "tracking", device="cpu", threads=2)
    monkeypatch.undo()
    monkeypatch.setattr(kr, "preload_rollout_kernels", counted)
    assert not loaded
    designs = get_space("aloha").sample(PARALLEL_MODELS_MIN, seed=5)
    bi = for_space([get_motion("bi_lift", 100)], "aloha")[0]
    motions = [Motion(bi.name, bi.pos[:12], bi.quat[:12], bi.dt)]
    two = evaluate_designs(designs, motions, "tracking", device="cpu", threads=2)
    assert len(loaded) == 1
    one = evaluate_designs(designs, motions, "tracking", device="cpu", threads=1)
    assert len(loaded) == 1  # one thread: models built here, nothing to overlap
    for name in one.metrics:
        np.testing.assert_array_equal(two.metrics[name], one.metrics[name], err_msg=name)


# ------------------------------------------------------------------------------ bad input
def test_bad_problems_fail_with_the_field_named():
    m = [_motion("toss", steps=10)]
    with pytest.raises(ValueError, match="nope"):
        Problem(space="nope", motions=tuple(m), reward="tracking", budget=5)
    with pytest.raises(ValueError, match="unknown reward 'nope'"):
        _problem(m, reward="nope")
    with pytest.raises(ValueError, match="motions is empty"):
        _problem([])
    with pytest.raises(ValueError, match="budget"):
        _problem(m, budget=0)
    with pytest.raises(ValueError, match="seed"):
        _problem(m, seed=-1)
    with pytest.raises(ValueError, match="unknown backend 'nope'"):
        _problem(m, backend="nope")
    with pytest.raises(ValueError, match="end effector"):
        Problem(space="aloha", motions=tuple(m), reward="tracking", budget=5)
    with pytest.raises(ValueError, match="unknown method"):
        get_optimizer("nope")
    with pytest.raises(ValueError, match="unknown cmaes options"):
        get_optimizer("cmaes", pop=5)
    with pytest.raises(ValueError, match="popsize"):
        CMAESConfig(popsize=1)
    with pytest.raises(ValueError, match="screen"):
        CMAESConfig(screen=1.0)


def test_budget_below_population_fails_before_any_rollout(monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("a rollout ran before the budget was checked")

    monkeypatch.setattr("tt.baselines.cmaes.warm_up_problem", no_work)
    monkeypatch.setattr("tt.baselines.cmaes.evaluate_designs", no_work)
    p = _problem([_motion("toss", steps=10)], budget=4)
    with pytest.raises(ValueError, match="budget 4 is below the CMA-ES population size 5"):
        CMAES().optimize(p)


# ------------------------------------------------------------------------------ tt optimize
@pytest.mark.parametrize(
    "args, message",
    [
        (["--reward", "nope", "--motion", "toss"], "unknown reward 'nope'"),
        (["--space", "nope", "--motion", "toss"], "nope"),
        ([], "no motion given"),
        (["--motion", "toss", "--budget", "3"], "budget 3 is below the CMA-ES population size 5"),
    ],
)
def test_optimize_cli_rejects_bad_input(args, message, tt_cli):
    code, out = tt_cli(["optimize", *args])
    assert code == 2, out
    assert message in out


def test_optimize_cli_writes_design_time_and_validated_metrics(tmp_path, tt_cli):
    # screw stays over the base where motions are placed, so even 10 candidates find a design
    # that tracks it to the end (on the toss's head none of them does: every metric is null).
    motion_file = tmp_path / "screw_short.npz"
    save_npz(_motion("screw", steps=75), motion_file)
    out = tmp_path / "opt.json"
    code, text = tt_cli(
        [
            "optimize",
            "--motion",
            str(motion_file),
            "--reward",
            "tracking_weight",
            "--budget",
            "10",
            "--seed",
            "1",
            "--json",
            str(out),
        ]
    )
    assert code == 0, text
    data = json.loads(out.read_text())
    space = get_space("viperx")
    design = space.from_dict(data["design"])
    assert isinstance(design, Design)
    space.validate(design)
    assert data["method"] == "cmaes" and data["rollouts"] == 10 and data["optimize_seconds"] > 0
    v = data["validated"]
    for key in ("pos_err", "orn_err", "survival_pct", "reward", "mass"):
        assert np.isfinite(v[key]), key
    assert 0 <= v["survival_pct"] <= 100
    # The oracle's reward of the winner is the objective the search measured (within 2%).
    assert v["reward"] == pytest.approx(data["objective"], rel=0.02)
    assert "kg" in text and "cmaes" in text
