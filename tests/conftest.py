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


def _cuda_missing() -> str | None:
    """Why 'cuda:0' cannot run tt here (None: it can). tt's kernels need Warp to see the GPU
    and its episodes and models need torch to (the rollout hands Warp arrays to torch)."""
    import torch
    import warp as wp

    if not wp.is_cuda_available():
        return "no CUDA device: Warp sees none (wp.is_cuda_available() is False)"
    if not torch.cuda.is_available():
        return f"no CUDA device for torch {torch.__version__} (a CPU build, or no driver)"
    return None


@pytest.fixture(params=["cpu", pytest.param("cuda:0", marks=pytest.mark.gpu)])
def device(request) -> str:
    """The device a kernel, rollout, tokenizer, reward or DiT test runs on: 'cpu', and
    'cuda:0' (marked `gpu`: `python -m pytest -m gpu` runs that half; without a GPU it shows
    as skipped with the reason). Warp's and MuJoCo-Warp's suites parametrise so too."""
    if request.param.startswith("cuda"):
        reason = _cuda_missing()
        if reason is not None:
            pytest.skip(reason)
    return request.param
