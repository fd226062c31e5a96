"""Critic guidance: Self-Guidance steered by a dynamics critic's gradient, on a tiny random DiT.

The references: the differentiable sampling path draws the very sample the plain one does;
the critic's autograd gradient with respect to the design it is given matches central
differences of its predicted reward (a smooth reward: no termination, broad falloffs, so
the finite differences are well conditioned); a critic gradient steers exactly as the same
gradient given as the simulator's at lambda = 1; guidance that starts after the last step is
plain sampling.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tt.dit.sampling import sample
from tt.dit.tasks import TaskSpec
from tt.guidance.critic_grad import CriticGradient
from tt.guidance.predicted import build_query
from tt.guidance.selfguide import DGSConfig, DynamicsSelfGuidance, GuidanceScales, SelfGuidance
from tt.guidance.zeroth import CandidateSampler, GuideContext
from tt.baselines.problem import Problem
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import get_reward
from tt.tokens.schema import STEP_ROLES
from tiny_dit import tiny_model

STEPS = 6

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def critic():
    return tiny_model(("robot", "dynamics"))


@pytest.fixture(scope="module")
def motions():
    return for_space([get_motion("toss"), get_motion("scrub")], "viperx")


def _context(critic, motions, n):
    queries = [build_query(critic.layout, critic.normalizer, m, n, device="cpu") for m in motions]
    names = tuple(s.name for s in critic.layout.specs if s.role not in STEP_ROLES)
    return GuideContext(objective=None, scheduler=None, timesteps=[], embodiment=names, layout=critic.layout,
                        motions=tuple(motions), queries=queries, split=None)


def test_differentiable_sampling_draws_the_plain_sample(critic, motions):
    q = build_query(critic.layout, critic.normalizer, motions[0], 3)
    task = TaskSpec("dynamics", critic.robot_diffusion_steps, "random")
    for eta in (0.0, 1.0):
        plain = sample(critic.model, q.tokens, task, num_steps=STEPS, eta=eta, generator=torch.Generator().manual_seed(4))
        diff = sample(critic.model, q.tokens, task, num_steps=STEPS, eta=eta, generator=torch.Generator().manual_seed(4),
                      differentiable=True)
        for name, v in plain.tokens.values.items():
            torch.testing.assert_close(diff.tokens.values[name].detach(), v, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="differentiable"):
        sample(critic.model, q.tokens, task, num_steps=STEPS, guide=lambda *a: {}, differentiable=True)


def test_critic_gradient_matches_central_differences(critic, motions):
    smooth = dataclasses.replace(get_reward("tracking", "viperx"), threshold=1e9, sigma_p=4.0, sigma_o=20.0)
    grad = CriticGradient(critic, smooth, num_steps=STEPS, seed=3)
    ctx = _context(critic, motions, 2)
    base = ctx.queries[0].tokens.values
    gen = torch.Generator().manual_seed(9)
    x0 = {n: (0.8 * torch.rand(base[n].shape, generator=gen) - 0.4) for n in ctx.embodiment}
    g = grad.token_gradient(ctx, x0, 0)
    assert set(g) == set(x0) and grad.stats.candidates == 2 and len(grad.stats.reward_trace) == 1
    assert any(bool(v.abs().sum() > 0) for v in g.values())

    def reward(values):
        with torch.no_grad():
            return grad.objective(ctx, values).double()

    for trial in range(3):
        direction = {n: torch.randn(v.shape, generator=gen) for n, v in x0.items()}
        analytic = sum(float((g[n].double() * direction[n].double()).sum()) for n in x0)
        h = 1e-2
        plus = reward({n: x0[n] + h * direction[n] for n in x0}).sum()
        minus = reward({n: x0[n] - h * direction[n] for n in x0}).sum()
        numeric = float(plus - minus) / (2 * h)
        # float32 network: a reward of ~200 rounds to ~2e-5, so the quotient is good to ~2e-3;
        # the curvature over h = 1e-2 adds about 0.5 %.
        assert analytic == pytest.approx(numeric, rel=2e-2, abs=5e-3), trial


class FixedGradient:
    """A stand-in x0-gradient source (critic or simulator): a fixed closed-form gradient."""

    def __init__(self):
        self.calls = 0

    def token_gradient(self, ctx, x0, step):
        self.calls += 1
        out = {n: torch.zeros_like(v) for n, v in x0.items()}
        out["link"][..., 3:6] = -2.0 * (x0["link"][..., 3:6] - 0.5)
        return out

    def summary(self):
        return {"calls": self.calls}


def test_critic_gradient_steers_as_the_simulators_and_start_step(critic, motions):
    sampler = CandidateSampler(critic, "cpu")
    cfg = get_reward("tracking", "viperx")

    def run(guidance):
        return sampler.run(motions[:1], cfg, 3, seed=5, num_steps=STEPS, eta=1.0, guidance=guidance).tokens.values["link"]

    by_critic = FixedGradient()
    a = run(SelfGuidance(2.0, critic=by_critic))
    b = run(SelfGuidance(2.0, sim=FixedGradient(), sim_weight=1.0))
    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)
    assert by_critic.calls == STEPS
    plain = run(None)
    assert not torch.equal(a, plain)
    late = FixedGradient()
    assert torch.equal(run(SelfGuidance(2.0, critic=late, start_step=STEPS)), plain)
    assert late.calls == 0


def test_guide_by_critic_config(critic, motions):
    with pytest.raises(ValueError, match="guide_by"):
        DGSConfig(guide_by="oracle")
    with pytest.raises(ValueError, match="guide_start"):
        DGSConfig(guide_start=-1)
    robot_only = dataclasses.replace(critic, tasks=("robot",))
    problem = Problem("viperx", tuple(motions[:1]), "tracking", 2, seed=0, device="cpu")
    with pytest.raises(ValueError, match="dynamics critic"):
        DynamicsSelfGuidance(DGSConfig(num_steps=2, guide_by="critic"), model=robot_only).generate(problem)
    with pytest.raises(ValueError, match="dynamics task"):
        CriticGradient(robot_only, get_reward("tracking", "viperx"))


def test_dgs_guided_by_a_critic_records_its_gradient(critic, motions):
    problem = Problem("viperx", tuple(motions[:1]), "tracking", 2, seed=0, device="cpu")
    gen, _, info = DynamicsSelfGuidance(DGSConfig(num_steps=3, guide_by="critic", guide_start=1),
                                        model=critic).generate(problem)
    assert info["guide_by"] == "critic" and info["guide_start"] == 1
    scales = GuidanceScales()
    # The critic's own scale, not the paper's 50 for the model's own dynamics; one for any motion count.
    assert info["scale"] == scales.critic["viperx"] != scales.single["viperx"]
    assert scales.scale("viperx", 3, "critic") == scales.scale("viperx", 1, "critic")
    with pytest.raises(ValueError, match="no critic guidance scale"):
        scales.scale("bimanual", 1, "critic")
    grad = info["critic_grad"]
    assert grad["steps"] == 2 and grad["candidates"] == 4 and len(grad["reward_trace"]) == 2
    assert gen.objective.shape == (2,)
