"""Online self-improvement (issue 51): a generator's proposals join the selection's screen.

The reference for the selection is an independent rollout of the whole screen, uniform
designs and proposals together, ranked with numpy (`test_motion_selected_data._rewards`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_motion_selected_data import _rewards

from tt.dit.online import _STREAM_NOISE, OnlineConfig, OnlineTokenSource
from tt.sim.designs import get_space
from tt.tokens.draws import _seed_int

GENERATOR = Path(__file__).resolve().parents[1] / "checkpoints" / "viperx_mini_robot.pt"
SMALL = dict(space="viperx", designs=2, motions=2, select=3, max_motion_steps=40, min_steps=20, absorbing=True)


def test_propose_is_refused_without_a_proposer_or_selection():
    with pytest.raises(ValueError, match="needs online.proposer"):
        OnlineConfig(space="viperx", select=4, propose=8)
    with pytest.raises(ValueError, match="online.select above 1"):
        OnlineConfig(space="viperx", propose=8, proposer="x.pt")
    with pytest.raises(ValueError, match="online.propose must be an integer >= 0"):
        OnlineConfig(space="viperx", select=4, propose=-1, proposer="x.pt")
    with pytest.raises(ValueError, match="online_source"):
        OnlineTokenSource(OnlineConfig(**SMALL, propose=2, proposer="x.pt"), device="cpu")
    from tt.guidance.proposer import online_source

    with pytest.raises(ValueError, match="online.proposer missing.pt does not exist"):
        online_source(OnlineConfig(**SMALL, propose=2, proposer="missing.pt"), device="cpu")


def test_proposals_join_the_screen_and_the_best_of_both_are_kept():
    """A proposer that offers the space's nominal design (a strong one) for each motion: the
    screen grows by it, and each motion keeps the best designs of the whole screen."""
    space = get_space("viperx")
    calls = []

    def proposer(motions, n, seed):
        calls.append((len(motions), n, seed))
        return [[space.nominal()] * n for _ in motions]

    cfg = OnlineConfig(**SMALL, propose=1, proposer="nominal")
    src = OnlineTokenSource(cfg, device="cpu", proposer=proposer)
    tokens = src._refresh(0)
    assert len(tokens) == cfg.designs * cfg.motions
    designs, motions = src.draw(0)
    assert len(designs) == cfg.designs * cfg.select + cfg.motions * cfg.propose
    assert src.proposed[0] == cfg.motions * cfg.propose
    assert calls[0][:2] == (cfg.motions, cfg.propose) and calls[0][2] == calls[1][2]  # one seed per refresh
    reward = _rewards(designs, motions, cfg.generate_config(), _seed_int(cfg.seed, 0, _STREAM_NOISE))
    chosen = src.selected[0]
    for m in range(cfg.motions):
        want = sorted(np.argsort(-reward[:, m], kind="stable")[: cfg.designs].tolist())
        assert sorted(d for d, mm in chosen if mm == m) == want
    kept = sum(d >= cfg.designs * cfg.select for d, _ in chosen)
    assert src.stats["proposed_kept"] == kept and src.stats["proposed"] == cfg.motions * cfg.propose


@pytest.mark.skipif(not GENERATOR.exists(), reason="the shipped generator is not in this checkout")
def test_the_shipped_generators_proposals_are_designs_of_the_space_and_repeat():
    """ModelProposer samples the shipped generator: valid designs of the space, the same for the
    same seed (so a resumed run regenerates its buffer), and a refresh of a source using it
    equals a second source's."""
    from tt.guidance.proposer import ModelProposer, online_source

    cfg = OnlineConfig(**SMALL, propose=2, proposer=str(GENERATOR), propose_steps=2)
    a, b = online_source(cfg, device="cpu"), online_source(cfg, device="cpu")
    da, ma = a.draw(0)
    db, _ = b.draw(0)
    space = get_space("viperx")
    proposed = da[cfg.designs * cfg.select :]
    assert len(proposed) == a.proposed[0] >= 1
    for d, e in zip(proposed, db[cfg.designs * cfg.select :]):
        assert d == e
        space.model(d)  # builds: a design of the space
    ta, tb = a._refresh(0), b._refresh(0)
    for name in ta.static_values:
        assert torch.equal(ta.static_values[name], tb.static_values[name])
    for name in ta.step_values:
        assert torch.equal(ta.step_values[name], tb.step_values[name])
    assert torch.equal(ta.lengths, tb.lengths)
    with pytest.raises(ValueError, match="needs the robot task"):
        ModelProposer(str(GENERATOR.parent / "viperx_mini_dynamics.pt"), "viperx")(ma, 1, 0)
