"""Training data of the DiT: episode windows, files, normalisation, and the bridge from
`tt.tokens` (tokenizer + episode tokens of a ViperX batch)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tt.dit.data import EpisodeTokens
from tt.dit.layout import LayoutError
from tt.dit.tasks import CONTROL, task_masks
from tt.dit.toy import toy_episodes
from tt.tokens.batch import TokenBatch
from tt.tokens.normalize import MIN_RANGE, Normalizer
from tt.tokens.schema import PAD_VALUE, SCHEMA


@pytest.fixture(scope="module")
def episodes():
    return toy_episodes(episodes=12, steps=20, seed=0)


def test_windows(episodes):
    g = torch.Generator().manual_seed(0)
    idx = torch.arange(len(episodes))
    steps = episodes.window_steps(idx, 8, "random", g)
    assert bool((steps[:, 1:] > steps[:, :-1]).all()) and int(steps.max()) < 20
    cons = episodes.window_steps(idx, 8, "consecutive", g)
    assert bool((cons[:, 1:] - cons[:, :-1] == 1).all()) and int(cons.max()) < 20
    window = episodes.window(idx, steps)
    layout = episodes.layout(8)
    layout.check(window)
    # Time IDs are episode steps; window step k holds episode step steps[k], entity by entity.
    time = window.ids["state"][..., layout["state"].time_index].reshape(len(idx), 8, -1)
    assert torch.equal(time, steps[:, :, None].expand_as(time))
    per_step = layout["state"].per_step
    e, k = 3, 5
    assert torch.equal(
        window.values["state"][e, k * per_step : (k + 1) * per_step], episodes.step_values["state"][e, steps[e, k]]
    )
    assert torch.equal(window.values["body"], episodes.static_values["body"])
    short = toy_episodes(episodes=2, steps=6)
    with pytest.raises(LayoutError, match="fewer than the window's 8"):
        short.sample(2, 8, "random")


def test_control_current_step_is_window_start(episodes):
    layout = episodes.layout(8)
    idx = torch.arange(len(episodes))
    steps = episodes.window_steps(idx, 8, "consecutive", torch.Generator().manual_seed(1))
    window = episodes.window(idx, steps)
    masks = task_masks(CONTROL, layout, window)
    time = window.ids["state"][..., layout["state"].time_index]
    clean = window.mask["state"] & ~masks.noised["state"]
    assert torch.equal(clean, window.mask["state"] & (time == steps[:, :1]))


def test_look_ahead_gives_each_slot_the_target_offset_steps_later(episodes):
    """The reference's control conditioning (`look_ahead`): a window of 8 + L consecutive steps
    becomes the 8-step window at the same start, but for its target poses, which are those of
    the window L steps later, under the first window's time IDs."""
    from tt.dit.tasks import TaskSpec, look_ahead

    layout, L = episodes.layout(8), 2
    idx = torch.arange(len(episodes))
    start = episodes.window_steps(idx, 8 + L, "consecutive", torch.Generator().manual_seed(4))[:, :1]
    shifted = look_ahead(layout, episodes.window(idx, start + torch.arange(8 + L)), L)
    here, later = episodes.window(idx, start + torch.arange(8)), episodes.window(idx, start + L + torch.arange(8))
    layout.check(shifted)
    for s in layout.specs:
        want = later if s.role.value == "condition" else here
        assert torch.equal(shifted.values[s.name], want.values[s.name]), s.name
        assert torch.equal(shifted.mask[s.name], want.mask[s.name]), s.name
        assert torch.equal(shifted.ids[s.name], here.ids[s.name]), s.name  # the slots' time IDs
    assert not torch.equal(shifted.values["target"], here.values["target"])
    with pytest.raises(LayoutError, match="are not 10 steps of"):
        look_ahead(layout, here, L)
    with pytest.raises(ValueError, match="target_offset 2 must be >= 0, and 0 for tasks other than control"):
        TaskSpec("robot", 100, "random", target_offset=2)


def test_file_round_trip(tmp_path, episodes):
    path = tmp_path / "episodes.npz"
    episodes.save(path)
    again = EpisodeTokens.load(path)
    assert again.layout(8) == episodes.layout(8)
    for group in ("static_values", "static_ids", "static_mask", "step_values", "step_ids", "step_mask"):
        for k, v in getattr(episodes, group).items():
            assert torch.equal(getattr(again, group)[k], v), f"{group}/{k}"
    assert torch.equal(again.lengths, episodes.lengths)
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    with pytest.raises(ValueError, match="not an episode token file"):
        EpisodeTokens.load(tmp_path / "other.npz")


def test_concatenate_pads_to_longest():
    a = toy_episodes(episodes=3, steps=10, seed=1)
    b = toy_episodes(episodes=2, steps=14, seed=2)
    for name in ("body", "hinge"):  # make b's robots one token shorter than a's
        for group in ("static_values", "static_ids", "static_mask"):
            getattr(b, group)[name] = getattr(b, group)[name][:, :-1].clone()
    both = EpisodeTokens.concatenate([a, b])
    assert len(both) == 5 and both.max_steps == 14
    assert torch.equal(both.lengths, torch.tensor([10, 10, 10, 14, 14]))
    assert torch.equal(both.static_values["body"][:3], a.static_values["body"])
    assert not bool(both.static_mask["body"][3:, -1].any())
    assert torch.equal(both.step_values["state"][3:], b.step_values["state"])
    assert torch.equal(both.step_values["state"][:3, :10], a.step_values["state"])
    assert both.layout(8)["body"].length == a.layout(8)["body"].length
    both.layout(8).check(both.sample(4, 8, "random", torch.Generator().manual_seed(0)))


def test_normalizer(episodes):
    norm = episodes.fit_normalizer()
    tokens = episodes.sample(6, 8, "random", torch.Generator().manual_seed(2))
    n = norm.normalize(tokens)
    for name, v in n.values.items():
        real = tokens.mask[name]
        assert bool((v[~real] == PAD_VALUE).all())
        assert float(v[real].min()) >= -1 - 1e-6 and float(v[real].max()) <= 1 + 1e-6
        torch.testing.assert_close(norm.denormalize_values(name, v)[real], tokens.values[name][real], rtol=0, atol=1e-5)
    # A constant feature maps to 0, and comes back.
    const = Normalizer({"a": torch.tensor([2.0, 0.0])}, {"a": torch.tensor([2.0, 4.0])})
    y = const.normalize_values("a", torch.tensor([[2.0, 1.0]]))
    torch.testing.assert_close(y, torch.tensor([[0.0, -0.5]]))
    torch.testing.assert_close(const.denormalize_values("a", y), torch.tensor([[2.0, 1.0]]))
    again = Normalizer.from_state_dict(norm.state_dict())
    torch.testing.assert_close(again.normalize(tokens).values["state"], n.values["state"], rtol=0, atol=0)
    # A fit widens a constant feature to MIN_RANGE about its value: 0 there, scaled around it.
    fit = Normalizer.fit({"a": (torch.tensor([[[2.0, 0.0], [2.0, 4.0]]]), torch.tensor([[True, True]]))})
    np.testing.assert_array_equal(fit.low["a"], [2.0 - MIN_RANGE / 2, 0.0])
    np.testing.assert_array_equal(fit.high["a"], [2.0 + MIN_RANGE / 2, 4.0])
    torch.testing.assert_close(
        fit.normalize_values("a", torch.tensor([[2.0, 1.0]], dtype=torch.float64)),
        torch.tensor([[0.0, -0.5]], dtype=torch.float64),
    )


def test_checkpoint_normalizer_state_loads_unchanged():
    """A checkpoint's normaliser state (float32 tensors, constant features at low == high as
    DiT fits wrote them before the normalisers were merged) loads, maps values by the
    formula x_n = 2 (x - low) / (high - low) - 1 evaluated in float32 as (x - low) (2 / span) - 1
    (constant features: x - low), and saves back to the same tensors."""
    import tt.dit

    assert tt.dit.Normalizer is Normalizer
    state = {
        "low": {"a": torch.tensor([0.5, -3.0, 7.0]), "b": torch.tensor([-1.0])},
        "high": {"a": torch.tensor([2.5, 1.0, 7.0]), "b": torch.tensor([0.25])},
    }
    norm = Normalizer.from_state_dict(state)
    x = torch.tensor([[1.0, 0.0, 7.5], [2.5, -3.0, 6.0]])
    lo, hi = state["low"]["a"], state["high"]["a"]
    span = hi - lo
    want = torch.stack(
        [(x[:, 0] - lo[0]) * (2.0 / span[0]) - 1, (x[:, 1] - lo[1]) * (2.0 / span[1]) - 1, x[:, 2] - lo[2]], -1
    )
    assert torch.equal(norm.normalize_values("a", x), want)
    torch.testing.assert_close(want, torch.tensor([[-0.5, 0.5, 0.5], [1.0, -1.0, -1.0]]))
    assert torch.equal(norm.denormalize_values("a", want), x)
    mask = torch.tensor([[True], [False]])
    out = norm.normalize(
        TokenBatch({"b": torch.tensor([[[0.25]], [[0.0]]])}, {"b": torch.zeros(2, 1, 1, dtype=torch.long)}, {"b": mask})
    )
    assert isinstance(out, TokenBatch)
    assert torch.equal(out.values["b"], torch.tensor([[[1.0]], [[PAD_VALUE]]]))
    saved = norm.state_dict()
    for part in ("low", "high"):
        for k, v in state[part].items():
            assert saved[part][k].dtype == torch.float32 and torch.equal(saved[part][k], v), (part, k)


def test_from_tokens_package():
    """Embodiment tokens from the tokenizer and per-step tokens from `episode_tokens` of a
    3-world ViperX batch become EpisodeTokens whose windows are the episode's values, and
    whose statistics are the tokens package's."""
    from tt.sim.designs import get_space
    from tt.sim.episode import Episode
    from tt.tokens.batch import TokenBatch
    from tt.tokens.episodes import episode_tokens
    from tt.tokens.tokenize import tokenize_models

    space = get_space("viperx")
    models = [space.model(d) for d in space.sample(3, 1)]
    emb = tokenize_models(models)
    w, t = 3, 12
    g = torch.Generator().manual_seed(0)
    nq, nu = max(m.nq for m in models), max(m.nu for m in models)
    quat = torch.nn.functional.normalize(torch.randn(w, t, 1, 4, generator=g), dim=-1)

    def r(*shape):
        return torch.randn(*shape, generator=g)

    episode = Episode(
        qpos=r(w, t, nq),
        qvel=r(w, t, nq),
        ctrl=r(w, t, nu),
        action=r(w, t, nu),
        act_force=r(w, t, nu),
        act_vel=r(w, t, nu),
        ee_pos=r(w, t, 1, 3),
        ee_quat=quat,
        target_pos=r(w, t, 1, 3),
        target_quat=quat,
        alive=torch.ones(w, t, dtype=torch.bool),
        fallen=torch.zeros(w, t, dtype=torch.bool),
        design_index=torch.arange(w),
        motion_index=torch.zeros(w, dtype=torch.long),
        dt=0.02,
    )
    dynamics = episode_tokens(episode, emb.index, step_index=torch.arange(t)[None].expand(w, t))
    data = EpisodeTokens.from_token_batches(emb.tokens, dynamics, torch.tensor([12, 10, 9]))
    layout = data.layout(8)
    assert layout.schema_version == emb.tokens.version
    idx = torch.arange(3)
    steps = data.window_steps(idx, 8, "consecutive", torch.Generator().manual_seed(3))
    window = data.window(idx, steps)
    layout.check(window)
    assert int(steps[2].max()) < 9  # inside the third episode's 9 executed steps
    # Control tokens of world 1 at its window's third step are the episode's actions there.
    n_act = layout["control"].per_step
    real = window.mask["control"][1, 2 * n_act : 3 * n_act]
    got = window.values["control"][1, 2 * n_act : 3 * n_act, 0][real]
    torch.testing.assert_close(got, episode.action[1, steps[1, 2], : int(real.sum())])
    # Statistics are the schema fit of the same tokens as a numpy TokenBatch (fixed ranges
    # for bits and rotations), and the torch window normalises to a TokenBatch again.
    ours = data.fit_normalizer()
    flat = {k: v.reshape(v.shape[0], -1, v.shape[-1]) for k, v in data.step_values.items()}
    valid = torch.arange(t)[None, :] < data.lengths[:, None]
    mask = {k: (valid[:, :, None] & data.step_mask[k][:, None, :]).reshape(3, -1) for k in flat}
    batch = TokenBatch(
        {**{k: v.numpy() for k, v in flat.items()}, **{k: v.numpy() for k, v in data.static_values.items()}},
        {
            **{k: np.zeros((*v.shape[:2], 2), np.int64) for k, v in flat.items()},
            **{k: v.numpy() for k, v in data.static_ids.items()},
        },
        {**{k: v.numpy() for k, v in mask.items()}, **{k: v.numpy() for k, v in data.static_mask.items()}},
    )
    theirs = Normalizer.fit(batch)
    assert sorted(ours.low) == sorted(theirs.low)
    for k in theirs.low:
        np.testing.assert_array_equal(ours.low[k], theirs.low[k], err_msg=k)
        np.testing.assert_array_equal(ours.high[k], theirs.high[k], err_msg=k)
    np.testing.assert_array_equal(ours.low["link"][SCHEMA["link"].slice("irot")], -1.0)
    back = ours.normalize(window)
    assert isinstance(back, TokenBatch)
    for k, v in back.values.items():
        torch.testing.assert_close(v, ours.normalize_values(k, window.values[k], window.mask[k]), rtol=0, atol=0, msg=k)
