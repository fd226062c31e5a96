"""The tree is clean under ruff, as pyproject.toml's [tool.ruff] configures it: formatted
(`ruff format`) and lint-free (`ruff check`: pycodestyle, pyflakes, import order; 120 columns).
Fix a failure with ``ruff format . && ruff check --fix .`` at the repository root."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _ruff(*args: str) -> subprocess.CompletedProcess:
    try:
        import ruff  # noqa: F401  (the test extra pins it; its binary runs as `python -m ruff`)
    except ImportError:
        pytest.fail("ruff is not installed: pip install -e '.[test]' -c constraints.txt")
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args, "--no-cache", "."], cwd=ROOT, capture_output=True, text=True
    )


def test_ruff_format():
    res = _ruff("format", "--check")
    assert res.returncode == 0, f"`ruff format --check` fails; run `ruff format .`:\n{res.stdout}{res.stderr}"


def test_ruff_check():
    res = _ruff("check")
    assert res.returncode == 0, (
        f"`ruff check` fails; run `ruff check --fix .` and fix the rest:\n{res.stdout}{res.stderr}"
    )
