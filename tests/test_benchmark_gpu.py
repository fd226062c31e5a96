"""`benchmarks/gpu.py --device cpu --quick`: the one-shot GPU benchmark's code paths, small, on
the CPU, so the script is known to run before a GPU is at hand."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_quick_cpu_run_measures_every_section(tmp_path):
    out = tmp_path / "gpu.md"
    res = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "gpu.py"), "--device", "cpu", "--quick", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    rows = [json.loads(line[len("RESULT ") :]) for line in res.stdout.splitlines() if line.startswith("RESULT ")]
    assert not [r for r in rows if "error" in r], rows
    by = {}
    for r in rows:
        by.setdefault(r["section"], []).append(r)
    assert set(by) == {"tests", "rollout", "training", "sampling", "online"}
    # The CUDA tests are skipped on the CPU (with their reason), and the run says so.
    assert by["tests"][0]["exit"] == 0 and "skipped" in by["tests"][0]["summary"]
    # Both backends, graphs on and off, measured at least once; rates are positive numbers.
    assert {(r["backend"], r["graph"]) for r in by["rollout"]} == {
        ("warp", True),
        ("warp", False),
        ("mjwarp", True),
        ("mjwarp", False),
    }
    assert all(r["world_steps_per_s"] > 0 for r in by["rollout"])
    assert by["training"][0]["samples_per_s"] > 0 and by["sampling"][0]["seconds"] > 0
    assert by["online"][0]["steps_per_s"] > 0 and by["online"][0]["refreshes"] >= 1
    text = out.read_text()
    for heading in ("## tests", "## rollout", "## training", "## sampling", "## online", "load average at start"):
        assert heading in text
    assert re.search(r"\| warp \(tt's fused kernels\) \| on \| [0-9.e+-]+ M", text)
