"""DDIM scheduler against the closed-form formulas, and the sampling loop on a known Gaussian.

References: the cosine schedule's definition (Nichol & Dhariwal 2021, eq. 17 with the
0.999 beta cap), DDIM's update and sigma (Song et al. 2021, eqs. 12 and 16), the DDPM
posterior variance, and the exact posterior-mean denoiser of Gaussian data.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn as nn

from tt.dit.ddim import CosineDDIM
from tt.dit.layout import Layout, TokenSpec
from tt.dit.sampling import sample
from tt.dit.tasks import TaskSpec
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import Role


def _f(u: float) -> float:
    return math.cos((u + 0.008) / 1.008 * math.pi / 2) ** 2


def _alpha_bars_by_hand(T: int) -> list[float]:
    out, prod = [], 1.0
    for i in range(T):
        beta = min(1.0 - _f((i + 1) / T) / _f(i / T), 0.999)
        prod *= 1.0 - beta
        out.append(prod)
    return out


@pytest.mark.parametrize("T", [5, 100])
def test_alpha_bar_matches_cosine_schedule(T):
    s = CosineDDIM(T)
    hand = _alpha_bars_by_hand(T)
    assert s.alpha_bars.tolist() == pytest.approx(hand, rel=1e-12, abs=1e-15)
    # Telescoping: below the cap alpha_bar_t = f((t+1)/T) / f(0); the last beta is capped.
    for t in range(T - 1):
        assert float(s.alpha_bar(t)) == pytest.approx(_f((t + 1) / T) / _f(0.0), rel=1e-10)
    assert float(s.betas[-1]) == 0.999
    assert float(s.alpha_bar(-1)) == 1.0
    # Same noise level at the same fraction of the process, whatever T.
    assert float(CosineDDIM(100).alpha_bar(59)) == pytest.approx(float(CosineDDIM(5).alpha_bar(2)), rel=1e-10)
    assert float(s.model_time(T - 1)) == 1.0


def test_alpha_bar_hand_values():
    # T = 5 by hand: f(0) = cos^2(0.008/1.008 pi/2) = 0.9998446, f(0.2) = cos^2(0.208/1.008 pi/2)
    # = 0.8985663, alpha_bar_0 = f(0.2) / f(0) = 0.8987059.
    f0 = math.cos(0.008 / 1.008 * math.pi / 2) ** 2
    f1 = math.cos(0.208 / 1.008 * math.pi / 2) ** 2
    assert f0 == pytest.approx(0.9998446, abs=1e-7)
    assert float(CosineDDIM(5).alpha_bar(0)) == pytest.approx(f1 / f0, rel=1e-12)
    assert float(CosineDDIM(5).alpha_bar(0)) == pytest.approx(0.8987059, abs=1e-7)


def test_sigma_formula_and_ddpm_limit():
    s = CosineDDIM(100)
    ab = s.alpha_bars.tolist()
    for t, tp in [(99, 89), (50, 40), (10, 0), (37, 36)]:
        expected = 0.7 * math.sqrt((1 - ab[tp]) / (1 - ab[t])) * math.sqrt(1 - ab[t] / ab[tp])
        assert s.sigma(t, tp, 0.7) == pytest.approx(expected, rel=1e-12)
        assert s.sigma(t, tp, 0.0) == 0.0
    # eta = 1 over one training step is the DDPM posterior variance beta_t (1 - ab_{t-1}) / (1 - ab_t).
    for t in (1, 20, 80):
        beta = float(s.betas[t])
        assert s.sigma(t, t - 1, 1.0) ** 2 == pytest.approx(beta * (1 - ab[t - 1]) / (1 - ab[t]), rel=1e-10)
    # The last step (to t' = -1, alpha_bar = 1) has no noise.
    assert s.sigma(0, -1, 1.0) == 0.0


def test_noise_round_trip_and_step_closed_form():
    s = CosineDDIM(100, clip_x0=None)
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(6, 4, 3, generator=g) * 2 - 1
    eps = torch.randn(6, 4, 3, generator=g)
    t = torch.tensor([0, 5, 17, 50, 98, 99])
    xt = s.add_noise(x0, eps, t)
    ab = s.alpha_bar(t).float()[:, None, None]
    torch.testing.assert_close(xt, ab.sqrt() * x0 + (1 - ab).sqrt() * eps)
    torch.testing.assert_close(s.predict_x0(xt, eps, t), x0, rtol=0, atol=2e-4)
    torch.testing.assert_close(s.predict_eps(xt, x0, t), eps, rtol=0, atol=2e-4)
    # One deterministic step from t=50 to 40 lands on the forward marginal with the same eps.
    x50 = s.add_noise(x0, eps, 50)
    x40, x0_hat = s.step(x50, eps, 50, 40, eta=0.0)
    torch.testing.assert_close(x40, s.add_noise(x0, eps, 40), rtol=0, atol=1e-5)
    torch.testing.assert_close(x0_hat, x0, rtol=0, atol=1e-5)
    # eta > 0 adds sigma z.
    z = torch.randn(6, 4, 3, generator=g)
    x40n, _ = s.step(x50, eps, 50, 40, eta=1.0, noise=z)
    sig = s.sigma(50, 40, 1.0)
    ab40 = float(s.alpha_bar(40))
    torch.testing.assert_close(
        x40n, math.sqrt(ab40) * x0 + math.sqrt(1 - ab40 - sig**2) * eps + sig * z, rtol=0, atol=1e-5
    )


def test_clip_and_guided_eps():
    s = CosineDDIM(10)
    xt = torch.full((1, 1, 1), 5.0)
    assert float(s.predict_x0(xt, torch.zeros_like(xt), 3)) == 1.0
    eps, grad = torch.ones(2, 3, 4), torch.full((2, 3, 4), 2.0)
    expected = 1.0 - math.sqrt(1 - float(s.alpha_bar(7))) * 0.5 * 2.0
    torch.testing.assert_close(s.guided_eps(eps, grad, 0.5, 7), torch.full((2, 3, 4), expected))


def test_timesteps_leading_spacing():
    assert CosineDDIM(100).timesteps() == list(range(99, -1, -1))
    assert CosineDDIM(100).timesteps(10) == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    assert CosineDDIM(5).timesteps() == [4, 3, 2, 1, 0]
    with pytest.raises(ValueError, match="num_steps"):
        CosineDDIM(5).timesteps(6)
    with pytest.raises(ValueError, match="spacing"):
        CosineDDIM(5).timesteps(2, "middle")
    with pytest.raises(ValueError, match="diffusion step"):
        CosineDDIM(5).alpha_bar(5)


def test_timesteps_trailing_spacing():
    # Lin et al. 2024, Table 2: trailing steps start at T - 1 and are T / n apart.
    assert CosineDDIM(1000).timesteps(10, "trailing") == [999, 899, 799, 699, 599, 499, 399, 299, 199, 99]
    assert CosineDDIM(100).timesteps(1, "trailing") == [99]
    assert CosineDDIM(5).timesteps(1, "trailing") == [4]
    assert CosineDDIM(5).timesteps(1) == [0]  # leading: one step starts at the least noisy level
    for T in (5, 100):
        assert CosineDDIM(T).timesteps(T, "trailing") == CosineDDIM(T).timesteps(T)
        for n in range(1, T + 1):
            steps = CosineDDIM(T).timesteps(n, "trailing")
            assert (
                len(steps) == n and steps[0] == T - 1 and steps == sorted(set(steps), reverse=True) and steps[-1] >= 0
            )


# ------------------------------------------------------------------ sampling a known Gaussian

MU, STD = 0.3, 0.2
LAYOUT = Layout(
    (
        TokenSpec("goal", 2, ("time",), Role.CONDITION, 4, 1),
        TokenSpec("shape", 3, ("link",), Role.EMBODIMENT, 2),
        TokenSpec("extra", 3, ("link",), Role.EMBODIMENT, 2),
    ),
    {"time": 8, "link": 4},
    steps=4,
)


class GaussianEps(nn.Module):
    """The exact eps of data ~ N(MU, STD^2) per feature: E[eps | x_t] =
    sqrt(1 - ab) (x_t - sqrt(ab) MU) / (ab STD^2 + 1 - ab). Has the RoboDiT call signature."""

    def __init__(self, scheduler: CosineDDIM):
        super().__init__()
        self.layout = LAYOUT
        self.scheduler = scheduler

    def forward(self, values, ids, noised, time, attend=None, outputs=None):
        t = int(round(float(time[0]) * self.scheduler.train_steps - 1))
        ab = float(self.scheduler.alpha_bar(t))
        return {n: math.sqrt(1 - ab) * (values[n] - math.sqrt(ab) * MU) / (ab * STD**2 + 1 - ab) for n in outputs}


def _tokens(b: int) -> TokenBatch:
    g = torch.Generator().manual_seed(1)
    values = {s.name: torch.randn(b, s.length, s.dim, generator=g) for s in LAYOUT.specs}
    ids = {
        "goal": torch.arange(4).repeat(b, 1)[..., None],
        "shape": torch.arange(2).repeat(b, 1)[..., None],
        "extra": torch.arange(2).repeat(b, 1)[..., None],
    }
    mask = {s.name: torch.ones(b, s.length, dtype=torch.bool) for s in LAYOUT.specs}
    return TokenBatch(values, ids, mask)


def _ddim_moments(sched: CosineDDIM, eta: float, temperature: float = 1.0) -> tuple[float, float]:
    """Exact mean and std after DDIM sampling of N(MU, STD^2) data with the exact eps, from
    x_T ~ N(0, temperature^2). With d = x_t - sqrt(ab) MU and v = ab STD^2 + 1 - ab, the step is affine:
    x_t' - sqrt(ab') MU = c d + sigma z, c = (sqrt(ab ab') STD^2 + sqrt((1 - ab)(1 - ab' - sigma^2))) / v."""
    steps = sched.timesteps()
    mean, var = 0.0, temperature**2
    for i, t in enumerate(steps):
        tp = steps[i + 1] if i + 1 < len(steps) else -1
        ab, abp = float(sched.alpha_bar(t)), float(sched.alpha_bar(tp))
        sig = sched.sigma(t, tp, eta)
        c = (math.sqrt(ab * abp) * STD**2 + math.sqrt((1 - ab) * (1 - abp - sig**2))) / (ab * STD**2 + 1 - ab)
        mean = math.sqrt(abp) * MU + c * (mean - math.sqrt(ab) * MU)
        var = c * c * var + sig**2
    return mean, math.sqrt(var)


@pytest.mark.parametrize("eta", [0.0, 1.0])
def test_ddim_recovers_known_gaussian(eta):
    sched = CosineDDIM(100, clip_x0=None)
    task = TaskSpec("robot", 100, "random")
    tokens = _tokens(4000)
    out = sample(GaussianEps(sched), tokens, task, scheduler=sched, eta=eta, generator=torch.Generator().manual_seed(2))
    x = torch.cat([out.tokens.values["shape"].reshape(-1), out.tokens.values["extra"].reshape(-1)])  # 48000 draws
    mean, std = _ddim_moments(sched, eta)
    # Monte-Carlo errors over 48000 draws: ~1e-3 on the mean, ~0.3 % on the std.
    assert float(x.mean()) == pytest.approx(mean, abs=4e-3)
    assert float(x.std()) == pytest.approx(std, rel=0.012)
    # The data distribution itself, up to the sampler's bias with 100 steps: the narrow
    # Gaussian makes the last deterministic steps stiff (3.5 % narrow), and eta = 1 adds the
    # posterior variance given x0 but not the uncertainty of x0 itself (7 % narrow).
    assert float(x.mean()) == pytest.approx(MU, abs=4e-3)
    assert float(x.std()) == pytest.approx(STD, rel=0.05 if eta == 0.0 else 0.1)
    # Conditioning tokens come back bit-identical.
    assert torch.equal(out.tokens.values["goal"], tokens.values["goal"])


def test_one_trailing_step_gives_the_conditional_mean():
    """One trailing step from pure noise returns x0_hat at the noisiest level, E[x0 | x_T]:
    for N(MU, STD^2) data (MU (1 - ab) + sqrt(ab) STD^2 x_T) / v, v = ab STD^2 + 1 - ab, so
    mean MU (1 - ab) / v (~ MU) and std sqrt(ab) STD^2 / v (~ 0). One leading step denoises
    pure noise as if it were nearly clean and returns noise."""
    sched = CosineDDIM(100, clip_x0=None)
    task = TaskSpec("robot", 100, "random")
    tokens = _tokens(4000)
    ab = float(sched.alpha_bar(99))
    v = ab * STD**2 + 1 - ab

    def draw(spacing: str) -> torch.Tensor:
        out = sample(
            GaussianEps(sched),
            tokens,
            task,
            scheduler=sched,
            num_steps=1,
            spacing=spacing,
            generator=torch.Generator().manual_seed(2),
        )
        return torch.cat([out.tokens.values["shape"].reshape(-1), out.tokens.values["extra"].reshape(-1)])

    x = draw("trailing")
    # Here the exact x0_hat is MU to 1e-8; eps -> x0_hat divides x_T - sqrt(1 - ab) eps (float32,
    # |x_T| < 5) by sqrt(ab) = 5e-4, which costs up to ~5e-4 of rounding.
    assert abs(MU * (1 - ab) / v - MU) < 1e-7 and math.sqrt(ab) * STD**2 / v < 1e-4
    assert float((x - MU).abs().max()) < 1e-3
    assert float(x.mean()) == pytest.approx(MU, abs=1e-4)
    assert float(draw("leading").std()) > 0.5


def test_guide_hook_shifts_only_guided_types():
    sched = CosineDDIM(100, clip_x0=None)
    task = TaskSpec("robot", 100, "random")
    model = GaussianEps(sched)
    tokens = _tokens(256)
    target = 0.8
    seen = []

    def guide(step, x_t, eps, x0):
        assert x_t["shape"].requires_grad
        seen.append(step)
        reward = -((x0["shape"] - target) ** 2).sum()
        (grad,) = torch.autograd.grad(reward, x_t["shape"])
        t = sched.timesteps()[step]
        # Returning a changed eps for "extra" too: it must be ignored, "extra" is not guided.
        return {"shape": sched.guided_eps(eps["shape"], grad, 5.0, t), "extra": eps["extra"] + 10.0}

    plain = sample(model, tokens, task, scheduler=sched, generator=torch.Generator().manual_seed(3))
    guided = sample(
        model, tokens, task, scheduler=sched, generator=torch.Generator().manual_seed(3), guide=guide, guided=["shape"]
    )
    assert seen == list(range(100))
    assert torch.equal(guided.tokens.values["extra"], plain.tokens.values["extra"])
    moved = float(guided.tokens.values["shape"].mean()) - float(plain.tokens.values["shape"].mean())
    assert moved > 0.1, f"guidance toward {target} moved the mean by only {moved}"
    assert torch.equal(guided.tokens.values["goal"], tokens.values["goal"])


def test_temperature_scales_the_starting_noise():
    """Deterministic DDIM is affine in x_T here, so starting from N(0, 0.5^2) narrows the samples
    by the closed form's factor; temperature 1 is the default's draw, bit for bit."""
    sched = CosineDDIM(100, clip_x0=None)
    task = TaskSpec("robot", 100, "random")
    tokens = _tokens(4000)

    def run(**kw):
        return sample(
            GaussianEps(sched), tokens, task, scheduler=sched, generator=torch.Generator().manual_seed(2), **kw
        )

    cold = run(temperature=0.5)
    x = torch.cat([cold.tokens.values["shape"].reshape(-1), cold.tokens.values["extra"].reshape(-1)])
    mean, std = _ddim_moments(sched, 0.0, temperature=0.5)
    assert std < 0.9 * _ddim_moments(sched, 0.0)[1]
    assert float(x.mean()) == pytest.approx(mean, abs=4e-3)
    assert float(x.std()) == pytest.approx(std, rel=0.012)
    assert torch.equal(run(temperature=1.0).tokens.values["shape"], run().tokens.values["shape"])
    with pytest.raises(ValueError, match="temperature"):
        run(temperature=0.0)
