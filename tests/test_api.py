"""The Python API (`tt.api`, re-exported lazily by `import tt`): light to import, the CLI's
defaults, the learned methods' shipped checkpoint and critic, and the common path end to end."""

import inspect
import subprocess
import sys

import pytest
import typer.main

import tt
from tt import api
from tt.cli import app


def test_import_tt_loads_nothing_heavy():
    code = (
        "import sys, tt; heavy = [m for m in ('torch', 'warp', 'mujoco', 'numpy', 'tt.kernels', 'tt.api') "
        "if m in sys.modules]; print(heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]", f"`import tt` imported {out}"


def test_lazy_names_are_the_api():
    for name in tt._API:
        assert getattr(tt, name) is getattr(api, name), name
        assert getattr(api, name).__doc__, f"tt.{name} has no docstring"
    assert set(tt._API) <= set(tt.__all__) and set(tt._API) <= set(dir(tt))
    assert issubclass(tt.TTError, ValueError) and isinstance(tt.__version__, str)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        tt.nope  # noqa: B018


def _cli_defaults(command: str) -> dict:
    cmd = typer.main.get_command(app).commands[command]
    return {p.name: p.default for p in cmd.params}


@pytest.mark.parametrize(
    "command, function", [("optimize", api.optimize), ("validate", api.validate), ("predict", api.predict)]
)
def test_cli_and_api_share_their_defaults(command, function):
    """Every option the CLI command and its API function both have defaults to the same value."""
    cli = _cli_defaults(command)
    lib = {
        k: p.default
        for k, p in inspect.signature(function).parameters.items()
        if p.default is not inspect.Parameter.empty
    }
    shared = sorted(set(cli) & set(lib))
    assert "reward" in shared, shared
    assert {k: cli[k] for k in shared} == {k: lib[k] for k in shared}


def test_learned_methods_default_to_the_shipped_checkpoint_and_critic():
    """The library's default is the CLI's: the shipped generator ranked by the shipped critic
    (issue 52: `get_optimizer("zeroth", checkpoint=...)` used to rank by the model's own dynamics)."""
    from tt.dit.checkpoint import default_checkpoint, shipped_critic
    from tt.optimizers import get_optimizer, learned_defaults

    try:
        generator = default_checkpoint("viperx", task="robot")
    except FileNotFoundError:
        pytest.skip("no shipped ViperX checkpoint")
    critic = shipped_critic("viperx", generator)
    opt = get_optimizer("zeroth", space="viperx")
    assert opt.config.checkpoint == str(generator)
    assert opt.config.critic_checkpoint == (None if critic is None else str(critic))
    # The paper's joint critic, or a critic asked about the sampled tokens, gets no shipped critic.
    assert "critic_checkpoint" not in learned_defaults("zeroth", "viperx", {"critic": "joint"})
    assert "critic_checkpoint" not in learned_defaults("dgs", "viperx", {"critic_on": "tokens"})
    assert "critic_checkpoint" not in learned_defaults("cmaes-init-model", "viperx", {})
    assert learned_defaults("cmaes", "viperx", {"popsize": 8}) == {"popsize": 8}


def test_the_common_path():
    """Optimize, validate and roll out through the API; the motions are placed for the space once."""
    toss = tt.motion("toss")
    result = tt.optimize("viperx", [toss], "tracking", method="random", budget=4, seed=0)
    ev = tt.validate([result.best], ["toss"])
    assert ev.reward.shape == (1, 1) and ev.metrics["pos_err"].shape == (1, 1)
    assert ev.reward[0, 0] == pytest.approx(result.best_reward, rel=0.05, abs=1.0)  # Warp vs the oracle
    ro = tt.rollout(n=2, seed=1)
    assert ro.reward.shape == (2, 1)
    with pytest.raises(tt.TTError, match="no motion given"):
        tt.optimize("viperx", [])
    with pytest.raises(tt.TTError, match="controllers: ik, model"):
        tt.validate([result.best], [toss], controller="pid")


def test_motions_are_placed_for_a_space_once():
    from tt.api import _placed
    from tt.sim.motions import for_space

    quad = tt.get_space("quadruped")
    raw = tt.motion("toss")
    once = for_space([raw], quad.name)[0]
    assert (_placed([raw], quad.name)[0].pos == once.pos).all()
    assert (_placed([once], quad.name)[0].pos == once.pos).all()  # already placed: kept
