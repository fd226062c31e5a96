"""The main job: co-design for one motion and reward, every method side by side.

`tt demo` runs each method on the same problem (ViperX, the toss motion, the tracking
reward by default), re-runs each winner on the MuJoCo + mink oracle, prints the paper-style
table (validated metrics and optimize time) and writes an HTML scene of the winners
tracking the motion.

The ALOHA (``tt demo --space aloha``) runs the paper's ALOHA experiment on one motion: a
bimanual validation fling (bi_fling:100) for the "Tracking Velocity" reward, the original
ALOHA (the space's nominal design) validated beside the winners, first in the table and the
scene, and each winner's change in position error and max joint speed from it printed
(`SPACE_DEFAULTS`; benchmarks/aloha.py runs it over 9 seeds). With the shipped ALOHA model and
critic it took 2.7 min on the repository's 2-core CPU when idle (Intel Xeon, 2026-12-07): 34 s
for Random, CMA-ES, Zeroth-Order and Zeroth + sim, and 128 s for Self-Guidance, which follows
the critic through every candidate's decoded design at every DDIM step (`--config
'methods=[...]'` leaves it out).

Methods: Random and batched CMA-ES (budget candidates each, scored by tt's batched Warp
rollout), and, when the design space has a shipped DiT checkpoint
(`tt.dit.checkpoint.default_checkpoint`) or one is given, the diffusion model's
Zeroth-Order search and Dynamics Self-Guidance (`samples` candidates each, `num_steps` DDIM
steps, ranked by a predicted reward: beside the shipped model, the shipped dynamics critic's,
which decodes every candidate and simulates only its first control step; else the model's
own) and the hybrid Zeroth + sim (the same samples, every one checked in one batched
rollout, the simulated best wins; `tt.guidance.hybrid`). Without a
checkpoint the learned methods are skipped and the output says why; a learned method none
of whose candidates decodes to a design of the space gets a "no design" row.

Time. The defaults keep the whole demo to a few minutes on a 2-core CPU: the learned
methods sample 16 candidates with 20 DDIM steps (of the process's 100; DDIM's strided
schedule) rather than the paper's 128 x 100. With the shipped ViperX checkpoint and critic
the whole `tt demo` took 38 s on the repository's 2-core CPU when idle (2026-12-04;
Zeroth-Order ~8 s and Self-Guidance ~11 s of it, mostly decoding the 16 candidates).
One-time costs are excluded from each method's optimize time, as the kernel compile is for
Random and CMA-ES: loading the checkpoint and building the space's decoding table (ViperX:
~10 s) happen once before the learned methods run and are reported on their own line.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tt.kernels.errors import TTError

log = logging.getLogger(__name__)

#: Methods that sample the diffusion model (need a checkpoint); zeroth-sim is the hybrid
#: (the model proposes, the batched simulator verifies every sample).
LEARNED = ("zeroth", "dgs", "zeroth-sim")
#: Every method the demo knows, in the order it runs them.
ALL_METHODS = ("random", "cmaes") + LEARNED


#: Each space's demo problem when none is named, (motion, reward, original): ViperX tosses for
#: the tracking reward; the ALOHA is the paper's ALOHA experiment, a bimanual validation fling
#: for "Tracking Velocity", the optimized designs beside the original ALOHA (`original`).
SPACE_DEFAULTS: dict[str, tuple[str, str, bool]] = {
    "viperx": ("toss", "tracking", False),
    "aloha": ("bi_fling:100", "tracking_velocity", True),
}


def space_defaults(space: str) -> tuple[str, str, bool]:
    """(motion, reward, original) of `space`'s demo: `SPACE_DEFAULTS`, else the space's default
    motion (`tt.sim.motions.default_motion`: the toss, or the bimanual fling for two-arm
    spaces), the tracking reward, no original."""
    if space in SPACE_DEFAULTS:
        return SPACE_DEFAULTS[space]
    from tt.api import _default_motion

    return _default_motion(space), "tracking", False


@dataclass(frozen=True)
class DemoConfig:
    """space / motion / reward: the problem (None: the space's, `space_defaults`). budget:
    candidates per motion for the rollout-based methods. samples: candidates for the learned
    methods; num_steps: their DDIM steps. checkpoint: DiT checkpoint file or run folder for
    the learned methods (None: the space's shipped one; where there is none they are
    skipped). methods: which to run, in order. original: also validate the space's nominal
    design (the robot it is built around: the original ALOHA), first in the table and the
    scene, with each winner's change from it (None: the space's default). out: folder for
    demo.json and demo.html. device: Warp/torch device (None: default)."""

    space: str = "viperx"
    motion: str | None = None
    reward: str | None = None
    budget: int = 64
    samples: int = 16
    num_steps: int = 20
    seed: int = 0
    methods: tuple[str, ...] = ALL_METHODS
    checkpoint: Path | None = None
    out: Path = Path("tt_demo")
    device: str | None = None
    cmaes_options: dict = field(default_factory=lambda: {"popsize": 8, "generations": 4})
    original: bool | None = None

    def __post_init__(self) -> None:
        from tt.sim.rewards import reward_name

        motion, reward, original = space_defaults(self.space)
        object.__setattr__(self, "motion", motion if self.motion is None else self.motion)
        reward = reward if self.reward is None else self.reward
        object.__setattr__(self, "reward", reward_name(reward))  # the paper's names become tt's
        object.__setattr__(self, "original", original if self.original is None else bool(self.original))
        unknown = [m for m in self.methods if m not in ALL_METHODS]
        if unknown:
            raise TTError(f"DemoConfig.methods has unknown methods {unknown}; valid: {list(ALL_METHODS)}")
        if self.samples < 1:
            raise TTError(f"DemoConfig.samples = {self.samples}; must be >= 1")
        if self.seed < 0:
            raise TTError(f"DemoConfig.seed = {self.seed}; must be >= 0")
        if self.checkpoint is not None:
            object.__setattr__(self, "checkpoint", Path(self.checkpoint))  # a --config value is a str
        from tt.dit.tasks import ROBOT

        if not 1 <= self.num_steps <= ROBOT.diffusion_steps:
            raise TTError(f"DemoConfig.num_steps = {self.num_steps}; must be in 1 .. {ROBOT.diffusion_steps}")


@dataclass
class LearnedSetup:
    """What the learned methods share: the loaded model, its checkpoint path, the space's
    design decoder, the seconds loading and building them took, and the critic that ranks
    their samples (the space's shipped dynamics specialist beside a shipped model, asked
    about the decoded designs; None: the model's own dynamics task)."""

    trained: object
    checkpoint: Path
    decoder: object
    seconds: float
    critic: object = None


def resolve_checkpoint(config: DemoConfig) -> tuple[Path | None, str]:
    """The checkpoint the learned methods use and a line saying which (or why none)."""
    from tt.dit.checkpoint import NoCheckpointError, default_checkpoint

    if config.checkpoint is not None:
        return Path(config.checkpoint), f"checkpoint {config.checkpoint}"
    try:
        path = default_checkpoint(config.space, task="robot")
    except NoCheckpointError as e:
        return None, f"the learned methods (Zeroth-Order, Self-Guidance, Zeroth + sim) skipped: {e}"
    return path, f"shipped checkpoint {path.name}"


def learned_setup(checkpoint: Path, space: str, device: str | None) -> LearnedSetup:
    """Load the model and build the decoder once for both learned methods."""
    from tt.dit.checkpoint import load_model, shipped_critic
    from tt.guidance.zeroth import DesignDecoder, check_critic
    from tt.kernels.device import default_device
    from tt.sim.designs import get_space
    from tt.tokens.design_fit import CandidateTable

    start = time.perf_counter()
    trained = load_model(checkpoint, device=device or default_device())
    critic = None
    if (critic_path := shipped_critic(space, checkpoint)) is not None:
        critic = load_model(critic_path, device=device or default_device())
        check_critic(trained, critic)
    sp = get_space(space)
    decoder = DesignDecoder(sp, table=CandidateTable(sp))
    return LearnedSetup(trained, Path(checkpoint), decoder, time.perf_counter() - start, critic)


def make_optimizer(method: str, config: DemoConfig, learned: LearnedSetup | None = None):
    from tt.optimizers import get_optimizer

    if method == "cmaes":
        return get_optimizer("cmaes", **config.cmaes_options)
    if method in LEARNED:
        from tt.guidance.selfguide import DGSConfig, DynamicsSelfGuidance
        from tt.guidance.zeroth import SamplerConfig, ZerothOrder

        if learned is None:
            raise TTError(f"method {method!r} needs a DiT checkpoint")
        if method in ("zeroth", "zeroth-sim"):
            zeroth = ZerothOrder(
                SamplerConfig(samples=config.samples, num_steps=config.num_steps),
                model=learned.trained,
                decoder=learned.decoder,
                critic_model=learned.critic,
            )
            if method == "zeroth":
                return zeroth
            from tt.guidance.hybrid import SimVerified

            return SimVerified(zeroth)
        return DynamicsSelfGuidance(
            DGSConfig(samples=config.samples, num_steps=config.num_steps),
            model=learned.trained,
            decoder=learned.decoder,
            critic_model=learned.critic,
        )
    return get_optimizer(method)


#: The row name of a space's original (nominal) design.
ORIGINAL = {"aloha": "Original ALOHA", "viperx": "Original ViperX"}
#: Metrics whose change from the original design the demo reports (the paper's ALOHA result).
CHANGED = (("pos_err", "position error", "cm"), ("max_joint_speed", "max joint speed", "rad/s"))


def changes_from_original(original: dict, row: dict) -> list[str]:
    """One line per `CHANGED` metric: the row's value against the original's, relative change."""
    parts = []
    for key, name, unit in CHANGED:
        a, b = original.get(key), row.get(key)
        if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)) or a == 0:
            continue
        parts.append(f"{name} {a:.2f} -> {b:.2f} {unit} ({100 * (b / a - 1):+.0f} %)")
    return [f"{row['name']} against {original['name']}: " + "; ".join(parts)] if parts else []


#: Row names, the paper's (CMA-ES is tt's batched CMA-ES; DGS is Dynamics Self-Guidance).
LABELS = {"random": "Random", "cmaes": "CMA-ES", "zeroth": "Zeroth", "dgs": "DGS", "zeroth-sim": "Zeroth + sim"}


def run_demo(config: DemoConfig, echo=print) -> list[dict]:
    """Run the demo; returns one validated row per method (also written to demo.json)."""
    from tt.baselines import Problem
    from tt.baselines.evaluate import evaluate_designs
    from tt.kernels.files import write_json
    from tt.report import summary_row
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, resolve_motion

    motions = for_space([resolve_motion(config.motion)], config.space)
    space = get_space(config.space)
    config.out.mkdir(parents=True, exist_ok=True)  # before the work: a folder that cannot be made fails now
    methods = list(config.methods)
    learned = None
    checkpoint_note = None
    if any(m in LEARNED for m in methods):
        checkpoint, checkpoint_note = resolve_checkpoint(config)
        echo(checkpoint_note)
        if checkpoint is None:
            methods = [m for m in methods if m not in LEARNED]
        else:
            learned = learned_setup(checkpoint, config.space, config.device)
            critic = "" if learned.critic is None else f", the critic {learned.critic.path.name}"
            echo(
                f"loaded the model (step {learned.trained.step}){critic} and the {config.space} decoding table in "
                f"{learned.seconds:.1f} s (once, not in the optimize times)"
            )
    results, labels, failures = [], [], []
    for method in methods:
        budget = config.samples if method in LEARNED else config.budget
        problem = Problem(
            space=config.space,
            motions=tuple(motions),
            reward=config.reward,
            budget=budget,
            seed=config.seed,
            device=config.device,
            progress=True,  # a note and a bar where the candidates' kernels compile first
        )  # the space's default backend
        what = f"{budget} samples, {config.num_steps} DDIM steps" if method in LEARNED else f"{budget} candidates"
        echo(f"[{method}] optimizing ({what}) ...")
        start = time.perf_counter()
        try:
            result = make_optimizer(method, config, learned).optimize(problem)
        except TTError as e:
            if method not in LEARNED:
                raise
            # A model whose candidates all fail to decode to the space's designs returns none;
            # the other methods' results still stand.
            echo(f"[{method}] no design: {e}")
            failures.append(
                {
                    "name": LABELS[method],
                    "seconds": time.perf_counter() - start,
                    "rollouts": 0,
                    "note": "no design decoded",
                }
            )
            continue
        kind = "objective" if result.rollouts else "predicted objective"  # no rollout: the critic's
        echo(f"[{method}] {result.rollouts} rollouts, {result.seconds:.1f} s, {kind} {result.best_reward:.1f}")
        results.append(result)
        labels.append(LABELS[method])

    winners = [r.best for r in results]
    # The original design (where asked) first: one oracle call validates it with the winners.
    originals = [space.nominal()] if config.original else []
    shown = originals + winners
    shown_labels = [ORIGINAL.get(config.space, "Original")] * len(originals) + labels
    ev = evaluate_designs(shown, motions, config.reward, backend="mujoco")
    rows = []
    if originals:
        rows.append({"name": shown_labels[0], **summary_row(ev.metrics, 0)})
    for i, r in enumerate(results):
        k = len(originals) + i
        row = {"name": labels[i], **summary_row(ev.metrics, k), "seconds": r.seconds, "rollouts": r.rollouts}
        if not np.isfinite(row.get("pos_err", 0.0)):
            # No step counted: the error is past the termination threshold from the start.
            row["note"] = "ended at step 1"
        rows.append(row)
    if originals:
        for row in rows[1:]:
            for line in changes_from_original(rows[0], row):
                echo(line)
    rows += failures

    config.out.mkdir(parents=True, exist_ok=True)
    write_json(
        config.out / "demo.json",
        {
            "space": config.space,
            "motion": config.motion,
            "reward": config.reward,
            "rows": rows,
            "designs": {label: space.to_dict(d) for label, d in zip(shown_labels, shown)},
            "checkpoint": None if learned is None else str(learned.checkpoint),
            "critic": None if learned is None or learned.critic is None else str(learned.critic.path),
            "checkpoint_note": checkpoint_note,
            "samples": config.samples,
            "num_steps": config.num_steps,
            "budget": config.budget,
        },
    )
    try:
        from tt.viz.cli import view_cmd
        from tt.viz.episode_file import save_episode_npz

        episode_file = save_episode_npz(
            config.out / "demo_episode.npz", ev.episode, shown, labels=shown_labels, motion_name=config.motion
        )
        view_cmd(str(episode_file), html=config.out / "demo.html", echo=lambda s: None)
        who = f"the {shown_labels[0]} and the winners" if originals else "the winners"
        echo(f"wrote {config.out / 'demo.html'} ({who} tracking {config.motion}; open it in a browser)")
    except Exception as e:  # the table is the result; a viewer problem must not hide it
        log.warning("could not write the demo scene: %s", e)
    return rows
