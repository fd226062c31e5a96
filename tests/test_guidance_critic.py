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
from tt.dit.ddim import CosineDDIM
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


def _tiny_shipped_critic(dynamics_start: bool):
    """The shipped critic's layout and units (they hold ViperX designs) on a tiny random network."""
    from tt.dit.checkpoint import TrainedModel, load_model
    from tt.dit.model import RoboDiT, get_config

    shipped = load_model("checkpoints/viperx_mini_dynamics.pt", device="cpu")
    torch.manual_seed(0)
    net = RoboDiT(shipped.layout, get_config("tiny")).eval()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return TrainedModel(net, shipped.normalizer, shipped.layout, 0, tasks=("dynamics",), dynamics_start=dynamics_start)


def test_gradient_at_the_decoded_design(motions):
    """at="design": the critic is asked about the tokens of the design each candidate decodes
    to. For candidates that are designs' own tokens it is the gradient at x0 itself; for noisy
    ones it is the gradient at the design, not at x0; a failed decode gets zero."""
    from tt.dit.layout import robot_embodiment
    from tt.guidance.zeroth import Decoded

    critic = _tiny_shipped_critic(dynamics_start=False)
    space = get_space("viperx")
    designs = space.sample(3, seed=2)
    cfg = dataclasses.replace(get_reward("tracking", "viperx"), threshold=1e9)
    ctx = _context(critic, motions[:1], 3)
    own, _ = robot_embodiment(critic.layout, critic.normalizer, [space.model(d) for d in designs])
    x0 = {n: own.values[n].clone() for n in ctx.embodiment}
    decoder = lambda batch, i: Decoded(designs[i])  # noqa: E731
    at_tokens = CriticGradient(critic, cfg, num_steps=STEPS, seed=1).token_gradient(ctx, x0, 0)
    g = CriticGradient(critic, cfg, decoder=decoder, num_steps=STEPS, seed=1, at="design").token_gradient(ctx, x0, 0)
    for n in ctx.embodiment:
        # float32 through the network: x0 and the designs' tokens agree to rounding.
        torch.testing.assert_close(g[n], at_tokens[n], atol=1e-5, rtol=1e-4)
    assert bool((g["link"] != 0).any())
    noisy = {n: v + 0.2 * torch.randn(v.shape, generator=torch.Generator().manual_seed(3)) for n, v in x0.items()}
    moved = CriticGradient(critic, cfg, decoder=decoder, num_steps=STEPS, seed=1, at="design").token_gradient(
        ctx, noisy, 0
    )
    torch.testing.assert_close(moved["link"], g["link"])  # the same designs, so the same gradient
    assert not torch.allclose(
        CriticGradient(critic, cfg, num_steps=STEPS, seed=1).token_gradient(ctx, noisy, 0)["link"], g["link"], atol=1e-3
    )
    failing = lambda batch, i: Decoded(None, "no") if i == 1 else Decoded(designs[i])  # noqa: E731
    some = CriticGradient(critic, cfg, decoder=failing, num_steps=STEPS, seed=1, at="design")
    g = some.token_gradient(ctx, x0, 0)
    assert some.stats.decode_failures == 1 and some.stats.candidates == 2
    assert bool((g["link"][1] == 0).all()) and bool((g["link"][[0, 2]] != 0).any())
    with pytest.raises(ValueError, match="needs a decoder"):
        CriticGradient(critic, cfg, at="design")
    with pytest.raises(ValueError, match="at = 'x0'"):
        CriticGradient(critic, cfg, decoder=decoder, at="x0")
    with pytest.raises(ValueError, match="critic_at"):
        DGSConfig(critic_at="x0")


def test_gradient_through_the_start_matches_central_differences(motions):
    """through_start adds (dR/dstart)(dstart/dc), carried to the tokens. Along the token change
    of each continuous choice c_j (the tokenizer's de/dc_j), what it adds is the central
    difference of the critic's objective with the design's tokens held and its start
    re-simulated at c_j +- h."""
    from tt.dit.checkpoint import load_model
    from tt.dit.layout import robot_embodiment
    from tt.guidance.critic_grad import START_REL_STEP
    from tt.guidance.predicted import start_tokens
    from tt.guidance.simgrad import design_stencil, token_jacobian
    from tt.guidance.zeroth import Decoded
    from tt.tokens.normalize import is_padding

    # The shipped critic itself: a random network's objective hardly moves with the start, and
    # its differences would be float32 rounding.
    critic = load_model("checkpoints/viperx_mini_dynamics.pt", device="cpu")
    space = get_space("viperx")
    design = space.sample(1, seed=5)[0]
    cfg = dataclasses.replace(get_reward("tracking", "viperx"), threshold=1e9)
    ctx = _context(critic, motions[:1], 1)
    own, _ = robot_embodiment(critic.layout, critic.normalizer, [space.model(design)])
    x0 = {n: own.values[n].clone() for n in ctx.embodiment}
    decoder = lambda batch, i: Decoded(design)  # noqa: E731
    plain = CriticGradient(critic, cfg, decoder=decoder, num_steps=STEPS, seed=1).token_gradient(ctx, x0, 0)
    through = CriticGradient(critic, cfg, decoder=decoder, num_steps=STEPS, seed=1, through_start=True)
    added = {n: v - plain[n] for n, v in through.token_gradient(ctx, x0, 0).items()}
    assert through.stats.start_terms == 1 and through.stats.start_projected == 0
    jac = token_jacobian(space, design)  # type -> (p, n_real, width), encoded units
    stencil, span = design_stencil(space, design, START_REL_STEP)
    moved = start_tokens(critic.layout, critic.normalizer, stencil, ctx.motions)
    numeric, analytic = [], []
    for j in range(len(design.continuous)):
        with torch.no_grad():
            value = [
                float(through.objective(ctx, x0, {n: v[:, [2 * j + s]] for n, v in moved.items()})) for s in (0, 1)
            ]
        numeric.append((value[0] - value[1]) / span[j])
        total = 0.0
        for n, d_e in jac.items():
            real = ~is_padding(x0[n][0])
            unit = torch.ones(1, x0[n].shape[-1], dtype=torch.float64)
            de_dx = (critic.normalizer.denormalize_values(n, unit) - critic.normalizer.denormalize_values(n, 0 * unit))[
                0
            ]
            total += float((added[n][0, real].double() * torch.as_tensor(d_e[j]) / de_dx).sum())
        analytic.append(total)
    numeric, analytic = np.array(numeric), np.array(analytic)
    assert np.abs(numeric).max() > 0.3, numeric  # the start does move the critic's objective
    # Linearising the objective over one difference step of the start: a few % of the largest.
    np.testing.assert_allclose(analytic, numeric, rtol=5e-2, atol=2e-2 * np.abs(numeric).max())
    # Decoded by projection: the same term, on the slots the design's structure uses.
    projected = CriticGradient(
        critic, cfg, decoder=lambda batch, i: Decoded(design, distance=2), num_steps=STEPS, seed=1, through_start=True
    )
    g = projected.token_gradient(ctx, x0, 0)
    assert projected.stats.start_projected == 1 and projected.stats.start_terms == 1
    for n in g:
        torch.testing.assert_close(g[n] - plain[n], added[n])
    with pytest.raises(ValueError, match="told the start"):
        CriticGradient(_tiny_shipped_critic(dynamics_start=False), cfg, decoder=decoder, through_start=True)
    with pytest.raises(ValueError, match="through_start"):
        DGSConfig(guide_by="model", through_start=True)


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
    late = FixedGradient()
    assert torch.equal(run(SelfGuidance(2.0, critic=late, start_step=STEPS)), plain)
    assert late.calls == 0


class AnchoredGradient(FixedGradient):
    """A stand-in critic taken at the decoded design: every candidate "decodes" to the fixed
    tokens `anchor`; the gradient is `gain` on three features of every slot, 0 elsewhere."""

    at = "design"

    def __init__(self, anchor, gain):
        super().__init__()
        self.tokens, self.gain, self.anchor = anchor, gain, None

    def token_gradient(self, ctx, x0, step):
        self.calls += 1
        n = next(iter(x0.values())).shape[0]
        self.anchor = (list(range(n)), {k: v.expand(n, *v.shape[1:]) for k, v in self.tokens.items()})
        return {k: self.direction(v) for k, v in x0.items()}

    def direction(self, like):
        out = torch.zeros_like(like)
        if like.shape[-1] >= 6:
            out[..., 3:6] = self.gain
        return out


def test_projected_guidance_lands_on_the_decoded_design(critic, motions):
    """project=True: each guided step continues from the anchor design plus the x0 shift
    s (1 - abar_t) g0 / rms(g0), so the sample ends at the anchor plus the last step's shift
    (exactly the anchor with a zero gradient), whatever the network predicts."""
    sampler = CandidateSampler(critic, "cpu")
    cfg = get_reward("tracking", "viperx")
    names = ctx_names(critic)
    q = build_query(critic.layout, critic.normalizer, motions[0], 1)
    gen = torch.Generator().manual_seed(8)
    anchor = {n: (0.6 * torch.rand(q.tokens.values[n].shape, generator=gen) - 0.3) for n in names}
    for eta in (0.0, 1.0):
        for gain in (0.0, 1.0):
            source = AnchoredGradient(anchor, gain)
            guidance = SelfGuidance(2.0, critic=source, project=True)
            out = sampler.run(motions[:1], cfg, 3, seed=5, num_steps=STEPS, eta=eta, guidance=guidance).tokens.values
            assert source.calls == STEPS and guidance.stats.steps == STEPS
            scheduler = CosineDDIM(critic.robot_diffusion_steps)
            ab = float(scheduler.alpha_bar(scheduler.timesteps(STEPS)[-1]))
            for n in names:
                # The stand-in's gradient is `gain` on 3 features of every slot: RMS gain * sqrt(3 / D) overall.
                entries = sum(out[k][0].numel() for k in names)
                rms = gain * math.sqrt(sum(3 * out[k].shape[1] for k in names) / entries) if gain else 1.0
                want = anchor[n].expand_as(out[n]) + 2.0 * (1 - ab) * source.direction(out[n]) / rms
                torch.testing.assert_close(out[n], want.clamp(-1, 1), atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="project"):
        SelfGuidance(2.0, critic=FixedGradient(), project=True)
    with pytest.raises(ValueError, match="project"):
        DGSConfig(guide_by="critic", project=True, scale=0.1)
    with pytest.raises(ValueError, match="explicit scale"):
        DGSConfig(guide_by="critic", critic_at="design", project=True)
    DGSConfig(guide_by="critic", critic_at="design", project=True, scale=0.1)


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
    gen, _, info = DynamicsSelfGuidance(
        DGSConfig(num_steps=3, guide_by="critic", guide_start=1), model=critic
    ).generate(problem)
    assert info["guide_by"] == "critic" and info["guide_start"] == 1
    scales = GuidanceScales()
    # The critic's own scale, not the paper's 50 for the model's own dynamics; one for any motion count.
    assert info["scale"] == scales.critic["viperx"] != scales.single["viperx"]
    assert scales.scale("viperx", 3, "critic") == scales.scale("viperx", 1, "critic")
    with pytest.raises(ValueError, match="no critic guidance scale"):
        scales.scale("bimanual", 1, "critic")
    grad = info["critic_grad"]
    assert grad["steps"] == 2 and grad["candidates"] == 4 and len(grad["objective_trace"]) == 2
    assert gen.objective.shape == (2,)


class EveryValue(FixedGradient):
    """A stand-in critic whose x0-gradient is 1 on every value of every token."""

    def token_gradient(self, ctx, x0, step):
        self.calls += 1
        return {n: torch.ones_like(v) for n, v in x0.items()}


def test_continuous_columns_are_the_schemas_non_binary_values():
    from tt.guidance.selfguide import continuous_columns
    from tt.tokens.schema import SCHEMA, Encoding

    for name in ("link", "dyna_joint", "fixed_joint", "actuator"):
        spec = SCHEMA[name]
        cols = continuous_columns(name, spec.width)
        bits = sum(a.width for a in spec.attributes if a.encoding is Encoding.BINARY)
        assert bits > 0 and int((~cols).sum()) == bits
        for a in spec.attributes:
            assert bool(cols[spec.slice(a.name)].all()) == (a.encoding is not Encoding.BINARY), (name, a.name)
    with pytest.raises(ValueError, match="schema has 35"):
        continuous_columns("link", 34)


def test_continuous_only_guidance_moves_only_continuous_values_of_real_tokens(critic, motions):
    """With continuous_only the guided eps differs from the model's only in the non-binary
    values of the tokens x0_hat holds as real; without it, everywhere the gradient reaches."""
    from tt.guidance.selfguide import continuous_columns

    names = ctx_names(critic)
    scheduler = CosineDDIM(critic.robot_diffusion_steps)
    q = build_query(critic.layout, critic.normalizer, motions[0], 2)
    gen = torch.Generator().manual_seed(4)
    base = {n: 0.5 * torch.rand(q.tokens.values[n].shape, generator=gen) for n in names}
    base["link"][:, 0] = -2.0  # x0_hat = x_t / 2: the first link slot is padding (all values -1)
    eps = {n: torch.randn(v.shape, generator=gen) for n, v in base.items()}
    ctx = GuideContext(
        objective=lambda x0, flag: torch.zeros(2, 1),
        scheduler=scheduler,
        timesteps=scheduler.timesteps(STEPS),
        embodiment=tuple(names),
        layout=critic.layout,
        motions=tuple(motions[:1]),
        queries=[q],
        split=None,
    )
    moved = {}
    for only in (False, True):
        x_t = {n: v.clone().requires_grad_() for n, v in base.items()}
        x0 = {n: 0.5 * v for n, v in x_t.items()}
        guidance = SelfGuidance(2.0, critic=EveryValue(), continuous_only=only)
        out = guidance.hook(ctx)(1, x_t, eps, x0)
        moved[only] = {n: (out[n] - eps[n]).detach().abs() > 0 for n in names}
    for n in names:
        cols = continuous_columns(n, base[n].shape[-1])
        assert bool(moved[False][n].all())
        assert bool(moved[True][n][..., cols].any()) and not bool(moved[True][n][..., ~cols].any())
    assert not bool(moved[True]["link"][:, 0].any()) and bool(
        moved[True]["link"][:, 1:][..., continuous_columns("link", 35)].all()
    )
    with pytest.raises(ValueError, match="choose one"):
        SelfGuidance(2.0, critic=AnchoredGradient({}, 1.0), project=True, continuous_only=True)
    with pytest.raises(ValueError, match="choose one"):
        DGSConfig(guide_by="critic", critic_at="design", project=True, scale=0.1, continuous_only=True)
