"""`tt train --config selection.designs=N`: every checkpoint scored on held-out designs as `tt predict`
uses it, the best kept as RUN/best.pt; the bookkeeping checked against `score_designs` run
directly on the same checkpoints."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from tt.cli import app
from tt.selection import SELECTION_SEED, CheckpointSelector, SelectionConfig, SelectionRow

pytestmark = pytest.mark.usefixtures("single_thread")

SPACE = "viperx-nominal"
CONFIG = SelectionConfig(designs=4, motions=2, num_steps=2, device="cpu")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny dynamics model trained 4 steps, a checkpoint every 2, each scored by the selector."""
    from tt.dit.online import OnlineConfig
    from tt.dit.train import TrainConfig, train

    out = tmp_path_factory.mktemp("select") / "run"
    cfg = TrainConfig(
        out=str(out),
        task="dynamics",
        size="tiny",
        steps=4,
        batch_size=4,
        warmup_steps=1,
        device="cpu",
        checkpoint_every=2,
        keep_checkpoints=5,
        prediction="x0",
        online=OnlineConfig(
            space=SPACE, designs=4, motions=1, refresh_every=100, buffer=1, min_steps=8, absorbing=True
        ),
    )
    selector = CheckpointSelector(out, CONFIG)
    calls = []

    def on_checkpoint(step, path):
        calls.append((step, path))
        selector(step, path)

    train(cfg, on_checkpoint=on_checkpoint)
    return out, selector, calls


def test_every_checkpoint_is_scored_as_score_designs_scores_it(run):
    from tt.dit.checkpoint import load_model
    from tt.ladder import heldout_designs, score_designs, validation_motions

    out, selector, calls = run
    assert [s for s, _ in calls] == [2, 4]
    with (out / "selection.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [2, 4]
    designs = heldout_designs(SPACE, CONFIG.designs, seed=SELECTION_SEED)
    motions = validation_motions(SPACE, CONFIG.motions)
    for (step, path), row in zip(calls, rows):
        direct = score_designs(load_model(path), designs, motions, CONFIG.reward, num_steps=CONFIG.num_steps)
        within = float(np.mean([r if math.isfinite(r) else 0.0 for r in direct.within]))  # no spread counts 0
        for key, want in (("within_r", within), ("pooled_r", direct.pooled)):
            got = float(row[key])
            assert (math.isnan(got) and math.isnan(want)) or got == pytest.approx(want, abs=1e-5), (step, key)


def test_best_checkpoint_is_a_copy_of_the_best_row(run):
    out, selector, calls = run
    best = selector.best
    assert best is not None
    assert best.within_r == max(r.within_r for r in selector.rows if math.isfinite(r.within_r))
    source = dict(calls)[best.step]
    assert (out / "best.pt").read_bytes() == source.read_bytes()
    meta = json.loads((out / "best.json").read_text())
    assert meta["step"] == best.step and meta["checkpoint"] == source.name
    assert (out / "selection.png").stat().st_size > 0


def test_a_resumed_selector_reads_the_run_back(run):
    out, selector, _ = run
    again = CheckpointSelector(out, CONFIG)
    assert again.rows == [
        SelectionRow(r.step, float(f"{r.within_r:.6g}"), float(f"{r.pooled_r:.6g}"), float(f"{r.seconds:.3f}"))
        for r in selector.rows
    ]


def test_best_skips_nan_and_prefers_the_earlier_of_a_tie(tmp_path):
    sel = CheckpointSelector(tmp_path)
    sel.rows = [
        SelectionRow(500, 0.4, 0.3, 1.0),
        SelectionRow(1000, float("nan"), 0.9, 1.0),
        SelectionRow(1500, 0.4, 0.5, 1.0),
        SelectionRow(2000, 0.2, 0.6, 1.0),
    ]
    assert sel.best.step == 500
    sel.rows = [SelectionRow(500, float("nan"), 0.1, 1.0)]
    assert sel.best is None


def test_selection_designs_are_not_the_ladders_report_designs():
    from tt.ladder import heldout_designs

    chosen_on = heldout_designs("viperx", 8, seed=SELECTION_SEED)
    reported_on = heldout_designs("viperx", 8)
    assert all(
        not np.allclose(a.continuous, b.continuous)
        for a in chosen_on
        for b in reported_on
        if len(a.continuous) == len(b.continuous)
    )


def test_a_foreign_csv_is_refused(tmp_path):
    (tmp_path / "selection.csv").write_text("step,loss\n1,0.5\n")
    with pytest.raises(ValueError, match="selection.csv has columns"):
        CheckpointSelector(tmp_path)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--config", "selection.designs=2"], "selection.designs = 2; a correlation needs at least 3 designs"),
        (["--config", "selection.designs=4", "--task", "control"], "needs a task with robot or dynamics"),
        (["--config", "selection.reward=speed"], "selection.reward = 'speed' is not a reward"),
        (["--config", "selection.motions=0"], "selection.motions = 0; must be an integer >= 1"),
        (["--config", "selection.samples=x"], "selection.samples = 'x' is not of type int"),
    ],
)
def test_bad_selection_flags_fail_clearly(tmp_path, args, message):
    r = CliRunner().invoke(
        app, ["train", "--online", "--task", "dynamics", "--steps", "1", "--out", str(tmp_path / "r"), *args]
    )
    assert r.exit_code == 2
    assert message in r.output


def test_other_settings_are_refused_and_a_fresh_run_starts_over(tmp_path):
    sel = CheckpointSelector(tmp_path, CONFIG)
    sel.rows = [SelectionRow(2, 0.5, 0.4, 1.0)]
    sel._write()
    (tmp_path / "best.pt").write_bytes(b"old")
    (tmp_path / "best.json").write_text(json.dumps({"step": 2}))
    assert CheckpointSelector(tmp_path, CONFIG).rows == sel.rows  # the same settings read back
    other_device = dataclasses.replace(CONFIG, device="cuda" if CONFIG.device != "cuda" else "cpu")
    assert CheckpointSelector(tmp_path, other_device).rows == sel.rows  # the device alone may change
    with pytest.raises(ValueError, match="do not compare"):
        CheckpointSelector(tmp_path, SelectionConfig(designs=5, motions=2, num_steps=2, device="cpu"))
    fresh = CheckpointSelector(tmp_path, SelectionConfig(designs=5), fresh=True)
    assert fresh.rows == [] and fresh.best is None
    assert (tmp_path / "selection.csv").exists()  # removed by start_over, which train calls holding the run's lock
    fresh.start_over()
    assert not any((tmp_path / n).exists() for n in ("best.pt", "best.json", "selection.csv", "selection.json"))
