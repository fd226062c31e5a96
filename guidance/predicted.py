"""What the model is asked for a motion, and the reward of what it predicts.

The motion-to-robot query. For one motion, a sequence holds the target poses of S control
steps (the layout's window, 8 in the paper) as conditioning tokens, and every embodiment,
dynamics and action slot of the layout to be diffused. IDs are positional: embodiment
slot i of a type is entity i (types with a joint-order ID hold two slots per entity:
entity i // 2, order i % 2); per-step slot j of a step is entity j at that step's time
ID. The robot does not exist yet, so every slot gets the ID a real token in that slot
would have; the model's padding prediction (every value at PAD_VALUE) says which slots
the robot does not use.

Which steps. ``"even"`` (default) takes the midpoints of S equal strata of the motion,
``floor((k + 1/2) T / S)`` for k < S: every candidate is judged on the same steps, and
the steps cover the whole motion. ``"random"`` draws S distinct steps uniformly per
sequence, as training windows are drawn (`tt.tokens.episodes.sample_steps`).

A motion shorter than the window (T < S). Every placement then takes all T steps, in
order, and fills the window's S - T later slots with the last step repeated, as
`tt.tokens.episodes.sample_steps` lays out a short episode; those slots are not the
motion's and are not scored (`scored_steps`): the reward, its termination, the
embodiment penalty and every metric count the motion's own T steps, as `tt validate`
does. (No training window is shorter than S, so the model's predictions on such a motion
are out of its training distribution; they are scored, not trusted more.)

The predicted reward. From the predicted clean tokens x0 (normalised; `sample`'s x0_hat
or its final tokens): denormalise (`tt.dit.Normalizer`, differentiable), then

* track-link observations -> end-effector poses at the S steps: position as is; the 9
  rotation values are projected onto SO(3) by Gram-Schmidt on the first two columns (no
  SVD, so gradients stay finite), then turned into a quaternion;
* actuator observations -> actuator force and velocity; slots the predicted robot does not
  use (its actuator token, or failing that the observation itself, is padding) count 0;
* link tokens -> size and mass (`token_size`, `token_mass`, the formulas of
  `tt.sim.rewards.robot_size` / `robot_mass` on token values).

These fill a `RewardInputs` of S steps, evaluated by `tt.sim.rewards.evaluate`, the
one definition of each reward. The S steps are a sample of the motion's T steps, so the
episode reward is estimated as (T / S) x the S-step reward: each counted step stands for
T / S steps of the motion, and the embodiment penalty, S alpha excess over S steps, scales
to T alpha excess, exactly the full episode's penalty. (For T < S: the T scored steps are
the motion's, each stands for itself, and the factor is 1.) Termination applies to the
subsample (the first of the S steps whose summed position error exceeds the threshold
ends the count). Falls are not predicted (no token says the robot fell).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tt.dit.layout import Layout, LayoutError, slot_ids
from tt.kernels.errors import TTError
from tt.kernels.rotations import quat_to_mat
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardConfig, RewardInputs, evaluate, log_reward
from tt.tokens.batch import TokenBatch
from tt.tokens.encodings import decode_binary, decode_log
from tt.tokens.normalize import Normalizer, is_padding
from tt.tokens.schema import GEOM_TYPES, SCHEMA, STEP_ROLES, Role

#: Ways to choose a query's control steps (see the module docstring; "start": step 0, then
#: the "even" steps after the first, for a critic told the episode's start).
PLACEMENTS = ("even", "random", "start")

_SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX = (
    GEOM_TYPES.index(n) for n in ("sphere", "capsule", "ellipsoid", "cylinder", "box")
)


# ------------------------------------------------------------------------------ steps
def query_steps(
    motion_steps: int, window: int, count: int, *, placement: str = "even", generator: torch.Generator | None = None
) -> torch.Tensor:
    """Control steps of `count` sequences of one motion, (count, window) long, ascending.

    motion_steps: T of the motion; window: S steps per sequence; placement: "even" or
    "random"; generator: CPU generator for "random". A motion shorter than the window gets
    its T steps, then its last step repeated, whatever the placement (`scored_steps`: only
    the first T are scored).
    """
    if placement not in PLACEMENTS:
        raise TTError(f"placement {placement!r} is not one of {list(PLACEMENTS)}")
    if motion_steps < 1 or window < 1:
        raise TTError(f"a query needs motion_steps >= 1 and window >= 1, got {motion_steps} and {window}")
    if motion_steps < window:  # every step, then the last repeated (not scored, `scored_steps`)
        steps = torch.arange(window).clamp(max=motion_steps - 1)
        return steps[None].expand(count, window).clone()
    if placement in ("even", "start"):
        k = torch.arange(window, dtype=torch.float64)
        steps = torch.floor((k + 0.5) * motion_steps / window).long().clamp(max=motion_steps - 1)
        if placement == "start":
            steps[0] = 0
        return steps[None].expand(count, window).clone()
    from tt.tokens.episodes import sample_steps

    steps, _ = sample_steps(
        torch.full((count,), motion_steps, dtype=torch.long), window, "random", generator, horizon=motion_steps
    )
    return steps


def scored_steps(motion_steps: int, window: int) -> int:
    """How many of a query's `window` steps are scored: all S of them, or the T steps of a
    motion shorter than the window (`query_steps` puts them first; the window's later slots
    repeat the last step and are no steps of the motion)."""
    return min(int(motion_steps), int(window))


# ------------------------------------------------------------------------------ query
@dataclass
class RobotQuery:
    """B motion-to-robot sequences of one motion.

    tokens: normalised tokens, conditioning set, diffused slots at 0 (the sampler replaces
        them with noise); steps: (B, S) control steps of each sequence's window;
    motion_steps: T, the motion's length in steps; target_pos (B, S, A, 3) [m] and
    target_quat (B, S, A, 4) (w, x, y, z): the targets at those steps, float32.
    """

    tokens: TokenBatch
    steps: torch.Tensor
    motion_steps: int
    target_pos: torch.Tensor
    target_quat: torch.Tensor

    @property
    def track_count(self) -> int:
        return int(self.target_pos.shape[2])

    @property
    def scored(self) -> int:
        """Steps of the window the reward counts (`scored_steps`): S, or T for a shorter motion."""
        return scored_steps(self.motion_steps, self.steps.shape[1])


def build_query(
    layout: Layout,
    normalizer: Normalizer,
    motion: Motion,
    count: int,
    *,
    placement: str = "even",
    generator: torch.Generator | None = None,
    device: str | torch.device = "cpu",
) -> RobotQuery:
    """`count` motion-to-robot sequences conditioned on `motion` (see the module docstring).

    layout: the model's layout (RoboToken schema types, with ``target_pose``); normalizer:
    the model's; generator: CPU generator for ``placement="random"``.
    Raises LayoutError when the layout cannot hold the motion (no target tokens, fewer
    track slots than end effectors, a motion longer than the time-ID table).
    """
    if count < 1:
        raise TTError(f"count must be >= 1, got {count}")
    if "target_pose" not in layout:
        raise LayoutError(f"the model's layout has no target_pose tokens to condition on; types: {list(layout.names)}")
    target_spec = layout["target_pose"]
    arms = motion.arms
    if target_spec.per_step < arms:
        raise LayoutError(
            f"motion {motion.name!r} has {arms} end effectors, the model's layout {target_spec.per_step} track slots"
        )
    time_rows = layout.id_sizes.get("time", 0)
    if motion.steps > time_rows:
        raise LayoutError(
            f"motion {motion.name!r} has {motion.steps} steps, the model's time IDs only {time_rows} rows"
        )
    S = layout.steps
    steps = query_steps(motion.steps, S, count, placement=placement, generator=generator)  # (B, S)
    pos = torch.as_tensor(motion.pos, dtype=torch.float64)[steps]  # (B, S, A, 3)
    quat = torch.as_tensor(motion.quat, dtype=torch.float64)[steps]  # (B, S, A, 4)
    values, ids, mask = {}, {}, {}
    for spec in layout.specs:
        per = spec.per_step if spec.role in STEP_ROLES else spec.length
        slot = slot_ids(spec, per, layout.id_sizes)  # (P, K)
        if spec.role in STEP_ROLES:
            i = slot[None, None].expand(count, S, per, len(spec.ids)).clone()  # (B, S, P, K)
            i[..., spec.time_index] = steps[:, :, None]
            ids[spec.name] = i.reshape(count, S * per, -1)
        else:
            ids[spec.name] = slot[None].expand(count, per, len(spec.ids)).clone()
        if spec.role is Role.CONDITION:
            if spec.name != "target_pose":
                raise LayoutError(
                    f"conditioning type {spec.name!r} is not a target pose; this query fills target_pose only"
                )
            raw = np.zeros((count, S, per, spec.dim))
            t = SCHEMA["target_pose"]
            raw[:, :, :arms, t.slice("pos")] = pos.numpy()
            raw[:, :, :arms, t.slice("rot")] = quat_to_mat(quat.numpy()).reshape(count, S, arms, 9)
            real = torch.zeros(count, S, per, dtype=torch.bool)
            real[:, :, :arms] = True
            real = real.reshape(count, S * per)
            raw_t = torch.as_tensor(raw, dtype=torch.float32).reshape(count, S * per, spec.dim)
            values[spec.name] = normalizer.normalize_values(spec.name, raw_t, real)
            mask[spec.name] = real
        else:
            values[spec.name] = torch.zeros(count, spec.length, spec.dim)
            mask[spec.name] = torch.ones(count, spec.length, dtype=torch.bool)
    tokens = TokenBatch(values, ids, mask).to(device)
    return RobotQuery(tokens, steps.to(device), int(motion.steps), pos.float().to(device), quat.float().to(device))


def design_query(
    layout: Layout,
    normalizer: Normalizer,
    motion: Motion,
    models,
    *,
    placement: str = "even",
    generator: torch.Generator | None = None,
    device: str | torch.device = "cpu",
) -> tuple[RobotQuery, dict[str, torch.Tensor]]:
    """A motion-to-robot query for given robots: `build_query` with one sequence per model
    whose embodiment slots hold that robot's tokens (normalised; padding at PAD_VALUE with
    its slot ID, as in training). Returns (query, known): known marks those slots (type ->
    (B, L) bool), for `tt.dit.sampling.sample`'s inpainting, so the model predicts the
    dynamics of these robots on the motion instead of inventing a robot.

    models: compiled MuJoCo models (`DesignSpace.model`). Raises LayoutError for a robot
    that does not fit the layout.
    """
    from tt.dit.layout import robot_embodiment

    query = build_query(
        layout, normalizer, motion, len(models), placement=placement, generator=generator, device=device
    )
    emb, _ = robot_embodiment(layout, normalizer, models, device)
    # The query's masks stay all-True: in the robot task every slot is visible, padding included.
    query.tokens = TokenBatch({**query.tokens.values, **emb.values}, {**query.tokens.ids, **emb.ids}, query.tokens.mask)
    static = [s for s in layout.specs if s.role is Role.EMBODIMENT]
    known = {s.name: torch.ones(len(models), s.length, dtype=torch.bool, device=device) for s in static}
    return query, known


def _mjbatch_first_step(models, motions):
    """The mjbatch episodes of every model on every motion, cut after the first control step's
    look-ahead target (`tt.sim.wbc.WBCConfig.lookahead_steps`): step 0 is the full episode's
    (the controller's start posture and first target are the same), at a few steps' cost."""
    from tt.sim.rollout import rollout
    from tt.sim.wbc import WBCConfig

    keep = WBCConfig().lookahead_steps + 2
    cut = [Motion(m.name, m.pos[:keep], m.quat[:keep], m.dt) for m in motions]
    return rollout(models, cut, backend="mjbatch", device="cpu")


def start_tokens(
    layout: Layout, normalizer: Normalizer, designs, motions, *, models=None, device: str | torch.device = "cpu"
) -> dict[str, torch.Tensor]:
    """Each design's first control step on each motion, simulated, as a model takes it: the
    normalised per-step tokens of step 0, type -> (M, D, P, dim) for every per-step type the
    model predicts (P: the layout's slots per step; padding at PAD_VALUE).

    One batched warp rollout runs one control step of every design on every motion (the
    controller looking ahead along the whole motion, as in the full episode; for a space with
    contacts, the quadruped, mjbatch on the motions cut after the first look-ahead), and the records
    go through the training data's path (`tt.tokens.episodes.episode_tokens`,
    `tt.dit.data.EpisodeTokens`, `with_slot_ids`, the normaliser), so the tokens are those of
    the full episodes' step 0.
    designs: D `tt.sim.designs.Design` of one space; motions: M motions placed for it;
    models: their compiled models when the caller has them (`DesignSpace.model`).
    """
    import warnings

    import warp as wp

    from tt.dit.data import EpisodeTokens
    from tt.dit.layout import with_slot_ids
    from tt.sim.backends import default_backend
    from tt.sim.controller import IKConfig
    from tt.sim.designs import get_space
    from tt.sim.rollout import group_episode, rollout_records
    from tt.tokens.episodes import episode_tokens
    from tt.tokens.tokenize import Tokenizer, TokenizeWarning

    device = torch.device(device)
    space = get_space(designs[0].space)
    models = [space.model(d) for d in designs] if models is None else list(models)
    trees = space.trees(designs)
    D, M = len(designs), len(motions)
    wp.init()  # mapping the torch device needs Warp's runtime, which this may be the first to use
    if default_backend(space.name) == "warp":
        records = rollout_records(
            models if trees is None else trees,
            space.ee_sites(),
            motions,
            device=str(wp.device_from_torch(device)),
            steps=1,
        )
        dt = IKConfig().control_dt
        groups = [
            (members, group_episode(members, arrays, M, models[members[0]].nu, perturbed=False, dt=dt))
            for members, arrays in records
        ]
    else:  # contacts: MuJoCo C's own physics (mjbatch), one padded episode of every design
        groups = [(list(range(D)), _mjbatch_first_step(models, motions))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TokenizeWarning)
        emb = Tokenizer()(models)
    counts = {s.name: s.per_step if s.role in STEP_ROLES else s.length for s in layout.specs}
    parts, worlds = [], []
    for members, ep in groups:
        first = torch.zeros((ep.worlds, 1), dtype=torch.long, device=ep.qpos.device)
        dynamics = episode_tokens(ep, emb.index, step_index=first)
        tokens = EpisodeTokens.from_token_batches(
            emb.tokens,
            dynamics,
            torch.ones(ep.worlds, dtype=torch.long),
            design_index=ep.design_index.cpu(),
            max_time=layout.id_sizes.get("time", 1024),
        )
        parts.append(tokens.pad_to(counts))
        worlds += [d * M + j for d in members for j in range(M)]  # the group's worlds, design-major
    data = EpisodeTokens.concatenate(parts)
    rows = torch.as_tensor(np.argsort(worlds), dtype=torch.long)  # world d * M + j: design d on motion j
    raw = data.window(rows, torch.zeros((D * M, layout.steps), dtype=torch.long))
    tokens = normalizer.normalize(with_slot_ids(layout, raw))
    return {
        s.name: tokens.values[s.name][:, : s.per_step].reshape(D, M, s.per_step, -1).transpose(0, 1).to(device)
        for s in layout.specs
        if s.role in STEP_ROLES and s.role is not Role.CONDITION
    }


def with_start(tokens: TokenBatch, first: dict[str, torch.Tensor]) -> TokenBatch:
    """A "start" query's tokens with step 0 set: first, type -> (B, P, D), one motion's slice of
    `start_tokens` (P: the slots per step; step 0 is the first P slots of each per-step type)."""
    values = dict(tokens.values)
    for name, v in first.items():
        values[name] = values[name].clone()
        values[name][:, : v.shape[1]] = v
    return TokenBatch(values, tokens.ids, tokens.mask)


# ------------------------------------------------------------------------------ critic
class CheckpointSpaceError(TTError):
    """A checkpoint trained on one design space asked about designs of another."""


def check_space(trained, space: str) -> None:
    """Raise `CheckpointSpaceError` when `trained` (a `tt.dit.checkpoint.TrainedModel`) was
    trained on a design space other than `space` (a checkpoint that recorded none passes;
    its layout still has to hold the robots)."""
    if trained.space is not None and trained.space != space:
        where = f"checkpoint {trained.path}" if trained.path is not None else "the model"
        raise CheckpointSpaceError(
            f"{where} was trained on design space {trained.space!r}, the designs are of space "
            f"{space!r}; give a checkpoint trained on {space!r} (--checkpoint)"
        )


@dataclass
class DesignPrediction:
    """The model's prediction for D given designs x M motions.

    reward: (D, M) predicted episode reward (reported alphas), the mean over `samples`
    samples; metrics: name -> (D, M) predicted metrics (`predicted_metrics`), means over the
    samples (NaN-free ones); samples: K; seconds: wall time of sampling and scoring;
    log_reward: (D, M) the smooth stand-in `tt.sim.rewards.log_reward` of the same samples,
    the mean of the finite ones, when asked for (``predict_designs(log=True)``), else None.
    """

    reward: np.ndarray
    metrics: dict[str, np.ndarray]
    samples: int
    seconds: float
    log_reward: np.ndarray | None = None


#: DDIM steps of a critic's prediction by default. On the R2 dynamics critic
#: (`benchmarks/results/dit_ladder_r2c.md`, step 2,000) held-out r is flat from 5 steps to all
#: 100 (0.43 / 0.41 / 0.38 / 0.36 pooled at 5 / 10 / 20 / 100) and collapses at 1 (0.07): 10
#: steps cost a tenth of 100.
CRITIC_DDIM_STEPS = 10


#: How `predict_designs` gives the model a design: as the dynamics task's clean condition, or
#: by inpainting it into the robot task.
VIAS = ("dynamics", "inpaint")


def default_via(trained) -> str:
    """How `predict_designs` gives `trained` a design by default: "dynamics" when it was
    trained on the dynamics task, else "inpaint"."""
    return "dynamics" if trained.trained_on("dynamics") else "inpaint"


def predict_designs(
    trained,
    designs,
    motions,
    cfg: RewardConfig,
    *,
    samples: int = 1,
    num_steps: int | None = CRITIC_DDIM_STEPS,
    seed: int = 0,
    placement: str = "even",
    chunk: int | None = None,
    device: str | torch.device | None = None,
    via: str | None = None,
    common_noise: bool = False,
    log: bool = False,
) -> DesignPrediction:
    """The model as a critic: predicted dynamics and reward of each design on each motion.

    Each design's embodiment tokens are given to the model (`design_query`), the model
    predicts the dynamics at the query's steps (`tt.dit.sampling.sample`), and
    `PredictedReward` scores them; with samples K, K samples per pair are averaged. How the
    design is given (``via``): "dynamics", the dynamics task's clean condition (the model
    must have been trained on that task), or "inpaint", the robot task with the embodiment
    inpainted (replacement method); None: "dynamics" when the model was trained on it. All
    D x M x K sequences go through one sampling call (``chunk``: at most that many sequences
    per call, for memory). A model trained told the episode's start (``dynamics_start``) is
    given it: each design's first control step on each motion is simulated (`start_tokens`,
    about 1 % of an episode's cost) and the query's steps are step 0 and the "even" ones after
    it, whatever ``placement`` says.

    trained: `tt.dit.checkpoint.TrainedModel`; designs: D `tt.sim.designs.Design` of one
    space, the space the checkpoint was trained on (`check_space`); motions: M motions
    placed for the space; cfg: the reward; num_steps: DDIM steps (`CRITIC_DDIM_STEPS` by
    default; None: all of the robot task's); seed: of the sampling noise; device: None for the model's; via: see above;
    common_noise: every design gets the same starting noise for a given motion and sample, so
    differences between the designs' predictions are the designs' and not the noise's (central
    differences, `tt.guidance.refine`; with eta 0 and via "dynamics" the sampling is then
    deterministic per row, inpainting draws fresh noise each step); log: also score the
    samples with the reward's smooth stand-in (`DesignPrediction.log_reward`).
    Raises CheckpointSpaceError, LayoutError (a robot or motion the layout cannot hold) and
    ValueError (bad arguments).
    """
    import time

    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import TaskSpec
    from tt.sim.designs import get_space

    designs, motions = list(designs), list(motions)
    via = default_via(trained) if via is None else via
    if via not in VIAS:
        raise TTError(f"via {via!r} is not one of {list(VIAS)}")
    if via == "dynamics" and not trained.trained_on("dynamics"):
        raise TTError(
            f"the model was trained on the tasks {list(trained.tasks)}, not 'dynamics', so it cannot take a "
            "design as a condition; train with --task robot+dynamics, or predict with via='inpaint'"
        )
    if not designs or not motions:
        raise TTError(f"predict needs at least one design and one motion, got {len(designs)} and {len(motions)}")
    if samples < 1:
        raise TTError(f"samples must be >= 1, got {samples}")
    if chunk is not None and chunk < 1:
        raise TTError(f"chunk must be >= 1 or None, got {chunk}")
    spaces = sorted({d.space for d in designs})
    if len(spaces) > 1:
        raise TTError(f"designs from several spaces in one call: {spaces}")
    check_space(trained, spaces[0])
    if device is None:
        held = next(iter(trained.model.parameters()), None)
        device = held.device if held is not None else "cpu"
    device = torch.device(device)
    start = time.perf_counter()
    model = trained.model.to(device).eval()
    layout, norm = trained.layout, trained.normalizer
    sp = get_space(spaces[0])
    D, M, K = len(designs), len(motions), int(samples)
    models = [sp.model(d) for d in designs]
    repeated = [m for m in models for _ in range(K)]  # row i * K + k: design i, sample k
    from_start = via == "dynamics" and trained.dynamics_start
    # A model trained told the episode's first step is given it, simulated.
    first = start_tokens(layout, norm, designs, motions, models=models, device=device) if from_start else None
    queries, tokens, known = [], [], []
    for j, m in enumerate(motions):
        q, kn = design_query(
            layout,
            norm,
            m,
            repeated,
            placement="start" if from_start else placement,
            generator=torch.Generator().manual_seed(int(seed)),
            device=device,
        )
        if first is not None:
            q.tokens = with_start(q.tokens, {name: v[j].repeat_interleave(K, dim=0) for name, v in first.items()})
        queries.append(q)
        tokens.append(q.tokens)
        known.append(kn)
    tokens = TokenBatch.concatenate(tokens)  # (M * D * K) sequences, motion-major
    known = {n: torch.cat([k[n] for k in known]) for n in known[0]}
    total = len(tokens)
    chunk = total if chunk is None else min(int(chunk), total)
    generator = torch.Generator(device=device).manual_seed(int(seed))
    task = TaskSpec(
        "dynamics" if via == "dynamics" else "robot", trained.robot_diffusion_steps, "start" if from_start else "random"
    )
    shared = None
    if common_noise:
        from tt.dit.tasks import output_types

        # Rows are motion-major, then design, then sample: one draw per (motion, sample). Every
        # type is drawn, in the tokens' order, so the stream (and the recorded results) stay
        # those of the first version; only the types the task diffuses are used.
        shared = {
            n: torch.randn((M, 1, K, *v.shape[1:]), generator=generator, device=device)
            .expand(M, D, K, *v.shape[1:])
            .reshape(total, *v.shape[1:])
            for n, v in tokens.values.items()
        }
        shared = {n: v for n, v in shared.items() if n in output_types(task, layout)}
    scheduler = CosineDDIM(task.diffusion_steps)
    values = []
    for c0 in range(0, total, chunk):
        rows = slice(c0, min(c0 + chunk, total))
        part = tokens.select(rows)
        res = sample(
            model,
            part,
            task,
            scheduler=scheduler,
            num_steps=num_steps,
            generator=generator,
            known=None if via == "dynamics" else {n: k[rows] for n, k in known.items()},
            init_noise=None if shared is None else {n: v[rows] for n, v in shared.items()},
        )
        values.append(res.tokens.values)
    values = {n: torch.cat([v[n] for v in values]) for n in values[0]}
    reward = np.zeros((D, M))
    smooth = np.full((D, M), np.nan) if log else None
    metrics: dict[str, np.ndarray] = {}
    for j, q in enumerate(queries):
        rows = slice(j * D * K, (j + 1) * D * K)
        scorer = PredictedReward(layout, norm, cfg, q)
        per = predicted_metrics(scorer, {n: v[rows] for n, v in values.items()})
        if log:
            with torch.no_grad():
                smooth[:, j] = _finite_mean(scorer({n: v[rows] for n, v in values.items()}, log=True), D, K)
        for name, v in per.items():
            metrics.setdefault(name, np.full((D, M), np.nan))[:, j] = _finite_mean(v, D, K)
        reward[:, j] = metrics["reward"][:, j]
    return DesignPrediction(reward, metrics, K, time.perf_counter() - start, smooth)


def _finite_mean(v: torch.Tensor, D: int, K: int) -> np.ndarray:
    """(D * K,) values, design-major -> (D,) the mean of each design's finite samples (NaN where none is)."""
    arr = v.double().cpu().numpy().reshape(D, K)
    counted = np.isfinite(arr)
    mean = np.where(counted, arr, 0.0).sum(1) / np.maximum(counted.sum(1), 1)
    return np.where(counted.any(1), mean, np.nan)


# ------------------------------------------------------------------------------ geometry
def orthonormalize(m: torch.Tensor) -> torch.Tensor:
    """Nine values (..., 9) row-major -> rotation matrices (..., 3, 3) by Gram-Schmidt on the
    first two columns (third = their cross product). Exact on rotations; differentiable
    wherever the first two columns are independent (degenerate input gets a finite result)."""
    r = m.reshape(*m.shape[:-1], 3, 3)
    a, b = r[..., :, 0], r[..., :, 1]
    e1 = a / torch.linalg.vector_norm(a, dim=-1, keepdim=True).clamp_min(1e-8)
    b = b - (e1 * b).sum(-1, keepdim=True) * e1
    e2 = b / torch.linalg.vector_norm(b, dim=-1, keepdim=True).clamp_min(1e-8)
    e3 = torch.linalg.cross(e1, e2, dim=-1)
    return torch.stack([e1, e2, e3], dim=-1)


def matrix_to_quat(r: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (w, x, y, z).

    Each of the four classic formulas gives 4 q_i q from linear terms of R; the one with the
    largest q_i^2 (at least 1/4 for a rotation) is used and normalised, so no square root
    and no division by a small number enters the gradient.
    """
    r00, r01, r02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    r10, r11, r12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    r20, r21, r22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    cand = torch.stack(
        [
            torch.stack([1 + r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01], -1),
            torch.stack([r21 - r12, 1 + r00 - r11 - r22, r01 + r10, r02 + r20], -1),
            torch.stack([r02 - r20, r01 + r10, 1 - r00 + r11 - r22, r12 + r21], -1),
            torch.stack([r10 - r01, r02 + r20, r12 + r21, 1 - r00 - r11 + r22], -1),
        ],
        -2,
    )  # (..., 4 formulas, 4)
    pick = torch.diagonal(cand, dim1=-2, dim2=-1).argmax(-1)  # (...)
    q = torch.gather(cand, -2, pick[..., None, None].expand(*pick.shape, 1, 4)).squeeze(-2)
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)


def token_size(geom_code: torch.Tensor, size: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """Robot size [m] from link tokens, (B,): the sum over real links of each geom's longest
    dimension, as `tt.sim.rewards.robot_size` measures a compiled model.

    geom_code: (B, L) long (`tt.tokens.schema.GEOM_TYPES`; unknown codes count 0);
    size: (B, L, 3) MuJoCo size convention [m] (negative values count 0); real: (B, L) bool.
    """
    s = size.clamp_min(0.0)
    r, h = s[..., 0], s[..., 1]
    longest = torch.zeros_like(r)
    longest = torch.where(geom_code == _SPHERE, 2 * r, longest)
    longest = torch.where(geom_code == _CAPSULE, 2 * (r + h), longest)
    longest = torch.where(geom_code == _CYLINDER, 2 * torch.maximum(r, h), longest)
    box_like = (geom_code == _BOX) | (geom_code == _ELLIPSOID)
    longest = torch.where(box_like, 2 * s.amax(-1), longest)
    return torch.where(real, longest, torch.zeros_like(longest)).sum(-1)


def token_mass(mass: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """Robot mass [kg] from link masses (B, L) [kg] of real links (B, L), (B,): the links
    carry the whole body masses (`tt.tokens.inertia` splits each body over its links), so
    their sum is `tt.sim.rewards.robot_mass`."""
    return torch.where(real, mass, torch.zeros_like(mass)).sum(-1)


# ------------------------------------------------------------------------------ reward
def _attr(name: str, raw: torch.Tensor, attr: str) -> torch.Tensor:
    return raw[..., SCHEMA[name].slice(attr)]


class PredictedReward:
    """The reward of predicted tokens for one `RobotQuery` (see the module docstring).

    layout, normalizer: the model's; cfg: the reward; query: the sequences x0 belongs to.
    Calling it on x0 (type -> (B, L, D) normalised) returns the episode reward estimate,
    (B,), differentiable in x0.
    """

    def __init__(self, layout: Layout, normalizer: Normalizer, cfg: RewardConfig, query: RobotQuery):
        self.layout = layout
        self.normalizer = normalizer
        self.cfg = cfg
        self.query = query
        need = ["track_link_obs"]
        if "act_force" in cfg.needs or "act_vel" in cfg.needs:
            need.append("actuator_obs")
        if "size" in cfg.needs or "mass" in cfg.needs:
            need.append("link")
        missing = [n for n in need if n not in layout]
        if missing:
            raise LayoutError(
                f"reward {cfg.name!r} reads predicted {missing}, which the model's layout lacks; "
                f"types: {list(layout.names)}"
            )
        if layout["track_link_obs"].per_step < query.track_count:
            raise LayoutError(
                f"the layout has {layout['track_link_obs'].per_step} track-link slots per step, "
                f"the motion {query.track_count} end effectors"
            )

    @property
    def scale(self) -> float:
        """T / S: motion steps each predicted step stands for (1 for a motion shorter than
        the window, whose T steps are all scored)."""
        return self.query.motion_steps / self.query.scored

    def _step_view(self, name: str, raw: torch.Tensor) -> torch.Tensor:
        """(B, S * P, D) -> (B, S, P, D)."""
        spec = self.layout[name]
        return raw.reshape(raw.shape[0], self.layout.steps, spec.per_step, raw.shape[-1])

    def inputs(self, x0: dict[str, torch.Tensor]) -> RewardInputs:
        """`RewardInputs` of S steps from predicted tokens (all fields the layout allows)."""
        norm, A = self.normalizer, self.query.track_count
        track = self._step_view("track_link_obs", norm.denormalize_values("track_link_obs", x0["track_link_obs"]))[
            :, :, :A
        ]
        ee_pos = _attr("track_link_obs", track, "pos")  # (B, S, A, 3)
        ee_quat = matrix_to_quat(orthonormalize(_attr("track_link_obs", track, "rot")))  # (B, S, A, 4)
        fields = {}
        if "actuator_obs" in self.layout:
            obs = self._step_view(
                "actuator_obs", norm.denormalize_values("actuator_obs", x0["actuator_obs"])
            )  # (B, S, P, 2)
            p = obs.shape[2]
            with torch.no_grad():
                if "actuator" in self.layout and self.layout["actuator"].length >= p:
                    used = ~is_padding(x0["actuator"][:, :p])[:, None, :]  # (B, 1, P)
                else:
                    used = ~is_padding(self._step_view("actuator_obs", x0["actuator_obs"]))  # (B, S, P)
            zero = torch.zeros((), dtype=obs.dtype, device=obs.device)
            fields["act_force"] = torch.where(used, _attr("actuator_obs", obs, "force")[..., 0], zero)
            fields["act_vel"] = torch.where(used, _attr("actuator_obs", obs, "velocity")[..., 0], zero)
        if "link" in self.layout:
            link = norm.denormalize_values("link", x0["link"])  # (B, L, 35)
            with torch.no_grad():
                real = ~is_padding(x0["link"])
                code = decode_binary(_attr("link", link, "geom_type"))
            fields["size"] = token_size(code, _attr("link", link, "size"), real)
            mass_attr = SCHEMA["link"].attribute("mass")
            fields["mass"] = token_mass(decode_log(_attr("link", link, "mass")[..., 0], mass_attr.log_offset), real)
        q = self.query
        dtype = ee_pos.dtype
        # The window's slots past a short motion's last step are no steps of it: not scored.
        scored = torch.full((ee_pos.shape[0],), q.scored, dtype=torch.long, device=ee_pos.device)
        return RewardInputs(
            ee_pos=ee_pos,
            ee_quat=ee_quat,
            target_pos=q.target_pos.to(dtype),
            target_quat=q.target_quat.to(dtype),
            motion_steps=scored,
            **{k: v.to(dtype) for k, v in fields.items()},
        )

    def __call__(self, x0: dict[str, torch.Tensor], *, guidance: bool = False, log: bool = False) -> torch.Tensor:
        """Episode reward estimate (T / S) x R_S, (B,); guidance: the guidance alphas; log: the
        smooth stand-in `tt.sim.rewards.log_reward` instead of the reward, scaled the same way."""
        inputs = self.inputs(x0)
        return self.scale * (
            log_reward(inputs, self.cfg, guidance=guidance)
            if log
            else evaluate(inputs, self.cfg, guidance=guidance).reward
        )


def predicted_metrics(reward: PredictedReward, x0: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Predicted metrics of each sequence (`tt.sim.rewards.metrics` on the scored steps: S,
    or a shorter motion's T, so ``length`` counts at most T; reward scaled to the motion
    length), detached, each (B,); plus ``query_pos_err``, the mean position error [cm] over
    all scored steps, counted or not: how far off the model puts the end effector, also
    where its prediction terminates the episode."""
    from tt.sim.rewards import metrics

    with torch.no_grad():
        inputs = reward.inputs(x0)
        out = metrics(inputs, reward.cfg)
        out["reward"] = out["reward"] * reward.scale
        n = reward.query.scored
        out["query_pos_err"] = query_position_error(inputs.ee_pos[:, :n], inputs.target_pos[:, :n])
    return out


def query_position_error(ee_pos: torch.Tensor, target_pos: torch.Tensor) -> torch.Tensor:
    """Mean position error [cm] over steps and end effectors, (B,), from (B, S, A, 3) poses [m]."""
    from tt.sim.rewards import position_error

    return 100.0 * position_error(ee_pos, target_pos).mean((1, 2))


__all__ = [
    "CRITIC_DDIM_STEPS",
    "VIAS",
    "default_via",
    "PLACEMENTS",
    "CheckpointSpaceError",
    "DesignPrediction",
    "PredictedReward",
    "RobotQuery",
    "build_query",
    "check_space",
    "design_query",
    "matrix_to_quat",
    "orthonormalize",
    "predict_designs",
    "predicted_metrics",
    "query_position_error",
    "query_steps",
    "scored_steps",
    "token_mass",
    "token_size",
]
