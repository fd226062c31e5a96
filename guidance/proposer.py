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
from dataclasses import dataclass, field

from tt.kernels.errors import TTError


@dataclass
class ModelProposer:
    """Designs that generator `checkpoint` samples for motions.

    checkpoint: a model trained on the robot task (its EMA weights); steps: DDIM steps of
    each sample; reward: the reward the sampler's joint critic scores with (unused by the
    proposals, which are taken as sampled); device: where the model samples (None: the
    default device). Calling it with (motions, n, seed) returns, per motion, the designs of
    n samples conditioned on that motion alone (seed + the motion's index), those whose
    tokens failed to decode left out.
    """

    checkpoint: str
    space: str
    steps: int = 10
    reward: str = "tracking"
    device: str | None = None
    _state: dict = field(default_factory=dict, init=False, repr=False)

    def _loaded(self):
        if not self._state:
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
            self._state.update(
                trained=trained,
                sampler=CandidateSampler(trained, self.device),
                decoder=DesignDecoder(get_space(self.space)),
                reward=get_reward(self.reward, self.space),
            )
        return self._state

    def __call__(self, motions: Sequence, n: int, seed: int) -> list[list]:
        from tt.guidance.zeroth import embodiment_batch

        st = self._loaded()
        out = []
        for i, motion in enumerate(motions):
            gen = st["sampler"].run((motion,), st["reward"], n, seed=seed + i, num_steps=self.steps, critic="joint")
            batch = embodiment_batch(st["trained"].layout, st["trained"].normalizer, gen.tokens)
            decoded = [st["decoder"](batch, j) for j in range(n)]
            out.append([d.design for d in decoded if d.design is not None])
        return out


def online_source(config, device: str | None = None, threads: int | None = None):
    """The `tt.dit.online.OnlineTokenSource` of `config` (an `OnlineConfig`), with a
    `ModelProposer` of ``config.proposer`` when ``config.propose`` asks for proposals."""
    from tt.dit.online import OnlineTokenSource

    proposer = None
    if config.propose:
        proposer = ModelProposer(
            config.proposer, config.space, steps=config.propose_steps, reward=config.reward, device=device
        )
    return OnlineTokenSource(config, device=device, threads=threads, proposer=proposer)


__all__ = ["ModelProposer", "online_source"]
