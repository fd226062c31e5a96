"""The shipped-checkpoint lookup, `tt optimize`'s use of it, and `tt demo` with and without a model.

The demo's learned rows are checked end to end with a tiny trained checkpoint (2 optimizer
steps on toy episodes) and a stand-in decoder: one that turns every candidate into the
nominal ViperX (so both learned winners are that design and the oracle must report the
nominal's tracking for them), and one that decodes nothing (the demo reports the method
without a design and keeps the others' rows).
"""

from __future__ import annotations

import json
import math

import pytest
import torch
from typer.testing import CliRunner

from tt.dit import checkpoint as ckpt
from tt.dit.toy import toy_episodes
from tt.dit.train import TrainConfig, train
from tt.guidance import zeroth
from tt.guidance.zeroth import Decoded

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


def test_default_checkpoint_prefers_the_largest_model_and_names_what_exists(tmp_path):
    for name in ("viperx_mini.pt", "viperx_small.pt", "quadruped.pt", "README.md", "viperx_notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert ckpt.default_checkpoint("viperx", tmp_path) == tmp_path / "viperx_small.pt"
    assert ckpt.default_checkpoint("quadruped", tmp_path) == tmp_path / "quadruped.pt"
    assert list(ckpt.shipped_checkpoints(tmp_path)) == ["quadruped", "viperx"]
    with pytest.raises(ckpt.NoCheckpointError, match=r"'bimanual'.*quadruped \(quadruped.pt\), viperx"):
        ckpt.default_checkpoint("bimanual", tmp_path)
    with pytest.raises(FileNotFoundError, match="spaces with one: none"):
        ckpt.default_checkpoint("viperx", tmp_path / "missing")
    # A task specialist serves its task first and never stands in for the generalist.
    (tmp_path / "viperx_mini_control.pt").write_bytes(b"")
    assert ckpt.default_checkpoint("viperx", tmp_path, task="control") == tmp_path / "viperx_mini_control.pt"
    assert ckpt.default_checkpoint("viperx", tmp_path) == tmp_path / "viperx_small.pt"
    assert ckpt.default_checkpoint("viperx", tmp_path, task="robot") == tmp_path / "viperx_small.pt"
    (tmp_path / "aloha_mini_control.pt").write_bytes(b"")
    with pytest.raises(
        ckpt.NoCheckpointError, match="'aloha' ships only checkpoints of other tasks.*aloha_mini_control.pt"
    ):
        ckpt.default_checkpoint("aloha", tmp_path)
    with pytest.raises(ValueError, match="task 'walk' does not exist"):
        ckpt.default_checkpoint("viperx", tmp_path, task="walk")
    # The shipped critic: the dynamics specialist, beside the shipped generalist only.
    assert ckpt.shipped_critic("viperx", tmp_path / "viperx_small.pt", tmp_path) is None  # no specialist yet
    (tmp_path / "viperx_mini_dynamics.pt").write_bytes(b"")
    assert ckpt.shipped_critic("viperx", tmp_path / "viperx_small.pt", tmp_path) == tmp_path / "viperx_mini_dynamics.pt"
    assert ckpt.shipped_critic("viperx", tmp_path / "viperx_mini.pt", tmp_path) is None  # not the default generalist
    assert ckpt.shipped_critic("viperx", tmp_path / "elsewhere.pt", tmp_path) is None
    assert ckpt.shipped_critic("quadruped", tmp_path / "quadruped.pt", tmp_path) is None
    assert ckpt.shipped_critic("bimanual", tmp_path / "x.pt", tmp_path) is None
    # A shipped generator (robot specialist) is what the learned optimizers sample, ranked by the same critic.
    (tmp_path / "viperx_mini_robot.pt").write_bytes(b"")
    assert ckpt.default_checkpoint("viperx", tmp_path, task="robot") == tmp_path / "viperx_mini_robot.pt"
    assert ckpt.default_checkpoint("viperx", tmp_path) == tmp_path / "viperx_small.pt"
    assert (
        ckpt.shipped_critic("viperx", tmp_path / "viperx_mini_robot.pt", tmp_path)
        == tmp_path / "viperx_mini_dynamics.pt"
    )
    assert ckpt.shipped_critic("viperx", tmp_path / "viperx_small.pt", tmp_path) == tmp_path / "viperx_mini_dynamics.pt"
    # A space that ships a generator and a critic but no generalist (ALOHA) pairs them too.
    for name in ("aloha_mini_robot.pt", "aloha_mini_dynamics.pt"):
        (tmp_path / name).write_bytes(b"")
    assert (
        ckpt.shipped_critic("aloha", tmp_path / "aloha_mini_robot.pt", tmp_path) == tmp_path / "aloha_mini_dynamics.pt"
    )
    assert ckpt.shipped_critic("aloha", tmp_path / "aloha_mini_control.pt", tmp_path) is None
    # The default folder is the repository's checkpoints/ (tt/checkpoints when installed).
    assert (
        ckpt.shipped_folder().name == "checkpoints"
        and ckpt.shipped_folder().parent == ckpt.Path(ckpt.__file__).resolve().parents[1]
    )


def test_optimize_without_checkpoint_fails_clearly_when_none_is_shipped(tmp_path, monkeypatch):
    from tt.cli import app

    monkeypatch.setattr(ckpt, "shipped_folder", lambda: tmp_path)
    result = CliRunner().invoke(app, ["optimize", "--method", "zeroth", "--motion", "toss", "--budget", "2"])
    assert result.exit_code == 2
    assert "no shipped DiT checkpoint for design space 'viperx'" in result.output


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """A tiny DiT trained for 2 steps on toy RoboToken episodes, saved as `tt train` saves it."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("run")
    episodes = toy_episodes(episodes=8, steps=16, seed=0, schema_counts=COUNTS)
    train(
        TrainConfig(
            out=str(out),
            task="robot",
            size="tiny",
            steps=2,
            batch_size=4,
            checkpoint_every=2,
            device="cpu",
            warmup_steps=1,
        ),
        episodes=episodes,
    )
    torch.set_num_threads(threads)
    return ckpt.latest_checkpoint(out)


class NominalDecoder:
    """Every candidate decodes to the space's nominal design."""

    def __init__(self, space, table=None):
        self.space = space

    def __call__(self, batch, index):
        return Decoded(self.space.nominal(), None, 0.0)


class NoDecoder(NominalDecoder):
    def __call__(self, batch, index):
        return Decoded(None, "no discrete choice of space 'viperx' has this token structure")


def _demo(tmp_path, monkeypatch, decoder, checkpoint, methods):
    from tt.demo import DemoConfig, run_demo
    from tt.tokens import design_fit

    monkeypatch.setattr(zeroth, "DesignDecoder", decoder)
    monkeypatch.setattr(design_fit, "CandidateTable", lambda space: None)  # the stand-in decoders need no table
    lines: list[str] = []
    config = DemoConfig(budget=4, samples=2, num_steps=2, methods=methods, checkpoint=checkpoint, out=tmp_path / "demo")
    rows = run_demo(config, echo=lines.append)
    return rows, lines, json.loads((tmp_path / "demo" / "demo.json").read_text())


def test_demo_runs_the_learned_methods_and_validates_their_winners(tmp_path, monkeypatch, tiny_checkpoint):
    from tt.baselines.evaluate import evaluate_designs
    from tt.report import summary_row
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, get_motion

    rows, lines, saved = _demo(
        tmp_path, monkeypatch, NominalDecoder, tiny_checkpoint, ("random", "zeroth", "dgs", "zeroth-sim")
    )
    assert [r["name"] for r in rows] == ["Random", "Zeroth", "DGS", "Zeroth + sim"]
    assert any(line.startswith(f"checkpoint {tiny_checkpoint}") for line in lines)
    want = summary_row(
        evaluate_designs(
            [get_space("viperx").nominal()], for_space([get_motion("toss")], "viperx"), "tracking", backend="mujoco"
        ).metrics,
        0,
    )
    for row in rows[1:]:
        # The model-only methods run no rollout; the hybrid checks its 2 samples on the motion.
        assert row["rollouts"] == (2 if row["name"] == "Zeroth + sim" else 0) and row["seconds"] > 0
        for key in ("pos_err", "orn_err", "survival_pct", "reward"):
            assert row[key] == pytest.approx(want[key], rel=1e-6), key
    assert math.isfinite(rows[0]["reward"])
    assert saved["designs"]["Zeroth"] == get_space("viperx").to_dict(get_space("viperx").nominal())
    assert (tmp_path / "demo" / "demo.html").is_file()


def test_demo_reports_a_learned_method_without_a_design_and_keeps_the_others(tmp_path, monkeypatch, tiny_checkpoint):
    rows, lines, _ = _demo(tmp_path, monkeypatch, NoDecoder, tiny_checkpoint, ("random", "zeroth"))
    assert [r["name"] for r in rows] == ["Random", "Zeroth"]
    assert "pos_err" in rows[0] and "pos_err" not in rows[1]
    assert rows[1]["note"].startswith("no design")
    assert any("[zeroth] no design: none of the 2 candidates decoded" in line for line in lines)


def test_demo_without_a_shipped_checkpoint_says_so_and_runs_the_baselines(tmp_path, monkeypatch):
    from tt.demo import DemoConfig, run_demo

    monkeypatch.setattr(ckpt, "shipped_folder", lambda: tmp_path / "none")
    lines: list[str] = []
    rows = run_demo(DemoConfig(budget=4, methods=("random", "zeroth", "dgs"), out=tmp_path / "demo"), echo=lines.append)
    assert [r["name"] for r in rows] == ["Random"]
    assert any(
        line.startswith(
            "the learned methods (Zeroth-Order, Self-Guidance, Zeroth + sim) skipped: no shipped DiT checkpoint"
        )
        for line in lines
    )


def test_aloha_demo_shows_the_original_against_the_optimized_designs(tmp_path, monkeypatch):
    """tt demo --space aloha: the paper's ALOHA experiment on the first validation fling for the
    velocity reward, without learned methods where no checkpoint ships; the original ALOHA
    (the space's nominal design) is the table's first row, validated as tt validate would, and
    the scene's first robot; each winner's change from it is printed."""
    from tt.baselines.evaluate import evaluate_designs
    from tt.demo import DemoConfig, run_demo
    from tt.report import summary_row
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, get_motion

    monkeypatch.setattr(ckpt, "shipped_folder", lambda: tmp_path / "none")
    config = DemoConfig(space="aloha", budget=16, out=tmp_path / "demo")
    assert (config.motion, config.reward, config.original) == ("bi_fling:100", "tracking_velocity", True)
    assert DemoConfig().original is False and DemoConfig(space="aloha", reward="tracking").reward == "tracking"
    lines: list[str] = []
    rows = run_demo(config, echo=lines.append)
    assert [r["name"] for r in rows] == ["Original ALOHA", "Random", "CMA-ES"]
    assert any(
        line.startswith("the learned methods (Zeroth-Order, Self-Guidance, Zeroth + sim) skipped") for line in lines
    )
    nominal = get_space("aloha").nominal()
    fling = for_space([get_motion("bi_fling:100")], "aloha")
    want = summary_row(evaluate_designs([nominal], fling, "tracking_velocity", backend="mujoco").metrics, 0)
    for key in ("pos_err", "max_joint_speed", "velocity", "reward"):
        assert rows[0][key] == pytest.approx(want[key], rel=1e-6), key
    for row in rows[1:]:
        assert math.isfinite(row["max_joint_speed"]) and row["rollouts"] == 16
        assert any(line.startswith(f"{row['name']} against Original ALOHA: position error") for line in lines)
    saved = json.loads((tmp_path / "demo" / "demo.json").read_text())
    assert saved["reward"] == "tracking_velocity" and list(saved["designs"])[0] == "Original ALOHA"
    assert saved["designs"]["Original ALOHA"] == get_space("aloha").to_dict(nominal)
    assert (tmp_path / "demo" / "demo.html").is_file()


def test_optimize_uses_the_shipped_checkpoint_by_default(tmp_path, monkeypatch, tiny_checkpoint):
    from tt.cli import app

    (tmp_path / "viperx_tiny.pt").symlink_to(tiny_checkpoint)
    monkeypatch.setattr(ckpt, "shipped_folder", lambda: tmp_path)
    monkeypatch.setattr(zeroth, "DesignDecoder", NominalDecoder)
    out = tmp_path / "result.json"
    result = CliRunner().invoke(
        app,
        [
            "optimize",
            "--method",
            "zeroth",
            "--motion",
            "toss",
            "--config",
            "samples=2",
            "--num-steps",
            "2",
            "--json",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    saved = json.loads(out.read_text())
    assert saved["method"] == "zeroth" and saved["info"]["samples"] == 2 and saved["info"]["num_steps"] == 2
    assert saved["validated"]["survival_pct"] == 100.0


def test_demo_cli_runs_the_methods_asked_for(tmp_path):
    """tt demo --config methods=[...]: only those run (samples, num_steps, checkpoint, seed and
    device are DemoConfig's keys too); an unknown method or key is refused naming the valid ones."""
    from tt.cli import app

    out = tmp_path / "demo"
    args = ["demo", "--budget", "4", "--out", str(out), "--config", 'methods=["random"]', "--config", "seed=2"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    saved = json.loads((out / "demo.json").read_text())
    assert [r["name"] for r in saved["rows"]] == ["Random"] and saved["budget"] == 4
    result = CliRunner().invoke(app, ["demo", "--config", 'methods=["random", "nope"]', "--out", str(out)])
    assert result.exit_code != 0 and "unknown methods ['nope']" in result.output
    result = CliRunner().invoke(app, ["demo", "--config", "steps=3", "--out", str(out)])
    assert result.exit_code != 0 and "valid keys: " in result.output and "num_steps" in result.output
