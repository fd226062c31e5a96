"""The masked diffusion tasks and the training objective.

``robot`` (motion-to-robot): condition on target poses; diffuse every embodiment,
dynamics and action token, padding included: padding tokens are targets at PAD_VALUE
that the model learns to produce (the detokenizer detects them), and nothing is masked in
attention. Windows are 8 random steps of an episode.

``dynamics`` (design-to-dynamics, the model as a critic): condition on the embodiment
(clean, padding slots included, so the model reads which slots the robot leaves empty) and
the target poses; diffuse every dynamics and action token as the robot task does. It asks
what a given design does on a motion. The robot task can answer that too, by inpainting
the embodiment (`tt.dit.sampling`'s replacement method), but there the model sees the
design only through noise as loud as the step's, so at the high noise levels where a
sample's coarse outcome (does the end effector reach the targets at all?) is decided, the
design is all but hidden. On R0 (`benchmarks/results/dit_recipe.md`, x0 prediction) the
predicted rewards correlate with the simulated ones at r = 0.97 through this task and 0.30
through inpainting. Trained beside the robot task (``tt train --task robot+dynamics``),
one model serves both. With window "start" (``tt train dynamics_start``) every window
holds the episode's first step, whose state and command are a clean condition: the critic
is then told where the robot starts, which one simulated control step gives it (on R2 the
start tells failing pairs from tracking ones at AUC 0.96, the design alone at 0.65-0.70:
`benchmarks/results/critic_failures.md`).

``control`` (cross-embodiment control): condition on the embodiment, the current state
(dynamics tokens of the window's earliest step) and the targets of 8 consecutive steps; diffuse the
actions of all 8 steps, or, with ``known_command``, of the 7 after the earliest, whose command
(the one that led to the current state: a position servo's setpoint, which a controller
always knows) is then a clean condition too. A servo that lags its setpoint keeps the next
command close to the last one, not to the current position: on ViperX windows the last
command explains 40-98 % of the next command's offset from the current joint position per
joint (a linear fit), the current velocity 0-55 %, the end effector's position error ~0 %
(`benchmarks/results/control_probe.md`). The states of the later steps are diffused too (extra supervision
that costs no inference input; ``future_states=False`` leaves them out instead). Padding
tokens are masked out of attention and loss.

A unified model trains both: each sample carries its own noise mask (fed to the model as
the noised-flag embedding), attention mask and diffusion time, so one forward pass
serves a batch that mixes the tasks.

Objective: epsilon prediction by default (or x0 or v, `tt.dit.ddim.PREDICTIONS`). For each
type, the elementwise loss (Huber with delta 1, as in the authors' configuration, or MSE)
between the network's output and its target (divided by the anchor's gain for an anchored
type with one, `tt.dit.anchors`: the residual's units, as min-max normalised delta actions
would have), times each sample's noise-level weight
(`tt.dit.ddim.CosineDDIM.loss_weight`: 1 unless a weighting is chosen), averaged over the
diffused entries of that type; the total is the sum over types, so each type weighs the same
whatever its token count, unless per-type weights scale the terms.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Mapping, Sequence

import torch
import torch.nn.functional as F

from tt.dit.ddim import CosineDDIM
from tt.dit.layout import Layout, LayoutError
from tt.dit.model import RoboDiT
from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import Role

#: Every task's name.
TASK_NAMES = ("robot", "dynamics", "control")


@dataclass(frozen=True)
class TaskSpec:
    """name: "robot", "dynamics" or "control"; diffusion_steps: T of its DDIM process; window: how the
    8 steps of a training window are drawn ("random", "consecutive", or for the dynamics task
    "start": step 0 and 7 random others, step 0's per-step tokens a clean condition); future_states
    (control): diffuse the states after step 0 (True) or leave them out (False);
    known_command (control): step 0's command is a clean condition (True) or diffused (False);
    target_offset (control): the target poses given at window slot i are those of step i +
    target_offset (`look_ahead`; 0: the window's own steps)."""

    name: str
    diffusion_steps: int
    window: str
    future_states: bool = True
    known_command: bool = False
    target_offset: int = 0

    def __post_init__(self) -> None:
        if self.name not in TASK_NAMES:
            raise TTError(f"task {self.name!r} does not exist; tasks: {', '.join(TASK_NAMES)}")
        if self.window not in ("random", "consecutive", "start"):
            raise TTError(f"task {self.name!r}: window {self.window!r} is not 'random', 'consecutive' or 'start'")
        if self.window == "start" and self.name != "dynamics":
            raise TTError(f"task {self.name!r}: window 'start' is the dynamics task's only")
        if self.diffusion_steps < 1:
            raise TTError(f"task {self.name!r}: diffusion_steps must be >= 1, got {self.diffusion_steps}")
        if self.target_offset < 0 or (self.target_offset and self.name != "control"):
            raise TTError(
                f"task {self.name!r}: target_offset {self.target_offset} must be >= 0, and 0 for tasks other "
                "than control"
            )


#: The paper's tasks: 100 DDIM steps for motion-to-robot, 5 for control; design-to-dynamics
#: (tt's) diffuses what the robot task diffuses, so it takes the robot task's process.
ROBOT = TaskSpec("robot", 100, "random")
DYNAMICS = TaskSpec("dynamics", 100, "random")
CONTROL = TaskSpec("control", 5, "consecutive")
TASKS = {"robot": ROBOT, "dynamics": DYNAMICS, "control": CONTROL}


def task_names(task: str) -> list[str]:
    """The tasks a training run's `task` names: one task, or distinct tasks joined by "+"
    ("robot+dynamics"); "both" is "robot+control". Raises ValueError for anything else."""
    names = ["robot", "control"] if task == "both" else str(task).split("+")
    if any(n not in TASK_NAMES for n in names) or len(set(names)) != len(names):
        raise TTError(
            f"task {task!r} is not one task or distinct tasks joined by '+'; tasks: "
            f"{', '.join(TASK_NAMES)} (and 'both' = robot+control)"
        )
    return names


def get_task(name: str) -> TaskSpec:
    if name not in TASKS:
        raise TTError(f"task {name!r} does not exist; tasks: {list(TASKS)}")
    return TASKS[name]


@dataclass
class TaskMasks:
    """Which tokens a task diffuses and which the model may see, for B sequences.

    noised: type -> (B, L) bool, tokens to denoise (all others stay at their given value);
    visible: type -> (B, L) bool, tokens that take part (False: masked out of attention and loss);
    attend: (B, N) bool over the concatenated sequence, or None when every token is visible.
    """

    noised: dict[str, torch.Tensor]
    visible: dict[str, torch.Tensor]
    attend: torch.Tensor | None

    def loss_mask(self, name: str) -> torch.Tensor:
        return self.noised[name] & self.visible[name]

    def attend_full(self, layout: Layout) -> torch.Tensor:
        """`attend`, materialised as (B, N) even when every token is visible."""
        if self.attend is not None:
            return self.attend
        return torch.cat([self.visible[n] for n in layout.names], dim=1)


def look_ahead(layout: Layout, tokens: TokenBatch, offset: int) -> TokenBatch:
    """Windows of ``layout.steps + offset`` consecutive steps -> windows of `layout.steps` steps
    whose target poses are those `offset` steps later.

    The control task's reference conditioning (the paper's code gives the actions of steps
    t .. t + 7 with the targets of t + 4 .. t + 11): DiffIK aims the command of step j at the
    target `lookahead_steps` later (`tt.sim.controller.IKConfig`), so with that offset each
    command token shares its time ID with the very target it was computed from. Every other
    per-step type keeps the first `layout.steps` steps; the targets keep those steps' time IDs.
    """
    S = layout.steps
    values, ids, mask = dict(tokens.values), dict(tokens.ids), dict(tokens.mask)
    for s in layout.specs:
        if not s.per_step:
            continue
        n, L = mask[s.name].shape
        e = s.per_step
        if L != (S + offset) * e:
            raise LayoutError(
                f"{s.name}: {L} tokens are not {S + offset} steps of {e} (a window of {S} + {offset} steps)"
            )
        keep = slice(offset, offset + S) if s.role is Role.CONDITION else slice(0, S)
        step = lambda x, sl: x.reshape(n, S + offset, e, *x.shape[2:])[:, sl].reshape(n, S * e, *x.shape[2:])  # noqa: E731
        values[s.name], mask[s.name] = step(values[s.name], keep), step(mask[s.name], keep)
        ids[s.name] = step(ids[s.name], slice(0, S)).clone()
        if s.role is Role.CONDITION:  # the targets' own IDs but for the time (the slot's)
            later = step(tokens.ids[s.name], keep)
            other = [k for k in range(later.shape[-1]) if k != s.time_index]
            ids[s.name][..., other] = later[..., other]
    return dataclasses.replace(tokens, values=values, ids=ids, mask=mask)


def task_windows(
    source,
    layout: Layout,
    n: int,
    task: TaskSpec,
    generator: torch.Generator | None = None,
    part: tuple[int, int] | None = None,
) -> TokenBatch:
    """n raw (unnormalised) windows of `task` from a token source (`tt.dit.data.TokenSource`):
    drawn as the task's window kind, cut to the task's target offset (`look_ahead`), every
    embodiment padding token carrying its slot's ID (`tt.dit.layout.with_slot_ids`). part: a
    data-parallel rank's windows (`tt.dit.data.EpisodeTokens.sample`)."""
    from tt.dit.layout import with_slot_ids

    raw = source.sample(n, layout.steps + task.target_offset, task.window, generator, part=part)
    if task.target_offset:
        raw = look_ahead(layout, raw, task.target_offset)
    return with_slot_ids(layout, raw)


def window_start(layout: Layout, tokens: TokenBatch) -> torch.Tensor:
    """Earliest time ID of each sequence's real per-step tokens, (B,) long (0 if it has none).

    Time IDs may be absolute control steps (`tt.tokens.episodes`) or window-relative; the
    control task's current step is this earliest one either way.
    """
    big = torch.iinfo(torch.long).max
    start = None
    for s in layout.specs:
        if s.per_step:
            t = tokens.ids[s.name][..., s.time_index].masked_fill(~tokens.mask[s.name], big).amin(dim=1)  # (B,)
            start = t if start is None else torch.minimum(start, t)
    if start is None:
        return torch.zeros(len(tokens), dtype=torch.long, device=tokens.device)
    return torch.where(start == big, torch.zeros_like(start), start)


def task_masks(task: TaskSpec, layout: Layout, tokens: TokenBatch) -> TaskMasks:
    """Noise and visibility masks of `task` for `tokens` (time IDs and padding masks are read)."""
    noised, visible = {}, {}
    from_start = task.name == "dynamics" and task.window == "start"
    start = window_start(layout, tokens) if task.name == "control" or from_start else None
    for s in layout.specs:
        real = tokens.mask[s.name]
        if task.name == "robot":
            noised[s.name] = torch.full_like(real, s.role is not Role.CONDITION)
            visible[s.name] = torch.ones_like(real)
            continue
        if task.name == "dynamics":
            noised[s.name] = torch.full_like(real, s.role not in (Role.CONDITION, Role.EMBODIMENT))
            if from_start and s.per_step and s.role not in (Role.CONDITION, Role.EMBODIMENT):
                noised[s.name] &= tokens.ids[s.name][..., s.time_index] != start[:, None]
            visible[s.name] = torch.ones_like(real)
            continue
        if s.role in (Role.EMBODIMENT, Role.CONDITION):
            noised[s.name] = torch.zeros_like(real)
            visible[s.name] = real
        elif s.role is Role.ACTION:
            current = tokens.ids[s.name][..., s.time_index] == start[:, None]
            noised[s.name] = real & ~current if task.known_command else real.clone()
            visible[s.name] = real
        else:
            current = tokens.ids[s.name][..., s.time_index] == start[:, None]
            noised[s.name] = real & ~current if task.future_states else torch.zeros_like(real)
            visible[s.name] = real & (current | task.future_states)
    attend = None if task.name in ("robot", "dynamics") else torch.cat([visible[n] for n in layout.names], dim=1)
    return TaskMasks(noised, visible, attend)


def output_types(task: TaskSpec, layout: Layout) -> tuple[str, ...]:
    """Types whose noise the model must predict for `task`."""
    if task.name == "robot":
        return layout.names_with(Role.EMBODIMENT, Role.DYNAMICS, Role.ACTION)
    if task.name == "dynamics" or task.future_states:
        return layout.names_with(Role.DYNAMICS, Role.ACTION)
    return layout.names_with(Role.ACTION)


@dataclass
class NoisedInputs:
    """One task's share of a training batch: model inputs and regression targets."""

    values: dict[str, torch.Tensor]  # type -> (B, L, D), noised where masks.noised
    ids: dict[str, torch.Tensor]  # type -> (B, L, K)
    eps: dict[str, torch.Tensor]  # type -> (B, L, D), the noise added (0 where not noised)
    masks: TaskMasks
    time: torch.Tensor  # (B,) model time in (0, 1]
    target: dict[str, torch.Tensor] | None = None  # type -> (B, L, D), what the network regresses onto (None: eps)
    weight: torch.Tensor | None = None  # (B,) noise-level loss weight (None: 1)
    step: torch.Tensor | None = None  # (B,) long, the diffusion step drawn


def noise_tokens(
    task: TaskSpec,
    scheduler: CosineDDIM,
    layout: Layout,
    tokens: TokenBatch,
    generator: torch.Generator | None = None,
    *,
    prediction: str = "eps",
    weighting: str = "none",
    gamma: float = 5.0,
    part: tuple[int, int] | None = None,
) -> NoisedInputs:
    """Draw a diffusion step per sample and noise the tokens `task` diffuses.

    tokens: normalised values (padding at PAD_VALUE); generator: on the tokens' device;
    prediction: what the network predicts (the targets); weighting, gamma: the noise-level
    loss weight (`CosineDDIM.loss_weight`).
    part: (first, batch): `tokens` are rows first .. first + len(tokens) - 1 of a batch of
        `batch` windows; the draws are that batch's (every row's noise is what a process
        noising the whole batch would draw), so data-parallel ranks together noise exactly
        as one process does. None: the tokens are the whole batch.
    """
    if scheduler.train_steps != task.diffusion_steps:
        raise TTError(
            f"task {task.name!r} diffuses over {task.diffusion_steps} steps, the scheduler over {scheduler.train_steps}"
        )
    b, device = len(tokens), tokens.device
    first, batch = (0, b) if part is None else part
    rows = slice(first, first + b)
    masks = task_masks(task, layout, tokens)
    t = scheduler.sample_train_steps(batch, generator, device=device)[rows]
    values, eps, target = {}, {}, {}
    for s in layout.specs:
        x0 = tokens.values[s.name]
        noise = torch.randn((batch, *x0.shape[1:]), generator=generator, device=device, dtype=x0.dtype)[rows]
        m = masks.noised[s.name].unsqueeze(-1)
        values[s.name] = torch.where(m, scheduler.add_noise(x0, noise, t), x0)
        eps[s.name] = torch.where(m, noise, torch.zeros_like(noise))
        aim = scheduler.training_target(x0, noise, t, prediction)
        target[s.name] = torch.where(m, aim, torch.zeros_like(aim))
    weight = scheduler.loss_weight(t, weighting, prediction, gamma=gamma).to(device=device, dtype=torch.float32)
    return NoisedInputs(values, dict(tokens.ids), eps, masks, scheduler.model_time(t).to(device), target, weight, t)


def _elementwise(kind: str, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    if kind == "huber":
        return F.huber_loss(pred, target, reduction="none", delta=1.0)
    if kind == "mse":
        return (pred - target) ** 2
    raise TTError(f"loss {kind!r} does not exist; losses: huber, mse")


def diffusion_loss(
    model: RoboDiT,
    parts: Sequence[tuple[TaskSpec, NoisedInputs]],
    *,
    loss: str = "huber",
    type_weights: Mapping[str, float] | None = None,
    forward=None,
    global_count=None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Loss over one forward pass of all `parts` (one per task) stacked along the batch.

    type_weights: type name -> factor on its term (absent types: 1).
    forward: the module to call (default `model`; a `DistributedDataParallel` wrapper of it);
    global_count: maps a 0-d count of loss tokens on this process to the count over the whole
    data-parallel batch (an all-reduce), so each type's term is this process's share of the
    whole batch's mean: the ranks' terms sum to the single-process loss.
    Returns (total, per-type loss terms before `type_weights`, detached 0-d tensors).
    """
    type_weights = dict(type_weights or {})
    unknown = sorted(set(type_weights) - set(model.layout.names))
    if unknown:
        raise TTError(f"type_weights name {unknown}, not token types of the model's layout: {list(model.layout.names)}")
    layout = model.layout
    names = layout.names
    values = {n: torch.cat([p.values[n] for _, p in parts]) for n in names}
    noised = {n: torch.cat([p.masks.noised[n] for _, p in parts]) for n in names}
    time = torch.cat([p.time for _, p in parts])
    if all(p.masks.attend is None for _, p in parts):
        attend = None
    else:
        attend = torch.cat([p.masks.attend_full(layout) for _, p in parts])
    ids = {n: torch.cat([p.ids[n] for _, p in parts]) for n in names}
    wanted = sorted({n for task, _ in parts for n in output_types(task, layout)}, key=names.index)
    pred = (model if forward is None else forward)(values, ids, noised, time, attend, outputs=wanted)
    total = torch.zeros((), device=time.device)
    per_type = {}
    weight = torch.cat(
        [p.weight if p.weight is not None else torch.ones(len(p.time), device=p.time.device) for _, p in parts]
    )  # (B,)
    for n in wanted:
        target = torch.cat([(p.target if p.target is not None else p.eps)[n] for _, p in parts])
        lmask = torch.cat([p.masks.loss_mask(n) for _, p in parts])  # (B, L)
        p_n, t_n = pred[n].float(), target.float()
        gain = model.anchor_gain(n)
        if gain is not None:
            # In the residual's own units (the anchors' x0 targets): the Huber's linear part then
            # starts one typical residual out, so the rare large ones do not drown the rest.
            p_n, t_n = p_n / gain, t_n / gain
        err = _elementwise(loss, p_n, t_n).mean(-1)  # (B, L)
        count = lmask.sum() if global_count is None else global_count(lmask.sum())
        term = (err * weight[:, None] * lmask).sum() / count.clamp_min(1)
        per_type[n] = term
        total = total + type_weights.get(n, 1.0) * term
    return total, {k: v.detach() for k, v in per_type.items()}
