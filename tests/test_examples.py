"""The examples run, write only where they are told, and show what they claim.

`examples/quickstart.py` optimizes a ViperX design for the toss with Random and CMA-ES; on the
same seed and budget its Random winner is the one `tt optimize --method random` returns. The
motion-file, MJCF, dataset and training examples each run as a researcher would run them
(`python examples/X.py --out DIR`), and their files are checked here.
"""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_example(name: str, *args, cwd: Path, timeout: int = 300) -> str:
    """Run examples/`name` with `args` in `cwd`; its stdout (the run must succeed)."""
    run = subprocess.run(
        [sys.executable, str(ROOT / "examples" / name), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    return run.stdout


def test_every_example_is_tested():
    tested = set(re.findall(r"run_example\(\s*\"(\w+\.py)\"", Path(__file__).read_text()))
    assert {p.name for p in (ROOT / "examples").glob("*.py")} <= tested


def test_quickstart_gives_the_cli_winner(tmp_path):
    out = tmp_path / "quickstart.json"
    stdout = run_example("quickstart.py", "--budget", 8, "--seed", 0, "--json", out, cwd=tmp_path)
    assert "winner:" in stdout and "random" in stdout and "cmaes" in stdout, stdout
    cli_json = tmp_path / "cli.json"
    cli = subprocess.run(
        [
            sys.executable,
            "-m",
            "tt.cli",
            "optimize",
            "--space",
            "viperx",
            "--motion",
            "toss",
            "--reward",
            "tracking",
            "--method",
            "random",
            "--budget",
            "8",
            "--seed",
            "0",
            "--json",
            str(cli_json),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert cli.returncode == 0, cli.stdout + cli.stderr
    example, command = json.loads(out.read_text())["random"], json.loads(cli_json.read_text())
    assert example["design"] == command["design"]
    assert example["objective"] == command["objective"]


def test_motion_file(tmp_path):
    """The edited toss is written as a motion file tt reads back at 50 Hz, and the CMA-ES design
    beats the nominal ViperX on it on the oracle."""
    import tt

    out = run_example("motion_file.py", "--out", tmp_path / "out", cwd=tmp_path)
    motion = tt.motion(tmp_path / "out" / "there_and_back.npz")
    assert motion.name == "there_and_back" and motion.steps == 304, out  # 406 samples 0.015 s apart
    toss = tt.motion("toss")
    assert abs(motion.pos[0, 0] - toss.pos[0, 0]).max() < 1e-12  # starts where the toss starts
    rows = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(nominal|cmaes)\s+([-\d.]+)", out, re.M)}
    assert set(rows) == {"nominal", "cmaes"} and rows["cmaes"] > rows["nominal"], out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing written beside it


def test_mjcf_tokens_round_trip(tmp_path):
    """The hand-written arm comes back from its RoboTokens with the same joints, actuators and
    mass, and its end effector within 1 micrometre at random joint angles."""
    import mujoco
    import numpy as np

    out = run_example("mjcf_tokens.py", "--out", tmp_path, cwd=tmp_path)
    worst = float(re.search(r"largest difference ([-+.\de]+) m", out).group(1))
    assert worst < 1e-6, out
    a = mujoco.MjModel.from_xml_path(str(tmp_path / "arm.xml"))
    b = mujoco.MjModel.from_xml_path(str(tmp_path / "arm_rebuilt.xml"))
    assert (a.njnt, a.nu) == (b.njnt, b.nu) == (3, 3)
    np.testing.assert_allclose(b.body_mass.sum(), a.body_mass.sum(), rtol=1e-6)
    np.testing.assert_allclose(b.jnt_range, a.jnt_range, atol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm.xml", "arm_rebuilt.xml", "arm_tokens.npz"]


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """examples/small_dataset.py's dataset (8 designs x 2 episodes) and its stdout."""
    tmp = tmp_path_factory.mktemp("dataset")
    out = run_example("small_dataset.py", "--out", tmp / "small", cwd=tmp)
    return tmp / "small", out


def test_small_dataset(small_dataset):
    """The dataset holds every episode of 8 designs x 2, complete, and a second call resumes it."""
    import tt

    path, out = small_dataset
    info = tt.dataset_info(path)
    assert info["space"] == "viperx" and info["complete"] and info["shards"] == 2
    assert info["designs"] == 8 and info["episodes_generated"] == 16 and 0 < info["episodes"] <= 16
    assert info["length"]["max"] <= 60 and info["length"]["min"] >= 20  # cut at 60 steps, kept from 20
    assert "nothing to do, every shard was already complete" in out, out
    assert f"{info['episodes']} episodes kept of 16" in out, out


def test_train_small(small_dataset, tmp_path):
    """A tiny robot+dynamics model trains on the example dataset, its checkpoint loads, and the
    design it proposes is a valid ViperX design."""
    import tt
    from tt.dit.checkpoint import load_model
    from tt.sim.designs import load_designs

    path, _ = small_dataset
    out = run_example("train_small.py", "--out", tmp_path, "--data", path, "--steps", 10, cwd=tmp_path)
    assert "trained 10 steps" in out, out
    checkpoint = Path(re.search(r"checkpoint: (\S+)", out).group(1))
    assert checkpoint.is_file() and tmp_path in checkpoint.parents
    trained = load_model(checkpoint, device="cpu")
    assert set(trained.tasks) == {"robot", "dynamics"}
    (design,) = load_designs(tmp_path / "best.json")
    space = tt.get_space("viperx")
    assert design.space == "viperx" and space.model(design).nu > 0  # it builds and compiles
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best.json", "run"]
