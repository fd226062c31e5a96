"""The layering of DESIGN.md holds: app > viz > guidance > baselines > dit > tokens > sim > kernels.

import-linter's `layers` contract in pyproject.toml states it. grimp (import-linter's graph
builder) finds a package's modules by walking its folder, and tt's subpackages live in
root folders mapped into `tt` by setuptools' package-dir, so the check lays the sources out
as one `tt` tree in a temporary folder (the layout an installed wheel has) and runs
lint-imports there.
"""

import ast
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _lay_out(dest: Path) -> Path:
    """Copy every package's Python files to dest/<package path>; return dest."""
    package_dir = _pyproject()["tool"]["setuptools"]["package-dir"]
    for package, folder in package_dir.items():
        target = dest.joinpath(*package.split("."))
        target.mkdir(parents=True, exist_ok=True)
        for f in (ROOT / folder).glob("*.py"):
            shutil.copy(f, target / f.name)
    shutil.copy(ROOT / "pyproject.toml", dest / "pyproject.toml")
    return dest


def _lint(tree: Path) -> subprocess.CompletedProcess:
    pytest.importorskip("importlinter", reason="import-linter is not installed (pip install -e '.[test]')")
    # This interpreter runs import-linter's command (no console script or shim needed); the
    # laid-out tree comes first on its path, ahead of the editable install's mapping.
    run = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run(
        [sys.executable, "-c", run, str(tree / "pyproject.toml"), "--no-cache"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_layers_contract_is_kept(tmp_path):
    res = _lint(_lay_out(tmp_path))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "1 kept, 0 broken" in res.stdout, res.stdout


def test_contract_sees_imports_inside_functions(tmp_path):
    """A lazy upward import (inside a function body) breaks the contract: the check is not blind to them."""
    tree = _lay_out(tmp_path)
    victim = tree / "tt" / "kernels" / "errors.py"
    victim.write_text(victim.read_text() + "\n\ndef _lazy():\n    from tt.viz import scene  # noqa: F401\n")
    res = _lint(tree)
    assert res.returncode != 0, res.stdout
    assert "tt.kernels.errors -> tt.viz.scene" in res.stdout, res.stdout


def test_no_layer_imports_the_root_package():
    """`tt` itself re-exports from below, and sits in no layer of the contract: no module under
    the app may import it (``import tt`` / ``from tt import X``), lazily or not."""
    package_dir = _pyproject()["tool"]["setuptools"]["package-dir"]
    offenders = []
    for package, folder in package_dir.items():
        if package == "tt":
            continue
        for f in (ROOT / folder).glob("*.py"):
            for node in ast.walk(ast.parse(f.read_text())):
                if isinstance(node, ast.Import) and any(a.name == "tt" for a in node.names):
                    offenders.append(f"{f.relative_to(ROOT)}:{node.lineno}")
                if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module == "tt":
                    offenders.append(f"{f.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, offenders
