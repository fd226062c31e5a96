"""Zeroth-Order optimization: n parallel diffusion processes, ranked by the model's own prediction.

For a problem (design space, motions, reward), `CandidateSampler` runs the trained DiT's
motion-to-robot process for n candidates at once, conditioned on the target motions
(`tt.guidance.predicted.build_query`; several motions are composed, `tt.guidance.compose`),
and scores each candidate with the reward of its own predicted dynamics and embodiment
tokens (`tt.guidance.predicted.PredictedReward`, the reported alphas): the objective is the
mean over motions of the predicted episode reward. No simulator runs. With a model also
trained on the design-to-dynamics task (``tt train --task robot+dynamics``) the critic can
instead re-predict each candidate's dynamics with its sampled embodiment as that task's
clean condition (``critic="dynamics"``, the default for such models): the robot task's own
dynamics are sampled jointly with an embodiment still being denoised, which predicts the
reward far worse (`benchmarks/results/dit_recipe.md`: r 0.30 against 0.97 on R0). The
dynamics critic can also be another checkpoint of the same space and layout (``critic_model``,
``SamplerConfig.critic_checkpoint``), e.g. a model trained on the dynamics task alone, which
on the full ViperX space ranks held-out designs far better than a model that shares its
training with the robot and control tasks (`benchmarks/results/dit_ladder_r2c.md`); the
sampled embodiments are carried into its normaliser's units when the two differ.

A sampled embodiment is often no robot of the space (its token structure a few attributes
off every discrete choice; decoding projects it onto the nearest design), so the dynamics
critic can instead be asked about the designs the candidates decode to (``critic_on=
"designs"``): every candidate is decoded first, and each design's tokens are given to the
critic as `tt predict` gives them (`tt.guidance.predicted.predict_designs`). It costs a
decode per candidate (about 0.1 s each for ViperX on this CPU, `benchmarks/results/decode.md`)
and ranks what will be built (`zeroth_ranking_dynamics_critic.md`, in git: docs/experiments.md,
"Results files in git").

Candidates are ranked by that objective and decoded to designs of the problem's space
(`tt.tokens.design_from_tokens`: the embodiment tokens are matched against every discrete
choice of the space and the continuous choices fitted). By default a candidate whose token
structure no discrete choice has exactly is projected onto the nearest one (the result's
info counts them: ``projected``); a decoder with ``max_distance`` set can refuse them, and a
candidate that does not decode is ranked last and counted. ``decode="best"``
decodes in rank order until one succeeds, which is what `optimize` needs; ``"all"``
decodes every candidate, for the full ranking.

The same sampler with a guidance hook is Dynamics Self-Guidance (`tt.guidance.selfguide`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol, Sequence

import numpy as np
import torch

from tt.baselines.problem import Optimizer, Problem, Result
from tt.dit.checkpoint import TrainedModel, load_model
from tt.dit.ddim import CosineDDIM
from tt.dit.layout import Layout, LayoutError
from tt.dit.sampling import GuideFn, sample
from tt.dit.tasks import DYNAMICS, ROBOT
from tt.guidance.compose import ComposedModel, compose_tokens, split_tokens, split_values
from tt.guidance.predicted import PLACEMENTS, PredictedReward, build_query, predicted_metrics
from tt.guidance.refine import RefineConfig, refine_designs
from tt.kernels.errors import TTError
from tt.sim.designs import Design, DesignSpace, get_space
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardConfig, get_reward
from tt.tokens.batch import TokenBatch
from tt.tokens.normalize import Normalizer
from tt.tokens.schema import STEP_ROLES

log = logging.getLogger(__name__)

#: Decoding policies (see the module docstring).
DECODE_MODES = ("best", "all")
#: Critics (see the module docstring): the candidates' jointly sampled dynamics, or the
#: dynamics task's prediction for their sampled embodiments.
CRITICS = ("joint", "dynamics")
#: What the dynamics critic is asked about (see the module docstring): the sampled embodiment
#: tokens, or the designs they decode to.
CRITIC_INPUTS = ("tokens", "designs")


# ------------------------------------------------------------------------------ config
def default_temperature(samples: int) -> float:
    """The starting-noise scale a search of `samples` candidates samples at by default.

    A low temperature narrows the generator's draws onto the designs it rates best; a search
    that keeps the best of many wants their spread. Measured with the shipped ViperX generator
    (`benchmarks/results/sample_quality.md`, 9 seeds x motions, 64 draws each, validated on
    the oracle): at 0.3 its draws track the whole motion in 99.5 % of episodes against 94.6 %
    at 1 (median reward 202 against 213), one or four samples score level with those at 1
    (159 / 160 at n = 1), and at 16 the critic's best falls from 247 to 236 (the first shipped
    generator: 226 against 258). So 0.3 up to four samples, for draws that rarely fail, and 1
    from there.
    """
    return 0.3 if samples <= 4 else 1.0


@dataclass(frozen=True)
class SamplerConfig:
    """How the learned optimizers sample.

    checkpoint: checkpoint file or run folder (its latest checkpoint); None when the
        optimizer is given a loaded model. samples: candidates n (None: the problem's
        budget). num_steps: DDIM steps (None: all 100 of the motion-to-robot process).
    eta: DDIM noise (0 deterministic). placement: the query's control steps, "even" or
        "random" (`tt.guidance.predicted`). decode: "best" or "all". chunk: candidates per
        sampling call (None: all n at once; lower it when n x motions sequences do not fit
        in memory). critic: "joint", "dynamics" or None (see the module docstring; None:
        "dynamics" when the model was trained on that task, else "joint"). critic_samples:
        dynamics predictions averaged per candidate by the "dynamics" critic (one prediction
        is one draw of the dynamics' distribution; on R1 four averaged raised pooled r from
        0.51 to 0.60, `benchmarks/results/dit_ladder_r1c.md`). critic_checkpoint: another
        checkpoint (file or run folder) whose dynamics task is the critic (None: the
        sampling model's own); it implies the "dynamics" critic. critic_on: "tokens" (the
        sampled embodiments) or "designs" (the decoded designs; see the module docstring);
        None: "designs" when the dynamics critic was trained told the episode's start
        (``dynamics_start``: it needs each design's simulated first step, which only a
        decoded design has), else "tokens". refine: iterations of critic refinement of the
        returned design (`tt.guidance.refine`: its continuous choices climb the dynamics
        critic's predicted reward along central differences, the start re-simulated; 0: none).
        temperature: scale of DDIM's starting noise (`tt.dit.sample`); None: `default_temperature`
        of the number of samples.
    """

    checkpoint: str | Path | None = None
    samples: int | None = None
    num_steps: int | None = None
    eta: float = 0.0
    placement: str = "even"
    decode: str = "best"
    chunk: int | None = None
    critic: str | None = None
    critic_samples: int = 1
    critic_checkpoint: str | Path | None = None
    critic_on: str | None = None
    refine: int = 0
    temperature: float | None = None

    def __post_init__(self) -> None:
        if self.refine < 0:
            raise TTError(f"refine = {self.refine}; must be >= 0")
        if self.temperature is not None and not self.temperature > 0:
            raise TTError(f"temperature = {self.temperature}; must be > 0")
        if self.samples is not None and self.samples < 1:
            raise TTError(f"samples = {self.samples}; must be >= 1")
        if self.num_steps is not None and not 1 <= self.num_steps <= ROBOT.diffusion_steps:
            raise TTError(f"num_steps = {self.num_steps}; must be in 1 .. {ROBOT.diffusion_steps}")
        if not self.eta >= 0:
            raise TTError(f"eta = {self.eta}; must be >= 0")
        if self.placement not in PLACEMENTS:
            raise TTError(f"placement = {self.placement!r}; valid: {list(PLACEMENTS)}")
        if self.decode not in DECODE_MODES:
            raise TTError(f"decode = {self.decode!r}; valid: {list(DECODE_MODES)}")
        if self.chunk is not None and self.chunk < 1:
            raise TTError(f"chunk = {self.chunk}; must be >= 1 or None")
        if self.critic is not None and self.critic not in CRITICS:
            raise TTError(f"critic = {self.critic!r}; valid: {list(CRITICS)} or None")
        if self.critic_samples < 1:
            raise TTError(f"critic_samples = {self.critic_samples}; must be >= 1")
        if self.critic == "joint" and self.critic_samples > 1:
            raise TTError(
                f"critic_samples = {self.critic_samples} needs the 'dynamics' critic: the joint critic "
                "scores the one draw sampled with the design"
            )
        if self.critic_on is not None and self.critic_on not in CRITIC_INPUTS:
            raise TTError(f"critic_on = {self.critic_on!r}; valid: {list(CRITIC_INPUTS)} or None")
        if self.critic == "joint" and self.critic_on == "designs":
            raise TTError(
                "critic_on = 'designs' asks the dynamics critic about the decoded designs; it does not go "
                "with critic = 'joint'"
            )
        if self.critic == "joint" and self.refine:
            raise TTError(
                f"refine = {self.refine} climbs the dynamics critic's prediction; it does not go with critic = 'joint'"
            )
        if self.critic == "joint" and self.critic_checkpoint is not None:
            raise TTError("critic_checkpoint is a dynamics critic; it does not go with critic = 'joint'")


# ------------------------------------------------------------------------------ sampling
@dataclass
class GuideContext:
    """What a guidance hook needs for one sampling call of n candidates over M motions.

    objective(x0, guidance) -> (n, M): predicted episode reward of each candidate on each
    motion from composed x0 (guidance: use the guidance alphas); scheduler, timesteps: the
    DDIM schedule (``timesteps[step]`` is t); embodiment: the embodiment type names (shared
    by the copies); layout: the composed layout; motions, queries: the motions and their
    per-motion queries; split: composed dict -> per-motion dicts.
    """

    objective: Callable[[dict[str, torch.Tensor], bool], torch.Tensor]
    scheduler: CosineDDIM
    timesteps: list[int]
    embodiment: tuple[str, ...]
    layout: Layout
    motions: tuple[Motion, ...]
    queries: list
    split: Callable[[dict[str, torch.Tensor]], list[dict[str, torch.Tensor]]]


class Guidance(Protocol):
    """A guidance method: builds the `sample` hook for one call; keeps its own statistics."""

    def hook(self, ctx: GuideContext) -> GuideFn: ...

    def summary(self) -> dict: ...


@dataclass
class Generation:
    """n sampled candidates for M motions.

    tokens: final composed tokens (normalised), n sequences; layout: the composed layout;
    reward: (n, M) predicted episode reward per motion (reported alphas); objective: (n,)
    its mean over motions; metrics: name -> (n, M) predicted metrics
    (`tt.guidance.predicted.predicted_metrics`); seconds: sampling wall time.
    """

    tokens: TokenBatch
    layout: Layout
    reward: np.ndarray
    objective: np.ndarray
    metrics: dict[str, np.ndarray]
    seconds: float


def check_critic(trained: TrainedModel, critic: TrainedModel) -> None:
    """Raise unless `critic` can be the dynamics critic of `trained`'s samples: trained on the
    dynamics task, on the same design space (`CheckpointSpaceError`, naming both) and with the
    same layout (`LayoutError`)."""
    from tt.guidance.predicted import CheckpointSpaceError

    where = f"critic checkpoint {critic.path}" if critic.path is not None else "the critic model"
    if not critic.trained_on("dynamics"):
        raise TTError(
            f"{where} was trained on {list(critic.tasks)}, not the dynamics task a critic needs "
            "(train it with --task dynamics)"
        )
    if trained.space is not None and critic.space is not None and trained.space != critic.space:
        raise CheckpointSpaceError(
            f"{where} was trained on design space {critic.space!r}, the sampling model on "
            f"{trained.space!r}; give a critic trained on {trained.space!r}"
        )
    if critic.layout != trained.layout:
        raise LayoutError(
            f"{where} has another token layout than the sampling model (types "
            f"{list(critic.layout.names)} against {list(trained.layout.names)}, or other lengths); "
            "its dynamics cannot be asked about these samples"
        )


def _same_normalizer(a: Normalizer, b: Normalizer) -> bool:
    return a.low.keys() == b.low.keys() and all(
        np.array_equal(np.asarray(a.low[k]), np.asarray(b.low[k]))
        and np.array_equal(np.asarray(a.high[k]), np.asarray(b.high[k]))
        for k in a.low
    )


def renormalize(values: dict[str, torch.Tensor], src: Normalizer, dst: Normalizer) -> dict[str, torch.Tensor]:
    """Normalised values (type -> (B, L, D); composed copies ``type@k`` too) in `src`'s units
    -> `dst`'s; padding tokens stay padding."""
    from tt.guidance.compose import SEPARATOR
    from tt.tokens.normalize import is_padding

    out = {}
    for name, v in values.items():
        base = name.split(SEPARATOR)[0]
        moved = dst.normalize_values(base, src.denormalize_values(base, v))
        out[name] = torch.where(is_padding(v)[..., None], v, moved.to(v.dtype))
    return out


class CandidateSampler:
    """Samples and scores candidates of a trained model (see the module docstring).

    trained: the model (EMA weights), its normaliser and layout; device: where to run;
    critic_model: another model whose dynamics task scores the samples (`check_critic`;
    None: `trained`'s own); progress: a tqdm bar over each sampling call's DDIM steps.
    """

    def __init__(
        self,
        trained: TrainedModel,
        device: str | torch.device | None = None,
        critic_model: TrainedModel | None = None,
        progress: bool = False,
    ):
        self.trained = trained
        self.progress = progress
        if device is None:
            held = next(iter([*trained.model.parameters(), *trained.model.buffers()]), None)
            device = held.device if held is not None else "cpu"
        self.device = torch.device(device)
        self.model = trained.model.to(self.device).eval()
        trained.layout.check_normalizer(trained.normalizer)
        self.critic_model = critic_model
        if critic_model is not None:
            check_critic(trained, critic_model)
            critic_model.layout.check_normalizer(critic_model.normalizer)
            critic_model.model.to(self.device).eval()

    def _objective(
        self, rewards: list[PredictedReward], split
    ) -> Callable[[dict[str, torch.Tensor], bool], torch.Tensor]:
        def objective(x0: dict[str, torch.Tensor], guidance: bool = False) -> torch.Tensor:
            parts = split(x0)
            return torch.stack([r(p, guidance=guidance) for r, p in zip(rewards, parts)], dim=1)  # (n, M)

        return objective

    def run(
        self,
        motions: Sequence[Motion],
        cfg: RewardConfig,
        samples: int,
        *,
        seed: int = 0,
        num_steps: int | None = None,
        eta: float = 0.0,
        placement: str = "even",
        chunk: int | None = None,
        guidance: Guidance | None = None,
        critic: str = "joint",
        critic_samples: int = 1,
        temperature: float = 1.0,
    ) -> Generation:
        """n = `samples` candidates for `motions`, scored by reward `cfg`; `guidance` steers
        the embodiment tokens (None: plain sampling, Zeroth-Order); `critic`: "joint" scores
        the dynamics sampled with each candidate, "dynamics" re-predicts them with the
        dynamics task from the sampled embodiment (deterministic DDIM, same steps), and with
        `critic_samples` k > 1 averages the rewards and metrics of k such draws (the tokens
        returned carry the first). With a `critic_model` the dynamics critic is that model's
        and "joint" is refused. temperature: scale of the starting noise (`tt.dit.sample`)."""
        motions = tuple(motions)
        if not motions:
            raise TTError("motions is empty; give at least one target motion")
        if critic not in CRITICS:
            raise TTError(f"critic {critic!r} is not one of {list(CRITICS)}")
        if critic == "joint" and self.critic_model is not None:
            raise TTError(
                "this sampler has a critic model, whose dynamics task is the critic; critic 'joint' would ignore it"
            )
        judge = self.critic_model or self.trained
        if critic == "dynamics" and not judge.trained_on("dynamics"):
            raise TTError(
                f"critic 'dynamics' needs a model trained on the dynamics task; this one was trained on "
                f"{list(self.trained.tasks)} (train with --task robot+dynamics, or use critic 'joint')"
            )
        if critic_samples < 1 or (critic == "joint" and critic_samples > 1):
            raise TTError(f"critic_samples = {critic_samples}: must be >= 1, and 1 for the joint critic")
        layout, norm = self.trained.layout, self.trained.normalizer
        M = len(motions)
        composed = ComposedModel(self.model, M)
        judged = composed if judge is self.trained else ComposedModel(judge.model, M)
        moved = not _same_normalizer(norm, judge.normalizer)
        scheduler = CosineDDIM(ROBOT.diffusion_steps)
        timesteps = scheduler.timesteps(num_steps)
        embodiment = tuple(s.name for s in layout.specs if s.role not in STEP_ROLES)
        generator = torch.Generator(device=self.device).manual_seed(int(seed))
        placement_gen = torch.Generator().manual_seed(int(seed))
        chunk = samples if chunk is None else min(int(chunk), samples)
        start = time.perf_counter()

        def split(values: dict[str, torch.Tensor]) -> list[dict[str, torch.Tensor]]:
            return split_values(layout, values, M)

        outs, rewards, metrics = [], [], []
        for c0 in range(0, samples, chunk):
            c = min(chunk, samples - c0)
            queries = [
                build_query(layout, norm, m, c, placement=placement, generator=placement_gen, device=self.device)
                for m in motions
            ]
            tokens = compose_tokens(layout, [q.tokens for q in queries])
            scorers = [PredictedReward(layout, norm, cfg, q) for q in queries]
            judges = [PredictedReward(layout, judge.normalizer, cfg, q) for q in queries] if moved else scorers
            hook = None
            if guidance is not None:
                ctx = GuideContext(
                    self._objective(scorers, split),
                    scheduler,
                    timesteps,
                    embodiment,
                    composed.layout,
                    motions,
                    queries,
                    split,
                )
                hook = guidance.hook(ctx)
            res = sample(
                composed,
                tokens,
                ROBOT,
                scheduler=scheduler,
                num_steps=num_steps,
                eta=eta,
                generator=generator,
                guide=hook,
                guided=embodiment if hook is not None else None,
                temperature=temperature,
                progress=self.progress,
            )
            draws, scoring = [res.tokens], scorers
            if critic == "dynamics":
                given = res.tokens
                if moved:
                    given = TokenBatch(
                        renormalize(given.values, norm, judge.normalizer), given.ids, given.mask, given.version
                    )
                    scoring = judges
                with torch.no_grad():
                    draws = [
                        sample(
                            judged, given, DYNAMICS, scheduler=scheduler, num_steps=num_steps, generator=generator
                        ).tokens
                        for _ in range(critic_samples)
                    ]
            reward_k, metrics_k = [], []
            with torch.no_grad():
                for drawn in draws:
                    parts = split_tokens(layout, drawn, M)
                    reward_k.append(torch.stack([s(p.values) for s, p in zip(scoring, parts)], dim=1))
                    per = [predicted_metrics(s, p.values) for s, p in zip(scoring, parts)]
                    metrics_k.append({k: torch.stack([d[k] for d in per], dim=1) for k in per[0]})
                rewards.append(torch.stack(reward_k).mean(0).cpu())
                metrics.append({k: torch.stack([m[k] for m in metrics_k]).double().mean(0).cpu() for k in metrics_k[0]})
            outs.append(res.tokens if moved and critic == "dynamics" else draws[0])
            log.info("sampled candidates %d..%d of %d", c0, c0 + c - 1, samples)
        seconds = time.perf_counter() - start
        reward = torch.cat(rewards).double().numpy()
        return Generation(
            tokens=TokenBatch.concatenate(outs) if len(outs) > 1 else outs[0],
            layout=composed.layout,
            reward=reward,
            objective=reward.mean(axis=1),
            metrics={k: torch.cat([m[k] for m in metrics]).double().numpy() for k in metrics[0]},
            seconds=seconds,
        )


# ------------------------------------------------------------------------------ decoding
@dataclass
class Decoded:
    """One candidate's decoding: design (None when it failed), error (why), residual (RMS
    token mismatch of the fitted design, inf on failure), distance (binary token attributes
    the candidate had to change to reach the design's structure: 0 when it decoded exactly;
    `tt.tokens.CandidateTable.distances`)."""

    design: Design | None
    error: str | None = None
    residual: float = float("inf")
    distance: int = 0


#: decoder(embodiment TokenBatch (encoded, padding detected), index) -> Decoded.
Decoder = Callable[[object, int], Decoded]


class DesignDecoder:
    """Decodes embodiment tokens to designs of one space (`tt.tokens.design_from_tokens`),
    keeping the space's candidate table between calls (ViperX: ~10 s to build).

    table: a prebuilt `tt.tokens.CandidateTable` of `space` (None: every discrete choice,
    built at the first call); max_distance: how far a candidate's token structure may be
    from the nearest discrete choice's (`design_from_tokens`; None, the default: any
    candidate is projected onto the nearest design, as the optimizers need a design; 0: only
    exact structures decode); top_k: how many nearest discrete choices get a continuous fit
    (two by default: a projected candidate has no exact fit to stop at, and more fits buy little).
    """

    def __init__(self, space: DesignSpace, table=None, max_distance: int | None = None, top_k: int = 2):
        if table is not None and table.space is not space:
            raise TTError(f"the candidate table is of space {table.space.name!r}, not {space.name!r}")
        self.space = space
        self._table = table
        self.max_distance = max_distance
        self.top_k = top_k

    @property
    def table(self):
        """The space's `tt.tokens.CandidateTable` (built at the first use)."""
        from tt.tokens.design_fit import CandidateTable

        if self._table is None:
            self._table = CandidateTable(self.space)
        return self._table

    def exact(self) -> "DesignDecoder":
        """A decoder of the same space and table that accepts exact token structures only."""
        return DesignDecoder(self.space, table=self.table, max_distance=0, top_k=self.top_k)

    def __call__(self, tokens, index: int) -> Decoded:
        from tt.tokens.design_fit import design_from_tokens

        try:
            fit = design_from_tokens(
                tokens, index, self.space, table=self.table, max_distance=self.max_distance, top_k=self.top_k
            )
        except Exception as e:  # a candidate's tokens may break the fit in any way; report, do not crash
            return Decoded(None, f"decoding failed: {type(e).__name__}: {e}")
        if fit.design is None:
            return Decoded(
                None,
                f"no discrete choice of space {self.space.name!r} is within {self.max_distance} binary "
                f"attributes of this token structure (nearest: {fit.distance})",
            )
        return Decoded(fit.design, None, fit.residual, fit.distance)


def embodiment_batch(layout: Layout, normalizer: Normalizer, tokens: TokenBatch):
    """The embodiment tokens of n candidates (normalised, `layout`'s types) as a numpy
    `tt.tokens.TokenBatch` of encoded values, padding detected from the values (as the
    detokenizer expects)."""
    from tt.tokens.batch import TokenBatch

    if layout.schema_version is None:
        raise LayoutError(
            "the model's layout is not a RoboToken schema layout; candidates cannot be decoded to designs"
        )
    names = [s.name for s in layout.specs if s.role not in STEP_ROLES]
    batch = TokenBatch(
        {n: tokens.values[n].detach().float().cpu() for n in names},
        {n: tokens.ids[n].cpu() for n in names},
        {n: tokens.mask[n].cpu() for n in names},
        layout.schema_version,
    )
    return normalizer.denormalize(batch, detect_padding=True, clip=True).to_numpy()


def decode_x0(
    layout: Layout, normalizer: Normalizer, x0: dict[str, torch.Tensor], like: TokenBatch, decoder: Decoder
) -> list[Decoded]:
    """Each candidate of predicted clean tokens decoded: x0, type -> (n, L, D) normalised
    (only the embodiment types are read); like: tokens whose IDs and masks they have (the
    sampling query's)."""
    names = [s.name for s in layout.specs if s.role not in STEP_ROLES]
    tokens = TokenBatch({k: x0[k] for k in names}, {k: like.ids[k] for k in names}, {k: like.mask[k] for k in names})
    batch = embodiment_batch(layout, normalizer, tokens)
    return [decoder(batch, i) for i in range(len(tokens))]


@dataclass
class Ranking:
    """Candidates ranked: order (n,) candidate indices, best first (decoded or not yet tried
    by predicted objective, failed decodes last); decoded: index -> `Decoded` for every
    candidate tried; failures: how many failed."""

    order: list[int]
    decoded: dict[int, Decoded] = field(default_factory=dict)

    @property
    def failures(self) -> int:
        return sum(d.design is None for d in self.decoded.values())

    @property
    def best(self) -> int | None:
        """Best candidate that decoded, None if none did."""
        for i in self.order:
            d = self.decoded.get(i)
            if d is not None and d.design is not None:
                return i
        return None


def rank_candidates(
    objective: np.ndarray, batch, decoder: Decoder, *, decode: str = "best", limit: int | None = None
) -> Ranking:
    """Rank by predicted objective (NaN last), decode, move failed decodes last (see module).

    limit: with decode="all", stop once this many candidates decoded (None: all of them);
    decode="best" is limit 1."""
    obj = np.where(np.isfinite(objective), objective, -np.inf)
    order = [int(i) for i in np.argsort(-obj, kind="stable")]
    want = 1 if decode == "best" else limit
    decoded: dict[int, Decoded] = {}
    successes = 0
    for i in order:
        decoded[i] = decoder(batch, i)
        successes += decoded[i].design is not None
        if want is not None and successes >= want:
            break
    ok = [i for i in order if i not in decoded or decoded[i].design is not None]
    failed = [i for i in order if i in decoded and decoded[i].design is None]
    return Ranking(ok + failed, decoded)


# ------------------------------------------------------------------------------ optimizer
def resolve_model(trained: TrainedModel | None, checkpoint, device: str | None) -> TrainedModel:
    """The given model, or the checkpoint's loaded on `device` (default: `tt.kernels.device.default_device()`)."""
    if trained is not None:
        return trained
    if checkpoint is None:
        raise TTError(
            "a learned optimizer needs a checkpoint (SamplerConfig.checkpoint / --checkpoint) or a loaded model"
        )
    from tt.kernels.device import default_device

    return load_model(checkpoint, device=device or default_device())


def learned_result(
    method: str,
    problem: Problem,
    gen: Generation,
    ranking: Ranking,
    seconds: float,
    *,
    rollouts: int = 0,
    history: list[float] | None = None,
    info: dict | None = None,
) -> Result:
    """A `Result` of a learned optimizer: designs / rewards are the decoded candidates in rank
    order with their predicted objectives; info holds the whole ranking."""
    best = ranking.best
    if best is None:
        reasons = sorted({d.error for d in ranking.decoded.values() if d.error})
        raise TTError(
            f"none of the {len(gen.objective)} candidates decoded to a design of space {problem.space!r}: "
            f"{'; '.join(reasons)}"
        )
    done = [i for i in ranking.order if i in ranking.decoded and ranking.decoded[i].design is not None]
    designs = [ranking.decoded[i].design for i in done]
    rewards = gen.objective[done]
    full = {
        "samples": int(len(gen.objective)),
        "ranking": ranking.order,
        "predicted_objective": [float(v) for v in gen.objective],
        "predicted_reward_per_motion": gen.reward.tolist(),
        "predicted_metrics_best": {k: [float(x) for x in v[best]] for k, v in gen.metrics.items()},
        "decoded": len(ranking.decoded),
        "decode_failures": ranking.failures,
        "decode_errors": {str(i): d.error for i, d in ranking.decoded.items() if d.error},
        "residual_best": float(ranking.decoded[best].residual),
        "distance_best": int(ranking.decoded[best].distance),
        "projected": sum(d.design is not None and d.distance > 0 for d in ranking.decoded.values()),
        "best_candidate": int(best),
        "sample_seconds": gen.seconds,
    }
    full.update(info or {})
    return Result(
        method=method,
        best=ranking.decoded[best].design,
        best_reward=float(gen.objective[best]),
        designs=designs,
        rewards=np.asarray(rewards, dtype=np.float64),
        seconds=seconds,
        rollouts=rollouts,
        history=history if history is not None else [float(gen.objective[best])],
        info=full,
    )


class ZerothOrder(Optimizer):
    """The paper's Zeroth-Order optimizer: best of n model samples, ranked by the model.

    config: `SamplerConfig`; model: a loaded model (else ``config.checkpoint`` is loaded on
    the problem's device at the first `optimize`); decoder: candidate decoder (default
    `DesignDecoder` of the problem's space); critic_model: a loaded critic model (else
    ``config.critic_checkpoint``, if given, is loaded).
    """

    name = "zeroth"

    def __init__(
        self,
        config: SamplerConfig = SamplerConfig(),
        *,
        model: TrainedModel | None = None,
        decoder: Decoder | None = None,
        critic_model: TrainedModel | None = None,
    ):
        self.config = config
        self._trained = model
        self._critic = critic_model
        self._decoder = decoder
        self._decoders: dict[str, DesignDecoder] = {}

    def _setup(self, problem: Problem) -> tuple[CandidateSampler, Decoder, RewardConfig, int]:
        c = self.config
        self._trained = resolve_model(self._trained, c.checkpoint, problem.device)
        if self._critic is None and c.critic_checkpoint is not None:
            self._critic = resolve_model(None, c.critic_checkpoint, problem.device)
        # On designs, `judge_designs` asks the critic model itself; the sampler only samples.
        sampler = CandidateSampler(
            self._trained,
            problem.device,
            critic_model=self._critic if self.critic_input() == "tokens" else None,
            progress=problem.progress,
        )
        if c.refine:
            self._refine_critic()  # before any sampling, not after it
        if self._decoder is not None:
            decoder = self._decoder
        else:
            decoder = self._decoders.setdefault(problem.space, DesignDecoder(get_space(problem.space)))
        return sampler, decoder, get_reward(problem.reward, problem.space), c.samples or problem.budget

    def rank(self, gen: Generation, decoder: Decoder, *, limit: int | None = None) -> Ranking:
        """The candidates of `gen` ranked and decoded: per the config's decode policy, or,
        with `limit`, until `limit` of them decoded."""
        batch = embodiment_batch(self._trained.layout, self._trained.normalizer, gen.tokens)
        if limit is not None:
            return rank_candidates(gen.objective, batch, decoder, decode="all", limit=limit)
        return rank_candidates(gen.objective, batch, decoder, decode=self.config.decode)

    def generate(self, problem: Problem) -> tuple[Generation, Decoder, dict]:
        """Sample and score the problem's n candidates: (generation, the decoder of the
        problem's space, what the result's info records about the sampling)."""
        c = self.config
        sampler, decoder, cfg, n = self._setup(problem)
        critic = self.critic()
        gen, decoder = self.sample_scored(sampler, decoder, problem, cfg, n)
        info = {
            "num_steps": c.num_steps or ROBOT.diffusion_steps,
            "eta": c.eta,
            "placement": c.placement,
            "critic": critic,
            "critic_samples": c.critic_samples,
            "critic_on": self.critic_input(),
        }
        if self._critic is not None:
            info["critic_checkpoint"] = str(self._critic.path) if self._critic.path is not None else "(given model)"
        return gen, decoder, info

    def sample_scored(
        self,
        sampler: CandidateSampler,
        decoder: Decoder,
        problem: Problem,
        cfg: RewardConfig,
        n: int,
        guidance: Guidance | None = None,
    ) -> tuple[Generation, Decoder]:
        """n candidates sampled (with `guidance`, if any) and scored by the config's critic:
        on their tokens inside the sampling call, or on their decoded designs afterwards
        (`judge_designs`, which also returns a decoder answering from its decodes)."""
        c = self.config
        on_designs = self.critic_input() == "designs"
        gen = sampler.run(
            problem.motions,
            cfg,
            n,
            seed=problem.seed,
            num_steps=c.num_steps,
            eta=c.eta,
            placement=c.placement,
            chunk=c.chunk,
            guidance=guidance,
            critic="joint" if on_designs else self.critic(),
            critic_samples=1 if on_designs else c.critic_samples,
            temperature=c.temperature if c.temperature is not None else default_temperature(n),
        )
        if on_designs:
            return self.judge_designs(problem, gen, decoder, cfg)
        return gen, decoder

    def judge_designs(
        self, problem: Problem, gen: Generation, decoder: Decoder, cfg: RewardConfig
    ) -> tuple[Generation, Decoder]:
        """`gen` scored on its decoded designs (``critic_on="designs"``): every candidate is
        decoded, the dynamics critic (the critic model, else the sampling model's own task)
        predicts each design's reward (`predict_designs`, ``critic_samples`` averaged, the
        config's DDIM steps, the problem's seed), and candidates that do not decode score NaN.
        Returns that generation and a decoder that answers from the decodes made here."""
        import dataclasses

        from tt.guidance.predicted import predict_designs

        c = self.config
        batch = embodiment_batch(self._trained.layout, self._trained.normalizer, gen.tokens)
        decoded = [decoder(batch, i) for i in range(len(gen.objective))]
        ok = [i for i, d in enumerate(decoded) if d.design is not None]
        reward = np.full_like(gen.reward, np.nan)
        metrics = {k: np.full_like(v, np.nan) for k, v in gen.metrics.items()}
        seconds = gen.seconds
        if ok:
            pred = predict_designs(
                self._critic or self._trained,
                [decoded[i].design for i in ok],
                problem.motions,
                cfg,
                samples=c.critic_samples,
                num_steps=c.num_steps,
                seed=problem.seed,
                placement=c.placement,
                chunk=c.chunk,
                device=problem.device,
            )
            reward[ok] = pred.reward
            metrics = {k: np.full((len(decoded),) + v.shape[1:], np.nan) for k, v in pred.metrics.items()}
            for k, v in pred.metrics.items():
                metrics[k][ok] = v
            seconds += pred.seconds
        scored = dataclasses.replace(
            gen, reward=reward, objective=reward.mean(axis=1), metrics=metrics, seconds=seconds
        )
        return scored, lambda tokens, index: decoded[index]

    def critic(self) -> str:
        """The critic of the loaded model: the config's, or by default "dynamics" when the
        model was trained on that task or a critic model is given."""
        if self.config.critic is not None:
            return self.config.critic
        if self._critic is not None or self.config.critic_checkpoint is not None or self.config.critic_on == "designs":
            return "dynamics"
        return "dynamics" if self._trained.trained_on("dynamics") else "joint"

    def critic_input(self) -> str:
        """What the critic is asked about (models loaded): the config's ``critic_on``, or by
        default "designs" when the dynamics critic was trained told the episode's start
        (it is given each decoded design's simulated first step), else "tokens".

        Raises ValueError for "tokens" with such a critic: a sampled embodiment has no
        simulated start, and without it that critic is asked out of its training."""
        judge = self._critic or self._trained
        start_aware = self.critic() == "dynamics" and judge is not None and judge.dynamics_start
        if self.config.critic_on is None:
            return "designs" if start_aware else "tokens"
        if self.config.critic_on == "tokens" and start_aware:
            raise TTError(
                "the dynamics critic was trained told the episode's start (dynamics_start); ask it about "
                "the decoded designs (critic_on='designs', the default for it), whose first step can be "
                "simulated, not about sampled tokens"
            )
        return self.config.critic_on

    def optimize(self, problem: Problem) -> Result:
        start = time.perf_counter()
        gen, decoder, info = self.generate(problem)
        ranking = self.rank(gen, decoder)
        result = learned_result(
            self.name,
            problem,
            gen,
            ranking,
            time.perf_counter() - start,
            rollouts=int(info.pop("rollouts", 0)),
            info=info,
        )
        if self.config.refine:
            result = self.refined(problem, result)
            result.seconds = time.perf_counter() - start
        return result

    def refined(self, problem: Problem, result: Result) -> Result:
        """`result` with its best design refined by the dynamics critic (``config.refine``
        iterations, `tt.guidance.refine`, ``critic_samples`` per prediction); info["refine"]
        records the climb. When a step was taken, the refined design leads ``designs`` and its
        re-predicted objective is ``best_reward``; the given best is re-predicted in the same
        call (same noise, info["refine"]["objective_before"]), since the ranking's figure came
        from another noise draw. With no step taken the result is the given one."""
        import dataclasses

        from tt.guidance.predicted import predict_designs

        c = self.config
        judge = self._refine_critic()
        cfg = get_reward(problem.reward, problem.space)
        out = refine_designs(
            judge,
            [result.best],
            problem.motions,
            cfg,
            RefineConfig(iterations=c.refine, samples=c.critic_samples),
            seed=problem.seed,
            device=problem.device,
        )
        record = {
            **out.summary(),
            "iterations": c.refine,
            "ranked_objective": result.best_reward,
        }
        if out.steps[0] == 0:
            return dataclasses.replace(result, info={**result.info, "refine": record})
        best = out.designs[0]
        before, objective = predict_designs(
            judge,
            [result.best, best],
            problem.motions,
            cfg,
            samples=c.critic_samples,
            num_steps=c.num_steps,
            seed=problem.seed,
            placement=c.placement,
            chunk=c.chunk,
            device=problem.device,
            common_noise=True,
        ).reward.mean(axis=1)
        record["objective_before"] = float(before)
        return dataclasses.replace(
            result,
            best=best,
            best_reward=float(objective),
            designs=[best] + result.designs,
            rewards=np.concatenate([[objective], result.rewards]),
            history=result.history + [float(objective)],
            info={**result.info, "refine": record},
        )

    def _refine_critic(self) -> TrainedModel:
        """The model refinement climbs (the critic, else the sampling model); ValueError when
        it was not trained on the dynamics task."""
        judge = self._critic or self._trained
        if not judge.trained_on("dynamics"):
            raise TTError(
                f"refine climbs the dynamics critic's prediction: the model was trained on "
                f"{list(judge.tasks)}; give a critic checkpoint trained on the dynamics task"
            )
        return judge


__all__ = [
    "CRITICS",
    "CRITIC_INPUTS",
    "DECODE_MODES",
    "CandidateSampler",
    "Decoded",
    "Decoder",
    "DesignDecoder",
    "default_temperature",
    "Generation",
    "GuideContext",
    "Guidance",
    "Ranking",
    "SamplerConfig",
    "ZerothOrder",
    "check_critic",
    "decode_x0",
    "embodiment_batch",
    "learned_result",
    "rank_candidates",
    "renormalize",
    "resolve_model",
]
