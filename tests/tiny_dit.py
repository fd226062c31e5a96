"""A tiny random DiT on a RoboToken layout with few slots, for tests that need a network
but no trained checkpoint: every weight is jittered (the adaLN-Zero heads would otherwise
predict eps = 0 for any input)."""

from __future__ import annotations

import torch

from tt.dit.checkpoint import TrainedModel
from tt.dit.model import RoboDiT, get_config
from tt.dit.toy import toy_episodes

#: Slots per type of the tiny layout.
COUNTS = dict(
    link=6,
    dyna_joint=6,
    fixed_joint=4,
    actuator=3,
    track_link_obs=1,
    dyna_joint_obs=3,
    actuator_obs=3,
    control=3,
    target_pose=1,
)


def tiny_model(tasks: tuple[str, ...] = ("robot",)) -> TrainedModel:
    """The tiny network (seeded: the same weights every call), trained on `tasks` as far as
    the optimizers are concerned."""
    episodes = toy_episodes(episodes=16, steps=16, seed=0, schema_counts=COUNTS)
    layout = episodes.layout(8)
    torch.manual_seed(0)
    model = RoboDiT(layout, get_config("tiny")).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return TrainedModel(model, episodes.fit_normalizer(), layout, 0, tasks=tasks)
