"""The DiT network, layouts and task masks: shapes, adaLN-Zero init, sizes, padding masks,
conditioning kept by sampling."""

from __future__ import annotations

import pytest
import torch

from tt.dit.layout import Layout, LayoutError, TokenSpec, layout_from_schema
from tt.dit.model import RoboDiT, get_config
from tt.dit.sampling import sample
from tt.dit.tasks import CONTROL, DYNAMICS, ROBOT, TaskSpec, output_types, task_masks
from tt.dit.toy import toy_episodes
from tt.tokens.schema import SCHEMA, SCHEMA_VERSION, Role

#: Largest ViperX robot as `tt.tokens` tokenizes it (tokens per robot / per step): 16
#: single-primitive links, 7 hinges and 9 rigid connections (two tokens each), 7 actuators,
#: one end effector.
VIPERX_COUNTS = dict(
    link=16,
    dyna_joint=14,
    fixed_joint=18,
    actuator=7,
    track_link_obs=1,
    dyna_joint_obs=7,
    actuator_obs=7,
    control=7,
    target_pose=1,
)


@pytest.fixture(scope="module")
def toy():
    episodes = toy_episodes(episodes=8, steps=16, seed=0)
    return episodes, episodes.layout(8), episodes.fit_normalizer()


def _randomise(model: RoboDiT, seed: int = 0) -> RoboDiT:
    """Give the zero-initialised modulations and heads random weights, so outputs depend on inputs."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            if bool((p == 0).all()):
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
    return model


def test_layout_from_schema_matches_schema():
    layout = layout_from_schema(VIPERX_COUNTS, steps=8)
    assert layout.schema_version == SCHEMA_VERSION
    for s in layout.specs:
        assert s.dim == SCHEMA[s.name].width
        assert s.ids == SCHEMA[s.name].ids
    assert layout["control"].role is Role.ACTION and layout["target_pose"].role is Role.CONDITION
    assert layout["dyna_joint_obs"].role is Role.DYNAMICS and layout["link"].role is Role.EMBODIMENT
    assert layout["dyna_joint_obs"].length == 8 * 7 and layout["link"].length == 16
    assert layout.seq_len == 16 + 14 + 18 + 7 + 8 * (1 + 7 + 7 + 7 + 1)
    assert Layout.from_dict(layout.to_dict()) == layout
    with pytest.raises(LayoutError, match="unknown token types"):
        layout_from_schema({"wheel": 2})


def test_model_sizes():
    layout = layout_from_schema(VIPERX_COUNTS)
    with torch.device("meta"):  # shapes only
        small = RoboDiT(layout, get_config("small"))
        large = RoboDiT(layout, get_config("large"))
    # The paper's small model: 11.6M parameters (its unified model also duplicates the
    # per-type projections per task); tt's single-head-set version lands within 5 %.
    assert 11.6e6 * 0.93 < small.parameter_count() < 11.6e6 * 1.05
    assert 63.6e6 * 0.95 < large.parameter_count() < 63.6e6 * 1.05
    with pytest.raises(ValueError, match="sizes"):
        get_config("huge")


def test_forward_shapes_and_adaln_zero_init(toy, device):
    episodes, layout, norm = toy
    model = RoboDiT(layout, get_config("tiny")).to(device)
    tokens = norm.normalize(episodes.sample(3, 8, "random", torch.Generator().manual_seed(0))).to(device)
    masks = task_masks(ROBOT, layout, tokens)
    out = model(tokens.values, tokens.ids, masks.noised, torch.rand(3, device=device), masks.attend)
    assert set(out) == set(layout.names_with(Role.EMBODIMENT, Role.DYNAMICS, Role.ACTION))
    for name, eps in out.items():
        assert eps.shape == tokens.values[name].shape
        # adaLN-Zero: every head starts at exactly zero.
        assert bool((eps == 0).all())
    # Every block starts as the identity.
    x = model.embed(tokens.values, tokens.ids, masks.noised)
    c = model.time_embed(torch.rand(3, device=device))
    assert torch.equal(model.blocks[0](x, c, None), x)


def test_tokens_check_names_the_problem(toy):
    episodes, layout, _ = toy
    tokens = episodes.sample(2, 8, "random", torch.Generator().manual_seed(0))
    layout.check(tokens)
    bad = tokens.clone()
    bad.ids["hinge"][0, 0, 0] = layout.id_sizes["joint"]
    with pytest.raises(LayoutError, match=r"ids\['hinge'\] kind 'joint'"):
        layout.check(bad)
    bad = tokens.clone()
    bad.values["state"] = bad.values["state"][:, :-1]
    with pytest.raises(LayoutError, match=r"values\['state'\]"):
        layout.check(bad)
    with pytest.raises(LayoutError, match="no 'time' ID"):
        TokenSpec("pose", 3, ("link",), Role.DYNAMICS, 8, 1)


def test_task_masks(toy):
    episodes, layout, _ = toy
    idx = torch.arange(4)
    steps = episodes.window_steps(idx, 8, "consecutive", torch.Generator().manual_seed(1))
    tokens = episodes.window(idx, steps)
    robot = task_masks(ROBOT, layout, tokens)
    assert robot.attend is None
    assert bool(robot.noised["body"].all()) and not bool(robot.noised["target"].any())
    control = task_masks(CONTROL, layout, tokens)
    # The current state is the window's first step (time IDs are episode steps).
    time = tokens.ids["state"][..., layout["state"].time_index]
    start = steps[:, :1]
    assert bool((start > 0).any())
    assert torch.equal(control.noised["state"], tokens.mask["state"] & (time > start))
    assert torch.equal(control.noised["command"], tokens.mask["command"])
    assert not bool(control.noised["body"].any())
    assert torch.equal(control.attend, torch.cat([tokens.mask[n] for n in layout.names], dim=1))
    # Design-to-dynamics: the embodiment and the targets are given (padding slots too), every
    # dynamics and action slot is diffused, nothing is masked.
    dynamics = task_masks(DYNAMICS, layout, tokens)
    assert dynamics.attend is None
    assert not bool(dynamics.noised["body"].any()) and not bool(dynamics.noised["target"].any())
    assert bool(dynamics.noised["state"].all()) and bool(dynamics.noised["command"].all())
    assert not bool(dynamics.noised["hinge"].any())
    assert output_types(DYNAMICS, layout) == ("state", "command")
    no_future = task_masks(TaskSpec("control", 5, "consecutive", future_states=False), layout, tokens)
    assert torch.equal(no_future.visible["state"], tokens.mask["state"] & (time == start))
    assert output_types(TaskSpec("control", 5, "consecutive", future_states=False), layout) == ("command",)


def test_control_padding_is_masked(toy):
    """With the control task's mask, padding tokens (values and IDs) cannot change any real
    token's output; without a mask (motion-to-robot) they do."""
    episodes, layout, norm = toy
    model = _randomise(RoboDiT(layout, get_config("tiny")))
    tokens = norm.normalize(episodes.sample(4, 8, "consecutive", torch.Generator().manual_seed(2)))
    assert not all(bool(m.all()) for m in tokens.mask.values()), "toy robots must have padding"
    changed = tokens.clone()
    g = torch.Generator().manual_seed(3)
    for name, real in tokens.mask.items():
        pad = ~real
        changed.values[name][pad] = torch.randn(int(pad.sum()), layout[name].dim, generator=g) * 3
        changed.ids[name][pad] = 1
    time = torch.full((4,), 0.5)
    for task, masked in ((CONTROL, True), (ROBOT, False)):
        m1, m2 = task_masks(task, layout, tokens), task_masks(task, layout, changed)
        with torch.no_grad():
            out1 = model(tokens.values, tokens.ids, m1.noised, time, m1.attend)
            out2 = model(changed.values, changed.ids, m2.noised, time, m2.attend)
        diff = {n: float((out1[n][tokens.mask[n]] - out2[n][tokens.mask[n]]).abs().max()) for n in out1}
        if masked:
            assert max(diff.values()) < 1e-5, f"padding changed real control outputs: {diff}"
        else:
            assert min(diff.values()) > 1e-3, f"without a mask padding should reach every real token: {diff}"


@pytest.mark.parametrize("task", [ROBOT, CONTROL])
def test_sampling_keeps_conditioning(toy, task):
    episodes, layout, norm = toy
    model = _randomise(RoboDiT(layout, get_config("tiny")), seed=1)
    tokens = norm.normalize(episodes.sample(3, 8, task.window, torch.Generator().manual_seed(4)))
    out = sample(
        model, tokens, task, num_steps=5 if task is ROBOT else None, eta=1.0, generator=torch.Generator().manual_seed(5)
    )
    masks = task_masks(task, layout, tokens)
    changed_any = False
    for name in layout.names:
        keep = ~(masks.noised[name] & masks.visible[name])
        assert torch.equal(out.tokens.values[name][keep], tokens.values[name][keep]), f"{task.name}: {name} changed"
        if bool((~keep).any()):
            changed_any |= not torch.equal(out.tokens.values[name], tokens.values[name])
        assert torch.isfinite(out.tokens.values[name]).all()
    assert changed_any
    if task is CONTROL:
        # Current state (first window step), embodiment, targets and padding came back bit-identical.
        time = tokens.ids["state"][..., layout["state"].time_index]
        first = time == time.amin(dim=1, keepdim=True)
        assert torch.equal(out.tokens.values["state"][first], tokens.values["state"][first])
        assert torch.equal(out.tokens.values["body"], tokens.values["body"])
