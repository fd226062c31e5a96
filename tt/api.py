"""tt's Python API: the common path of co-design in a few functions.

``import tt`` re-exports these names lazily (`tt.__getattr__`), so importing tt loads nothing
heavy; each function imports what it needs when called. The CLI calls the same functions
with the same defaults, defined once here (``DEFAULT_*``) or in the function they wrap::

    import tt

    toss = tt.motion("toss")                        # library name, "toss:7", or a motion file
    best = tt.optimize("viperx", [toss], "tracking", method="cmaes", budget=60, seed=0)
    check = tt.validate([best.best], [toss])        # the oracle: MuJoCo C + mink
    tt.view([best.best], motion=toss, html="best.html")

Motions may be given as `Motion` objects or as strings (`motion`); every function moves them
into the design space's workspace as the CLI does (`tt.sim.motions.for_space`), once.
Designs may be given as `Design` objects or as a design file spec (``designs.json``,
``designs.json#i``, ``best.json`` from ``tt optimize --json``; `tt.sim.designs.load_designs`).
Bad input raises `tt.TTError` (a ValueError) naming the argument and what would be valid.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Sequence, Union

if TYPE_CHECKING:
    from tt.baselines import Evaluation, Result
    from tt.guidance.predicted import DesignPrediction
    from tt.sim.designs import Design
    from tt.sim.designs.base import DesignSpace
    from tt.sim.motions import Motion
    from tt.viz.cli import ViewResult

    MotionLike = Union[Motion, str, Path]
    DesignsLike = Union[Sequence[Design], str, Path]

#: Design space when none is named (`tt rollout`, `tt optimize`, `tt demo`, ...).
DEFAULT_SPACE = "viperx"
#: Reward when none is named (`tt.sim.rewards.REWARDS` lists them; every function here also
#: takes the paper's names, `tt.sim.rewards.REWARD_ALIASES`, e.g. "Tracking Velocity").
DEFAULT_REWARD = "tracking"
#: Motion of `tt rollout` and `tt demo` when none is named.
DEFAULT_MOTION = "toss"
#: Optimizer of `optimize` (`tt.optimizers.METHODS` lists them).
DEFAULT_METHOD = "cmaes"
#: Candidate designs per motion of `optimize`.
DEFAULT_BUDGET = 60
#: Random seed.
DEFAULT_SEED = 0
#: Controller of `validate`: "ik", the MuJoCo C + mink oracle, or "model", the DiT.
DEFAULT_CONTROLLER = "ik"
#: The controllers `validate` knows.
CONTROLLERS = ("ik", "model")


def get_space(name: str = DEFAULT_SPACE) -> DesignSpace:
    """The design space `name`: viperx, viperx-nominal, aloha, bimanual or quadruped
    (`tt.sim.designs.SPACE_NAMES`). ``space.sample(n, seed)`` draws designs,
    ``space.nominal()`` is the robot it is built around, ``space.to_mjcf(design)`` its MJCF."""
    from tt.sim.designs import get_space as _get_space

    return _get_space(name)


def motion(spec: str | Path) -> Motion:
    """A target motion: a library name (``"toss"``, ``"toss:7"`` for a variant; ``tt motions``
    lists them) or a motion file (``.npz``, or a UMI ``.zarr`` store), placed over the robot's
    base as the library's motions are. 50 Hz end-effector poses (`tt.sim.motions.Motion`)."""
    from tt.sim.motions import load_motion_file, resolve_motion

    if isinstance(spec, Path):
        return load_motion_file(spec)
    return resolve_motion(spec)


#: `motion` by its other name: a motion file read from disk.
load_motion = motion


def rollout(
    designs: DesignsLike | None = None,
    motions: Sequence[MotionLike] | None = None,
    reward: str = DEFAULT_REWARD,
    *,
    space: str = DEFAULT_SPACE,
    n: int = 16,
    seed: int = DEFAULT_SEED,
    backend: str | None = None,
    device: str | None = None,
    threads: int | None = None,
    graph: bool | None = None,
    progress: bool = False,
) -> Evaluation:
    """Roll out every design on every motion in one batch and score it (``tt rollout``).

    designs: designs of one space (None: `n` random designs of `space`, seed `seed`).
    motions: None: the toss. backend: "warp" (tt's kernels), "mjwarp", "newton", "mjbatch" or
    "mujoco" (None: "warp", or "mjbatch" for spaces with contacts: `tt.baselines.default_backend`).
    threads: CPU threads of the warp backend (None: every core; results are the same).
    Returns a `tt.baselines.Evaluation`: ``objective`` (D,), ``reward`` (D, M), ``metrics``
    name -> (D, M) (units in `tt.sim.rewards.METRIC_UNITS`: position error in cm, ...) and the
    ``episode`` (worlds design-major)."""
    from tt.baselines import default_backend, evaluate_designs

    designs = _designs(designs) if designs is not None else get_space(space).sample(n, seed)
    sp = _one_space(designs)
    ms = _placed(motions if motions is not None else [DEFAULT_MOTION], sp)
    return evaluate_designs(
        designs,
        ms,
        reward,
        backend=backend or default_backend(sp),
        device=device,
        progress=progress,
        threads=threads,
        graph=graph,
    )


def control_checkpoint(space: str, checkpoint: str | Path | None = None) -> Path:
    """The DiT checkpoint `validate(controller="model")` runs: `checkpoint`, else the space's
    shipped controller (``<space>_<size>_control.pt``), else its shipped generalist."""
    if checkpoint is not None:
        return Path(checkpoint)
    from tt.dit.checkpoint import default_checkpoint

    return default_checkpoint(space, task="control")


def validate(
    designs: DesignsLike,
    motions: Sequence[MotionLike] | None = None,
    reward: str = DEFAULT_REWARD,
    *,
    controller: str = DEFAULT_CONTROLLER,
    checkpoint: str | Path | None = None,
    device: str | None = None,
    ensemble: int | None = None,
    progress: bool = False,
) -> Evaluation:
    """Run a controller on every design x motion and score it (``tt validate``).

    controller: "ik", the oracle (MuJoCo C + mink DiffIK, one world at a time: the reference
    every result is validated on), or "model", the DiT's control task on tt's batched Warp
    physics (`control_checkpoint`; ensemble: queries each command averages, None for all whose
    window holds the step; `tt.dit.policies.ControllerConfig`). motions: None, the toss.
    Returns a `tt.baselines.Evaluation` (see `rollout`)."""
    from tt.baselines import Evaluation, evaluate_designs

    if controller not in CONTROLLERS:
        from tt.kernels.errors import TTError

        raise TTError(f"controller {controller!r} does not exist; controllers: {', '.join(CONTROLLERS)}")
    designs = _designs(designs)
    sp = _one_space(designs)
    ms = _placed(motions if motions is not None else [DEFAULT_MOTION], sp)
    if controller == "ik":
        return evaluate_designs(designs, ms, reward, backend="mujoco")
    from tt.baselines.evaluate import score_episode
    from tt.dit.policies import ControllerConfig, model_rollout

    ep = model_rollout(
        designs,
        ms,
        control_checkpoint(sp, checkpoint),
        device=device,
        progress=progress,
        config=ControllerConfig(ensemble=ensemble),
    )
    r, metrics = score_episode(ep, designs, ms, reward)
    return Evaluation(objective=r.mean(axis=1), reward=r, metrics=metrics, episode=ep)


def optimize(
    space: str = DEFAULT_SPACE,
    motions: Sequence[MotionLike] | None = None,
    reward: str = DEFAULT_REWARD,
    *,
    method: str = DEFAULT_METHOD,
    budget: int = DEFAULT_BUDGET,
    seed: int = DEFAULT_SEED,
    checkpoint: str | Path | None = None,
    backend: str | None = None,
    device: str | None = None,
    threads: int | None = None,
    **options,
) -> Result:
    """Optimize one design of `space` for `motions` and `reward` (``tt optimize``).

    method: "random", "cmaes" (batched CMA-ES), "zeroth" and "dgs" (the DiT's Zeroth-Order
    search and Dynamics Self-Guidance), "zeroth-sim" and "dgs-sim" (the model proposes, the
    batched simulator verifies) or "cmaes-init-model" (CMA-ES started from the model's
    samples); `tt.optimizers.METHODS`. budget: candidate designs per motion (the learned
    methods' sample count unless ``samples=`` says otherwise). checkpoint: the learned
    methods' DiT (None: the space's shipped one, ranked by the shipped critic:
    `tt.optimizers.learned_defaults`). backend / device / threads: how candidates are
    rolled out (`rollout`). options: the method's config fields (`tt.baselines.CMAESConfig`,
    `tt.guidance.zeroth.SamplerConfig`, `tt.guidance.selfguide.DGSConfig`; e.g. popsize=8,
    num_steps=20, refine=10).

    Returns a `tt.baselines.Result`: ``best`` (the design), ``best_reward`` (its objective as
    the method measured or predicted it), ``seconds``, ``rollouts``, every candidate and its
    objective. Validate the winner with `validate`."""
    from tt.baselines import Problem
    from tt.optimizers import run_optimizer

    if not motions:
        from tt.kernels.errors import TTError

        raise TTError(
            "optimize: no motion given; pass motions=[...]: library names such as 'toss', motion files "
            "or tt.motion(...) objects"
        )
    get_space(space)  # an unknown space fails here, naming the valid ones
    problem = Problem(
        space=space,
        motions=tuple(_placed(motions, space)),
        reward=reward,
        budget=budget,
        seed=seed,
        backend=backend,
        device=device,
        threads=threads,
    )
    if checkpoint is not None:
        options["checkpoint"] = checkpoint
    return run_optimizer(problem, method, **options)


def predict_checkpoint(space: str, checkpoint: str | Path | None = None) -> Path:
    """The DiT checkpoint `predict` asks: `checkpoint`, else the space's shipped dynamics
    critic (``<space>_<size>_dynamics.pt``), else its shipped generalist."""
    if checkpoint is not None:
        return Path(checkpoint)
    from tt.dit.checkpoint import default_checkpoint

    return default_checkpoint(space, task="dynamics")


def predict(
    designs: DesignsLike,
    motions: Sequence[MotionLike] | None = None,
    reward: str = DEFAULT_REWARD,
    *,
    checkpoint: str | Path | None = None,
    samples: int = 1,
    num_steps: int | None = None,
    seed: int = DEFAULT_SEED,
    device: str | None = None,
    via: str | None = None,
) -> DesignPrediction:
    """The DiT as a critic: each design's predicted dynamics on each motion and their reward,
    without simulating (``tt predict``).

    checkpoint: `predict_checkpoint`. samples: predictions averaged per design x motion.
    num_steps: DDIM steps (None: `tt.guidance.predicted.CRITIC_DDIM_STEPS`). via: how the
    design is given, "dynamics" or "inpaint" (None: "dynamics" when the checkpoint was trained
    on that task). motions: None, the toss. Returns a `tt.guidance.predicted.DesignPrediction`:
    ``reward`` (D, M) and ``metrics`` name -> (D, M)."""
    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import CRITIC_DDIM_STEPS, predict_designs
    from tt.kernels.device import default_device
    from tt.sim.rewards import get_reward

    designs = _designs(designs)
    sp = _one_space(designs)
    ms = _placed(motions if motions is not None else [DEFAULT_MOTION], sp)
    cfg = get_reward(reward, sp)
    trained = load_model(predict_checkpoint(sp, checkpoint), device=device or default_device())
    return predict_designs(
        trained,
        designs,
        ms,
        cfg,
        samples=samples,
        seed=seed,
        via=via,
        num_steps=CRITIC_DDIM_STEPS if num_steps is None else num_steps,
    )


def generate_dataset(space: str, designs: int, out: str | Path, **options) -> str:
    """Generate (or resume) a RoboToken dataset (``tt generate``): `designs` random designs of
    `space`, each rolled out on augmented training motions, filtered, tokenized and written to
    `out` as checksummed zarr shards. options: `tt.generate.generate_cmd`'s (episodes_per_design
    10, workers, bias="cmaes", seed, ray, designs_per_shard, min_steps, action_noise, threads,
    select, uniform_share). Returns the summary text. (Named apart from `generate` because
    `tt.generate` is the module that implements it.)"""
    from tt.generate import generate_cmd

    return generate_cmd(space, designs, out, **options)


def view(
    source: DesignsLike | Evaluation,
    *,
    designs: DesignsLike | None = None,
    motion: MotionLike | None = None,
    html: str | Path | None = None,
    serve: bool = False,
    png: str | Path | None = None,
    time: float | None = None,
    block: bool = True,
) -> ViewResult:
    """Show designs or rollouts in meshcat (``tt view``): one self-contained offline HTML file
    (`html`; default ``<source name>.html``, ``tt_view.html`` for objects), or a live server
    (`serve`; with `block` it runs until Ctrl-C).

    source: designs (`Design` objects or a design file spec), an episode file
    (``episode.npz[#w]``), or the `Evaluation` of `rollout` / `validate` with its `designs`
    (their rollouts animated). motion: the target motion drawn with the robots (a `Motion`,
    library name or file). png: also a screenshot of the HTML (headless Chromium); time: the
    animation time [s] the HTML opens paused at."""
    import tempfile

    from tt.viz.cli import view_cmd

    lookup = None
    if motion is not None and not isinstance(motion, str):
        motion_obj = motion if not isinstance(motion, Path) else load_motion(motion)
        lookup = lambda _name: motion_obj  # noqa: E731  (the object itself, not a library look-up)
        motion = motion_obj.name
    if isinstance(source, (str, Path)):
        return view_cmd(
            str(source), motion=motion, html=html, serve=serve, png=png, time=time, block=block, motion_lookup=lookup
        )
    if html is None and not serve:
        html = Path("tt_view.html")
    with tempfile.TemporaryDirectory(prefix="tt_view_") as tmp:
        if hasattr(source, "episode"):
            from tt.viz.episode_file import save_episode_npz

            if designs is None:
                from tt.kernels.errors import TTError

                raise TTError("view: an Evaluation does not carry its designs; pass them too: view(ev, designs=...)")
            path = save_episode_npz(Path(tmp) / "episode.npz", source.episode, _designs(designs))
        else:
            from tt.sim.designs import save_designs

            path = Path(tmp) / "designs.json"
            save_designs(_designs(source), path)
        return view_cmd(
            str(path), motion=motion, html=html, serve=serve, png=png, time=time, block=block, motion_lookup=lookup
        )


def _designs(designs: DesignsLike) -> list[Design]:
    """Designs from Design objects or a design file spec."""
    if isinstance(designs, (str, Path)):
        from tt.sim.designs import load_designs

        return list(load_designs(str(designs)))
    designs = list(designs)
    if not designs:
        from tt.kernels.errors import TTError

        raise TTError(
            "no designs given; pass Design objects (tt.get_space(...).sample(n, seed)) or a designs.json path"
        )
    return designs


def _one_space(designs: Sequence[Design]) -> str:
    spaces = sorted({d.space for d in designs})
    if len(spaces) > 1:
        from tt.kernels.errors import TTError

        raise TTError(f"designs from several spaces in one call: {spaces}")
    return spaces[0]


def _placed(motions: Sequence[MotionLike], space: str) -> list[Motion]:
    """Motions (objects or specs) moved into `space`'s workspace, each once: a motion already
    moved by an offset (`for_space` records it in ``meta["space_offset"]``) is kept as it is."""
    from tt.sim.motions import Motion, for_space

    out = []
    for m in motions:
        m = m if isinstance(m, Motion) else motion(m)
        out.append(m if "space_offset" in m.meta else for_space([m], space)[0])
    return out


__all__ = [
    "DEFAULT_BUDGET",
    "DEFAULT_CONTROLLER",
    "DEFAULT_METHOD",
    "DEFAULT_MOTION",
    "DEFAULT_REWARD",
    "DEFAULT_SEED",
    "DEFAULT_SPACE",
    "control_checkpoint",
    "generate_dataset",
    "get_space",
    "load_motion",
    "motion",
    "optimize",
    "predict",
    "predict_checkpoint",
    "rollout",
    "validate",
    "view",
]
