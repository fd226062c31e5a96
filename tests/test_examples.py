"""The examples run, and agree with the CLI.

`examples/quickstart.py` optimizes a ViperX design for the toss with Random and CMA-ES; on the
same seed and budget its Random winner is the one `tt optimize --method random` returns.
"""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_quickstart_gives_the_cli_winner(tmp_path):
    out = tmp_path / "quickstart.json"
    run = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "quickstart.py"), "--budget", "8", "--seed", "0", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "winner:" in run.stdout and "random" in run.stdout and "cmaes" in run.stdout, run.stdout
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
