"""Zeroth-Order, Dynamics Self-Guidance and composition on a tiny random DiT.

No trained checkpoint is needed: a tiny network with random weights everywhere (its
adaLN-Zero heads would otherwise predict eps = 0 for any input) on a RoboToken layout
with few slots. What is checked holds for any network: guidance with scale 0 is plain
sampling, the sign of the scale decides the direction a fixed reward moves, composing one
motion is not composing, the composed eps of the embodiment is the mean over copies, and
the optimizers rank by the predicted objective with failed decodes last.
"""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from tiny_dit import tiny_model

from tt.baselines.problem import Problem
from tt.dit.checkpoint import TrainedModel
from tt.dit.ddim import CosineDDIM
from tt.dit.layout import layout_from_schema
from tt.dit.model import RoboDiT
from tt.dit.sampling import sample
from tt.dit.tasks import ROBOT, task_masks
from tt.guidance.compose import ComposedModel, compose_tokens, split_tokens
from tt.guidance.predicted import build_query, query_steps
from tt.guidance.selfguide import DGSConfig, DynamicsSelfGuidance, GuidanceScales, SelfGuidance
from tt.guidance.zeroth import (
    CandidateSampler,
    Decoded,
    DesignDecoder,
    SamplerConfig,
    ZerothOrder,
    default_temperature,
    embodiment_batch,
    rank_candidates,
)
from tt.kernels.errors import TTError
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.rewards import get_reward
from tt.tokens.normalize import Normalizer

STEPS = 8  # DDIM steps in these tests (of the process's 100)


@pytest.fixture(scope="module")
def tiny():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: a second thread only waits
    yield tiny_model()
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def motions():
    return for_space([get_motion("toss"), get_motion("scrub")], "viperx")


class ToyObjective:
    """Guidance toward a fixed toy reward of the embodiment: -|link size features - 0.5|^2."""

    def __init__(self, inner: SelfGuidance):
        self.inner = inner

    @staticmethod
    def reward(x0: dict[str, torch.Tensor]) -> torch.Tensor:
        return -((x0["link"][..., 3:6] - 0.5) ** 2).sum((1, 2))

    def hook(self, ctx):
        return self.inner.hook(dataclasses.replace(ctx, objective=lambda x0, guidance: self.reward(x0)[:, None]))

    def summary(self):
        return self.inner.summary()


def test_scale_zero_equals_plain_sampling(tiny, motions):
    sampler = CandidateSampler(tiny, "cpu")
    cfg = get_reward("tracking_size", "viperx")
    plain = sampler.run(motions[:1], cfg, 3, seed=1, num_steps=STEPS, eta=1.0)
    zero = SelfGuidance(0.0)
    guided = sampler.run(motions[:1], cfg, 3, seed=1, num_steps=STEPS, eta=1.0, guidance=zero)
    assert zero.stats.steps == STEPS
    for name in plain.tokens.values:
        assert torch.equal(plain.tokens.values[name], guided.tokens.values[name]), name
    np.testing.assert_array_equal(plain.objective, guided.objective)
    # A nonzero scale does move the embodiment (so the comparison above can fail).
    moved = sampler.run(motions[:1], cfg, 3, seed=1, num_steps=STEPS, eta=1.0, guidance=SelfGuidance(50.0))
    assert not torch.equal(plain.tokens.values["link"], moved.tokens.values["link"])


def test_temperature_reaches_the_sampler_and_its_default_follows_the_samples(tiny, motions, monkeypatch):
    """The sampler's starting noise scale (`tt.dit.sample`'s temperature, checked against the
    closed form in test_dit_ddim.py) is what SamplerConfig.temperature sets; unset, a search of
    at most four samples samples at 0.3 and a larger one at 1 (`default_temperature`)."""
    sampler = CandidateSampler(tiny, "cpu")
    cfg = get_reward("tracking", "viperx")
    plain = sampler.run(motions[:1], cfg, 3, seed=1, num_steps=STEPS)
    same = sampler.run(motions[:1], cfg, 3, seed=1, num_steps=STEPS, temperature=1.0)
    cold = sampler.run(motions[:1], cfg, 3, seed=1, num_steps=STEPS, temperature=0.5)
    assert torch.equal(plain.tokens.values["link"], same.tokens.values["link"])
    assert not torch.equal(plain.tokens.values["link"], cold.tokens.values["link"])
    assert [default_temperature(n) for n in (1, 4, 5, 64)] == [0.3, 0.3, 1.0, 1.0]
    seen, run = [], CandidateSampler.run

    def spy(self, *args, **kwargs):
        seen.append(kwargs["temperature"])
        return run(self, *args, **kwargs)

    monkeypatch.setattr(CandidateSampler, "run", spy)
    for n, t in ((3, None), (5, None), (5, 0.7)):
        problem = Problem(space="viperx", motions=tuple(motions[:1]), reward="tracking", budget=n, seed=0)
        ZerothOrder(SamplerConfig(num_steps=STEPS, temperature=t), model=tiny, decoder=ListDecoder(n)).optimize(problem)
    assert seen == [0.3, 1.0, 0.7]
    with pytest.raises(TTError, match="temperature"):
        SamplerConfig(temperature=0.0)


def test_sign_of_guidance_moves_a_toy_reward(tiny, motions):
    sampler = CandidateSampler(tiny, "cpu")
    cfg = get_reward("tracking", "viperx")
    final = {}
    for s in (-2.0, 0.0, 2.0):
        gen = sampler.run(motions[:1], cfg, 8, seed=3, num_steps=STEPS, eta=1.0, guidance=ToyObjective(SelfGuidance(s)))
        final[s] = ToyObjective.reward(gen.tokens.values)
    # Same seed, so the same noise: every candidate gains with s > 0. With s < 0 values are
    # pushed toward the data range's edge, where x0's clip at -1 stops some of them, so only
    # the mean is compared there.
    assert bool((final[2.0] > final[0.0]).all()), final
    assert float(final[2.0].mean()) > float(final[0.0].mean()) + 2.0 > float(final[-2.0].mean()) + 2.5, final


def test_nonfinite_gradients_are_zeroed_and_counted(tiny, motions):
    """Candidate 0's reward is NaN with NaN gradients at every step; zeroing them must give
    exactly the samples of a reward whose gradient for candidate 0 is 0."""

    def objective(first):
        class Objective(ToyObjective):
            @staticmethod
            def reward(x0):
                r = ToyObjective.reward(x0)
                return torch.cat([first(x0["link"][:1].sum((1, 2))), r[1:]])

        return Objective

    nan_first = objective(lambda u: torch.sqrt(-1.0 + 0.0 * u))  # NaN value, NaN gradient
    zero_first = objective(lambda u: 0.0 * u)
    sampler = CandidateSampler(tiny, "cpu")
    cfg = get_reward("tracking", "viperx")
    nan_guidance = SelfGuidance(2.0)
    got = sampler.run(motions[:1], cfg, 4, seed=0, num_steps=STEPS, eta=1.0, guidance=nan_first(nan_guidance))
    want = sampler.run(motions[:1], cfg, 4, seed=0, num_steps=STEPS, eta=1.0, guidance=zero_first(SelfGuidance(2.0)))
    for name in got.tokens.values:
        assert torch.equal(got.tokens.values[name], want.tokens.values[name]), name
    per_candidate = sum(s.length * s.dim for s in tiny.layout.specs if s.role.value == "embodiment")
    assert nan_guidance.stats.nonfinite_candidates == STEPS
    assert nan_guidance.stats.nonfinite_entries == STEPS * per_candidate


class ToySim:
    """A stand-in simulator gradient: d(toy reward)/dx0 in closed form, or zero."""

    def __init__(self, zero: bool = False):
        self.zero = zero
        self.calls = 0

    def token_gradient(self, ctx, x0, step):
        self.calls += 1
        out = {n: torch.zeros_like(v) for n, v in x0.items()}
        if not self.zero:
            out["link"][..., 3:6] = -2.0 * (x0["link"][..., 3:6] - 0.5)
        return out

    def summary(self):
        return {"calls": self.calls}


def test_simulator_gradient_mixing(tiny, motions):
    """lambda = 1 with a simulator whose x0-gradient is the toy reward's steers exactly like
    lambda = 0 on the toy reward (both are carried to x_t through the network); a zero
    simulator gradient at lambda = 1 is plain sampling; lambda = 1/2 of two equal gradients
    is that gradient."""
    sampler = CandidateSampler(tiny, "cpu")
    cfg = get_reward("tracking", "viperx")

    def run(guidance):
        return sampler.run(motions[:1], cfg, 3, seed=5, num_steps=STEPS, eta=1.0, guidance=guidance).tokens.values[
            "link"
        ]

    toy = run(ToyObjective(SelfGuidance(2.0)))
    sim = ToySim()
    pure = run(ToyObjective(SelfGuidance(2.0, sim=sim, sim_weight=1.0)))
    half = run(ToyObjective(SelfGuidance(2.0, sim=ToySim(), sim_weight=0.5)))
    torch.testing.assert_close(pure, toy, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(half, toy, atol=1e-5, rtol=1e-5)
    assert sim.calls == STEPS
    plain = run(None)
    assert torch.equal(run(ToyObjective(SelfGuidance(2.0, sim=ToySim(zero=True), sim_weight=1.0))), plain)
    with pytest.raises(ValueError, match="sim_weight"):
        SelfGuidance(1.0, sim=sim, sim_weight=1.5)


def test_composition_of_one_motion_equals_plain_sampling(tiny, motions):
    layout, model = tiny.layout, tiny.model
    query = build_query(layout, tiny.normalizer, motions[0], 3)
    plain = sample(model, query.tokens, ROBOT, num_steps=STEPS, eta=1.0, generator=torch.Generator().manual_seed(2))
    composed = sample(
        ComposedModel(model, 1),
        compose_tokens(layout, [query.tokens]),
        ROBOT,
        num_steps=STEPS,
        eta=1.0,
        generator=torch.Generator().manual_seed(2),
    )
    (back,) = split_tokens(layout, composed.tokens, 1)
    for name in layout.names:
        assert torch.equal(back.values[name], plain.tokens.values[name]), name


def test_composed_eps_is_the_mean_over_copies(tiny, motions):
    layout, model = tiny.layout, tiny.model
    queries = [build_query(layout, tiny.normalizer, m, 3) for m in motions]
    g = torch.Generator().manual_seed(4)
    composed = ComposedModel(model, 2)
    tokens = compose_tokens(layout, [q.tokens for q in queries])
    tokens.values = {
        k: (torch.randn(v.shape, generator=g) if k != "target_pose@0" and k != "target_pose@1" else v)
        for k, v in tokens.values.items()
    }
    masks = task_masks(ROBOT, composed.layout, tokens)
    time = torch.full((3,), 0.4)
    with torch.no_grad():
        eps = composed(tokens.values, tokens.ids, masks.noised, time)
        copies = []
        for part in split_tokens(layout, tokens, 2):
            m = task_masks(ROBOT, layout, part)
            copies.append(model(part.values, part.ids, m.noised, time))
    for name in ("link", "dyna_joint", "fixed_joint", "actuator"):
        torch.testing.assert_close(eps[name], 0.5 * (copies[0][name] + copies[1][name]), atol=1e-6, rtol=1e-5)
        # The copies really differ (different motions), so the mean is not trivially either.
        assert float((copies[0][name] - copies[1][name]).abs().max()) > 1e-4
    for m in range(2):
        for name in ("track_link_obs", "actuator_obs", "control"):
            torch.testing.assert_close(eps[f"{name}@{m}"], copies[m][name], atol=1e-6, rtol=1e-5)


class ListDecoder:
    """Decodes candidate i to designs[i], except the candidates in `fail`; records calls."""

    def __init__(self, n: int, fail=()):
        self.designs = get_space("viperx").sample(n, seed=9)
        self.fail = set(fail)
        self.calls: list[int] = []

    def __call__(self, batch, i):
        self.calls.append(i)
        if i in self.fail or (self.fail == {"first"} and len(self.calls) == 1):
            return Decoded(None, "no discrete choice matches (test)")
        return Decoded(self.designs[i], None, 0.0)


def test_zeroth_order_ranks_by_prediction_and_puts_failed_decodes_last(tiny, motions):
    n = 5
    problem = Problem(space="viperx", motions=tuple(motions[:1]), reward="tracking", budget=n, seed=0)
    dec = ListDecoder(n, fail={"first"})
    result = ZerothOrder(SamplerConfig(num_steps=STEPS), model=tiny, decoder=dec).optimize(problem)
    objective = np.array(result.info["predicted_objective"])
    order = list(np.argsort(-objective, kind="stable"))
    assert dec.calls == order[:2]  # the predicted best failed, so the next one was decoded
    assert result.best == dec.designs[order[1]]
    assert result.best_reward == pytest.approx(objective[order[1]])
    assert result.info["decode_failures"] == 1
    assert result.info["ranking"] == order[1:] + order[:1]
    assert result.method == "zeroth" and result.rollouts == 0 and result.info["samples"] == n
    json.dumps(result.info)  # `tt optimize --json` writes it
    # decode="all": every candidate decoded, the failed ones ranked last in their own order.
    dec = ListDecoder(n, fail={order[0], order[2]})
    result = ZerothOrder(SamplerConfig(num_steps=STEPS, decode="all"), model=tiny, decoder=dec).optimize(problem)
    assert sorted(dec.calls) == list(range(n))
    assert result.info["ranking"] == [order[1], order[3], order[4], order[0], order[2]]
    assert result.designs == [dec.designs[i] for i in (order[1], order[3], order[4])]
    np.testing.assert_allclose(result.rewards, objective[[order[1], order[3], order[4]]])
    # Nothing decodes: a clear error.
    with pytest.raises(ValueError, match="none of the 5 candidates decoded"):
        ZerothOrder(SamplerConfig(num_steps=STEPS), model=tiny, decoder=ListDecoder(n, fail=range(n))).optimize(problem)


def test_rank_candidates_puts_nan_objectives_last():
    dec = ListDecoder(4)
    ranking = rank_candidates(np.array([1.0, np.nan, 3.0, 2.0]), None, dec, decode="all")
    assert ranking.order == [2, 3, 0, 1] and ranking.best == 2 and ranking.failures == 0


def test_dgs_optimizer_scales_and_statistics(tiny, motions):
    problem = Problem(space="viperx", motions=tuple(motions[:1]), reward="tracking_size", budget=3, seed=0)
    # The paper's guidance by the model's own dynamics (tiny is a robot-task model: its default is the critic's).
    paper = DGSConfig(num_steps=STEPS, guide_by="model")
    result = DynamicsSelfGuidance(paper, model=tiny, decoder=ListDecoder(3)).optimize(problem)
    assert result.method == "dgs"
    assert result.info["scale"] == 50.0 and result.info["eta"] == 1.0
    assert result.info["guided_steps"] == STEPS and len(result.info["objective_trace"]) == STEPS
    assert result.info["nonfinite_grad_entries"] == 0
    two = dataclasses.replace(problem, motions=tuple(motions))
    result = DynamicsSelfGuidance(dataclasses.replace(paper, num_steps=2), model=tiny, decoder=ListDecoder(3)).optimize(
        two
    )
    assert result.info["scale"] == 500.0
    assert np.asarray(result.info["predicted_reward_per_motion"]).shape == (3, 2)
    scales = GuidanceScales()
    assert (scales.scale("bimanual", 1), scales.scale("quadruped", 1), scales.scale("bimanual", 3)) == (0.2, 100.0, 0.2)


def test_decoder_recovers_a_real_design_from_normalised_tokens():
    """Normalised, padded tokens of a real design (as a perfect model would output them) go
    through `embodiment_batch` and `DesignDecoder` back to that design."""
    from tt.tokens.design_fit import CandidateTable
    from tt.tokens.tokenize import tokenize_models

    space = get_space("viperx")
    designs = space.sample(4, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models([space.model(d) for d in designs]).tokens
    norm = Normalizer.fit(emb)
    counts = {n: int(np.asarray(emb.mask[n]).sum(1).max()) + 2 for n in emb.types}  # room for padding
    layout = layout_from_schema(counts, steps=8)
    padded = norm.normalize(emb.pad_to({n: counts[n] for n in emb.types}).to_torch())
    from tt.tokens.batch import TokenBatch

    tokens = TokenBatch(dict(padded.values), dict(padded.ids), dict(padded.mask))
    batch = embodiment_batch(layout, norm, tokens)
    table = CandidateTable(space, discrete=[designs[0].discrete, designs[1].discrete])
    decoded = DesignDecoder(space, table=table)(batch, 0)
    assert decoded.design is not None and decoded.design.discrete == designs[0].discrete
    np.testing.assert_allclose(decoded.design.continuous, designs[0].continuous, atol=1e-4)
    assert decoded.residual < 1e-4
    assert decoded.distance == 0

    # One wrong link-ID bit (what an undertrained model emits): the default decoder projects it
    # onto the nearest design, the exact twin (what the simulator gradient uses) refuses it.
    from tt.tokens.schema import SCHEMA

    col = SCHEMA["dyna_joint"].slice("link_id").start
    batch.values["dyna_joint"][0, 0, col] = 1.0 - batch.values["dyna_joint"][0, 0, col]
    decoder = DesignDecoder(space, table=table)
    projected = decoder(batch, 0)
    assert projected.design is not None and projected.design.discrete == designs[0].discrete and projected.distance == 1
    refused = decoder.exact()(batch, 0)
    assert refused.design is None and "nearest: 1" in refused.error


class OracleEps(torch.nn.Module):
    """A stand-in network that knows the clean tokens x0* of each sequence: it predicts
    eps = (x_t - sqrt(abar) x0*) / sqrt(1 - abar), so every x0_hat is x0* and the samples end
    at x0* (up to the sampler's clip)."""

    def __init__(self, layout, target: dict[str, torch.Tensor]):
        super().__init__()
        self.layout = layout
        self.target = target
        self.scheduler = CosineDDIM(ROBOT.diffusion_steps)

    def forward(self, values, ids, noised, time, attend=None, outputs=None):
        t = int(round(float(time[0]) * self.scheduler.train_steps)) - 1
        ab = float(self.scheduler.alpha_bar(t))
        names = outputs if outputs is not None else [s.name for s in self.layout.specs if s.role.value != "condition"]
        return {n: (values[n] - ab**0.5 * self.target[n]) / (1 - ab) ** 0.5 for n in names}


def test_zeroth_order_returns_the_design_with_the_best_predicted_tracking(motions):
    """End to end: query, sampling, predicted reward, ranking, decoding. Candidate k's
    clean tokens are real design k's embodiment and end-effector poses `offset_k` off the
    targets, so the winner must be the design with the smallest offset, decoded exactly."""
    from tt.tokens.batch import TokenBatch
    from tt.tokens.design_fit import CandidateTable
    from tt.tokens.tokenize import tokenize_models

    space = get_space("viperx")
    designs = space.sample(3, seed=11)
    offsets = torch.tensor([0.03, 0.01, 0.05])  # [m] along x
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models([space.model(d) for d in designs]).tokens
    counts = {n: int(np.asarray(emb.mask[n]).sum(1).max()) for n in emb.types}
    counts.update(track_link_obs=1, target_pose=1)
    layout = layout_from_schema(counts, steps=8)
    motion = motions[0]
    steps = query_steps(motion.steps, 8, 3).numpy()  # the query's steps
    target_pos = torch.tensor(motion.pos[steps][:, :, 0], dtype=torch.float32)  # (3, 8, 3)
    wxyz = motion.quat[steps][:, :, 0].reshape(-1, 4)
    mats = torch.tensor(
        Rotation.from_quat(np.roll(wxyz, -1, axis=-1)).as_matrix().reshape(3, 8, 9), dtype=torch.float32
    )
    ee = target_pos + torch.stack([offsets, 0 * offsets, 0 * offsets], -1)[:, None]
    track = torch.cat([ee, mats], -1)  # (3, 8, 12)
    target = torch.cat([target_pos, mats], -1)
    # Statistics covering every value the candidates hold.
    ones = np.ones((3, 8), bool)
    dyn = TokenBatch(
        {"track_link_obs": track.numpy(), "target_pose": target.numpy()},
        {"track_link_obs": np.zeros((3, 8, 2), np.int64), "target_pose": np.zeros((3, 8, 2), np.int64)},
        {"track_link_obs": ones, "target_pose": ones},
    )
    norm = Normalizer.fit([emb, dyn])
    x0 = {n: v for n, v in norm.normalize(emb.to_torch()).values.items()}
    x0["track_link_obs"] = norm.normalize(dyn.subset(["track_link_obs"]).to_torch()).values["track_link_obs"]
    model = OracleEps(layout, x0)
    trained = TrainedModel(model, norm, layout, 0)
    table = CandidateTable(space, discrete=[d.discrete for d in designs])
    problem = Problem(space="viperx", motions=(motion,), reward="tracking", budget=3, seed=0)
    result = ZerothOrder(
        SamplerConfig(num_steps=10, decode="all"), model=trained, decoder=DesignDecoder(space, table=table)
    ).optimize(problem)
    assert result.info["ranking"] == [1, 0, 2] and result.info["decode_failures"] == 0
    assert result.best.discrete == designs[1].discrete
    np.testing.assert_allclose(result.best.continuous, designs[1].continuous, atol=1e-4)
    # The predicted objective is the tracking reward of those poses: (T / 8) sum_k exp(-d^2 / sigma_p - ...).
    T = motion.steps
    want = T * torch.exp(-(offsets.double() ** 2) / 0.01)
    np.testing.assert_allclose(result.info["predicted_objective"], want.numpy(), rtol=1e-3)


class _Recorder(torch.nn.Module):
    """A network wrapper that records what the sampler feeds it."""

    def __init__(self, inner: RoboDiT):
        super().__init__()
        self.inner = inner
        self.layout = inner.layout
        self.calls = []

    def forward(self, values, ids, noised, time, attend=None, outputs=None):
        self.calls.append(
            ({k: v.detach().clone() for k, v in values.items()}, {k: v.clone() for k, v in noised.items()})
        )
        return self.inner(values, ids, noised, time, attend, outputs=outputs)


def test_inpainting_keeps_known_tokens_and_noises_them_to_each_step(tiny, motions):
    """Known tokens enter every network call as q(x_t | x0) at that call's step (the implied
    noise is standard normal), flagged as diffused, and come out exactly as given; an empty
    `known` is plain sampling."""
    layout, n = tiny.layout, 64
    q = build_query(layout, tiny.normalizer, motions[0], n)
    given = torch.rand(q.tokens.values["link"].shape, generator=torch.Generator().manual_seed(3)) * 2 - 1
    q.tokens.values["link"] = given
    known = {"link": torch.ones(n, layout["link"].length, dtype=torch.bool)}
    scheduler = CosineDDIM(ROBOT.diffusion_steps)
    rec = _Recorder(tiny.model)
    res = sample(
        rec,
        q.tokens,
        ROBOT,
        scheduler=scheduler,
        num_steps=STEPS,
        known=known,
        generator=torch.Generator().manual_seed(0),
    )
    assert torch.equal(res.tokens.values["link"], given) and not res.updated["link"].any()
    assert not torch.equal(res.tokens.values["actuator"], q.tokens.values["actuator"])
    steps = scheduler.timesteps(STEPS)
    assert len(rec.calls) == len(steps)
    for (values, noised), t in zip(rec.calls, steps):
        ab = scheduler.alpha_bar(t).float()
        eps = (values["link"] - ab.sqrt() * given) / (1 - ab).sqrt()
        assert abs(float(eps.mean())) < 0.05 and abs(float(eps.std()) - 1) < 0.05, (
            t,
            float(eps.mean()),
            float(eps.std()),
        )
        assert noised["link"].all()
    plain = sample(
        tiny.model, q.tokens, ROBOT, scheduler=scheduler, num_steps=STEPS, generator=torch.Generator().manual_seed(0)
    )
    empty = sample(
        tiny.model,
        q.tokens,
        ROBOT,
        scheduler=scheduler,
        num_steps=STEPS,
        known={},
        generator=torch.Generator().manual_seed(0),
    )
    for name in layout.names:
        assert torch.equal(plain.tokens.values[name], empty.tokens.values[name]), name
    with pytest.raises(ValueError, match="does not diffuse"):
        sample(tiny.model, q.tokens, ROBOT, scheduler=scheduler, num_steps=STEPS, known={"target_pose": known["link"]})
