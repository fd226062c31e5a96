"""A generator's proposals for online training's screen: iterated self-improvement (issue 51).

Online training with ``online.select`` keeps, per motion, the best of a screen of uniform
designs. With ``online.propose`` n, the screen also holds n designs per motion that a frozen
generator (``online.proposer``) samples for that motion, so the selection keeps the best of
both and the model trained on it learns from designs better than a uniform screen finds
(sample, simulate, keep the best, fine-tune). A next round proposes with this round's model.

`ModelProposer` samples and decodes (the motion-to-robot task, plain DDIM, as Zeroth-Order
draws its candidates); `online_source` builds the `tt.dit.online.OnlineTokenSource` with it,
since dit sits below the sampler's decoding and cannot build it itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from tt.kernels.errors import TTError


@dataclass
class ModelProposer:
    """Designs that generator `checkpoint` samples for motions.

    checkpoint: a model trained on the robot task (its EMA weights); steps: DDIM steps of
    each sample; reward: the reward the sampler's joint critic scores with (unused by the
    proposals, which are taken as sampled); device: where the model samples (None: the
    default device); progress: a tqdm bar over the motions sampled for. Calling it with
    (motions, n, seed) returns, per motion, the designs of n samples conditioned on that
    motion alone (seed + the motion's index), those whose tokens failed to decode left out.
    """

    checkpoint: str
    space: str
    steps: int = 10
    reward: str = "tracking"
    device: str | None = None
    progress: bool = False

    @cached_property
    def _parts(self) -> tuple:
        """(model, its sampler, the space's decoder, the reward), loaded at the first call."""
        from tt.dit.checkpoint import load_model
        from tt.guidance.zeroth import CandidateSampler, DesignDecoder
        from tt.sim.designs import get_space
        from tt.sim.rewards import get_reward

        trained = load_model(self.checkpoint, device=self.device)
        if not trained.trained_on("robot"):
            raise TTError(
                f"online.proposer {self.checkpoint} was trained on {list(trained.tasks)}; proposing designs "
                "needs the robot task"
            )
        if trained.space is not None and trained.space != self.space:
            raise TTError(
                f"online.proposer {self.checkpoint} is a model of space {trained.space!r}; this run trains "
                f"on {self.space!r}"
            )
        sampler = CandidateSampler(trained, self.device)
        return trained, sampler, DesignDecoder(get_space(self.space)), get_reward(self.reward, self.space)

    def __call__(self, motions: Sequence, n: int, seed: int) -> list[list]:
        from tqdm import tqdm

        from tt.guidance.zeroth import embodiment_batch

        trained, sampler, decoder, reward = self._parts
        out = []
        bar = tqdm(
            motions, desc=f"proposing {n} designs per motion", unit="motion", leave=False, disable=not self.progress
        )
        for i, motion in enumerate(bar):
            gen = sampler.run((motion,), reward, n, seed=seed + i, num_steps=self.steps, critic="joint")
            batch = embodiment_batch(trained.layout, trained.normalizer, gen.tokens)
            decoded = [decoder(batch, j) for j in range(n)]
            out.append([d.design for d in decoded if d.design is not None])
        return out


def online_source(config, device: str | None = None, threads: int | None = None, progress: bool = False):
    """The `tt.dit.online.OnlineTokenSource` of `config` (an `OnlineConfig`) on `device` (None:
    the default), with a `ModelProposer` of ``config.proposer`` when ``config.propose`` asks for
    proposals; progress: tqdm bars over each refresh's proposals and rollout. Raises TTError
    when the proposer's checkpoint does not exist."""
    from tt.dit.online import OnlineTokenSource
    from tt.kernels.device import resolve_device

    device = str(resolve_device(device))
    proposer = None
    if config.propose:
        if not Path(config.proposer).exists():
            raise TTError(f"online.proposer {config.proposer} does not exist (a checkpoint with the robot task)")
        proposer = ModelProposer(
            config.proposer,
            config.space,
            steps=config.propose_steps,
            reward=config.reward,
            device=device,
            progress=progress,
        )
    return OnlineTokenSource(config, device=device, threads=threads, proposer=proposer, progress=progress)


__all__ = ["ModelProposer", "online_source"]
