"""Training data made while training: ``tt train --online``.

`OnlineTokenSource` is a `tt.dit.data.TokenSource` that generates its episodes with the
batched sim instead of reading a dataset. Refresh k draws `designs` new designs of the
space and `motions` augmented training motions (the draws of `tt generate`: the same
augmentation, control perturbation and minimum length), rolls every design out on every
motion, tokenizes the episodes and adds them to a buffer that holds the last `buffer`
refreshes; training windows are drawn from that buffer. Training step s reads the
buffer of refresh ``s // refresh_every``.

The rollout backend is the one `tt generate` uses for the space
(`tt.sim.backends.default_backend`): tt's Warp kernels for contact-free spaces, and
for spaces with contacts (the quadruped) ``mjbatch``, MuJoCo C's own physics on every CPU
thread with the batched whole-body controller, called as `tt generate` calls it
(`tt.sim.rollout.rollout` on the compiled models), so a refresh's episodes are the ones
`tt generate` records for the same designs and motions.

No copy between Warp and torch on the Warp backend: the rollout kernel's records stay Warp
arrays, and the Episode the tokenizer reads holds torch views of them
(`tt.sim.rollout.group_episode`, one per topology group, so designs of different DoF need no
padded copy); tokenization runs in torch on the sim's device, and only the finished tokens
move to the buffer (CPU). ``mjbatch`` returns one zero-padded Episode of CPU tensors.

Every draw of refresh k is a function of (seed, k), and both rollouts are deterministic
(mjbatch for every thread count), so a resumed run regenerates exactly the buffer it had
(and, with the data generator state of its checkpoint, draws the same windows).

Normalisation: a new run fits the normaliser on refresh 0 (`EpisodeTokens.fit_normalizer`);
``--init`` keeps the checkpoint's, so fine-tuning a dataset-trained model on online data
sees values in the same units.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch

from tt.dit.data import EpisodeTokens
from tt.dit.layout import Layout, LayoutError
from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch
from tt.tokens.draws import GenerateConfig, check_selection, default_action_noise
from tt.tokens.normalize import Normalizer

log = logging.getLogger(__name__)

# Random streams of a refresh (the third SeedSequence entry), apart from tt generate's
# shard streams (0..3) so an online run and a dataset with the same seed differ.
_STREAM_DESIGNS, _STREAM_MOTIONS, _STREAM_NOISE, _STREAM_SELECT, _STREAM_PROPOSE = 10, 11, 12, 13, 14


@dataclass(frozen=True)
class OnlineConfig:
    """What `OnlineTokenSource` generates.

    space: design space (contact-free spaces roll out on tt's Warp kernels, spaces with
    contacts on ``mjbatch``: `backend`); designs, motions: designs and augmented training
    motions per refresh (every design runs every motion); refresh_every: optimizer steps
    between refreshes; buffer: refreshes whose episodes windows are drawn from; seed: root of
    every draw; action_noise (None: what `tt generate` gives the space,
    `tt.tokens.draws.default_action_noise`), min_steps, max_motion_steps: as
    `tt.tokens.draws.GenerateConfig`; max_time: time-ID rows;
    absorbing: a terminated episode stays in the data to the motion's end. The rollout's
    records after termination repeat the terminal state (its end effector already past the
    threshold) beside the motion's true targets (`tt.kernels.rollout`), so windows that reach
    past the end teach the model which designs fail and where, which the motion-to-robot
    query's evenly placed steps ask about; without it (the default, as `tt generate`) windows
    stop at the end and episodes shorter than `min_steps` are dropped, so the data never shows
    a design failing.
    select: designs screened per kept episode. Refresh k then rolls ``designs * select`` new
    designs out on every motion and keeps, per motion, the `designs` episodes that
    `tt.tokens.draws.select_episodes` picks by `reward` (the best, and a `uniform_share` of
    them drawn uniformly), so each episode's design was chosen for that episode's motion and
    the motion-to-robot task learns which designs suit a motion, not the prior. 1: every
    design on every motion, unselected (``designs * motions`` episodes a refresh).
    propose: self-improvement (issue 51): designs per motion that the generator `proposer` (a
    checkpoint with the motion-to-robot task) samples for each of the refresh's motions, in
    `propose_steps` DDIM steps; they join the screen (and run every motion, as its uniform
    designs do), so the selection keeps the best of both. A frozen proposer keeps refresh k a
    function of (seed, k, proposer); a next round proposes with the run this one trains. The
    source needs the sampler built above dit (`tt.guidance.proposer.online_source`). 0: no
    proposals.
    """

    space: str = "viperx"
    designs: int = 64
    motions: int = 4
    refresh_every: int = 50
    buffer: int = 4
    seed: int = 0
    action_noise: float | None = None
    min_steps: int = 100
    max_motion_steps: int | None = None
    max_time: int = 1024
    absorbing: bool = False
    select: int = 1
    uniform_share: float = 0.0
    reward: str = "tracking"
    propose: int = 0
    proposer: str = ""
    propose_steps: int = 10

    def __post_init__(self) -> None:
        from tt.sim.designs import get_space
        from tt.sim.rewards import REWARDS, reward_name

        if self.refresh_every < 1 or self.buffer < 1:
            raise TTError(
                f"online training needs refresh_every >= 1 and buffer >= 1, got {self.refresh_every}, {self.buffer}"
            )
        check_selection(self.select, self.uniform_share, "online.select", "online.uniform_share")
        if not (isinstance(self.propose, int) and self.propose >= 0) or self.propose_steps < 1:
            raise TTError(
                f"online.propose must be an integer >= 0 and online.propose_steps >= 1, got {self.propose!r}, "
                f"{self.propose_steps!r}"
            )
        if self.propose and (not self.proposer or self.select == 1):
            raise TTError(
                "online.propose adds a generator's designs to the selection's screen: it needs online.proposer "
                f"(a checkpoint with the robot task) and online.select above 1, got proposer {self.proposer!r}, "
                f"select {self.select}"
            )
        try:
            object.__setattr__(self, "reward", reward_name(self.reward))  # the paper's names too
        except TTError:
            raise TTError(f"online.reward {self.reward!r} is not a reward; valid: {', '.join(REWARDS)}") from None
        get_space(self.space)  # raises listing the valid spaces
        if self.action_noise is None:
            object.__setattr__(self, "action_noise", default_action_noise(self.backend))
        self.generate_config()  # validates the shared fields

    @property
    def backend(self) -> str:
        """The rollout backend, `tt generate`'s for the space (`tt.sim.backends.default_backend`)."""
        from tt.sim.backends import default_backend

        return default_backend(self.space)

    def generate_config(self) -> GenerateConfig:
        """The `tt generate` config whose draws (augmentation, noise, filtering) a refresh uses."""
        return GenerateConfig(
            space=self.space,
            designs=self.designs,
            episodes_per_design=self.motions,
            seed=self.seed,
            designs_per_shard=self.designs,
            group_designs=self.designs,
            min_steps=self.min_steps,
            max_motion_steps=self.max_motion_steps,
            backend=self.backend,
            action_noise=self.action_noise,
        )


class OnlineTokenSource:
    """Episodes generated by the batched sim as training goes (see the module docstring).

    config: what to generate; device: Warp / torch device of the rollouts (None: the default;
    mjbatch runs on the CPU whatever the device, and its episodes are tokenized there);
    threads: CPU threads of the rollouts (None: every core; the episodes are the same for
    every count); proposer: with ``config.propose``, ``proposer(motions, n, seed)`` -> per
    motion a list of at most n designs sampled for it (`tt.guidance.proposer.ModelProposer`;
    dit cannot import the sampler's decoding); progress: a tqdm bar over each refresh's
    rollout (its control steps), so the minutes a refresh takes show on screen.
    ``stats`` counts refreshes, episodes kept and dropped, world-steps simulated and the
    seconds spent generating (and, with proposals, the designs proposed, the episodes of
    them the selection kept and the seconds spent sampling).
    """

    def __init__(
        self,
        config: OnlineConfig,
        device: str | None = None,
        threads: int | None = None,
        proposer=None,
        progress: bool = False,
    ):
        if config.propose and proposer is None:
            raise TTError(
                "online.propose needs the generator's sampler: build the source with "
                "tt.guidance.proposer.online_source (tt train does)"
            )
        from tt.kernels.device import resolve_device
        from tt.sim.designs import get_space
        from tt.tokens.draws import space_token_maxima
        from tt.tokens.tokenize import Tokenizer

        self.config = config
        self.device = resolve_device(device)
        self.threads = threads
        self.proposer = proposer
        self.progress = progress
        self.space = get_space(config.space)
        self._generate = config.generate_config()
        self.maxima = {k: int(v) for k, v in space_token_maxima(config.space)["maxima"].items() if int(v) > 0}
        self._tokenizer = Tokenizer()
        self._refreshes: dict[int, EpisodeTokens] = {}
        #: refresh -> the (design, motion) pairs its selection kept (``select`` > 1), before the filters.
        self.selected: dict[int, list[tuple[int, int]]] = {}
        #: refresh -> how many of its screen's designs (the last ones) were proposed.
        self.proposed: dict[int, int] = {}
        self._propose_seconds = 0.0
        self._data: EpisodeTokens | None = None
        self._current: int | None = None
        self.stats = {"refreshes": 0, "episodes": 0, "dropped": 0, "world_steps": 0, "seconds": 0.0}

    def __len__(self) -> int:
        return 0 if self._data is None else len(self._data)

    @property
    def design_space(self) -> str:
        """Name of the design space the episodes are of (recorded in checkpoints)."""
        return self.config.space

    def layout(self, steps: int = 8) -> Layout:
        """The layout of the space's largest robot (what a `tt generate` dataset of it has)."""
        from tt.dit.layout import layout_from_schema

        return layout_from_schema(self.maxima, steps=steps, max_time=self.config.max_time)

    def fit_normalizer(self) -> Normalizer:
        """Normalisation statistics of refresh 0."""
        return self._refresh(0).fit_normalizer()

    def start_step(self, step: int) -> None:
        """Make the buffer the one training step `step` reads (generating what it lacks)."""
        k = step // self.config.refresh_every
        if k == self._current:
            return
        wanted = range(max(0, k - self.config.buffer + 1), k + 1)
        parts = [self._refresh(j) for j in wanted]
        self._refreshes = {j: self._refreshes[j] for j in wanted}
        self._data = EpisodeTokens.concatenate(parts)
        self._current = k

    def sample(
        self,
        n: int,
        steps: int,
        kind: str,
        generator: torch.Generator | None = None,
        part: tuple[int, int] | None = None,
    ) -> TokenBatch:
        """n raw windows from the buffer (refresh 0's if no step was started); part: see
        `tt.dit.data.EpisodeTokens.sample`. Every data-parallel rank generates the same
        refreshes (on its own device) and reads its part of the windows."""
        if self._data is None:
            self.start_step(0)
        return self._data.sample(n, steps, kind, generator, part=part)

    # -------------------------------------------------------------- one refresh
    def draw(self, k: int) -> tuple[list, list]:
        """The designs (``designs * select`` uniform ones, then any proposed per motion: the
        screen) and augmented, placed training motions of refresh `k` (every design runs every
        motion), a function of (seed, k) and the proposer."""
        from tt.tokens.draws import _rng, _seed_int, episode_motion, training_motions

        cfg = self.config
        designs = self.space.sample(cfg.designs * cfg.select, seed=_seed_int(cfg.seed, k, _STREAM_DESIGNS))
        rng = _rng(cfg.seed, k, _STREAM_MOTIONS)
        base = training_motions(cfg.space)
        motion_ids = rng.choice(len(base), size=cfg.motions, replace=cfg.motions > len(base))
        motions = [
            episode_motion(self._generate, base[m], s)
            for m, s in zip(motion_ids, rng.integers(0, 2**31, size=cfg.motions))
        ]
        if cfg.propose:
            t0 = time.perf_counter()
            proposed = [
                d for per in self.proposer(motions, cfg.propose, _seed_int(cfg.seed, k, _STREAM_PROPOSE)) for d in per
            ]
            self.proposed[k] = len(proposed)
            self._propose_seconds = time.perf_counter() - t0
            designs = [*designs, *proposed]
        return designs, motions

    def noise_seed(self, k: int) -> int:
        """The seed of refresh `k`'s control perturbation, a function of (seed, k)."""
        from tt.tokens.draws import _seed_int

        return _seed_int(self.config.seed, k, _STREAM_NOISE)

    def _refresh(self, k: int) -> EpisodeTokens:
        if k in self._refreshes:
            return self._refreshes[k]
        from tt.tokens.draws import finite_worlds

        cfg, t0 = self.config, time.perf_counter()
        designs, motions = self.draw(k)
        if cfg.propose:
            self.stats["proposed"] = self.stats.get("proposed", 0) + self.proposed[k]
            self.stats["propose_seconds"] = self.stats.get("propose_seconds", 0.0) + self._propose_seconds
        too_long = max(m.steps for m in motions)
        if too_long > cfg.max_time:
            raise LayoutError(
                f"a training motion has {too_long} steps, the layout's time IDs {cfg.max_time} rows; "
                "set max_motion_steps"
            )
        models = [self.space.model(d) for d in designs]
        parts, dropped, world_steps, groups = [], 0, 0, []
        for members, ep in self._rollout(k, designs, models, motions):
            lengths = ep.lengths()
            world_steps += int(lengths.sum())
            if cfg.absorbing:
                lengths = torch.tensor([m.steps for m in motions], device=lengths.device)[
                    ep.motion_index.to(lengths.device)
                ]
            keep = torch.as_tensor(finite_worlds(ep), device=lengths.device) & (lengths >= cfg.min_steps)
            dropped += int((~keep).sum())
            groups.append((members, ep, lengths, keep))
        if cfg.select > 1:
            groups = self._select(k, groups, motions)
        # Every screened model is tokenized (about 0.2 ms each, small beside building it), so
        # episodes index the embodiment by their own design index.
        embodiment = self._tokenizer(models)
        for members, ep, lengths, keep in groups:
            if not bool(keep.any()):
                continue
            parts.append(episode_token_batch(ep, embodiment, lengths, keep.nonzero()[:, 0], cfg.max_time, self.maxima))
        if not parts:
            raise RuntimeError(
                f"online refresh {k}: all {dropped} episodes were dropped (non-finite or shorter than "
                f"{cfg.min_steps} steps)"
            )
        out = EpisodeTokens.concatenate(parts)
        seconds = time.perf_counter() - t0
        self.stats["refreshes"] += 1
        self.stats["episodes"] += len(out)
        self.stats["dropped"] += dropped
        self.stats["world_steps"] += world_steps
        self.stats["seconds"] += seconds
        log.info(
            "online refresh %d: %d episodes (%d dropped), %d world-steps in %.1f s",
            k,
            len(out),
            dropped,
            world_steps,
            seconds,
        )
        self._refreshes[k] = out
        return out

    def _rollout(self, k: int, designs: list, models: list, motions: list) -> list:
        """Refresh k's episodes: [(design indices, Episode)], one per Warp topology group
        (zero-copy views of the kernel's records), or one padded Episode of every design on
        mjbatch, rolled out as `tt generate` rolls out a group (`tt.generate.generate_shard`)."""
        from tt.sim.controller import IKConfig
        from tt.sim.rollout import group_episode, rollout, rollout_records

        cfg = self.config
        noise_seed = self.noise_seed(k)
        if cfg.backend != "warp":
            ep = rollout(
                models,
                motions,
                backend=cfg.backend,
                device=self.device,
                action_noise=cfg.action_noise,
                threads=self.threads,
                noise_seed=noise_seed,
                progress=self.progress,
            )
            return [(list(range(len(models))), ep)]
        # The tokenizer reads the models; the rollout simulates the tree fields the space
        # builds directly where it can, as every warp rollout of Designs does.
        trees = self.space.trees(designs)
        records = rollout_records(
            models if trees is None else trees,
            self.space.ee_sites(),
            motions,
            device=self.device,
            action_noise=cfg.action_noise,
            noise_seed=noise_seed,
            threads=self.threads,
            progress=self.progress,
        )
        return [
            (
                members,
                group_episode(
                    members,
                    arrays,
                    len(motions),
                    models[members[0]].nu,
                    perturbed=cfg.action_noise > 0,
                    dt=IKConfig().control_dt,
                ),
            )
            for members, arrays in records
        ]

    def _select(self, k: int, groups: list, motions: list) -> list:
        """The groups' keep masks narrowed to the episodes `select_episodes` picks per motion."""
        from tt.sim.rewards import RewardInputs, get_reward, metrics
        from tt.tokens.draws import _rng, select_episodes

        cfg = self.config
        reward_cfg = get_reward(cfg.reward, cfg.space)
        rewards, motion_of, eligible = [], [], []
        for _, ep, _, keep in groups:
            dev = ep.ee_pos.device
            steps = torch.tensor([m.steps for m in motions], device=dev)[ep.motion_index.to(dev)]
            # float64 sums: the ranking does not depend on the rollout's thread count.
            inputs = RewardInputs.from_episode(ep, motion_steps=steps, double=True)
            rewards.append(metrics(inputs, reward_cfg)["reward"].cpu().numpy())
            motion_of.append(ep.motion_index.cpu().numpy())
            eligible.append(keep.cpu().numpy())
        motion_of = np.concatenate(motion_of)
        chosen = select_episodes(
            np.concatenate(rewards),
            motion_of,
            np.concatenate(eligible),
            cfg.designs,
            cfg.uniform_share,
            _rng(cfg.seed, k, _STREAM_SELECT),
        )
        out, start = [], 0
        for members, ep, lengths, keep in groups:
            mask = torch.as_tensor(chosen[start : start + ep.worlds], device=keep.device)
            start += ep.worlds
            out.append((members, ep, lengths, keep & mask))
        self.stats["screened"] = self.stats.get("screened", 0) + start
        design_of = np.concatenate([ep.design_index.cpu().numpy() for _, ep, _, _ in groups])
        self.selected[k] = [(int(design_of[w]), int(motion_of[w])) for w in np.nonzero(chosen)[0]]
        if self.proposed.get(k):
            kept = sum(d >= cfg.designs * cfg.select for d, _ in self.selected[k])  # proposals come last
            self.stats["proposed_kept"] = self.stats.get("proposed_kept", 0) + kept
            log.info("online refresh %d: %d of %d kept episodes were proposed", k, kept, len(self.selected[k]))
        return out


def episode_token_batch(
    ep, embodiment, lengths: torch.Tensor, keep: torch.Tensor, max_time: int, maxima
) -> EpisodeTokens:
    """The token episodes of worlds `keep` (k,) of a rollout's episode batch `ep` (W worlds x T
    steps), each `lengths` (W,) steps long, with the designs' embodiment tokens (`Tokenizer`
    output), time IDs up to `max_time`, padded to `maxima`."""
    from tt.tokens.episodes import episode_tokens

    W, T = ep.worlds, ep.steps
    dynamics = episode_tokens(ep, embodiment.index, step_index=torch.arange(T, device=lengths.device).expand(W, T))
    # Worlds left out (some end at step 0) are cut out right after; clamped so they pass
    # EpisodeTokens' length check until then.
    tokens = EpisodeTokens.from_token_batches(
        embodiment.tokens, dynamics, lengths.clamp_min(1).cpu(), design_index=ep.design_index.cpu(), max_time=max_time
    )
    return tokens.subset(keep.cpu()).pad_to(maxima)


__all__ = ["OnlineConfig", "OnlineTokenSource", "episode_token_batch"]
