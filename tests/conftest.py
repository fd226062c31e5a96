"""Fixtures shared by the test modules."""

import pytest


@pytest.fixture
def tt_cli():
    """Run the ``tt`` command line in-process: tt_cli(args) -> (exit code, stdout + stderr)."""
    from typer.testing import CliRunner

    from tt.cli import app

    def run(args: list[str]) -> tuple[int, str]:
        res = CliRunner().invoke(app, args)
        return res.exit_code, res.output + (res.stderr if res.stderr_bytes is not None else "")

    return run
