"""`tt train --drop-type`: a lean critic whose sequence leaves out per-step types no reward
reads. The layout loses exactly those types, the run records them (a resume with others is
refused), `tt predict` scores the tracking reward with it and refuses the effort rewards,
whose actuator observations it no longer predicts."""

from __future__ import annotations

import pytest
import torch

from tt.dit.layout import LayoutError
from tt.dit.train import DROPPABLE, TrainConfig, train

pytestmark = pytest.mark.usefixtures("single_thread")

SPACE = "viperx-nominal"
LEAN = ("dyna_joint_obs", "actuator_obs", "control")


def _config(out, **kw):
    from tt.dit.online import OnlineConfig

    base = dict(
        out=str(out),
        task="dynamics",
        size="tiny",
        steps=2,
        batch_size=4,
        warmup_steps=1,
        device="cpu",
        checkpoint_every=2,
        prediction="x0",
        anchor_track=True,
        online=OnlineConfig(
            space=SPACE, designs=4, motions=1, refresh_every=100, buffer=1, min_steps=8, absorbing=True
        ),
    )
    return TrainConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def lean_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("lean") / "run"
    return out, train(_config(out, drop_types=LEAN))


def test_layout_without_drops_exactly_the_named_types():
    from tt.dit.online import OnlineConfig, OnlineTokenSource

    full = OnlineTokenSource(OnlineConfig(space=SPACE, designs=2, motions=1, min_steps=8), device="cpu").layout(8)
    lean = full.without(LEAN)
    assert lean.names == tuple(n for n in full.names if n not in LEAN)
    assert lean.seq_len == full.seq_len - sum(full[n].length for n in LEAN)
    assert all(lean[n] == full[n] for n in lean.names)
    assert full.without(()) is full
    with pytest.raises(LayoutError, match="cannot drop token types"):
        full.without(["no_such_type"])


def test_the_lean_run_trains_a_model_without_them(lean_run):
    from tt.dit.checkpoint import load_model

    out, result = lean_run
    trained = load_model(result.checkpoint)
    assert not set(LEAN) & set(trained.layout.names)
    assert {"link", "track_link_obs", "target_pose"} <= set(trained.layout.names)
    assert torch.isfinite(result.losses).all()


def test_a_resume_with_other_drop_types_is_refused(lean_run):
    out, _ = lean_run
    with pytest.raises(ValueError, match="--drop-type"):
        train(_config(out, steps=4, drop_types=("control",)))


def test_predict_scores_tracking_and_refuses_effort_rewards(lean_run):
    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import predict_designs
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, get_motion
    from tt.sim.rewards import get_reward

    _, result = lean_run
    trained = load_model(result.checkpoint)
    designs = get_space(SPACE).sample(2, seed=3)
    motions = for_space([get_motion("toss")], SPACE)
    pred = predict_designs(trained, designs, motions, get_reward("tracking", SPACE), num_steps=2)
    assert pred.reward.shape == (2, 1) and (pred.reward >= 0).all()
    with pytest.raises(LayoutError, match="actuator_obs"):
        predict_designs(trained, designs, motions, get_reward("tracking_torque", SPACE), num_steps=2)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(drop_types=("track_link_obs",)), "cannot be dropped"),
        (dict(drop_types=("link",)), "cannot be dropped"),
        (dict(drop_types=("control",), task="robot+control"), "control task reads and writes"),
    ],
)
def test_bad_drop_types_are_refused(tmp_path, kw, message):
    with pytest.raises(ValueError, match=message):
        _config(tmp_path / "r", **kw)


def test_droppable_types_are_per_step_schema_types():
    from tt.tokens.schema import SCHEMA, STEP_ROLES

    assert all(SCHEMA[n].role in STEP_ROLES for n in DROPPABLE)
