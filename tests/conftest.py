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


@pytest.fixture
def single_thread():
    """torch on one thread for the test (tiny models run fastest so, and stay fast when other
    jobs share the cores); the previous setting is restored after it."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
