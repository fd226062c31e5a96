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
    import mujoco

    from tt.baselines import Evaluation, Result
    from tt.dit.train import TrainResult
    from tt.guidance.predicted import DesignPrediction
    from tt.sim.designs import Design
    from tt.sim.designs.base import DesignSpace
    from tt.sim.motions import Motion
    from tt.tokens import DetokenizeResult, Embodiments, TokenBatch
    from tt.viz.cli import ViewResult

    MotionLike = Union[Motion, str, Path]
    DesignsLike = Union[Sequence[Design], str, Path]

#: Design space when none is named (`tt rollout`, `tt optimize`, `tt demo`, ...).
DEFAULT_SPACE = "viperx"
#: Reward when none is named (`tt.sim.rewards.REWARDS` lists them; every function here also
#: takes the paper's names, `tt.sim.rewards.REWARD_ALIASES`, e.g. "Tracking Velocity").
DEFAULT_REWARD = "tracking"
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


def save_motion(path: str | Path, pos, quat=None, *, dt: float | None = None, name: str | None = None) -> Motion:
    """Write a target motion as a ``.npz`` motion file that `motion` (and ``tt optimize --motion
    FILE.npz``) reads, the format of ``tt motions --name NAME --out FILE.npz`` (`tt.sim.motions.io`).

    pos: end-effector positions [m], (T, 3), or (T, 2, 3) for two end effectors; or a `Motion`
    (then `quat`, `dt` and `name` come from it). quat: unit quaternions (w, x, y, z) of the
    same (T, 4) / (T, 2, 4) shape; None: (1, 0, 0, 0) throughout, the end effector level with
    its approach axis (x) along world x. dt: sample period [s] (None: 0.02, tt's 50 Hz); any
    other rate is resampled to 50 Hz when read. name: the motion's name (None: the file's
    stem). Reading the file moves the motion's start over the robot's base in (x, y), heights
    kept, as the library's motions are. Returns the `Motion` written (as given, not yet placed or resampled); bad arrays
    raise `tt.sim.motions.MotionError` (a `TTError`) naming the field."""
    import numpy as np

    from tt.sim.motions import MOTION_DT, Motion, save_npz

    if isinstance(pos, Motion):
        if quat is not None or dt is not None or name is not None:
            from tt.sim.motions import MotionError

            raise MotionError("save_motion: pass quat, dt and name with position arrays, not with a Motion")
        m = pos
    else:
        pos = np.asarray(pos, dtype=np.float64)
        if quat is None:
            quat = np.zeros(pos.shape[:-1] + (4,))
            quat[..., 0] = 1.0
        m = Motion(name or Path(path).stem, pos, quat, MOTION_DT if dt is None else dt)
    save_npz(m, path)
    return m


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
    motions: None: the toss (bi_fling for two-arm spaces). backend: "warp" (tt's kernels),
    "mjwarp", "newton", "mjbatch" or "mujoco" (None: "warp", or "mjbatch" for spaces with
    contacts: `tt.baselines.default_backend`).
    threads: CPU threads of the warp backend (None: every core; results are the same).
    Returns a `tt.baselines.Evaluation`: ``objective`` (D,), ``reward`` (D, M), ``metrics``
    name -> (D, M) (units in `tt.sim.rewards.METRIC_UNITS`: position error in cm, ...) and the
    ``episode`` (worlds design-major)."""
    from tt.baselines import default_backend, evaluate_designs

    designs = _designs(designs) if designs is not None else get_space(space).sample(n, seed)
    sp = _one_space(designs)
    ms = _placed(motions if motions is not None else [_default_motion(sp)], sp)
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
    window holds the step; `tt.dit.policies.ControllerConfig`). motions: None, the toss (bi_fling for two-arm spaces).
    Returns a `tt.baselines.Evaluation` (see `rollout`)."""
    from tt.baselines import Evaluation, evaluate_designs

    if controller not in CONTROLLERS:
        from tt.kernels.errors import TTError

        raise TTError(f"controller {controller!r} does not exist; controllers: {', '.join(CONTROLLERS)}")
    designs = _designs(designs)
    sp = _one_space(designs)
    ms = _placed(motions if motions is not None else [_default_motion(sp)], sp)
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
    on that task). motions: None, the toss (bi_fling for two-arm spaces). Returns a
    `tt.guidance.predicted.DesignPrediction`:
    ``reward`` (D, M) and ``metrics`` name -> (D, M)."""
    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import CRITIC_DDIM_STEPS, predict_designs
    from tt.kernels.device import default_device
    from tt.sim.rewards import get_reward

    designs = _designs(designs)
    sp = _one_space(designs)
    ms = _placed(motions if motions is not None else [_default_motion(sp)], sp)
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


def dataset_info(path: str | Path) -> dict:
    """What a RoboToken dataset holds (``tt dataset info --json``): a JSON-ready dict with
    ``space``, ``config`` (the arguments it was generated with), ``complete``, ``shards``,
    ``designs``, ``episodes`` (kept; ``episodes_generated`` and ``dropped`` by reason),
    ``steps``, ``bytes``, token ``maxima`` and per-episode summaries (n, mean, std, min, p50,
    max) of ``length``, ``reward``, ``pos_err``, ``orn_err`` and ``survival``
    (`tt.tokens.info.dataset_info`). A folder that is not a dataset raises
    `tt.tokens.store.DatasetError` (a `TTError`)."""
    from tt.tokens.info import dataset_info as _dataset_info

    return _dataset_info(path)[0]


def train(data: str | Path | None, out: str | Path, *, online=None, **options) -> TrainResult:
    """Train the diffusion transformer (``tt train``) on the RoboToken dataset `data` (a folder
    from `generate_dataset`, or an episode token file), or, with ``data=None``, on episodes the
    batched simulator generates as training goes (`online`: True for `tt.dit.online.OnlineConfig`'s
    defaults, or a dict of its fields, e.g. ``dict(space="viperx", designs=16, motions=2)``; its
    seed defaults to the run's, as ``tt train --online``'s does).

    out: the run folder (checkpoints, loss.csv, loss.png); a folder that holds a run of the same
    arguments is resumed. options: `tt.dit.cli.train_cmd`'s, the CLI's defaults (task "robot";
    "robot+dynamics" also makes the model a critic for `predict` and ranked optimizers; size
    "small", "tiny" for a quick run; steps 10,000; batch_size 64; lr None, the paper's for the
    size; device; seed 0; checkpoint_every 1,000; resume True; init, a checkpoint to fine-tune;
    progress True, a tqdm bar; and the recipe, `tt.dit.train.TrainConfig`'s fields).

    Returns a `tt.dit.train.TrainResult`: ``step``, ``losses`` (one per step), ``checkpoint``
    (the last one written: pass it as ``checkpoint=`` to `optimize` or `predict`) and
    ``parameters``."""
    from tt.kernels.errors import TTError

    if (data is None) == (online is None or online is False):
        raise TTError(
            "train: give exactly one source of training data: data=DATASET_FOLDER, or data=None with "
            f"online=True / online=dict(...); got data={data!r}, online={online!r}"
        )
    if data is not None and not Path(data).exists():
        raise TTError(f"train: data {str(data)!r} does not exist (a dataset folder from generate_dataset)")
    config = None
    if online is not None and online is not False:
        from tt.dit.online import OnlineConfig

        if isinstance(online, OnlineConfig):
            config = online
        elif online is True or isinstance(online, dict):
            fields = {} if online is True else online
            config = OnlineConfig(**{"seed": options.get("seed", 0), **fields})  # as tt train: the run's seed
        else:
            raise TTError(
                f"train: online must be True, a dict of OnlineConfig fields or an OnlineConfig, got {online!r}"
            )
    from tt.dit.cli import train_cmd

    if config is not None and "episodes" not in options:  # as tt train
        from tt.dit.train import DataParallel
        from tt.guidance.proposer import online_source

        progress = options.get("progress", True) and DataParallel.reports()
        options["episodes"] = online_source(config, options.get("device"), progress=progress)
    return train_cmd(data, out=out, online=config, **options)


def tokenize(robots, *, ee_sites: Sequence[str] | None = None) -> Embodiments:
    """RoboTokens of robots (``tt tokenize``): the embodiment tokens (links, joints, actuators)
    the DiT reads and writes.

    robots: an MJCF or URDF file, a design file spec (``designs.json``, ``designs.json#i``,
    ``best.json``), a `mujoco.MjModel`, a `Design`, or a list of models and designs.
    ee_sites: the end-effector sites in order (None: the sites named ``ee_0``, ``ee_1``, ...).
    What RoboTokens cannot represent exactly is warned about (`tt.tokens.TokenizeWarning`:
    meshes become boxes, tendons are dropped); a robot they cannot hold raises
    `tt.tokens.TokenizeError` (a `TTError`).

    Returns `tt.tokens.Embodiments`: ``tokens`` (a `TokenBatch`: ``counts()`` per type,
    ``save(path)`` the ``.npz`` that ``tt detokenize`` reads) and ``index``, per robot, which
    MuJoCo element each token came from."""
    from tt.tokens import TokenizeConfig, tokenize_models

    return tokenize_models(_models(robots), TokenizeConfig(ee_sites=None if ee_sites is None else tuple(ee_sites)))


def detokenize(tokens: TokenBatch | Embodiments | str | Path, *, model: str = "robot") -> list[DetokenizeResult]:
    """Robots back from RoboTokens (``tt detokenize``): MJCF text compiled by MuJoCo.

    tokens: a `TokenBatch`, the `Embodiments` of `tokenize`, or a tokens ``.npz`` file
    (``tt tokenize --out``, ``TokenBatch.save``). model: the MJCF model name. Returns one
    `tt.tokens.DetokenizeResult` per robot: ``xml`` (the MJCF), ``model`` (the `mujoco.MjModel`;
    None when MuJoCo refused it, with the reason in ``error``; ``ok`` says which) and
    ``notes`` on anything repaired. Bad tokens give a result that is not ``ok``; they do not
    raise."""
    from tt.tokens import DetokenizeConfig, TokenBatch
    from tt.tokens import detokenize as _detokenize

    if isinstance(tokens, (str, Path)):
        tokens = TokenBatch.load(tokens)
    tokens = getattr(tokens, "tokens", tokens)
    return _detokenize(tokens, DetokenizeConfig(model=model))


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


def _models(robots) -> list[mujoco.MjModel]:
    """MuJoCo models from a robot file / design file spec, a model, a design, or a list of
    models and designs."""
    import mujoco

    from tt.kernels.errors import TTError
    from tt.sim.designs import Design

    if isinstance(robots, (str, Path)):
        from tt.tokens.cli import _load_robots  # the robots of a file, as `tt tokenize` reads them

        return [m for _, _, m in _load_robots(str(robots))]
    items = [robots] if isinstance(robots, (mujoco.MjModel, Design)) else list(robots)
    if not items:
        raise TTError("tokenize: no robots given; pass an MJCF file, a mujoco.MjModel, a Design or a list of them")
    out = []
    for i, r in enumerate(items):
        if isinstance(r, Design):
            r = get_space(r.space).model(r)
        if not isinstance(r, mujoco.MjModel):
            raise TTError(f"tokenize: robots[{i}] is a {type(r).__name__}; give mujoco.MjModel or Design objects")
        out.append(r)
    return out


def _one_space(designs: Sequence[Design]) -> str:
    spaces = sorted({d.space for d in designs})
    if len(spaces) > 1:
        from tt.kernels.errors import TTError

        raise TTError(f"designs from several spaces in one call: {spaces}")
    return spaces[0]


def _default_motion(space: str) -> str:
    """The motion run when none is named: the toss, or the bimanual fling for two-arm spaces."""
    from tt.sim.motions import default_motion

    return default_motion(get_space(space).ee_count)


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
    "DEFAULT_REWARD",
    "DEFAULT_SEED",
    "DEFAULT_SPACE",
    "control_checkpoint",
    "dataset_info",
    "detokenize",
    "generate_dataset",
    "get_space",
    "load_motion",
    "motion",
    "optimize",
    "predict",
    "predict_checkpoint",
    "rollout",
    "save_motion",
    "tokenize",
    "train",
    "validate",
    "view",
]
