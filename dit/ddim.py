"""DDIM with a cosine noise schedule and epsilon prediction (Song et al. 2021; Nichol & Dhariwal 2021).

Schedule. With T training steps, f(u) = cos^2(((u + s) / (1 + s)) pi / 2), s = 0.008,
beta_i = min(1 - f((i + 1) / T) / f(i / T), 0.999) and alpha_bar_t = prod_{i <= t} (1 - beta_i)
for t = 0 .. T-1 (the "squaredcos_cap_v2" schedule of the paper's DDIM). Away from the cap,
the product telescopes: alpha_bar_t = f((t + 1) / T) / f(0), so the same noise level sits
at the same fraction (t + 1) / T whatever T is; `model_time` hands the model that fraction,
which lets one network serve the 100-step motion-to-robot and the 5-step control process.

Forward process: x_t = sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) eps.

Reverse step from t to t' < t (t' = -1 means the end, alpha_bar_{-1} = 1):
  x0_hat  = (x_t - sqrt(1 - alpha_bar_t) eps) / sqrt(alpha_bar_t), clipped to +-clip_x0
  sigma   = eta sqrt((1 - alpha_bar_t') / (1 - alpha_bar_t)) sqrt(1 - alpha_bar_t / alpha_bar_t')
  x_t'    = sqrt(alpha_bar_t') x0_hat + sqrt(1 - alpha_bar_t' - sigma^2) eps + sigma z
The direction term uses the model's eps, not one recomputed from the clipped x0_hat.
eta = 0 is deterministic DDIM, eta = 1 has the DDPM posterior variance.

What the network predicts (``prediction``, `PREDICTIONS`): the noise eps (the paper's
choice), the clean sample x0, or the velocity v = sqrt(alpha_bar_t) eps - sqrt(1 - alpha_bar_t) x0
(Salimans & Ho 2022). Any of them gives the other two at a known x_t:
  from x0: eps = (x_t - sqrt(alpha_bar_t) x0) / sqrt(1 - alpha_bar_t)
  from v:  eps = sqrt(alpha_bar_t) v + sqrt(1 - alpha_bar_t) x_t
so the sampler turns the output into eps (`eps_from_output`) and steps as above.

Loss weighting over noise levels (`loss_weight`, `WEIGHTINGS`), with SNR_t = alpha_bar_t /
(1 - alpha_bar_t). A weighting is defined on the x0 error and carried over to the predicted
quantity: at a fixed x_t, |x0 - x0_hat|^2 = |eps - eps_hat|^2 / SNR = |v - v_hat|^2 / (1 + SNR),
so a weight w_x0 on the x0 loss is w_x0 / SNR on the eps loss and w_x0 / (1 + SNR) on the v loss.
  none:    1 on whatever is predicted (the plain loss);
  min_snr: w_x0 = min(SNR, gamma) (Hang et al. 2023, gamma = 5): eps min(SNR, gamma) / SNR,
           v min(SNR, gamma) / (SNR + 1), x0 min(SNR, gamma);
  edm:     w_x0 = (sigma^2 + sigma_data^2) / (sigma sigma_data)^2 with sigma^2 = 1 / SNR (Karras
           et al. 2022, sigma_data = 0.5), capped at `EDM_WEIGHT_CAP` times its value at
           SNR = 1 on the predicted quantity: EDM draws log-normal noise levels and rarely
           visits the cosine schedule's noisiest steps, where the uncapped weight reaches 1e6.

Guidance (classifier-guided DDIM, Dhariwal & Nichol 2021): to ascend a reward R, shift
eps_hat = eps - sqrt(1 - alpha_bar_t) s grad R (`guided_eps`) and step with eps_hat.
"""

from __future__ import annotations

import math

import torch

from tt.kernels.errors import TTError

#: Offset s of the cosine schedule.
COSINE_OFFSET = 0.008
#: Largest beta, so the last steps stay invertible.
MAX_BETA = 0.999
#: What a network may predict (see the module docstring).
PREDICTIONS = ("eps", "x0", "v")
#: Spacings of the sampling steps (`CosineDDIM.timesteps`).
SPACINGS = ("leading", "trailing")
#: Noise-level loss weightings (see the module docstring).
WEIGHTINGS = ("none", "min_snr", "edm")
#: gamma of min-SNR weighting (Hang et al. 2023).
MIN_SNR_GAMMA = 5.0
#: sigma_data of EDM weighting: normalised tokens span +-1.
EDM_SIGMA_DATA = 0.5
#: Cap of the EDM weight, relative to its value at SNR = 1.
EDM_WEIGHT_CAP = 10.0


def cosine_alpha_bar(u: torch.Tensor, s: float = COSINE_OFFSET) -> torch.Tensor:
    """f(u) = cos^2(((u + s) / (1 + s)) pi / 2) for u in [0, 1]."""
    return torch.cos((u + s) / (1.0 + s) * (math.pi / 2)) ** 2


class CosineDDIM:
    """Cosine-schedule DDIM over ``train_steps`` discrete noise levels.

    train_steps: T (100 for motion-to-robot, 5 for control in the paper); clip_x0: clip of
    the predicted clean sample in normalised units (1.0: the data range), None for none.
    alpha_bars: (T,) float64, alpha_bar_t for t = 0 .. T-1.
    """

    def __init__(self, train_steps: int, *, clip_x0: float | None = 1.0):
        if train_steps < 1:
            raise TTError(f"train_steps must be >= 1, got {train_steps}")
        if clip_x0 is not None and clip_x0 <= 0:
            raise TTError(f"clip_x0 must be positive or None, got {clip_x0}")
        self.train_steps = int(train_steps)
        self.clip_x0 = clip_x0
        u = torch.arange(self.train_steps + 1, dtype=torch.float64) / self.train_steps
        f = cosine_alpha_bar(u)
        self.betas = (1.0 - f[1:] / f[:-1]).clamp(max=MAX_BETA)
        self.alpha_bars = torch.cumprod(1.0 - self.betas, dim=0)

    def __repr__(self) -> str:
        return f"CosineDDIM(train_steps={self.train_steps}, clip_x0={self.clip_x0})"

    # ------------------------------------------------------------ schedule lookups
    def alpha_bar(self, t: torch.Tensor | int) -> torch.Tensor:
        """alpha_bar_t as float64; t = -1 gives 1 (the clean end). t: int or long tensor (B,)."""
        t = torch.as_tensor(t, dtype=torch.long)
        if bool(((t < -1) | (t >= self.train_steps)).any()):
            raise TTError(f"diffusion step {t.tolist()} outside -1 .. {self.train_steps - 1}")
        padded = torch.cat([torch.ones(1, dtype=torch.float64), self.alpha_bars])
        return padded[t.cpu() + 1]

    def _coef(self, values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Per-sample coefficients (B,) or a scalar, shaped to broadcast against `like` (B, ...)."""
        values = values.to(device=like.device, dtype=like.dtype)
        if values.ndim == 0:
            return values
        return values.reshape(values.shape[0], *([1] * (like.ndim - 1)))

    def model_time(self, t: torch.Tensor | int) -> torch.Tensor:
        """The noise level as the fraction (t + 1) / T in (0, 1], float32 (shape of t)."""
        return (torch.as_tensor(t, dtype=torch.float32) + 1.0) / self.train_steps

    def timesteps(self, num_steps: int | None = None, spacing: str = "leading") -> list[int]:
        """Sampling steps, descending, n of the T. spacing (`SPACINGS`): "leading", T // n apart
        from 0 (tt's default, the paper's); "trailing", T / n apart down from T - 1 (Lin et al.
        2024), so even one step starts at the noisiest level, where from pure noise the
        network's x0_hat is its estimate of the conditional mean. Both are all T steps at n = T."""
        n = self.train_steps if num_steps is None else int(num_steps)
        if not 1 <= n <= self.train_steps:
            raise TTError(f"num_steps must be in 1 .. {self.train_steps}, got {num_steps}")
        if spacing not in SPACINGS:
            raise TTError(f"spacing = {spacing!r}; valid: {list(SPACINGS)}")
        if spacing == "trailing":
            return [round(self.train_steps - i * self.train_steps / n) - 1 for i in range(n)]
        ratio = self.train_steps // n
        return [i * ratio for i in range(n - 1, -1, -1)]

    def sample_train_steps(self, n: int, generator: torch.Generator | None = None, device=None) -> torch.Tensor:
        """Uniform training steps (n,) long in 0 .. T-1."""
        return torch.randint(0, self.train_steps, (n,), generator=generator, device=device)

    # ------------------------------------------------------------ closed forms
    def add_noise(self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor | int) -> torch.Tensor:
        """x_t = sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) eps; t int or (B,)."""
        ab = self.alpha_bar(t)
        return self._coef(ab.sqrt(), x0) * x0 + self._coef((1 - ab).sqrt(), x0) * eps

    def predict_x0(
        self, x_t: torch.Tensor, eps: torch.Tensor, t: torch.Tensor | int, *, clip: bool = True
    ) -> torch.Tensor:
        """x0_hat = (x_t - sqrt(1 - alpha_bar_t) eps) / sqrt(alpha_bar_t), clipped to +-clip_x0 when `clip`."""
        ab = self.alpha_bar(t)
        x0 = (x_t - self._coef((1 - ab).sqrt(), x_t) * eps) / self._coef(ab.sqrt(), x_t)
        if clip and self.clip_x0 is not None:
            x0 = x0.clamp(-self.clip_x0, self.clip_x0)
        return x0

    def predict_eps(self, x_t: torch.Tensor, x0: torch.Tensor, t: torch.Tensor | int) -> torch.Tensor:
        """eps = (x_t - sqrt(alpha_bar_t) x0) / sqrt(1 - alpha_bar_t)."""
        ab = self.alpha_bar(t)
        return (x_t - self._coef(ab.sqrt(), x_t) * x0) / self._coef((1 - ab).sqrt(), x_t)

    def snr(self, t: torch.Tensor | int) -> torch.Tensor:
        """SNR_t = alpha_bar_t / (1 - alpha_bar_t), float64 (shape of t)."""
        ab = self.alpha_bar(t)
        return ab / (1 - ab)

    def training_target(
        self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor | int, prediction: str
    ) -> torch.Tensor:
        """What a network predicting `prediction` regresses onto for x_t = add_noise(x0, eps, t)."""
        _check_prediction(prediction)
        if prediction == "eps":
            return eps
        if prediction == "x0":
            return x0
        ab = self.alpha_bar(t)
        return self._coef(ab.sqrt(), x0) * eps - self._coef((1 - ab).sqrt(), x0) * x0

    def eps_from_output(
        self, out: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor | int, prediction: str
    ) -> torch.Tensor:
        """The eps a network output `out` of kind `prediction` stands for at x_t (see the module docstring)."""
        _check_prediction(prediction)
        if prediction == "eps":
            return out
        if prediction == "x0":
            return self.predict_eps(x_t, out, t)
        ab = self.alpha_bar(t)
        return self._coef(ab.sqrt(), x_t) * out + self._coef((1 - ab).sqrt(), x_t) * x_t

    def loss_weight(
        self,
        t: torch.Tensor | int,
        weighting: str,
        prediction: str,
        *,
        gamma: float = MIN_SNR_GAMMA,
        sigma_data: float = EDM_SIGMA_DATA,
    ) -> torch.Tensor:
        """Per-sample loss weight (shape of t, float64) of `weighting` for a network predicting
        `prediction` (see the module docstring)."""
        _check_prediction(prediction)
        if weighting not in WEIGHTINGS:
            raise TTError(f"loss weighting {weighting!r} does not exist; weightings: {list(WEIGHTINGS)}")
        snr = self.snr(t)
        if weighting == "none":
            return torch.ones_like(snr)
        to_target = {"eps": 1.0 / snr, "x0": torch.ones_like(snr), "v": 1.0 / (1.0 + snr)}[prediction]
        if weighting == "min_snr":
            if not gamma > 0:
                raise TTError(f"min-SNR gamma must be > 0, got {gamma}")
            return snr.clamp(max=gamma) * to_target
        sd2 = sigma_data**2
        w_x0 = (1.0 / snr + sd2) * snr / sd2
        at_one = {"eps": 1.0, "x0": 1.0, "v": 0.5}[prediction] * (1.0 + sd2) / sd2
        return (w_x0 * to_target).clamp(max=EDM_WEIGHT_CAP * at_one)

    def sigma(self, t: int, t_prev: int, eta: float) -> float:
        """DDIM noise scale of the step t -> t_prev (see the module docstring)."""
        ab, ab_prev = float(self.alpha_bar(t)), float(self.alpha_bar(t_prev))
        return eta * math.sqrt((1 - ab_prev) / (1 - ab)) * math.sqrt(1 - ab / ab_prev)

    def guided_eps(self, eps: torch.Tensor, grad: torch.Tensor, scale: float, t: int) -> torch.Tensor:
        """eps_hat = eps - sqrt(1 - alpha_bar_t) scale grad, the eps that ascends a reward with gradient `grad`."""
        return eps - math.sqrt(1.0 - float(self.alpha_bar(t))) * scale * grad

    def step(
        self,
        x_t: torch.Tensor,
        eps: torch.Tensor,
        t: int,
        t_prev: int,
        *,
        eta: float = 0.0,
        noise: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One reverse step t -> t_prev; returns (x_prev, x0_hat). `noise` (shape of x_t) or a
        `generator` supplies z when eta > 0."""
        if not -1 <= t_prev < t:
            raise TTError(f"a reverse step needs -1 <= t_prev < t, got t={t}, t_prev={t_prev}")
        ab_prev = float(self.alpha_bar(t_prev))
        x0 = self.predict_x0(x_t, eps, t)
        sig = self.sigma(t, t_prev, eta)
        x_prev = math.sqrt(ab_prev) * x0 + math.sqrt(max(1.0 - ab_prev - sig**2, 0.0)) * eps
        if sig > 0:
            if noise is None:
                noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
            x_prev = x_prev + sig * noise
        return x_prev, x0


def _check_prediction(prediction: str) -> None:
    if prediction not in PREDICTIONS:
        raise TTError(f"prediction {prediction!r} does not exist; predictions: {list(PREDICTIONS)}")
