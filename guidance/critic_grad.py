"""The dynamics critic's gradient: Self-Guidance steered by a model that knows what designs do.

Dynamics Self-Guidance (`tt.guidance.selfguide`) differentiates the sampling model's own
prediction of the candidate's dynamics, jointly sampled with its embodiment. When that
model does not know how a design moves (the shipped generalist's own dynamics rank held-out
designs at r = 0.01-0.09) its gradient points nowhere in particular. A dynamics critic (a
checkpoint trained on the dynamics task, e.g. `checkpoints/viperx_mini_dynamics.pt`, r =
0.83 / 0.86 on held-out ViperX designs) can give the gradient instead:

    g = d R_critic(e) / d e   at e = the embodiment tokens of x0_hat,

where R_critic(e) is, by default, the smooth stand-in of the reward (`FORMS`,
`tt.sim.rewards.log_reward`; guidance alphas, no termination, `tt.guidance.predicted.PredictedReward`)
of the dynamics the critic predicts for embodiment e on the motion: its DDIM sampling
(`tt.dit.sampling.sample(differentiable=True)`, fixed noise per call, `num_steps` steps)
with e as the clean condition, differentiated back to e through every step. Several motions:
the mean over motions. `tt.guidance.selfguide.SelfGuidance(critic=...)` carries g to x_t
through the sampling network, as it does the simulator's gradient (`tt.guidance.simgrad`).

A critic trained told the episode's start (``dynamics_start``) is given each candidate's
simulated first control step (`tt.guidance.predicted.start_tokens`) for the design x0_hat
decodes to (projected onto the nearest structure when it has none exactly). By default the
start is a constant of the gradient: it moves with the design, but not differentiably.
Candidates that do not decode get a zero gradient and are counted.

The gradient is taken at x0_hat's own tokens (in the critic's units when its normaliser
differs from the sampler's), so it is the gradient of the tokens the sampler moves. Taking
it at the decoded design's tokens, moving x0_hat onto that design, moving only the
continuous attributes, or adding a term through the simulated start all lost on ViperX and
were taken out (docs/experiments.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from tt.dit.checkpoint import TrainedModel
from tt.guidance.predicted import CRITIC_DDIM_STEPS, PredictedReward, build_query, start_tokens, with_start
from tt.kernels.errors import TTError
from tt.sim.designs import get_space
from tt.sim.rewards import RewardConfig
from tt.tokens.batch import TokenBatch
from tt.tokens.normalize import Normalizer
from tt.tokens.schema import STEP_ROLES

#: The termination threshold of the gradient's reward [m of summed position error]: never
#: reached, so every query step counts. With the reward's own (0.5 m for ViperX) most of the
#: designs a noisy x0_hat decodes to are predicted to stop at the first step (reward 0, flat).
NO_TERMINATION = 1e6


#: What the critic's gradient differentiates: "log", `tt.sim.rewards.log_reward` of the
#: predicted dynamics (the reward's tracking term exp(-e_p^2 / sigma_p) is flat at the errors
#: most sampled designs are predicted to have, its log is not); "reward", the predicted reward.
FORMS = ("log", "reward")


@dataclass
class CriticStats:
    """steps: guided steps the critic's gradient ran at; candidates: candidate-steps it
    differentiated; decode_failures: candidate-steps whose x0_hat did not decode (a start-aware
    critic needs the design; zero gradient); nonfinite_entries: gradient entries set to 0;
    objective_trace: per step of the last call, the mean over candidates of the critic's
    objective at x0_hat (the form's, guidance alphas, no termination unless asked)."""

    steps: int = 0
    candidates: int = 0
    decode_failures: int = 0
    nonfinite_entries: int = 0
    objective_trace: list[float] = field(default_factory=list)


class CriticGradient:
    """dR_critic/dx0 for the embodiment tokens of a guided step (`token_gradient`).

    critic: a model trained on the dynamics task, with the sampling model's layout
    (`tt.guidance.zeroth.check_critic`); cfg: the reward; normalizer: the units of the x0 it
    is given (the sampling model's; None: the critic's own), turned into the critic's units
    inside the differentiated function; decoder: decodes a candidate to a design
    (`tt.guidance.zeroth.Decoder`), needed by a start-aware critic; num_steps: the critic's
    DDIM steps; seed: of the critic's sampling noise, the same at every step so the objective
    does not jitter; terminate: keep the reward's termination (default off: every query step
    counts, see `NO_TERMINATION`); form: what is differentiated (`FORMS`).
    """

    def __init__(
        self,
        critic: TrainedModel,
        cfg: RewardConfig,
        *,
        normalizer: Normalizer | None = None,
        decoder=None,
        num_steps: int = CRITIC_DDIM_STEPS,
        seed: int = 0,
        terminate: bool = False,
        form: str = "log",
    ):
        if not critic.trained_on("dynamics"):
            raise TTError(
                f"guidance by a critic needs a dynamics critic: the critic was trained on {list(critic.tasks)}, "
                "not the dynamics task its gradient needs (give a critic checkpoint trained on it)"
            )
        if critic.dynamics_start and decoder is None:
            raise TTError(
                "a critic trained told the episode's start needs a decoder: its start is simulated for the "
                "design each candidate decodes to"
            )
        if num_steps < 1:
            raise TTError(f"num_steps = {num_steps}; must be >= 1")
        if form not in FORMS:
            raise TTError(f"form = {form!r}; valid: {list(FORMS)}")
        # A design predicted to terminate at its first counted step scores a flat 0 around it, so
        # its gradient says nothing; without termination it still points to smaller error.
        self.cfg = cfg if terminate else dataclasses.replace(cfg, threshold=NO_TERMINATION)
        self.critic, self.decoder, self.form = critic, decoder, form
        self.normalizer = critic.normalizer if normalizer is None else normalizer
        self.num_steps, self.seed = int(num_steps), int(seed)
        self.stats = CriticStats()

    def summary(self) -> dict:
        s = self.stats
        return {
            "steps": s.steps,
            "candidates": s.candidates,
            "decode_failures": s.decode_failures,
            "nonfinite_grad_entries": s.nonfinite_entries,
            "objective_trace": list(s.objective_trace),
        }

    def reset(self) -> None:
        """Start a new sampling call's trace."""
        self.stats.objective_trace = []

    def objective(
        self, ctx, embodiment: dict[str, torch.Tensor], first: dict[str, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """R_critic of k candidates, (k,): the mean over ctx's motions of the form's objective
        (guidance alphas) of the dynamics the critic predicts for `embodiment` on each motion.
        embodiment: type -> (k, L, D) in `normalizer`'s units (differentiable); first: the
        start-aware critic's step-0 tokens, type -> (M, k, P, D) (`start_tokens`)."""
        from tt.dit.ddim import CosineDDIM
        from tt.dit.sampling import sample
        from tt.dit.tasks import TaskSpec
        from tt.guidance.zeroth import renormalize

        critic = self.critic
        layout, norm = critic.layout, critic.normalizer
        if critic.dynamics_start and first is None:
            raise ValueError("a critic trained told the episode's start needs each candidate's simulated first step")
        k = next(iter(embodiment.values())).shape[0]
        device = next(iter(embodiment.values())).device
        if self.normalizer is not norm:
            embodiment = renormalize(embodiment, self.normalizer, norm)
        model = critic.model.to(device).eval()
        placement = "start" if critic.dynamics_start else "even"
        task = TaskSpec("dynamics", critic.robot_diffusion_steps, "start" if critic.dynamics_start else "random")
        scheduler = CosineDDIM(task.diffusion_steps)
        total = torch.zeros(k, device=device)
        for j, motion in enumerate(ctx.motions):
            q = build_query(
                layout,
                norm,
                motion,
                k,
                placement=placement,
                generator=torch.Generator().manual_seed(self.seed),
                device=device,
            )
            tokens = TokenBatch({**q.tokens.values, **embodiment}, q.tokens.ids, q.tokens.mask)
            if first is not None:
                tokens = with_start(tokens, {name: v[j] for name, v in first.items()})
            res = sample(
                model,
                tokens,
                task,
                scheduler=scheduler,
                num_steps=self.num_steps,
                generator=torch.Generator(device=device).manual_seed(self.seed),
                differentiable=True,
            )
            total = total + PredictedReward(layout, norm, self.cfg, q)(
                res.tokens.values, guidance=True, log=self.form == "log"
            )
        return total / len(ctx.motions)

    def token_gradient(self, ctx, x0: dict[str, torch.Tensor], step: int) -> dict[str, torch.Tensor]:
        """dR_critic/dx0 for the embodiment types of `x0` (in `normalizer`'s units, (n, L, D)
        each; per-step types are ignored); zero for candidates that do not decode."""
        from tt.guidance.zeroth import decode_x0

        critic = self.critic
        layout = critic.layout
        names = [s.name for s in layout.specs if s.role not in STEP_ROLES and s.name in x0]
        out = {n: torch.zeros_like(v) for n, v in x0.items()}
        if not names:
            return out
        n = x0[names[0]].shape[0]
        device = x0[names[0]].device
        ok = list(range(n))
        first = None
        if critic.dynamics_start:
            decoded = decode_x0(layout, self.normalizer, x0, ctx.queries[0].tokens, self.decoder)
            ok = [i for i in range(n) if decoded[i].design is not None]
            self.stats.decode_failures += n - len(ok)
            if ok:
                designs = [decoded[i].design for i in ok]
                space = get_space(designs[0].space)
                models = [space.model(d) for d in designs]
                first = start_tokens(layout, critic.normalizer, designs, ctx.motions, models=models, device=device)
        self.stats.steps += 1
        if not ok:
            return out
        rows = torch.as_tensor(ok, dtype=torch.long, device=device)
        leaf = {k: x0[k].detach()[rows].clone().requires_grad_(True) for k in names}
        with torch.enable_grad():
            value = self.objective(ctx, leaf, first)
            grads = torch.autograd.grad(value.sum(), [leaf[k] for k in names], allow_unused=True)
        self.stats.objective_trace.append(float(value.detach().mean()))
        for k, g in zip(names, grads):
            if g is None:
                continue
            bad = ~torch.isfinite(g)
            if bool(bad.any()):
                self.stats.nonfinite_entries += int(bad.sum())
                g = torch.where(bad, torch.zeros_like(g), g)
            out[k][rows] = g.to(out[k].dtype)
        self.stats.candidates += len(ok)
        return out


__all__ = ["FORMS", "NO_TERMINATION", "CriticGradient", "CriticStats"]
