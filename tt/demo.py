"""The main job: co-design for one motion and reward, every method side by side.

`tt demo` runs each method on the same problem (ViperX, the toss motion, the tracking
reward by default), re-runs each winner on the MuJoCo + mink oracle, prints the paper-style
table (validated metrics and optimize time) and writes an HTML scene of the winners
tracking the motion.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoConfig:
    """space / motion / reward: the problem. budget: candidates per motion for the rollout-based
    methods. samples: candidates for the learned methods. methods: which to run, in order.
    out: folder for demo.json and demo.html. device: Warp/torch device (None: default)."""

    space: str = "viperx"
    motion: str = "toss"
    reward: str = "tracking"
    budget: int = 64
    samples: int = 16
    seed: int = 0
    methods: tuple[str, ...] = ("random", "cmaes")
    out: Path = Path("tt_demo")
    device: str | None = None
    cmaes_options: dict = field(default_factory=lambda: {"popsize": 8, "generations": 4})


def make_optimizer(method: str, config: DemoConfig):
    from tt.baselines import get_optimizer

    if method == "cmaes":
        return get_optimizer("cmaes", **config.cmaes_options)
    return get_optimizer(method)


def run_demo(config: DemoConfig, echo=print) -> list[dict]:
    """Run the demo; returns one validated row per method (also written to demo.json)."""
    import json

    from tt.baselines import Problem
    from tt.baselines.evaluate import evaluate_designs
    from tt.report import summary_row
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, resolve_motion

    motions = for_space([resolve_motion(config.motion)], config.space)
    space = get_space(config.space)
    results = []
    for method in config.methods:
        budget = config.samples if method in ("zeroth", "dgs") else config.budget
        problem = Problem(space=config.space, motions=tuple(motions), reward=config.reward, budget=budget,
                          seed=config.seed, backend="warp", device=config.device)
        echo(f"[{method}] optimizing ({budget} candidates) ...")
        result = make_optimizer(method, config).optimize(problem)
        echo(f"[{method}] {result.rollouts} rollouts, {result.seconds:.1f} s, objective {result.best_reward:.1f}")
        results.append(result)

    winners = [r.best for r in results]
    ev = evaluate_designs(winners, motions, config.reward, backend="mujoco")
    rows = []
    for i, r in enumerate(results):
        rows.append({"name": r.method, **summary_row(ev.metrics, i), "seconds": r.seconds, "rollouts": r.rollouts})

    config.out.mkdir(parents=True, exist_ok=True)
    (config.out / "demo.json").write_text(json.dumps({
        "space": config.space, "motion": config.motion, "reward": config.reward, "rows": rows,
        "designs": {r.method: space.to_dict(r.best) for r in results},
    }, indent=1))
    try:
        from tt.viz.episode_file import save_episode_npz
        from tt.viz.cli import view_cmd

        episode_file = save_episode_npz(config.out / "demo_episode.npz", ev.episode, winners,
                                        labels=[r.method for r in results], motion_name=config.motion)
        view_cmd(str(episode_file), html=config.out / "demo.html", echo=lambda s: None)
        echo(f"wrote {config.out / 'demo.html'} (the winners tracking {config.motion}; open it in a browser)")
    except Exception as e:  # the table is the result; a viewer problem must not hide it
        log.warning("could not write the demo scene: %s", e)
    return rows
