"""The quadruped in the optimizers and the oracle's episode ends: CMA-ES against Random on a
small fixed problem, and termination at the paper's 0.8 m position error (not the arms' 0.5 m).

References: the oracle (MuJoCo C + mink whole-body controller, `tt.sim.validate`) for every
rollout; the paper's termination rule (appendix, "an episode is terminated if the robot falls
over ... or if eps_p exceeds ... 80cm for the quadruped") for the episode ends; Random search
on the same problem and seed for CMA-ES. Falls (base height and tilt) are tested in
tests/test_wbc.py.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from tt.baselines import CMAES, Problem
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardInputs, get_reward, metrics
from tt.sim.validate import oracle_rollout
from tt.sim.wbc import WBCConfig


@pytest.fixture(scope="module")
def space():
    return get_space("quadruped")


def _rising(model: mujoco.MjModel, steps: int = 100, height: float = 1.5) -> Motion:
    """From the home end-effector pose straight up by `height` [m] over `steps` control steps,
    orientation held: the robot keeps standing while the target leaves its reach."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_kinematics(model, data)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, data.site("ee_0").xmat)
    path = data.site("ee_0").xpos + np.outer(np.linspace(0.0, height, steps), [0.0, 0.0, 1.0])
    return Motion("rise", path, np.tile(quat, (steps, 1)))


# ------------------------------------------------------------------------------ termination
def test_episode_ends_past_08m_of_position_error_not_at_05m(space):
    """The target rises 1.5 m in 2 s. The robot tracks the start, then falls behind: it stays
    alive while the error passes the arms' 0.5 m and ends at the first step past 0.8 m, standing
    (not a fall). With termination_pos_error = 0.5 the same episode ends at the first step past
    0.5 m: the threshold is the controller config's, and 0.8 m is the quadruped's default."""
    design = space.nominal()
    motion = _rising(space.model(design))
    ep = oracle_rollout([design], [motion])
    alive = ep.alive[0].numpy()
    n = int(alive.sum())
    assert 0 < n < motion.steps and alive[:n].all() and not alive[n:].any(), "alive must be a prefix"
    err = (ep.ee_pos - ep.target_pos).norm(dim=-1).sum(-1)[0].numpy()  # summed over end effectors, (T,)
    assert err[:n].max() <= 0.8 < err[n]
    assert (err[:n] > 0.5).sum() >= 5, "the episode must run well past the arms' 0.5 m"
    assert not bool(ep.fallen[0].any()), "the robot is standing: this end is the position error's"
    assert ep.qpos[0, n, 2] > 0.5 * space.model(design).key("home").qpos[2]
    for name in ("qpos", "ctrl", "ee_pos"):
        held = getattr(ep, name)[0, n:]
        assert torch.equal(held, held[:1].expand_as(held)), f"{name} must repeat the terminal record"
    # The reward counts the same steps (its own test: summed error <= the space's 0.8 m).
    assert get_reward("tracking", "quadruped").threshold == 0.8
    assert int(metrics(RewardInputs.from_episode(ep), get_reward("tracking", "quadruped"))["length"][0]) == n

    strict = oracle_rollout([design], [motion], wbc_config=WBCConfig(termination_pos_error=0.5))
    k = int(strict.alive[0].sum())
    assert k < n and err[:k].max() <= 0.5 < err[k]
    assert torch.equal(strict.ee_pos[0, :k], ep.ee_pos[0, :k]), "the threshold must not change the steps before it"


# ------------------------------------------------------------------------------ CMA-ES vs Random
def _reach_up_and_ahead(steps: int = 40) -> Motion:
    """The first 0.8 s of reach_place:100, placed for the quadruped and moved 45 cm ahead and
    35 cm up: within reach of long arms only, so the continuous choices matter."""
    m = for_space([get_motion("reach_place", 100)], "quadruped")[0]
    return Motion("reach_place:100+ahead+up", m.pos[:steps] + np.array([0.45, 0.0, 0.35]), m.quat[:steps], m.dt)


def test_cmaes_improves_over_random_designs_on_the_quadruped(space):
    """The paper's comparison (quadruped, single trajectory: Random 3.4 cm, CMA-ES 1.9 cm):
    Random is the performance of randomly sampled designs, CMA-ES the design it returns. Same
    problem and seed for both, 20 candidates, the oracle evaluating (reward `tracking`, 40
    steps, at most 40). CMA-ES (5 screened random designs, then 3 generations of 5 from the
    best of them) must return a design that tracks better than the random designs do on
    average, and its generations, not the screening, must have found it.

    At equal budget, the best of 20 random designs is as good as CMA-ES's on this problem
    (measured over seeds 0-3: 33.9-36.6 vs 31.8-33.7): with 20 candidates Random sees 20
    discrete choices, CMA-ES refines one. That is the best-of-budget strength of Random that
    benchmarks/results/optimize.md shows for ViperX at small budgets."""
    from tt.baselines import evaluate_designs

    motion = _reach_up_and_ahead()
    problem = Problem(space="quadruped", motions=(motion,), reward="tracking", budget=20, seed=0)
    assert problem.backend == "mjbatch", "a space with contacts is evaluated on MuJoCo C, batched, by default"
    random_designs = space.sample(problem.budget, seed=problem.seed)  # what RandomSearch draws and scores
    rnd = evaluate_designs(random_designs, [motion], "tracking", backend="mujoco")
    cma = CMAES().optimize(problem)
    assert len(random_designs) == len(cma.designs) == 20
    best = evaluate_designs([cma.best], [motion], "tracking", backend="mujoco")
    assert best.objective[0] == pytest.approx(cma.best_reward, rel=1e-6), "the oracle is deterministic"

    # CMA-ES's design against the random designs (the paper's Random row): reward and error.
    assert cma.best_reward > 2.0 * float(np.mean(rnd.objective))  # measured 32.7 vs 13.0
    assert best.metrics["pos_err"][0, 0] < 0.5 * float(np.mean(rnd.metrics["pos_err"]))  # measured 4.4 vs 18.4 cm
    assert best.metrics["survival"][0, 0] == 1.0
    # The generations improved on the screening batch, and the winner came from them.
    screen = cma.info["screen"]
    assert screen == 5 and int(np.argmax(cma.rewards)) >= screen
    assert cma.history[-1] > cma.history[0] + 1.0  # measured 29.3 -> 32.7 (reward of 40)


# ------------------------------------------------------------------------------ the CLI
def test_cli_optimizes_generates_and_views_the_quadruped(tmp_path, tt_cli):
    """`tt optimize --method random|cmaes`, `tt generate` and `tt view` on the quadruped with
    no backend named: mjbatch (MuJoCo C batched, equal to the oracle) evaluates, and asking for
    'warp' fails naming the contacts."""
    import json

    from tt.sim.motions import save_npz

    toss = get_motion("toss", 100)
    motion_file = tmp_path / "toss20.npz"
    save_npz(Motion("toss[:20]", toss.pos[:20], toss.quat[:20], toss.dt), motion_file)
    common = ["optimize", "--space", "quadruped", "--motion", str(motion_file), "--seed", "3"]
    for method, budget, extra in (("random", 2, []), ("cmaes", 5, ["--config", "generations=1"])):
        out = tmp_path / f"{method}.json"
        code, text = tt_cli([*common, "--method", method, "--budget", str(budget), *extra, "--json", str(out)])
        assert code == 0, text
        data = json.loads(out.read_text())
        assert data["backend"] == "mjbatch" and data["rollouts"] == budget
        get_space("quadruped").validate(get_space("quadruped").from_dict(data["design"]))
        v = data["validated"]
        assert v["survival_pct"] == 100.0 and 0.0 < v["pos_err"] < 20.0, v
        # The oracle's reward of the winner is the objective the search measured on the oracle.
        assert v["reward"] == pytest.approx(data["objective"], rel=1e-5)
    code, text = tt_cli([*common, "--method", "random", "--budget", "2", "--backend", "warp"])
    assert code == 2 and "has contacts" in text, text

    dataset = tmp_path / "ds"
    code, text = tt_cli(
        [
            "generate",
            "--space",
            "quadruped",
            "--designs",
            "1",
            "--episodes-per-design",
            "1",
            "--config",
            "min_steps=10",
            "--out",
            str(dataset),
        ]
    )
    assert code == 0, text
    assert "1 episodes kept of 1 generated" in text, text
    code, text = tt_cli(["dataset", "info", str(dataset), "--json"])
    config = json.loads(text)["config"]
    assert (config["backend"], config["action_noise"]) == ("mjbatch", 0.0)

    code, text = tt_cli(["designs", "--space", "quadruped", "--n", "2", "--out", str(tmp_path / "d")])
    assert code == 0, text
    html = tmp_path / "q.html"
    code, text = tt_cli(["view", str(tmp_path / "d" / "designs.json"), "--html", str(html)])
    assert code == 0 and html.stat().st_size > 10_000, text
    # `tt validate` rolls out on the oracle and saves the rollout that `tt view` animates.
    episode = tmp_path / "ep.npz"
    code, text = tt_cli(
        [
            "validate",
            "--design",
            f"{tmp_path / 'd' / 'designs.json'}#1",
            "--motion",
            str(motion_file),
            "--episode",
            str(episode),
            "--json",
            str(tmp_path / "val.json"),
        ]
    )
    assert code == 0 and episode.exists(), text
    assert json.loads((tmp_path / "val.json").read_text())["metrics"][0]["survival_pct"] == 100.0
    code, text = tt_cli(["view", str(episode), "--html", str(tmp_path / "ep.html")])
    assert code == 0 and "0.38 s animation" in text, text
