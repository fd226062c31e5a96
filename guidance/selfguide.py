"""Dynamics Self-Guidance (DGS): classifier-guided DDIM with the model's own reward prediction.

At each reverse step the network predicts eps for every token; the predicted clean tokens
x0_hat = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t) hold the candidate's embodiment and
its dynamics on the target motion, so the reward of x0_hat (`tt.guidance.predicted`, with
the guidance alphas of `tt.sim.rewards`: alpha_size = alpha_mass = 0.005) is a
differentiable function of the noisy tokens x_t through the network. Its gradient shifts
the noise prediction of the embodiment tokens only (Dhariwal & Nichol 2021):

    eps_hat = eps - sqrt(1 - abar_t) s grad_{x_t} R(x0_hat(x_t))

and the DDIM step uses eps_hat (`tt.dit.sampling.sample`'s guide hook; dynamics and action
tokens keep the model's eps). Gradient entries that are not finite are set to 0 and
counted. With several motions (`tt.guidance.compose`) R is the mean over motions of the
per-motion rewards, taken with respect to the shared embodiment tokens. The paper samples
with eta = 1 for DGS (it explores; eta does not matter to Zeroth-Order) and returns the best
of the n guided candidates ranked by the model, as Zeroth-Order does.

Guidance scale s. R is the episode reward (summed over the motion's steps, as reported),
and the paper's scales are for that: 50 ViperX, 100 quadruped, 0.2 bimanual, 500
multi-trajectory ViperX (appendix "Inference": the largest scale that does not push the
model out of distribution). ALOHA is two ViperX arms and takes the ViperX scales (tt's
choice; the paper has no ALOHA experiment). Multi-trajectory scales the paper does not
give fall back to the single-motion scale.

Differentiable-simulation ablation: with ``sim_grad_weight`` lambda > 0, the gradient
mixes in the gradient of the reward of a differentiable Warp rollout of the decoded
candidate (`tt.guidance.simgrad`): grad = (1 - lambda) grad R_model + lambda grad R_sim,
both with respect to x_t (the simulator's gradient with respect to x0_hat is carried to
x_t through the network like the model's). lambda = 0 is pure self-guidance, 1 the pure
simulator gradient.

Critic guidance (``guide_by="critic"``): R's gradient comes from a dynamics critic's
prediction for x0_hat's embodiment instead of the sampling model's own jointly sampled
dynamics (`tt.guidance.critic_grad`): grad = (1 - lambda) grad R_critic + lambda grad R_sim,
the critic's gradient taken at x0_hat's own tokens. The other places tried (at the decoded
design, projected onto it, the continuous attributes only, through the simulated start) and
a late guidance start lost on ViperX and were taken out (docs/experiments.md).

At the decoded design (``refine``, `SamplerConfig`'s): once sampling has ended, the
returned design's continuous choices climb the critic's prediction along its central
differences, each design's start re-simulated (`tt.guidance.refine`). Token-space guidance
acts on an x0_hat that decodes only by projection and on a start the gradient cannot see;
the decoded design has neither problem (codesign_guidance_refine.md, in git: docs/experiments.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import torch

from tt.baselines.problem import Problem
from tt.dit.sampling import GuideFn
from tt.dit.tasks import ROBOT
from tt.guidance.zeroth import Decoder, Generation, GuideContext, SamplerConfig, ZerothOrder
from tt.kernels.errors import TTError

#: What the guidance gradient differentiates (`DGSConfig.guide_by`).
GUIDES = ("model", "critic")


# ------------------------------------------------------------------------------ scales
def _paper_single() -> dict[str, float]:
    return {"viperx": 50.0, "aloha": 50.0, "bimanual": 0.2, "quadruped": 100.0}


def _paper_multi() -> dict[str, float]:
    return {"viperx": 500.0, "aloha": 500.0}


def _critic_scales() -> dict[str, float]:
    # tt's, the better of 0.5 and 5 on ViperX at n = 1 with the old generalist as generator
    # (9 seeds: validated reward 142 against 79; 79 on 9 fresh seeds; codesign_guidance.md and
    # codesign_guidance_fresh.md, in git: docs/experiments.md, "Results files in git").
    # ALOHA is two ViperX arms. The mobile bimanual robot's: the best of 0.05, 0.5 and 5 at
    # n = 1 (9 seeds, benchmarks/results/codesign_guidance_bimanual.md: validated reward 201,
    # 166, 121), though every one of them stays below unguided Zeroth-Order's 245 there. The
    # quadruped's: the better of 0.05 and 5 at n = 1 (9 seeds,
    # benchmarks/results/codesign_quadruped_learned.md: level with Zeroth-Order at 0.05, +0.06
    # +- 1.3 reward, and -2.2 +- 3.5 at 5). Every generator but ViperX's is trained on the
    # robot task alone and guided by its critic (`DGSConfig.guide_by`).
    return {"viperx": 5.0, "aloha": 5.0, "bimanual": 0.05, "quadruped": 0.05}


@dataclass(frozen=True)
class GuidanceScales:
    """Guidance scale per design space: `single` for one motion, `multi` for several
    (spaces missing from `multi` use `single`), both for guidance by the model's own
    dynamics (defaults: the paper's, module docstring); `critic` for guidance by the dynamics
    critic (``guide_by="critic"``: the log form's gradient is far larger than the reward's; one
    scale for any number of motions, as its objective is their mean)."""

    single: Mapping[str, float] = field(default_factory=_paper_single)
    multi: Mapping[str, float] = field(default_factory=_paper_multi)
    critic: Mapping[str, float] = field(default_factory=_critic_scales)

    def scale(self, space: str, motions: int, guide_by: str = "model") -> float:
        if guide_by == "critic":
            if space not in self.critic:
                raise TTError(
                    f"no critic guidance scale for design space {space!r}; spaces with one: "
                    f"{sorted(self.critic)} (give DGSConfig.scale)"
                )
            return float(self.critic[space])
        if motions > 1 and space in self.multi:
            return float(self.multi[space])
        if space not in self.single:
            raise TTError(
                f"no guidance scale for design space {space!r}; spaces with one: {sorted(self.single)} "
                "(give DGSConfig.scale)"
            )
        return float(self.single[space])


# ------------------------------------------------------------------------------ the hook
@dataclass
class GuidanceStats:
    """What guidance did over all sampling calls.

    steps: guided steps (summed over calls); nonfinite_entries: gradient entries that were
    NaN or inf and set to 0; nonfinite_candidates: (candidate, step) pairs with at least one
    such entry; nonfinite_sim_entries: entries of the simulator's (or critic's) x0-gradient that were not
    finite and set to 0 before mixing; objective_trace: per step of the last call, the mean
    over candidates of the guidance objective at x0_hat.
    """

    steps: int = 0
    nonfinite_entries: int = 0
    nonfinite_candidates: int = 0
    nonfinite_sim_entries: int = 0
    objective_trace: list[float] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "guided_steps": self.steps,
            "nonfinite_grad_entries": self.nonfinite_entries,
            "nonfinite_grad_candidate_steps": self.nonfinite_candidates,
            "nonfinite_sim_grad_entries": self.nonfinite_sim_entries,
            "objective_trace": list(self.objective_trace),
        }


class SelfGuidance:
    """The DGS hook factory (`tt.guidance.zeroth.Guidance`).

    scale: s; sim: a `tt.guidance.simgrad.SimGradient` (or anything with its
    ``token_gradient``), required when sim_weight > 0; sim_weight: lambda in [0, 1];
    critic: a `tt.guidance.critic_grad.CriticGradient` (or anything with its
    ``token_gradient``) whose gradient replaces the model's own objective's.
    """

    def __init__(self, scale: float, *, sim=None, sim_weight: float = 0.0, critic=None):
        if not 0.0 <= sim_weight <= 1.0:
            raise TTError(f"sim_weight = {sim_weight}; must be in [0, 1]")
        if sim_weight > 0 and sim is None:
            raise TTError("sim_weight > 0 needs a simulator gradient (sim=SimGradient(...))")
        self.scale = float(scale)
        self.sim = sim
        self.sim_weight = float(sim_weight)
        self.critic = critic
        self.stats = GuidanceStats()

    def summary(self) -> dict:
        out = self.stats.to_dict()
        if self.sim is not None and self.sim_weight > 0:
            out["sim"] = self.sim.summary()
        if self.critic is not None:
            out["critic_grad"] = self.critic.summary()
        return out

    def hook(self, ctx: GuideContext) -> GuideFn:
        stats = self.stats
        stats.objective_trace = []
        if self.critic is not None and hasattr(self.critic, "reset"):
            self.critic.reset()
        lam = self.sim_weight

        def x0_gradient(source, step, x0, names) -> dict[str, torch.Tensor]:
            """The source's x0-gradient (critic or simulator), in x0's dtype, non-finite entries
            set to 0 and counted."""
            g0 = source.token_gradient(ctx, {n: x0[n].detach() for n in names}, step)
            out = {}
            for n in names:
                g = g0[n].to(device=x0[n].device, dtype=x0[n].dtype)
                bad = ~torch.isfinite(g)
                if bool(bad.any()):
                    stats.nonfinite_sim_entries += int(bad.sum())
                    g = torch.where(bad, torch.zeros_like(g), g)
                out[n] = g
            return out

        def guide(
            step: int, x_t: dict[str, torch.Tensor], eps: dict[str, torch.Tensor], x0: dict[str, torch.Tensor]
        ) -> dict[str, torch.Tensor]:
            t = ctx.timesteps[step]
            names = [n for n in ctx.embodiment if n in x_t and x_t[n].requires_grad]
            by_critic = self.critic is not None
            with torch.set_grad_enabled(not by_critic):  # guided by the critic, the own objective is only traced
                objective = ctx.objective(x0, True).mean(1)  # (n,)
            stats.objective_trace.append(float(objective.detach().nanmean()))

            def chained(source) -> torch.Tensor:
                # sum(g * x0): its gradient with respect to x_t carries an x0-gradient g through the network.
                g0 = x0_gradient(source, step, x0, names)
                return sum(((g0[n] * x0[n]).sum() for n in names), torch.zeros((), device=objective.device))

            surrogate = torch.zeros((), device=objective.device)
            if lam < 1.0:
                surrogate = (1.0 - lam) * (chained(self.critic) if by_critic else objective.sum())
            if lam > 0.0:
                surrogate = surrogate + lam * chained(self.sim)
            grads = torch.autograd.grad(surrogate, [x_t[n] for n in names], allow_unused=True)
            out = {}
            flagged = torch.zeros(objective.shape[0], dtype=torch.bool, device=objective.device)
            for n, g in zip(names, grads):
                if g is None:
                    g = torch.zeros_like(x_t[n])
                bad = ~torch.isfinite(g)
                if bool(bad.any()):
                    stats.nonfinite_entries += int(bad.sum())
                    flagged |= bad.flatten(1).any(1)
                    g = torch.where(bad, torch.zeros_like(g), g)
                out[n] = ctx.scheduler.guided_eps(eps[n], g, self.scale, t)
            stats.nonfinite_candidates += int(flagged.sum())
            stats.steps += 1
            return out

        return guide


def default_guide(trained, critic=None) -> str:
    """`DGSConfig.guide_by`'s default for sampling model `trained` and critic model `critic`
    (`tt.dit.checkpoint.TrainedModel`s, critic None: none given): "critic" when a critic is
    given and `trained` was not trained on the dynamics task, else "model"."""
    return "critic" if critic is not None and not trained.trained_on("dynamics") else "model"


# ------------------------------------------------------------------------------ optimizer
@dataclass(frozen=True)
class DGSConfig(SamplerConfig):
    """`SamplerConfig` (eta defaults to the paper's 1 for DGS) plus

    scale: guidance scale (None: `scales` for the problem's space, motion count and guide_by);
    scales: per-space defaults; sim_grad_weight: lambda of the simulator gradient (0: none);
    sim_grad_start: first step (0 = noisiest) at which the simulator gradient is mixed in;
    before it x0_hat is too noisy to decode to a design. guide_by: "model" (the sampling
    model's own jointly sampled dynamics, the paper's) or "critic" (the dynamics critic's
    prediction for x0_hat's embodiment: ``critic_checkpoint`` / ``critic_model``, else the
    sampling model's own dynamics task; `tt.guidance.critic_grad`, at x0_hat's tokens);
    None: "critic" when a critic is given and the sampling model was not trained on the
    dynamics task (a generator trained on the robot task alone, as ALOHA's, the mobile
    bimanual robot's and the quadruped's are, has no trained dynamics of its own to follow),
    else "model".
    """

    eta: float = 1.0
    scale: float | None = None
    scales: GuidanceScales = field(default_factory=GuidanceScales)
    sim_grad_weight: float = 0.0
    sim_grad_start: int = 0
    guide_by: str | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.guide_by is not None and self.guide_by not in GUIDES:
            raise TTError(f"guide_by = {self.guide_by!r}; valid: {list(GUIDES)}")
        if not 0.0 <= self.sim_grad_weight <= 1.0:
            raise TTError(f"sim_grad_weight = {self.sim_grad_weight}; must be in [0, 1]")
        if self.sim_grad_start < 0:
            raise TTError(f"sim_grad_start = {self.sim_grad_start}; must be >= 0")


class DynamicsSelfGuidance(ZerothOrder):
    """The paper's Dynamics Self-Guidance optimizer: n guided samples, best ranked by the model.

    config: `DGSConfig`; model, decoder, critic_model: as `ZerothOrder` (the critic ranks the
    guided samples; the guidance follows `DGSConfig.guide_by`).
    """

    name = "dgs"

    def __init__(
        self, config: DGSConfig = DGSConfig(), *, model=None, decoder: Decoder | None = None, critic_model=None
    ):
        super().__init__(config, model=model, decoder=decoder, critic_model=critic_model)

    def generate(self, problem: Problem) -> tuple[Generation, Decoder, dict]:
        """As `ZerothOrder.generate`, with the guidance hook (info also holds its statistics
        and, under "rollouts", the simulator-gradient rollouts it ran)."""
        c: DGSConfig = self.config
        sampler, decoder, cfg, n = self._setup(problem)
        guide_by = c.guide_by or default_guide(self._trained, self._critic)
        scale = c.scale if c.scale is not None else c.scales.scale(problem.space, len(problem.motions), guide_by)
        sim = None
        if c.sim_grad_weight > 0:
            from tt.guidance.simgrad import SimGradient

            # The simulator gradient lands on the candidate's own tokens: exact structures only.
            exact = decoder.exact() if hasattr(decoder, "exact") else decoder
            sim = SimGradient(
                problem.space, cfg, self._trained, decoder=exact, start_step=c.sim_grad_start, device=problem.device
            )
        guide_critic = None
        if guide_by == "critic":
            from tt.guidance.critic_grad import CriticGradient
            from tt.guidance.zeroth import check_critic

            judge = self._critic or self._trained
            if judge is not self._trained:
                check_critic(self._trained, judge)
            guide_critic = CriticGradient(
                judge,
                cfg,
                normalizer=self._trained.normalizer,
                decoder=decoder,
                seed=problem.seed,
            )
        guidance = SelfGuidance(scale, sim=sim, sim_weight=c.sim_grad_weight, critic=guide_critic)
        critic = self.critic()
        gen, decoder = self.sample_scored(sampler, decoder, problem, cfg, n, guidance=guidance)
        summary = guidance.summary()
        rollouts = int(summary.get("sim", {}).get("rollouts", 0))
        info = {
            "num_steps": c.num_steps or ROBOT.diffusion_steps,
            "eta": c.eta,
            "placement": c.placement,
            "critic": critic,
            "critic_samples": c.critic_samples,
            "critic_on": self.critic_input(),
            "scale": scale,
            "sim_grad_weight": c.sim_grad_weight,
            "guide_by": guide_by,
            **summary,
            "rollouts": rollouts,
        }
        return gen, decoder, info


__all__ = [
    "GUIDES",
    "DGSConfig",
    "DynamicsSelfGuidance",
    "GuidanceScales",
    "GuidanceStats",
    "SelfGuidance",
    "default_guide",
]
