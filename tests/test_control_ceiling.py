"""tt.dit.control_ceiling (the logic of benchmarks/control_ceiling.py): its variants' grammar,
and DAgger windows that read the last command from what was executed and the next one from
DiffIK's labels."""

import pytest
import torch

from tt.dit import control_ceiling as ceiling

#: The space the benchmark runs on by default.
SPACE = "viperx"


def test_variants_parse_and_bad_ones_are_refused():
    v = ceiling.Variant.parse("joints/huber/dagger2")
    assert (v.anchor, v.loss, v.dagger, v.label) == ("joints", "huber", 2, "joints/huber/dagger2")
    assert ceiling.Variant.parse("command/mse") == ceiling.Variant("command", "mse", 0)
    v = ceiling.Variant.parse("command/mse/film/dagger1")
    assert (v.model, v.dagger, v.label) == ("film", 1, "command/mse/film/dagger1")
    assert ceiling.Variant.parse("joints/mse/film") == ceiling.Variant("joints", "mse", 0, "film")
    for bad in (
        "joint/mse",
        "command/l1",
        "command",
        "command/mse/dagger0",
        "command/mse/rounds2",
        "a/b/c/d",
        "command/mse/dagger1/film",
        "command/mse/film/film",
        "command/mse/cnn",
        "command/mse/mlp",
    ):
        with pytest.raises(ValueError, match="variant"):
            ceiling.Variant.parse(bad)


def test_labelled_windows_take_the_next_command_from_the_labels():
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.tasks import CONTROL, task_windows

    source = OnlineTokenSource(
        OnlineConfig(space=SPACE, designs=2, motions=1, refresh_every=100, buffer=1, min_steps=8), device="cpu"
    )
    layout, norm = source.layout(ceiling.STEPS), source.fit_normalizer()
    raw = task_windows(source, layout, 16, CONTROL, torch.Generator().manual_seed(0))
    labels = raw.clone()
    labels.values["control"] = labels.values["control"] + 0.25  # DiffIK's commands, other than what ran
    plain = ceiling.Windows.of(raw, layout, norm)
    mixed = ceiling.Windows.of(raw, layout, norm, labels=labels)
    assert bool(plain.real.any())
    torch.testing.assert_close(mixed.c0, plain.c0)  # the last command: what was executed
    torch.testing.assert_close(mixed.c1[mixed.real], plain.c1[plain.real] + 0.25)  # the next: the label
    torch.testing.assert_close(mixed.X, plain.X)  # the features see what ran
    torch.testing.assert_close(mixed.q, plain.q)
    # The joints anchor's features leave the last command out; the command anchor's keep it.
    P = layout["control"].per_step
    command, joints = ceiling.Variant("command", "mse"), ceiling.Variant("joints", "mse")
    assert plain.inputs(command) is plain.X
    tokens = norm.normalize(raw)
    free = ceiling.features(tokens, layout, command=False)
    assert plain.X.shape[1] - free.shape[1] == P
    torch.testing.assert_close(plain.inputs(joints), free)
    assert plain.anchor(command) is plain.c0 and plain.anchor(joints) is plain.q


def test_trimming_drops_the_windows_with_a_large_offset_in_any_joint():
    gen = torch.Generator().manual_seed(1)
    n, P = 200, 3
    c0 = torch.randn(n, P, generator=gen)
    step = 0.01 * torch.randn(n, P, generator=gen)
    step[:10, 1] = 5.0  # ten windows with one large jump each
    real = torch.ones(n, P, dtype=torch.bool)
    real[:, 2] = False  # a slot no design has: its values never count
    step[:, 2] = 100.0
    data = ceiling.Windows(torch.randn(n, 4, generator=gen), c0, c0 + step, real, c0 - 0.1, torch.tensor([0, 2]))
    command = ceiling.Variant("command", "mse")
    assert ceiling.trimmed(data, command, 1.0) is data
    kept = ceiling.trimmed(data, command, 0.9)
    assert len(kept) < n - 10 and not bool(((kept.c1 - kept.c0).abs()[:, :2] > 1.0).any())
    # Relative to the joints (c1 - q = step + 0.1) the same ten jumps are out.
    joints = ceiling.trimmed(data, ceiling.Variant("joints", "mse"), 0.95)
    assert len(joints) <= n - 10 and not bool(((joints.c1 - joints.q).abs()[:, :2] > 1.0).any())


def test_design_pool_draws_cycle_through_its_designs():
    from tt.sim.designs import get_space

    space = get_space(SPACE)
    designs = space.sample(2, seed=3)
    pool = ceiling.DesignPool(space, designs)
    assert pool.sample(5, seed=9) == [designs[0], designs[1], designs[0], designs[1], designs[0]]
    assert ceiling.DesignPool(space, designs[:1]).sample(3) == [designs[0]] * 3
    assert pool.ee_sites() == space.ee_sites()  # everything else is the wrapped space's


def test_film_reads_the_design_columns_and_starts_as_the_plain_state_mlp():
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.tasks import CONTROL, task_windows

    source = OnlineTokenSource(
        OnlineConfig(space=SPACE, designs=2, motions=1, refresh_every=100, buffer=1, min_steps=8), device="cpu"
    )
    layout, norm = source.layout(ceiling.STEPS), source.fit_normalizer()
    tokens = norm.normalize(task_windows(source, layout, 8, CONTROL, torch.Generator().manual_seed(0)))
    embodiment = torch.cat(
        [tokens.values[s.name].float().reshape(8, -1) for s in layout.specs if s.role.value == "embodiment"], 1
    )
    for command in (True, False):
        X, design = ceiling.features(tokens, layout, command=command), ceiling.design_columns(layout, command=command)
        assert design.shape == X.shape[1:]
        torch.testing.assert_close(X[:, design], embodiment)  # exactly the embodiment tokens' values
    design = ceiling.design_columns(layout)
    F, P = len(design), layout["control"].per_step
    torch.manual_seed(0)
    model = ceiling.FiLMRegressor(design, P, torch.ones(P), torch.zeros(F), torch.ones(F), hidden=16, depth=2)
    x = torch.randn(5, F)
    other = x.clone()
    other[:, design] = torch.randn(5, int(design.sum()))
    # Zero-initialised modulation: the design does not matter yet ...
    torch.testing.assert_close(model(x), model(other))
    # ... and once the modulation is trained it does, while the state columns always do.
    torch.nn.init.normal_(model.cond[-1].weight)
    assert not torch.allclose(model(x), model(other))
    moved = x.clone()
    moved[:, ~design] += 1.0
    assert not torch.allclose(model(x), model(moved))


def test_drawn_windows_are_the_concatenated_draws_in_one_random_order():
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.tasks import CONTROL, task_windows

    def source():
        return OnlineTokenSource(
            OnlineConfig(space=SPACE, designs=2, motions=1, refresh_every=1, buffer=1, min_steps=8), device="cpu"
        )

    src = source()
    layout, norm = src.layout(ceiling.STEPS), src.fit_normalizer()
    n, chunk, refreshes = 11, 3, 2
    drawn = ceiling.draw_windows(src, n, layout, norm, seed=5, chunk=chunk, refreshes=refreshes)
    # Reference: the same draws, concatenated, then permuted by the generator's next draw.
    ref_src, gen, parts = source(), torch.Generator().manual_seed(5), []
    for k, share in enumerate((6, 5)):
        ref_src.start_step(k)
        for a in range(0, share, chunk):
            parts.append(
                ceiling.Windows.of(task_windows(ref_src, layout, min(chunk, share - a), CONTROL, gen), layout, norm)
            )
    ref = ceiling.Windows.cat(parts).take(torch.randperm(n, generator=gen))
    assert len(drawn) == n
    for field in ("X", "c0", "c1", "real", "q"):
        torch.testing.assert_close(getattr(drawn, field), getattr(ref, field))
