"""benchmarks/sim.py --quick: the speed benchmark's measurement and report code runs end to end
(tiny sizes, a short motion, no CLI subprocesses), and its report states what it measured. The
script runs as a reader runs it, in its own process."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "sim.py"


@pytest.mark.slow  # ~30 s alone on an idle 2-core machine: a fresh process loads the 3 ViperX kernel modules
def test_quick_benchmark_writes_every_table(tmp_path):
    out = tmp_path / "sim.md"
    res = subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--cli-n", "0", "--threads", "1", "2", "--out", str(out)],
        cwd=BENCH.parents[1],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    text = out.read_text()
    for heading in ("## World-steps per second", "## Ratios", "## Thread scaling", "## Setup"):
        assert heading in text, heading
    assert "load average (1, 5, 15 min)" in text and "PROJECTION, not measured" in text
    # One row per backend and thread count, a measured rate in every cell.
    for row in ("oracle (MuJoCo C + mink", "mujoco.rollout (C, ", "1 thread |", "2 threads |"):
        line = next(line for line in text.splitlines() if row in line)
        cells = line.strip("|").split("|")[1:]
        assert len(cells) == 2 and all(re.fullmatch(r" [\d.]+( [kM])? ", c) for c in cells), line
