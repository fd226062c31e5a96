"""Sample-efficiency options of training (prediction target, loss weighting, per-type weights,
bf16 on the CPU, DDIM training steps) against their formulas; the defaults are the measured winners."""

from __future__ import annotations

import math

import pytest
import torch

from tt.dit.ddim import EDM_SIGMA_DATA, EDM_WEIGHT_CAP, CosineDDIM
from tt.dit.model import RoboDiT, get_config
from tt.dit.sampling import sample
from tt.dit.tasks import ROBOT, TaskSpec, diffusion_loss, noise_tokens
from tt.dit.toy import toy_episodes
from tt.dit.train import TrainConfig, train

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def episodes():
    return toy_episodes(episodes=12, steps=20, seed=0)


def _x(shape=(6, 5, 3), seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=g, dtype=torch.float64), torch.randn(shape, generator=g, dtype=torch.float64)


def test_every_target_reconstructs_the_same_x0_and_eps():
    """x_t = sqrt(ab) x0 + sqrt(1 - ab) eps; the exact eps / x0 / v targets of that x_t, turned
    back into eps by `eps_from_output`, give the true eps and (through `predict_x0`) the true x0,
    at every noise level from the cleanest to the noisiest."""
    s = CosineDDIM(100, clip_x0=None)
    x0, eps = _x()
    t = torch.tensor([0, 1, 10, 50, 90, 99])
    x_t = s.add_noise(x0, eps, t)
    ab = s.alpha_bar(t)[:, None, None]
    v_formula = ab.sqrt() * eps - (1 - ab).sqrt() * x0
    torch.testing.assert_close(s.training_target(x0, eps, t, "v"), v_formula, rtol=0, atol=1e-12)
    torch.testing.assert_close(s.training_target(x0, eps, t, "x0"), x0, rtol=0, atol=0)
    torch.testing.assert_close(s.training_target(x0, eps, t, "eps"), eps, rtol=0, atol=0)
    for kind in ("eps", "x0", "v"):
        out = s.training_target(x0, eps, t, kind)
        e = s.eps_from_output(out, x_t, t, kind)
        # eps from x0 divides by sqrt(1 - ab), about 1e-1 at t = 0: error up to ~1e-14 there.
        torch.testing.assert_close(e, eps, rtol=0, atol=1e-9, msg=kind)
        torch.testing.assert_close(s.predict_x0(x_t, e, t, clip=False), x0, rtol=0, atol=1e-9, msg=kind)
    # v also gives x0 directly: x0 = sqrt(ab) x_t - sqrt(1 - ab) v.
    torch.testing.assert_close(ab.sqrt() * x_t - (1 - ab).sqrt() * v_formula, x0, rtol=0, atol=1e-12)


def test_loss_weights_match_their_formulas():
    s = CosineDDIM(100)
    t = torch.arange(100)
    ab = s.alpha_bar(t)
    snr = ab / (1 - ab)
    assert torch.equal(s.snr(t), snr)
    for kind in ("eps", "x0", "v"):
        assert torch.equal(s.loss_weight(t, "none", kind), torch.ones(100, dtype=torch.float64))
    g = 5.0
    torch.testing.assert_close(s.loss_weight(t, "min_snr", "eps"), torch.minimum(snr, torch.tensor(g)) / snr)
    torch.testing.assert_close(s.loss_weight(t, "min_snr", "x0"), torch.minimum(snr, torch.tensor(g)))
    torch.testing.assert_close(s.loss_weight(t, "min_snr", "v"), torch.minimum(snr, torch.tensor(g)) / (snr + 1))
    # Hang et al.: the eps weight is 1 wherever SNR <= gamma (the noisy half) and gamma / SNR below.
    w = s.loss_weight(t, "min_snr", "eps", gamma=g)
    torch.testing.assert_close(w[snr <= g], torch.ones_like(w[snr <= g]))
    assert torch.all(w[snr > g] < 1)
    # EDM: lambda(sigma) = (sigma^2 + sd^2) / (sigma sd)^2 on the x0 loss, sigma^2 = 1 / SNR.
    sd = EDM_SIGMA_DATA
    sigma2 = 1 / snr
    lam = (sigma2 + sd**2) / (sigma2 * sd**2)
    for kind, to_target, at_one in (("x0", 1.0, 1.0), ("eps", 1 / snr, 1.0), ("v", 1 / (1 + snr), 0.5)):
        expected = (lam * to_target).clamp(max=EDM_WEIGHT_CAP * at_one * (1 + sd**2) / sd**2)
        torch.testing.assert_close(s.loss_weight(t, "edm", kind), expected)
    # Where the cap does not bite, the three targets weigh the same x0 error the same:
    # w_eps |d eps|^2 = w_x0 |d x0|^2 with |d eps|^2 = SNR |d x0|^2.
    cap = EDM_WEIGHT_CAP * (1 + sd**2) / sd**2
    free = (lam / snr < cap) & (lam < cap)
    assert free.sum() >= 10
    torch.testing.assert_close((s.loss_weight(t, "edm", "eps") * snr)[free], s.loss_weight(t, "edm", "x0")[free])
    with pytest.raises(ValueError, match="weighting"):
        s.loss_weight(t, "karras", "eps")
    with pytest.raises(ValueError, match="prediction"):
        s.loss_weight(t, "none", "score")


def _parts(episodes, prediction="eps", weighting="none", seed=0):
    layout = episodes.layout(4)
    norm = episodes.fit_normalizer()
    from tt.dit.layout import with_slot_ids

    tokens = norm.normalize(with_slot_ids(layout, episodes.sample(8, 4, "random", torch.Generator().manual_seed(seed))))
    task = TaskSpec("robot", 100, "random")
    inputs = noise_tokens(
        task,
        CosineDDIM(100),
        layout,
        tokens,
        torch.Generator().manual_seed(seed + 1),
        prediction=prediction,
        weighting=weighting,
    )
    return layout, tokens, task, inputs


def test_training_targets_and_weights_reach_the_loss(episodes):
    """The loss regresses onto the chosen target, scaled per sample by the chosen weight: with a
    network that outputs 0 the MSE term of a type is mean_b w_b |target_b|^2 over its entries."""
    torch.manual_seed(0)
    layout = episodes.layout(4)
    model = RoboDiT(layout, get_config("tiny"))  # adaLN-Zero: every head outputs 0 at init
    s = CosineDDIM(100)
    for prediction, weighting in (("eps", "none"), ("v", "min_snr"), ("x0", "edm")):
        _, tokens, task, inputs = _parts(episodes, prediction, weighting)
        x0 = tokens.values
        t = inputs.step
        total, per_type = diffusion_loss(model, [(task, inputs)], loss="mse")
        w = s.loss_weight(t, weighting, prediction).float()
        expected_total = 0.0
        for n, term in per_type.items():
            m = inputs.masks.loss_mask(n)
            target = s.training_target(x0[n], inputs.eps[n], t, prediction)
            err = (target.float() ** 2).mean(-1)
            expected = (err * w[:, None] * m).sum() / m.sum()
            torch.testing.assert_close(term, expected, rtol=1e-5, atol=1e-7, msg=f"{prediction}/{weighting}/{n}")
            expected_total += float(expected)
        assert math.isclose(float(total.detach()), expected_total, rel_tol=1e-5)


def test_type_weights_scale_their_terms(episodes):
    torch.manual_seed(0)
    layout = episodes.layout(4)
    model = RoboDiT(layout, get_config("tiny"))
    _, _, task, inputs = _parts(episodes)
    total, per_type = diffusion_loss(model, [(task, inputs)])
    name = next(iter(per_type))
    weighted, per_type_w = diffusion_loss(model, [(task, inputs)], type_weights={name: 4.0})
    assert torch.equal(per_type[name], per_type_w[name])  # the reported terms are unweighted
    assert math.isclose(float(weighted.detach()), float(total.detach()) + 3.0 * float(per_type[name]), rel_tol=1e-6)
    with pytest.raises(ValueError, match="not token types"):
        diffusion_loss(model, [(task, inputs)], type_weights={"no_such_type": 2.0})


def test_defaults_are_the_measured_winners():
    """x0 prediction and sinusoidal time IDs (benchmarks/results/dit_recipe.md); the rest is the
    paper's recipe."""
    c = TrainConfig()
    assert (c.prediction, c.time_ids, c.anchor_track) == ("x0", "sinusoidal", False)
    assert (c.weighting, c.type_weights, c.bf16_cpu) == ("none", {}, False)
    assert (c.robot_diffusion_steps, c.control_diffusion_steps) == (100, 5)
    with pytest.raises(ValueError, match="prediction"):
        TrainConfig(prediction="score")
    with pytest.raises(ValueError, match="weighting"):
        TrainConfig(weighting="p2")
    with pytest.raises(ValueError, match="type_weights"):
        TrainConfig(type_weights={"link": -1.0})


def _config(tmp_path, **kw) -> TrainConfig:
    base = dict(
        out=str(tmp_path / "run"),
        size="tiny",
        batch_size=8,
        warmup_steps=5,
        lr=3e-3,
        device="cpu",
        checkpoint_every=1000,
        window=4,
        steps=3,
    )
    base.update(kw)
    return TrainConfig(**base)


def test_prediction_is_kept_by_the_checkpoint_and_used_by_the_sampler(tmp_path, episodes):
    """A v-model's checkpoint loads as a v-model, and the sampler turns its output into eps: a
    one-step DDIM run's x0 is sqrt(ab) x_t - sqrt(1 - ab) v (clipped) of the network's raw output."""
    from tt.dit.checkpoint import load_model

    train(_config(tmp_path, prediction="v"), episodes=episodes)
    trained = load_model(tmp_path / "run")
    assert trained.model.prediction == "v"
    layout, norm = trained.layout, trained.normalizer
    from tt.dit.layout import with_slot_ids

    tokens = norm.normalize(with_slot_ids(layout, episodes.sample(4, 4, "random", torch.Generator().manual_seed(3))))
    s = CosineDDIM(ROBOT.diffusion_steps)
    res = sample(
        trained.model, tokens, ROBOT, scheduler=s, num_steps=1, generator=torch.Generator().manual_seed(4), keep_x0=True
    )
    # Rebuild the step by hand from the network's raw output.
    from tt.dit.tasks import output_types, task_masks

    masks = task_masks(ROBOT, layout, tokens)
    # The sampler draws the initial noise type by type, in layout order, from its generator.
    x_t, g = {}, torch.Generator().manual_seed(4)
    wanted = output_types(ROBOT, layout)
    for n in layout.names:
        upd = masks.noised[n] & masks.visible[n]
        if n in wanted:
            x_t[n] = torch.where(upd.unsqueeze(-1), torch.randn(tokens.values[n].shape, generator=g), tokens.values[n])
        else:
            x_t[n] = tokens.values[n]
    with torch.no_grad():
        t = s.timesteps(1)[0]
        out = trained.model(
            x_t, tokens.ids, masks.noised, torch.full((4,), float(s.model_time(t))), masks.attend, outputs=wanted
        )
    ab = float(s.alpha_bar(t))
    for n in wanted:
        x0 = (math.sqrt(ab) * x_t[n] - math.sqrt(1 - ab) * out[n]).clamp(-1, 1)
        torch.testing.assert_close(res.x0_history[0][n], x0, rtol=1e-4, atol=1e-5, msg=n)


def test_bf16_cpu_autocasts_the_network(tmp_path, episodes):
    """bf16_cpu runs the network's linears in bfloat16 on the CPU; without it they stay float32."""
    seen = []
    from torch.nn.modules.module import register_module_forward_hook

    handle = register_module_forward_hook(
        lambda m, a, o: seen.append(o.dtype) if isinstance(m, torch.nn.Linear) else None
    )
    try:
        plain = train(_config(tmp_path / "a", steps=2), episodes=episodes)
        dtypes_plain = set(seen)
        seen.clear()
        fast = train(_config(tmp_path / "b", steps=2, bf16_cpu=True), episodes=episodes)
        dtypes_fast = set(seen)
    finally:
        handle.remove()
    assert dtypes_plain == {torch.float32} and torch.bfloat16 in dtypes_fast
    # Same data, noise and initial weights. The first loss is exact either way (adaLN-Zero heads
    # output 0 at init); after one update the two agree to bfloat16's precision, not bit for bit.
    assert plain.losses[0] == fast.losses[0]
    assert plain.losses[1] != fast.losses[1]
    assert math.isclose(float(plain.losses[1]), float(fast.losses[1]), rel_tol=3e-2)


def test_ddim_training_steps_set_the_noise_levels_trained(tmp_path, episodes):
    """robot_diffusion_steps = 4: the network sees model times (t + 1) / 4 only."""
    from torch.nn.modules.module import register_module_forward_hook

    times = []
    handle = register_module_forward_hook(
        lambda m, a, o: times.append(a[3].detach().clone()) if isinstance(m, RoboDiT) else None
    )
    try:
        train(_config(tmp_path, steps=6, robot_diffusion_steps=4), episodes=episodes)
    finally:
        handle.remove()
    seen = torch.cat(times).unique()
    assert set(seen.tolist()) <= {0.25, 0.5, 0.75, 1.0} and len(seen) >= 3
