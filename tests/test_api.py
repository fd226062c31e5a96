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


def test_save_motion_writes_what_motion_reads(tmp_path):
    """Arrays (one end effector, default orientation) and a Motion object round-trip through the
    motion file; reading places the start over the base and resamples to 50 Hz."""
    import numpy as np

    t = np.linspace(0.0, 1.0, 51)
    pos = np.stack([0.3 + 0.1 * np.sin(2 * np.pi * t), 0.05 * t, 0.2 + 0.05 * t], axis=1)
    written = tt.save_motion(tmp_path / "wave.npz", pos)
    back = tt.motion(tmp_path / "wave.npz")
    assert back.name == "wave" and back.steps == 51 and written.steps == 51
    np.testing.assert_allclose(back.pos[:, 0] - back.pos[0, 0], pos - pos[0], atol=1e-12)
    np.testing.assert_array_equal(back.pos[0, 0, :2], [0.0, 0.0])  # placed over the base, height kept
    assert back.pos[0, 0, 2] == pos[0, 2]
    np.testing.assert_array_equal(back.quat[:, 0], np.tile([1.0, 0.0, 0.0, 0.0], (51, 1)))
    tt.save_motion(tmp_path / "slow.npz", pos, dt=0.04, name="slow")
    slow = tt.motion(str(tmp_path / "slow.npz"))  # a string naming a file reads it too
    assert slow.name == "slow" and slow.steps == 101  # 2 s at 50 Hz
    toss = tt.motion("toss")
    tt.save_motion(tmp_path / "toss.npz", toss)
    again = tt.motion(tmp_path / "toss.npz")
    np.testing.assert_array_equal(again.pos, toss.pos)
    np.testing.assert_array_equal(again.quat, toss.quat)
    with pytest.raises(tt.TTError, match="not with a Motion"):
        tt.save_motion(tmp_path / "x.npz", toss, dt=0.01)
    with pytest.raises(tt.TTError, match="quat shape"):
        tt.save_motion(tmp_path / "x.npz", pos, np.ones((3, 4)))
    with pytest.raises(tt.TTError, match="norm"):
        tt.save_motion(tmp_path / "x.npz", pos, np.ones((51, 4)))
    assert not (tmp_path / "x.npz").exists()


def test_tokenize_and_detokenize_round_trip(tmp_path):
    """A design, a model and an MJCF file tokenize alike; detokenizing gives back the robot."""
    import mujoco
    import numpy as np

    space = tt.get_space("viperx")
    design = space.sample(1, seed=3)[0]
    model = space.model(design)
    emb = tt.tokenize(design)
    counts = {k: int(v[0]) for k, v in emb.tokens.counts().items()}
    assert counts == {k: int(v[0]) for k, v in tt.tokenize([model]).tokens.counts().items()}
    (tmp_path / "arm.xml").write_text(space.to_mjcf(design))
    assert counts == {k: int(v[0]) for k, v in tt.tokenize(tmp_path / "arm.xml").tokens.counts().items()}
    emb.tokens.save(tmp_path / "tokens.npz")
    for source in (emb, emb.tokens, tmp_path / "tokens.npz", str(tmp_path / "tokens.npz")):
        (result,) = tt.detokenize(source, model="back")
        assert result.ok, result.error
        assert 'model="back"' in result.xml
        assert (result.model.njnt, result.model.nu) == (model.njnt, model.nu)
        assert np.isclose(result.model.body_mass.sum(), model.body_mass.sum(), rtol=1e-5)
    back = mujoco.MjModel.from_xml_string(result.xml)
    assert back.nq == model.nq
    with pytest.raises(tt.TTError, match="no robots given"):
        tt.tokenize([])
    with pytest.raises(tt.TTError, match=r"robots\[0\] is a str"):
        tt.tokenize(["arm.xml"])
    with pytest.raises(tt.TTError, match="does not exist"):
        tt.tokenize(tmp_path / "nope.xml")


def test_dataset_info_and_train_reject_bad_input(tmp_path):
    with pytest.raises(tt.TTError):
        tt.dataset_info(tmp_path)  # an empty folder is no dataset
    with pytest.raises(tt.TTError, match="exactly one source of training data"):
        tt.train(None, tmp_path / "run")
    with pytest.raises(tt.TTError, match="exactly one source of training data"):
        tt.train(tmp_path, tmp_path / "run", online=True)
    with pytest.raises(tt.TTError, match="does not exist"):
        tt.train(tmp_path / "nope", tmp_path / "run")
    with pytest.raises(tt.TTError, match="online must be"):
        tt.train(None, tmp_path / "run", online=5)
    assert not (tmp_path / "run").exists()


def test_train_online_writes_a_checkpoint(tmp_path, single_thread):
    """`tt.train` with data=None trains on episodes simulated as it goes; the run seed seeds them."""
    from tt.dit.checkpoint import load_model

    online = dict(space="viperx", designs=4, motions=1, refresh_every=2, min_steps=20, max_motion_steps=40)
    run = tt.train(
        None, tmp_path / "run", online=online, size="tiny", steps=2, batch_size=4, device="cpu", progress=False
    )
    assert run.step == 2 and len(run.losses) == 2 and run.checkpoint.is_file()
    assert tmp_path / "run" in run.checkpoint.parents
    assert load_model(run.checkpoint, device="cpu").tasks == ("robot",)
