"""The hybrids of `tt.guidance.hybrid`: the model proposes, the batched simulator decides.

The selection logic is checked with a stand-in sampler whose candidates and predictions are
fixed (so the simulator's verdict is known from `evaluate_designs`); the fallback with a
model that knows nothing uses a tiny random network on the shipped checkpoint's layout.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tt.baselines import CMAES, CMAESConfig, Problem, RandomSearch, evaluate_designs
from tt.baselines.cmaes import _decode, _encode
from tt.guidance.hybrid import ModelInitCMAES, SimVerified, VerifyConfig
from tt.guidance.zeroth import Decoded, Generation, Ranking, SamplerConfig, ZerothOrder
from tt.sim.designs import get_space
from tt.sim.motions import Motion, for_space, get_motion


def _short(name: str, steps: int) -> Motion:
    m = for_space([get_motion(name)], "viperx")[0]
    return Motion(m.name, m.pos[:steps], m.quat[:steps], m.dt)


@pytest.fixture(scope="module")
def motions():
    return (_short("toss", 80), _short("scrub", 80))


class FixedProposals:
    """A stand-in learned sampler: `designs` with predicted objectives `predicted`."""

    name = "fixed"

    def __init__(self, designs, predicted):
        self.designs, self.predicted = list(designs), np.asarray(predicted, dtype=np.float64)
        self.config = SamplerConfig(samples=len(self.designs))
        self.ranked_with: list = []

    def generate(self, problem):
        gen = Generation(
            tokens=None,
            layout=None,
            reward=self.predicted[:, None].repeat(len(problem.motions), 1),
            objective=self.predicted,
            metrics={},
            seconds=0.0,
        )
        return gen, None, {}

    def rank(self, gen, decoder, *, limit=None):
        self.ranked_with.append(limit)
        order = [int(i) for i in np.argsort(-gen.objective, kind="stable")]
        todo = order if limit is None else order[:limit]
        return Ranking(order, {i: Decoded(self.designs[i], None, 0.0, 0) for i in todo})


def test_zeroth_sim_returns_the_best_simulated_of_the_top_k(motions, monkeypatch):
    import tt.guidance.hybrid as hybrid

    # learned_result reads model tokens for its info; the stand-in has none.
    monkeypatch.setattr(
        hybrid,
        "learned_result",
        lambda method, problem, gen, ranking, seconds, rollouts=0, info=None: type(
            "R", (), {"info": dict(info or {}, samples=len(gen.objective)), "rollouts": rollouts}
        )(),
    )
    designs = get_space("viperx").sample(6, seed=3)
    truth = evaluate_designs(designs, motions, "tracking").objective  # (6,) mean over the two motions
    predicted = -truth  # a model that ranks them exactly backwards
    problem = Problem(space="viperx", motions=motions, reward="tracking", budget=6, seed=0)
    for k in (1, 3, 6):
        proposer = FixedProposals(designs, predicted)
        result = SimVerified(proposer, VerifyConfig(k)).optimize(problem)
        top_k = list(np.argsort(-predicted, kind="stable")[:k])
        assert proposer.ranked_with == [k]
        assert result.info["verified_candidates"] == top_k and result.rollouts == k * len(motions)
        np.testing.assert_allclose(result.info["verified_simulated"], truth[top_k], rtol=1e-6)
        best = top_k[int(np.argmax(truth[top_k]))]
        assert result.best == designs[best] and result.best_reward == pytest.approx(truth[best], rel=1e-6)
        np.testing.assert_allclose(result.info["verified_predicted"], predicted[top_k])
    assert result.info["predicted_vs_simulated_r"] == pytest.approx(-1.0)
    assert result.info["best_predicted_rank"] == 5  # the model's worst is the simulator's best


def test_verify_larger_than_samples_is_refused(motions):
    problem = Problem(space="viperx", motions=motions, reward="tracking", budget=4, seed=0)
    proposer = FixedProposals(get_space("viperx").sample(4, seed=0), np.zeros(4))
    with pytest.raises(ValueError, match="verify = 5 is larger than samples = 4"):
        SimVerified(proposer, VerifyConfig(5)).optimize(problem)
    with pytest.raises(ValueError, match="verify"):
        VerifyConfig(0)


def test_cmaes_proposals_take_half_the_screen_and_set_the_step_size(motions):
    """Proposals near the nominal arm (far better than random designs) fill half the screen;
    the restart that starts from the best of them steps by their spread; plain CMA-ES by sigma0."""
    space = get_space("viperx")
    problem = Problem(space="viperx", motions=motions, reward="tracking", budget=20, seed=1)
    nominal = space.nominal()
    x0 = _encode(space, nominal)
    rng = np.random.default_rng(0)
    xs = [np.clip(x0 + 0.08 * rng.standard_normal(x0.size), 0.0, 1.0) for _ in range(8)]
    proposals = [_decode(space, nominal.discrete, x) for x in xs]
    opt = CMAES(CMAESConfig(popsize=5, generations=2))
    plan = opt.plan(problem)
    assert (plan.screen, plan.restarts) == (10, 1)
    result = opt.optimize(problem, proposals=proposals)
    assert result.designs[:5] == proposals[:5]  # half the screen, best first
    assert all(d.discrete != nominal.discrete or d in proposals for d in result.designs[5:10])
    assert result.rollouts == problem.budget * len(motions)  # the budget of plain CMA-ES
    assert result.designs[10].discrete == nominal.discrete  # the restart started from a proposal
    spread = float(np.std(np.stack([_encode(space, d) for d in proposals]), axis=0).mean())
    assert result.info["sigmas"] == [pytest.approx(np.clip(spread, 0.05, 0.25), rel=1e-9)]
    assert opt.optimize(problem).info["sigmas"] == [0.25]
    with pytest.raises(ValueError, match="space 'viperx'"):
        opt.optimize(problem, proposals=get_space("aloha").sample(2, seed=0))


@pytest.fixture(scope="module")
def blank_model():
    """A model that knows nothing: tiny random network, the shipped checkpoint's layout and statistics."""
    from tt.dit.checkpoint import TrainedModel, default_checkpoint, load_model
    from tt.dit.model import RoboDiT, get_config

    shipped = load_model(default_checkpoint("viperx"), device="cpu")
    torch.manual_seed(0)
    net = RoboDiT(shipped.layout, get_config("tiny")).eval()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))  # adaLN-Zero would otherwise predict eps = 0
    return TrainedModel(net, shipped.normalizer, shipped.layout, 0)


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["--method", "zeroth-sim", "--config", "samples=4", "--config", "verify=8"],
            "verify = 8 is larger than samples = 4",
        ),
        (["--method", "random", "--config", "verify=2"], "unknown key 'verify'"),
        (["--method", "cmaes", "--config", "verify=2"], "valid keys: popsize, generations"),
        (["--method", "cmaes-init-model", "--config", "popsize=one"], "popsize = 'one' is not of type int"),
        (["--method", "zeroth", "--config", "critic=oracle"], "critic = 'oracle'; valid: ['joint', 'dynamics']"),
        (
            ["--method", "zeroth", "--config", "critic=joint", "--config", "critic_samples=4"],
            "critic_samples = 4 needs the 'dynamics' critic",
        ),
        (["--method", "zeroth", "--config", "critic_samples=0"], "critic_samples = 0; must be >= 1"),
        (["--method", "cmaes", "--refine", "3"], "--refine applies to the learned methods"),
        (
            ["--space", "viperx-gravcomp", "--method", "cmaes-init-model"],
            "no shipped DiT checkpoint for design space 'viperx-gravcomp'",
        ),
    ],
)
def test_cli_refuses_bad_hybrid_options(tt_cli, args, message):
    motion = [] if "--motion" in args else ["--motion", "toss"]
    code, out = tt_cli(["optimize", *motion, "--budget", "10", *args])
    assert code != 0 and message in out, out
    assert "Traceback" not in out


def test_model_init_without_a_checkpoint_is_refused(motions):
    from tt.optimizers import get_optimizer

    opt = get_optimizer("cmaes-init-model", popsize=5, generations=1)
    problem = Problem(space="viperx", motions=motions, reward="tracking", budget=10, seed=0)
    with pytest.raises(ValueError, match="needs a checkpoint"):
        opt.optimize(problem)


@pytest.mark.slow
def test_hybrids_with_a_blank_model_fall_back_to_random_and_cmaes(blank_model, motions):
    """With a model that knows nothing, zeroth-sim is best-of-n over scattered designs (Random's
    performance) and cmaes-init-model is CMA-ES with half a random screen: over 5 seeds,
    neither falls below its baseline, i.e. the 95 % Student-t interval of the paired
    per-seed difference (hybrid minus baseline, as the benchmarks report it) is not wholly
    below 0. (Near the reward's ceiling the baselines' own spread is ~0.1 of ~80, too narrow a
    yardstick for a method whose structure choice differs on some seeds.)"""
    from tt.guidance.zeroth import DesignDecoder

    decoder = DesignDecoder(get_space("viperx"))
    sampler = lambda: ZerothOrder(SamplerConfig(num_steps=5), model=blank_model, decoder=decoder)  # noqa: E731
    rows = []
    for seed in range(5):
        problem = Problem(space="viperx", motions=motions[:1], reward="tracking", budget=20, seed=seed)
        rows.append(
            [
                SimVerified(sampler()).optimize(problem).best_reward,
                RandomSearch().optimize(problem).best_reward,
                ModelInitCMAES(sampler(), CMAESConfig(popsize=5, generations=2)).optimize(problem).best_reward,
                CMAES(CMAESConfig(popsize=5, generations=2)).optimize(problem).best_reward,
            ]
        )
    zsim, rand, cinit, cma = np.asarray(rows).T
    t95 = 2.776  # Student t, two-sided 95 %, 4 degrees of freedom
    for hybrid_, base in ((zsim, rand), (cinit, cma)):
        d = hybrid_ - base
        assert d.mean() + t95 * d.std(ddof=1) / np.sqrt(d.size) >= -1e-9, rows
