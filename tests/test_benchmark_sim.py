"""benchmarks/sim.py --quick: the speed benchmark's measurement and report code runs end to end
(tiny sizes, a short motion, no CLI subprocesses), and its report states what it measured."""

import importlib.util
import re
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "sim.py"


@pytest.mark.slow  # ~30 s alone on an idle 2-core machine: a fresh process loads the 3 ViperX kernel modules
def test_quick_benchmark_writes_every_table(tmp_path):
    spec = importlib.util.spec_from_file_location("tt_bench_sim", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "sim.md"
    bench.main(["--quick", "--cli-n", "0", "--threads", "1", "2", "--out", str(out)])
    text = out.read_text()
    for heading in ("## World-steps per second", "## Ratios", "## Thread scaling", "## Setup"):
        assert heading in text, heading
    assert "load average (1, 5, 15 min)" in text and "PROJECTION, not measured" in text
    # One row per backend and thread count, a measured rate in every cell.
    for row in ("oracle (MuJoCo C + mink", "mujoco.rollout (C, ", "1 thread |", "2 threads |"):
        line = next(line for line in text.splitlines() if row in line)
        cells = line.strip("|").split("|")[1:]
        assert len(cells) == 2 and all(re.fullmatch(r" [\d.]+( [kM])? ", c) for c in cells), line
