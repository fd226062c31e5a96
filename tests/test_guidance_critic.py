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
import math

import numpy as np
import pytest
import torch
from tiny_dit import tiny_model

from tt.baselines.problem import Problem
from tt.dit.sampling import sample
from tt.dit.tasks import TaskSpec
from tt.guidance.critic_grad import FORMS, CriticGradient
from tt.guidance.predicted import build_query
from tt.guidance.selfguide import DGSConfig, DynamicsSelfGuidance, GuidanceScales, SelfGuidance
from tt.guidance.zeroth import CandidateSampler, GuideContext, renormalize
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import get_reward
from tt.tokens.schema import STEP_ROLES, Role

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
    return GuideContext(
        objective=None,
        scheduler=None,
        timesteps=[],
        embodiment=names,
        layout=critic.layout,
        motions=tuple(motions),
        queries=queries,
        split=None,
    )


def test_differentiable_sampling_draws_the_plain_sample(critic, motions):
    q = build_query(critic.layout, critic.normalizer, motions[0], 3)
    task = TaskSpec("dynamics", critic.robot_diffusion_steps, "random")
    for eta in (0.0, 1.0):
        plain = sample(
            critic.model, q.tokens, task, num_steps=STEPS, eta=eta, generator=torch.Generator().manual_seed(4)
        )
        diff = sample(
            critic.model,
            q.tokens,
            task,
            num_steps=STEPS,
            eta=eta,
            generator=torch.Generator().manual_seed(4),
            differentiable=True,
        )
        for name, v in plain.tokens.values.items():
            torch.testing.assert_close(diff.tokens.values[name].detach(), v, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="differentiable"):
        sample(critic.model, q.tokens, task, num_steps=STEPS, guide=lambda *a: {}, differentiable=True)


@pytest.mark.parametrize("form", FORMS)
def test_critic_gradient_matches_central_differences(critic, motions, form):
    smooth = dataclasses.replace(get_reward("tracking", "viperx"), threshold=1e9, sigma_p=4.0, sigma_o=20.0)
    grad = CriticGradient(critic, smooth, num_steps=STEPS, seed=3, form=form)
    ctx = _context(critic, motions, 2)
    x0 = _embodiment(ctx, seed=9)
    g = grad.token_gradient(ctx, x0, 0)
    assert set(g) == set(x0) and grad.stats.candidates == 2 and len(grad.stats.objective_trace) == 1

    def objective(values):
        with torch.no_grad():
            return grad.objective(ctx, values).double()

    gen = torch.Generator().manual_seed(11)
    norm = math.sqrt(sum(float(v.square().sum()) for v in g.values()))
    along = {n: v / norm for n, v in g.items()}  # the steepest direction: its derivative is |g|
    directions = [along] + [{n: torch.randn(v.shape, generator=gen) for n, v in x0.items()} for _ in range(2)]
    for trial, direction in enumerate(directions):
        analytic = sum(float((g[n].double() * direction[n].double()).sum()) for n in x0)
        h = 1e-2
        plus = objective({n: x0[n] + h * direction[n] for n in x0}).sum()
        minus = objective({n: x0[n] - h * direction[n] for n in x0}).sum()
        numeric = float(plus - minus) / (2 * h)
        if trial == 0:  # far above the tolerance, so the comparisons can fail
            assert numeric > 0.1, numeric
        # float32 network: an objective of ~1e2..1e3 rounds to ~1e-5..1e-4, so the quotient is
        # good to ~1e-2 absolute; the curvature over h = 1e-2 adds about 0.5 %.
        assert analytic == pytest.approx(numeric, rel=2e-2, abs=5e-3 * max(1.0, abs(float(plus)) / 200)), trial


def _embodiment(ctx, seed: int) -> dict[str, torch.Tensor]:
    base = ctx.queries[0].tokens.values
    gen = torch.Generator().manual_seed(seed)
    return {n: (0.8 * torch.rand(base[n].shape, generator=gen) - 0.4) for n in ctx.embodiment}


def test_critic_takes_tokens_in_the_samplers_units(critic, motions):
    """A critic whose normaliser differs from the sampler's is given the sampler's x0 in its own
    units: the objective on the sampler's tokens equals the objective on the same tokens
    moved to the critic's units by hand."""
    import copy

    sampler_norm = copy.deepcopy(critic.normalizer)
    for name in ctx_names(critic):
        sampler_norm.low[name] = np.asarray(sampler_norm.low[name]) - 0.3
        sampler_norm.high[name] = np.asarray(sampler_norm.high[name]) + 0.5
    cfg = get_reward("tracking", "viperx")
    ctx = _context(critic, motions[:1], 2)
    x0 = _embodiment(ctx, seed=2)
    moved = renormalize(x0, sampler_norm, critic.normalizer)
    assert not torch.allclose(moved["link"], x0["link"])
    with torch.no_grad():
        a = CriticGradient(critic, cfg, normalizer=sampler_norm, num_steps=STEPS).objective(ctx, x0)
        b = CriticGradient(critic, cfg, num_steps=STEPS).objective(ctx, moved)
    torch.testing.assert_close(a, b)


def ctx_names(critic) -> list[str]:
    return [s.name for s in critic.layout.specs if s.role not in STEP_ROLES]


def test_start_aware_critic_gets_the_simulated_start_of_the_decoded_designs(critic, motions, monkeypatch):
    """A start-aware critic: every candidate is decoded, the ones that decode get the start of
    their design (written at step 0 of each motion's query) and a gradient, the others zero."""
    import tt.guidance.critic_grad as critic_grad
    from tt.guidance.zeroth import Decoded

    aware = dataclasses.replace(critic, dynamics_start=True)
    designs = get_space("viperx").sample(3, seed=1)
    per_step = [s for s in critic.layout.specs if s.role in STEP_ROLES and s.role is not Role.CONDITION]
    seen = []

    def fake_start(layout, normalizer, given, ms, device="cpu", models=None):
        seen.append(list(given))
        return {s.name: torch.full((len(ms), len(given), s.per_step, s.dim), 0.25) for s in per_step}

    monkeypatch.setattr(critic_grad, "start_tokens", fake_start)
    decoder = lambda batch, i: Decoded(None, "no") if i == 1 else Decoded(designs[i])  # noqa: E731
    grad = CriticGradient(aware, get_reward("tracking", "viperx"), decoder=decoder, num_steps=STEPS)
    ctx = _context(critic, motions, 3)
    x0 = _embodiment(ctx, seed=4)
    g = grad.token_gradient(ctx, x0, 0)
    assert seen == [[designs[0], designs[2]]]
    assert grad.stats.decode_failures == 1 and grad.stats.candidates == 2
    assert bool((g["link"][1] == 0).all()) and bool((g["link"][[0, 2]] != 0).any())
    # The start reaches the critic: another start gives another gradient.
    again = CriticGradient(aware, get_reward("tracking", "viperx"), decoder=decoder, num_steps=STEPS)
    monkeypatch.setattr(
        critic_grad, "start_tokens", lambda *a, **k: {n: 0.0 * v - 0.25 for n, v in fake_start(*a, **k).items()}
    )
    assert not torch.allclose(again.token_gradient(ctx, x0, 0)["link"], g["link"])
    with pytest.raises(ValueError, match="needs a decoder"):
        CriticGradient(aware, get_reward("tracking", "viperx"))


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


def test_critic_gradient_steers_as_the_simulators(critic, motions):
    sampler = CandidateSampler(critic, "cpu")
    cfg = get_reward("tracking", "viperx")

    def run(guidance):
        return sampler.run(motions[:1], cfg, 3, seed=5, num_steps=STEPS, eta=1.0, guidance=guidance).tokens.values[
            "link"
        ]

    by_critic = FixedGradient()
    a = run(SelfGuidance(2.0, critic=by_critic))
    b = run(SelfGuidance(2.0, sim=FixedGradient(), sim_weight=1.0))
    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)
    assert by_critic.calls == STEPS
    plain = run(None)
    assert not torch.equal(a, plain)


def test_guide_by_critic_config(critic, motions):
    with pytest.raises(ValueError, match="guide_by"):
        DGSConfig(guide_by="oracle")
    robot_only = dataclasses.replace(critic, tasks=("robot",))
    problem = Problem("viperx", tuple(motions[:1]), "tracking", 2, seed=0, device="cpu")
    with pytest.raises(ValueError, match="dynamics critic"):
        DynamicsSelfGuidance(DGSConfig(num_steps=2, guide_by="critic"), model=robot_only).generate(problem)
    with pytest.raises(ValueError, match="dynamics task"):
        CriticGradient(robot_only, get_reward("tracking", "viperx"))


def test_dgs_guides_by_the_critic_when_the_generator_has_no_dynamics(critic, motions):
    """guide_by None: the critic's gradient for a robot-only generator given a critic (its own
    dynamics tokens are untrained noise to follow), else the model's own dynamics (the paper's)."""
    problem = Problem("viperx", tuple(motions[:1]), "tracking", 2, seed=0, device="cpu")
    robot_only = dataclasses.replace(critic, tasks=("robot",))
    _, _, info = DynamicsSelfGuidance(DGSConfig(num_steps=2), model=robot_only, critic_model=critic).generate(problem)
    assert info["guide_by"] == "critic" and info["scale"] == GuidanceScales().critic["viperx"]
    assert info["critic_grad"]["steps"] == 2
    for model in (critic, robot_only):  # trained on dynamics; or robot-only with no critic to follow
        _, _, info = DynamicsSelfGuidance(DGSConfig(num_steps=2), model=model).generate(problem)
        assert info["guide_by"] == "model" and info["scale"] == GuidanceScales().single["viperx"]
        assert "critic_grad" not in info


def test_dgs_guided_by_a_critic_records_its_gradient(critic, motions):
    problem = Problem("viperx", tuple(motions[:1]), "tracking", 2, seed=0, device="cpu")
    gen, _, info = DynamicsSelfGuidance(DGSConfig(num_steps=3, guide_by="critic"), model=critic).generate(problem)
    assert info["guide_by"] == "critic"
    scales = GuidanceScales()
    # The critic's own scale, not the paper's 50 for the model's own dynamics; one for any motion count.
    assert info["scale"] == scales.critic["viperx"] != scales.single["viperx"]
    assert scales.scale("viperx", 3, "critic") == scales.scale("viperx", 1, "critic")
    with pytest.raises(ValueError, match="no critic guidance scale"):
        GuidanceScales(critic={"viperx": 5.0}).scale("bimanual", 1, "critic")
    grad = info["critic_grad"]
    assert grad["steps"] == 3 and grad["candidates"] == 6 and len(grad["objective_trace"]) == 3
    assert gen.objective.shape == (2,)
