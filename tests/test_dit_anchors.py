"""Track-link poses anchored on their targets (`tt.dit.anchors`) and sinusoidal time-step IDs:
the anchor map against the normaliser it is read off, an untrained anchored network
predicting exactly the target pose, description round trips, and clear errors."""

from __future__ import annotations

import pytest
import torch

from tt.dit.anchors import Anchor, pose_anchors
from tt.dit.layout import LayoutError
from tt.dit.model import DiTConfig, RoboDiT, TimeIdEmbedder, get_config
from tt.dit.tasks import DYNAMICS, task_masks
from tt.dit.toy import toy_episodes

COUNTS = dict(
    link=4,
    dyna_joint=6,
    fixed_joint=4,
    actuator=3,
    track_link_obs=1,
    dyna_joint_obs=3,
    actuator_obs=3,
    control=3,
    target_pose=1,
)


@pytest.fixture(scope="module")
def schema_toy():
    episodes = toy_episodes(episodes=8, steps=16, seed=0, schema_counts=COUNTS)
    return episodes, episodes.layout(8), episodes.fit_normalizer()


def test_anchor_map_is_the_targets_pose_in_the_observations_units(schema_toy):
    _, layout, norm = schema_toy
    anchor = pose_anchors(layout, norm)["track_link_obs"]
    scale, offset = torch.tensor(anchor.scale, dtype=torch.float64), torch.tensor(anchor.offset, dtype=torch.float64)
    x = torch.rand(5, 12, dtype=torch.float64) * 2 - 1
    reference = norm.normalize_values("track_link_obs", norm.denormalize_values("target_pose", x))
    torch.testing.assert_close(scale * x + offset, reference, rtol=0, atol=1e-12)


def test_untrained_anchored_network_predicts_the_target(schema_toy):
    """adaLN-Zero heads output 0, so x0 of the track-link pose is the target's pose, in metres."""
    episodes, layout, norm = schema_toy
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=pose_anchors(layout, norm)).eval()
    tokens = norm.normalize(episodes.sample(4, 8, "random", torch.Generator().manual_seed(1)))
    masks = task_masks(DYNAMICS, layout, tokens)
    noisy = {n: torch.where(masks.noised[n][..., None], torch.randn_like(v), v) for n, v in tokens.values.items()}
    with torch.no_grad():
        out = model(noisy, tokens.ids, masks.noised, torch.full((4,), 0.7))
    pos = slice(0, 3)
    predicted = norm.denormalize_values("track_link_obs", out["track_link_obs"].double())[..., pos]
    target = norm.denormalize_values("target_pose", tokens.values["target_pose"].double())[..., pos]
    torch.testing.assert_close(predicted, target, rtol=0, atol=1e-5)
    plain = RoboDiT(layout, get_config("tiny"), prediction="x0").eval()
    with torch.no_grad():
        assert bool((plain(noisy, tokens.ids, masks.noised, torch.full((4,), 0.7))["track_link_obs"] == 0).all())


def test_descriptions_round_trip_and_bad_anchors_fail(schema_toy):
    _, layout, norm = schema_toy
    anchors = pose_anchors(layout, norm)
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=anchors)
    again = RoboDiT.from_description(model.describe())
    assert again.anchors == anchors and again.config.time_ids == "sinusoidal"
    again.load_state_dict(model.state_dict())
    with pytest.raises(ValueError, match="need prediction 'x0', not 'eps'"):
        RoboDiT(layout, get_config("tiny"), anchors=anchors)
    with pytest.raises(LayoutError, match="anchored on a condition"):
        RoboDiT(
            layout,
            get_config("tiny"),
            prediction="x0",
            anchors={
                "track_link_obs": Anchor(
                    "track_link_obs", anchors["track_link_obs"].scale, anchors["track_link_obs"].offset
                )
            },
        )
    with pytest.raises(LayoutError, match="3 scales and 3 offsets for 12 values"):
        Anchor("target_pose", (1.0,) * 3, (0.0,) * 3).check(layout, "track_link_obs")
    from tt.dit.train import TrainConfig

    with pytest.raises(ValueError, match="anchor_track needs prediction x0"):
        TrainConfig(anchor_track=True, prediction="eps")


def test_time_ids_embed_by_step_and_old_descriptions_keep_their_table(schema_toy):
    _, layout, _ = schema_toy
    emb = TimeIdEmbedder(16)
    ids = torch.tensor([[0, 5, 5, 900]])
    e = emb(ids)
    assert e.shape == (1, 4, 16) and torch.equal(e[0, 1], e[0, 2]) and not torch.equal(e[0, 0], e[0, 3])
    model = RoboDiT(layout, get_config("tiny"))
    assert isinstance(model.id_embed["time"], TimeIdEmbedder) and isinstance(model.id_embed["link"], torch.nn.Embedding)
    old = model.describe()
    del old["config"]["time_ids"], old["anchors"]
    legacy = RoboDiT.from_description(old)
    assert legacy.config.time_ids == "learned" and isinstance(legacy.id_embed["time"], torch.nn.Embedding)
    with pytest.raises(ValueError, match="time_ids 'rope' does not exist"):
        DiTConfig(time_ids="rope")


def test_untrained_control_anchored_network_holds_the_current_position(schema_toy):
    """Delta actions: with the control anchor, x0 of every step's command of actuator i is the
    window's current position of dynamic joint i (adaLN-Zero heads output 0), in radians."""
    from tt.dit.anchors import control_anchors
    from tt.dit.tasks import CONTROL

    episodes, layout, norm = schema_toy
    anchors = control_anchors(layout, norm)
    assert anchors["control"].on == "dyna_joint_obs" and anchors["control"].value == 0
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=anchors).eval()
    tokens = norm.normalize(episodes.sample(4, 8, "consecutive", torch.Generator().manual_seed(2)))
    masks = task_masks(CONTROL, layout, tokens)
    noisy = {n: torch.where(masks.noised[n][..., None], torch.randn_like(v), v) for n, v in tokens.values.items()}
    with torch.no_grad():
        out = model(noisy, tokens.ids, masks.noised, torch.full((4,), 0.5))
    P, J = layout["control"].per_step, layout["dyna_joint_obs"].per_step
    command = norm.denormalize_values("control", out["control"].double()).reshape(4, 8, P)
    joints = norm.denormalize_values("dyna_joint_obs", tokens.values["dyna_joint_obs"].double()).reshape(4, 8, J, 2)
    current = joints[:, 0, :P, 0]  # (B, P): qpos of the window's first step, the control task's clean state
    torch.testing.assert_close(command, current[:, None, :].expand(4, 8, P), rtol=0, atol=1e-5)
    assert bool(masks.noised["dyna_joint_obs"].reshape(4, 8, J)[:, 0].logical_not().all())  # the base is clean


def test_control_anchor_round_trips_and_refuses_what_it_cannot_anchor(schema_toy):
    from tt.dit.anchors import control_anchors

    _, layout, norm = schema_toy
    anchors = control_anchors(layout, norm)
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=anchors)
    assert RoboDiT.from_description(model.describe()).anchors == anchors
    a = anchors["control"]
    with pytest.raises(LayoutError, match="value 2 of 'dyna_joint_obs'"):
        Anchor(a.on, a.scale, a.offset, 2).check(layout, "control")
    with pytest.raises(LayoutError, match="their slots differ"):  # slot for slot, a command is no joint state
        RoboDiT(
            layout, get_config("tiny"), prediction="x0", anchors={"control": Anchor("dyna_joint_obs", (1.0,), (0.0,))}
        )
    from tt.dit.train import TrainConfig

    with pytest.raises(ValueError, match="anchor_control needs prediction x0"):
        TrainConfig(anchor_control="joints", prediction="eps")
    with pytest.raises(ValueError, match="anchor_control command needs known_command"):
        TrainConfig(anchor_control="command")
    with pytest.raises(ValueError, match="anchor_control 'velocity' does not exist"):
        TrainConfig(anchor_control="velocity", known_command=True)


def test_joint_actuator_check_reads_the_models():
    """ViperX's servos drive its dynamic joints in order; a robot index whose actuators are
    listed in another order is refused by name."""
    import dataclasses

    import numpy as np

    from tt.dit.anchors import check_joint_actuators
    from tt.sim.designs import get_space
    from tt.tokens.tokenize import Tokenizer

    space = get_space("viperx")
    models = space.models(space.sample(3, seed=0))
    robots = Tokenizer()(models).index
    check_joint_actuators(robots, models)
    swapped = dataclasses.replace(robots[1], actuator_mj=np.roll(robots[1].actuator_mj, 1))
    with pytest.raises(LayoutError, match="design 1: its actuators drive"):
        check_joint_actuators([robots[0], swapped, robots[2]], models)


def test_control_anchor_gain_is_the_residuals_spread(schema_toy):
    """The gain is the RMS of command minus current joint position, in normalised units;
    the untrained network (output 0) still holds the current position, and a unit output
    moves the command by one gain."""
    from tt.dit.anchors import control_anchors
    from tt.dit.tasks import CONTROL

    episodes, layout, norm = schema_toy
    windows = episodes.sample(64, 8, "consecutive", torch.Generator().manual_seed(3))
    anchors = control_anchors(layout, norm, windows)
    gain = anchors["control"].gain[0]
    P, J = layout["control"].per_step, layout["dyna_joint_obs"].per_step
    command = norm.normalize_values("control", windows.values["control"].double()).reshape(64, 8, P)
    joints = windows.values["dyna_joint_obs"].double().reshape(64, 8, J, 2)[:, :1, :P, 0].expand(64, 8, P)
    held = norm.normalize_values("control", joints.reshape(64, 8 * P, 1)).reshape(64, 8, P)  # the command "hold"
    real = windows.mask["control"].reshape(64, 8, P)
    assert gain == pytest.approx(float((command - held)[real].pow(2).mean().sqrt()), rel=1e-9)
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=anchors).eval()
    assert RoboDiT.from_description(model.describe()).anchors == anchors
    tokens = norm.normalize(windows)
    masks = task_masks(CONTROL, layout, tokens)
    with torch.no_grad():
        out = model(tokens.values, tokens.ids, masks.noised, torch.full((64,), 0.5))
        torch.nn.init.constant_(model.heads["control"].linear.bias, 1.0)  # every residual output 1
        moved = model(tokens.values, tokens.ids, masks.noised, torch.full((64,), 0.5))
    torch.testing.assert_close(out["control"].double().reshape(64, 8, P)[real], held[real], rtol=0, atol=1e-5)
    torch.testing.assert_close(
        (moved["control"] - out["control"]).double(), torch.full_like(out["control"], gain).double(), rtol=0, atol=1e-5
    )
    with pytest.raises(LayoutError, match="gains must be > 0"):
        Anchor("dyna_joint_obs", (1.0,), (0.0,), 0, (0.0,)).check(layout, "control")


def test_known_command_is_a_condition_and_the_command_anchor_repeats_it(schema_toy):
    """With known_command the control task keeps step 0's command clean (the servo's setpoint
    that led to the current state) and diffuses the 7 after it; anchored on it, an untrained
    network repeats the last command at every step."""
    from tt.dit.anchors import control_anchors
    from tt.dit.tasks import CONTROL, TaskSpec

    episodes, layout, norm = schema_toy
    task = TaskSpec("control", CONTROL.diffusion_steps, "consecutive", False, known_command=True)
    windows = episodes.sample(16, 8, "consecutive", torch.Generator().manual_seed(4))
    tokens = norm.normalize(windows)
    P = layout["control"].per_step
    masks = task_masks(task, layout, tokens)
    real = tokens.mask["control"].reshape(16, 8, P)
    noised = masks.noised["control"].reshape(16, 8, P)
    assert not noised[:, 0].any() and torch.equal(noised[:, 1:], real[:, 1:])
    assert torch.equal(
        task_masks(CONTROL, layout, tokens).noised["control"], tokens.mask["control"]
    )  # default: all diffused
    anchors = control_anchors(layout, norm, windows, base="command")
    assert anchors["control"].on == "control" and anchors["control"].scale == pytest.approx((1.0,))
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=anchors).eval()
    noisy = {n: torch.where(masks.noised[n][..., None], torch.randn_like(v), v) for n, v in tokens.values.items()}
    with torch.no_grad():
        out = model(noisy, tokens.ids, masks.noised, torch.full((16,), 0.5))["control"].reshape(16, 8, P)
    last = tokens.values["control"].reshape(16, 8, P)[:, :1].expand(16, 8, P)
    torch.testing.assert_close(out[real], last[real], rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="base 'torque' does not exist"):
        control_anchors(layout, norm, base="torque")


def test_gain_anchored_loss_is_huber_in_the_residuals_units(schema_toy):
    """An anchored type with a gain is scored on (x0 error) / gain: a residual of 3 gains off
    costs Huber(3) = 2.5, not Huber(3 gain)."""
    from tt.dit.anchors import control_anchors
    from tt.dit.ddim import CosineDDIM
    from tt.dit.tasks import CONTROL, TaskSpec, diffusion_loss, noise_tokens

    episodes, layout, norm = schema_toy
    task = TaskSpec("control", CONTROL.diffusion_steps, "consecutive", False, known_command=True)
    windows = episodes.sample(8, 8, "consecutive", torch.Generator().manual_seed(5))
    anchors = control_anchors(layout, norm, windows, base="command")
    model = RoboDiT(layout, get_config("tiny"), prediction="x0", anchors=anchors)
    parts = [
        (
            task,
            noise_tokens(
                task,
                CosineDDIM(task.diffusion_steps),
                layout,
                norm.normalize(windows),
                torch.Generator().manual_seed(0),
                prediction="x0",
            ),
        )
    ]
    target = parts[0][1].target["control"]
    mask = parts[0][1].masks.loss_mask("control")
    gain = anchors["control"].gain[0]
    with torch.no_grad():
        off = target + 3 * gain  # every diffused command 3 gains off its target
        model.forward = lambda *a, **k: {"control": off}  # noqa: E731
        _, terms = diffusion_loss(model, parts)
    assert bool(mask.any()) and float(terms["control"]) == pytest.approx(2.5, rel=1e-4)
