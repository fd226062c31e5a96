"""Training loop: AdamW, warm-up + cosine learning rate, gradient clipping, EMA, checkpoints.

Defaults follow the paper's Table "Model Hyperparameters": lr 5e-3 (1e-4 for the large
model, as its appendix says), 500 warm-up steps, batch 64, weight decay 0, EMA power 0.75,
windows of 8 steps; gradients are clipped at norm 1 (the authors' configuration).

Learning rate of the k-th optimizer step (k = 0, 1, ...), with W warm-up and K total steps:
lr (k + 1) / W for k < W, then lr (1 + cos(pi (k - W) / (K - W))) / 2.

Every `checkpoint_every` steps and at the end, the run folder gets a checkpoint
(`tt.dit.checkpoint`), ``loss.csv`` and ``loss.png``. With ``resume`` (default) a run
folder that has checkpoints continues from its latest one; resuming reproduces the
uninterrupted run exactly on the same device (data and noise generator states are
checkpointed).

Data parallel: started by ``torchrun --nproc-per-node K $(which tt) train ...`` (or any
launcher that sets WORLD_SIZE, RANK and LOCAL_RANK), the run trains with torch
DistributedDataParallel over K processes (gloo on the CPU, nccl on CUDA, one GPU per
process: cuda:LOCAL_RANK). ``batch_size`` stays the global batch: every rank draws the
same window selection and diffusion noise from the same generators and reads and computes
only its share (windows r B/K .. (r + 1) B/K - 1 of each task), each type's loss is
normalised by the token count of the whole batch, so K ranks take the same steps as one
process at batch B (to float round-off). Rank 0 alone writes checkpoints, loss.csv and
loss.png; a resume loads the checkpoint on every rank.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import torch

from tt.dit.anchors import CONTROL_BASES, control_anchors, pose_anchors
from tt.dit.checkpoint import (
    RESUME_KEYS,
    checkpoint_file,
    checkpoint_path,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    load_model,
    save_checkpoint,
)
from tt.dit.data import EpisodeTokens
from tt.dit.ddim import CosineDDIM
from tt.dit.ema import EMA
from tt.dit.layout import LayoutError
from tt.dit.model import DIT_CONFIGS, RoboDiT, get_config
from tt.dit.online import OnlineConfig, OnlineTokenSource
from tt.dit.tasks import TaskSpec, diffusion_loss, noise_tokens, task_names, task_windows
from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, atomic_write, write_text
from tt.tokens.normalize import Normalizer

log = logging.getLogger(__name__)


class DivergedError(TTError, FloatingPointError):
    """The training loss became NaN or infinite: the run's settings diverge (not a bug in tt)."""


#: `tt train`'s flag of each `TrainConfig` field that has one, for messages; the others are
#: `--config` keys, named as themselves (`flag_of`).
FLAGS = {
    "data": "--data",
    "out": "--out",
    "task": "--task",
    "size": "--size",
    "steps": "--steps",
    "batch_size": "--batch-size",
    "seed": "--seed",
    "init": "--init",
    "online": "--online",
}


def flag_of(name: str) -> str:
    """How a message names `TrainConfig` field `name`: its flag, or its `--config` key."""
    return FLAGS.get(name, name)


#: `tt train`'s flag of each `OnlineConfig` field that has one, for messages.
ONLINE_FLAGS = {
    "space": "online.space",
    "designs": "online.designs",
    "motions": "online.motions",
    "refresh_every": "online.refresh_every",
    "buffer": "online.buffer",
    "seed": "--seed",
    "action_noise": "online.action_noise",
    "absorbing": "online.absorbing",
    "select": "online.select",
    "uniform_share": "online.uniform_share",
    "reward": "online.reward",
}

#: Learning rate when none is given: the paper's 5e-3, and 1e-4 for the large model.
DEFAULT_LR = {"tiny": 5e-3, "mini": 1e-3, "small": 5e-3, "large": 1e-4}


@dataclass
class TrainConfig:
    """One training run.

    data: episode token file (`EpisodeTokens.save`); out: run folder; task: the tasks
    trained, "robot", "dynamics", "control" or several joined by "+" (a unified model; each
    batch splits evenly between them, e.g. "robot+dynamics"); "both" is "robot+control";
    size: "tiny", "mini", "small" or "large"; steps: total optimizer steps; lr: None for
    `DEFAULT_LR`; window: control steps per training window; *_diffusion_steps: T of each
    task's DDIM process; future_states: the control task also diffuses the states after the
    current step; loss: "huber" or "mse"; bf16: autocast to bfloat16 on CUDA; device: None
    for `tt.kernels.device.default_device()`; keep_checkpoints: how many of the newest
    checkpoints to keep; init: a checkpoint to start a new run from (its EMA weights and
    normaliser; a fresh optimizer, learning-rate schedule and EMA from step 0), e.g. to
    fine-tune after a change of the training data; ignored when the run resumes; compile:
    run the forward pass through `torch.compile` (the first steps pay the compile); online:
    train on episodes the batched sim generates as training goes (`tt.dit.online`) instead
    of `data` (a dict is read as `OnlineConfig` fields).

    Sample-efficiency choices (defaults: the paper's recipe, but for x0 prediction and
    sinusoidal time IDs, which `benchmarks/dit_recipe.py` measured as the winners; the paper
    predicts eps): prediction: what the network predicts, "eps", "x0" or "v"
    (`tt.dit.ddim.PREDICTIONS`); weighting: noise-level loss
    weighting "none", "min_snr" (gamma `min_snr_gamma`) or "edm" (`CosineDDIM.loss_weight`);
    type_weights: token type -> factor on its loss term (e.g. more on ``track_link_obs``, what
    the rewards read); bf16_cpu: autocast to bfloat16 on the CPU too (``bf16`` alone autocasts
    on CUDA only); anchor_track: predict track-link poses as residuals from their targets
    (`tt.dit.anchors`; needs prediction "x0"); anchor_control: predict commands as residuals
    (delta actions; `tt.dit.anchors`, needs prediction "x0") from the current positions of the
    joints they drive ("joints") or from the last command ("command", needs known_command);
    known_command: the control task is given the command that led to the current state
    (`tt.dit.tasks.TaskSpec.known_command`); control_target_offset: the control task's target
    poses at window slot i are those of step i + offset (`tt.dit.tasks.look_ahead`: the
    reference's conditioning, each command beside the target DiffIK aimed it at with the
    offset `IKConfig.lookahead_steps`); dynamics_start: the dynamics task's windows hold
    step 0, its per-step tokens a clean condition (`tt.dit.tasks`, window "start"); time_ids:
    "sinusoidal" or "learned" time-step ID embeddings (`tt.dit.model.DiTConfig.time_ids`).
    """

    data: str = ""
    out: str = "runs/dit"
    task: str = "robot"
    size: str = "small"
    steps: int = 10_000
    batch_size: int = 64
    lr: float | None = None
    warmup_steps: int = 500
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    window: int = 8
    robot_diffusion_steps: int = 100
    control_diffusion_steps: int = 5
    future_states: bool = True
    loss: str = "huber"
    checkpoint_every: int = 1000
    keep_checkpoints: int = 3
    seed: int = 0
    device: str | None = None
    bf16: bool = True
    resume: bool = True
    init: str = ""
    compile: bool = False
    online: OnlineConfig | None = None
    prediction: str = "x0"
    weighting: str = "none"
    min_snr_gamma: float = 5.0
    type_weights: dict[str, float] = field(default_factory=dict)
    bf16_cpu: bool = False
    anchor_track: bool = False
    anchor_control: str = ""
    known_command: bool = False
    control_target_offset: int = 0
    dynamics_start: bool = False
    time_ids: str = "sinusoidal"

    def __post_init__(self) -> None:
        from tt.dit.ddim import PREDICTIONS, WEIGHTINGS

        if isinstance(self.online, dict):
            self.online = OnlineConfig(**self.online)
        if self.prediction not in PREDICTIONS:
            raise TTError(f"prediction {self.prediction!r} does not exist; predictions: {list(PREDICTIONS)}")
        if self.weighting not in WEIGHTINGS:
            raise TTError(f"weighting {self.weighting!r} does not exist; weightings: {list(WEIGHTINGS)}")
        for flag, on in (("anchor_track", self.anchor_track), ("anchor_control", self.anchor_control)):
            if on and self.prediction != "x0":
                raise TTError(f"{flag} needs prediction x0, got {self.prediction!r}")
        if self.anchor_control not in ("", *CONTROL_BASES):
            raise TTError(
                f"anchor_control {self.anchor_control!r} does not exist; use one of "
                f"{', '.join(CONTROL_BASES)} (or leave it out)"
            )
        if self.anchor_control == "command" and not self.known_command:
            raise TTError("anchor_control command needs known_command: the last command must be given to be a base")
        if self.control_target_offset < 0 or (self.control_target_offset and "control" not in task_names(self.task)):
            raise TTError(
                f"control_target_offset {self.control_target_offset} must be >= 0 and needs the control "
                f"task; the run trains --task {self.task}"
            )
        if self.dynamics_start and "dynamics" not in task_names(self.task):
            raise TTError(f"dynamics_start needs the dynamics task; the run trains --task {self.task}")
        if not self.min_snr_gamma > 0:
            raise TTError(f"min_snr_gamma must be > 0, got {self.min_snr_gamma}")
        self.type_weights = {str(k): float(v) for k, v in dict(self.type_weights).items()}
        bad = {k: v for k, v in self.type_weights.items() if not (math.isfinite(v) and v >= 0)}
        if bad:
            raise TTError(
                f"type_weights weights must be finite and >= 0, got {', '.join(f'{k}={v}' for k, v in bad.items())}"
            )
        if self.robot_diffusion_steps < 1 or self.control_diffusion_steps < 1:
            raise TTError(
                f"robot_diffusion_steps and control_diffusion_steps must be >= 1, got "
                f"{self.robot_diffusion_steps}, {self.control_diffusion_steps}"
            )
        if self.online is not None and self.data:
            raise TTError(f"give training data either as a dataset (--data {self.data}) or --online, not both")
        self.task_names()  # validates
        self.model_config()  # validates size and time_ids
        if self.lr is not None and not self.lr >= 0:
            raise TTError(f"lr must be >= 0 (0: the weights stay), got {self.lr}")
        if self.loss not in ("huber", "mse"):
            raise TTError(f"loss {self.loss!r} does not exist; losses: huber, mse")
        for name in ("steps", "batch_size", "window", "checkpoint_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise TTError(f"{flag_of(name)} must be >= 1, got {getattr(self, name)}")
        if self.batch_size < len(self.task_names()):
            raise TTError(
                f"--task {self.task} trains {len(self.task_names())} tasks, so it needs --batch-size >= "
                f"{len(self.task_names())}, got {self.batch_size}"
            )
        if self.warmup_steps < 0 or self.grad_clip <= 0 or self.weight_decay < 0:
            raise TTError(
                f"need warmup_steps >= 0, grad_clip > 0, weight_decay >= 0; got {self.warmup_steps}, "
                f"{self.grad_clip}, {self.weight_decay}"
            )

    def model_config(self):
        """The network's `tt.dit.model.DiTConfig`: the size's, with `time_ids`."""
        import dataclasses

        return dataclasses.replace(get_config(self.size), time_ids=self.time_ids)

    @property
    def learning_rate(self) -> float:
        return DEFAULT_LR[self.size] if self.lr is None else self.lr

    def task_names(self) -> list[str]:
        """Names of the tasks trained, in `task`'s order (`tt.dit.tasks.task_names`)."""
        return task_names(self.task)

    def tasks(self) -> list[tuple[TaskSpec, int]]:
        """(task, windows per batch) of each task trained: batch_size // k each, the last
        task the remainder."""
        spec = {
            "robot": TaskSpec("robot", self.robot_diffusion_steps, "random"),
            "dynamics": TaskSpec("dynamics", self.robot_diffusion_steps, "start" if self.dynamics_start else "random"),
            "control": TaskSpec(
                "control",
                self.control_diffusion_steps,
                "consecutive",
                self.future_states,
                self.known_command,
                self.control_target_offset,
            ),
        }
        names = self.task_names()
        each = self.batch_size // len(names)
        counts = [each] * (len(names) - 1) + [self.batch_size - each * (len(names) - 1)]
        return [(spec[n], c) for n, c in zip(names, counts)]

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        names = {f.name for f in fields(TrainConfig)}
        return TrainConfig(**{k: v for k, v in d.items() if k in names})


#: The `TrainConfig` fields a run started with ``init`` takes from the checkpoint's own run
#: (`init_settings`): the network, its outputs' anchors and the tasks' token layout.
INIT_FIELDS = (
    "size",
    "time_ids",
    "prediction",
    "anchor_track",
    "anchor_control",
    "known_command",
    "future_states",
    "control_target_offset",
    "dynamics_start",
    "robot_diffusion_steps",
    "control_diffusion_steps",
)


def init_settings(path: str | Path, task: str) -> dict:
    """The `INIT_FIELDS` of the run that wrote checkpoint `path`, as `TrainConfig` keywords, for
    a new run of `task` started from it (``tt train --init``): what the network and its token
    layout were trained with, so a fine-tuning recipe need not repeat them. A field the
    checkpoint does not record (an older one) is left out; ``dynamics_start`` and
    ``control_target_offset`` only when `task` trains the task they shape."""
    path = checkpoint_file(path)
    state = load_checkpoint(path)
    stored = state.get("train_config") or {}
    out = {k: stored[k] for k in INIT_FIELDS if stored.get(k) is not None}
    names = task_names(task)
    if "dynamics" not in names:
        out.pop("dynamics_start", None)
    if "control" not in names:
        out.pop("control_target_offset", None)
    return out


@dataclass
class TrainResult:
    """step: optimizer steps taken in total; losses: (step,) training loss per step;
    checkpoint: the last checkpoint written; parameters: network parameter count."""

    step: int
    losses: torch.Tensor
    checkpoint: Path
    parameters: int


def lr_factor(k: int, warmup: int, total: int) -> float:
    """Learning-rate multiplier of optimizer step k (see the module docstring)."""
    if k < warmup:
        return (k + 1) / warmup
    span = max(total - warmup, 1)
    return 0.5 * (1.0 + math.cos(math.pi * min(k - warmup, span) / span))


def write_loss_curve(losses: torch.Tensor, folder: str | Path) -> Path:
    """``loss.csv`` (step, loss) and ``loss.png`` (per-step loss and a 1 %-of-run moving average)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    y = losses.double().numpy()
    steps = range(1, len(y) + 1)
    write_text(folder / "loss.csv", "step,loss\n" + "".join(f"{s},{v:.6g}\n" for s, v in zip(steps, y)))
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    ax.plot(list(steps), y, lw=0.5, alpha=0.4, label="per step")
    w = max(1, len(y) // 100)
    if len(y) >= 2 * w > 2:
        kernel = torch.ones(w, dtype=torch.float64) / w
        smooth = torch.nn.functional.conv1d(torch.from_numpy(y)[None, None], kernel[None, None]).flatten().numpy()
        ax.plot(list(range(w, len(y) + 1)), smooth, lw=1.5, label=f"mean of {w}")
    ax.set_xlabel("optimizer step")
    ax.set_ylabel("diffusion loss")
    if (y > 0).all():
        ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = folder / "loss.png"
    with atomic_write(path) as f:
        fig.savefig(f, format="png")
    plt.close(fig)
    return path


@dataclass(frozen=True)
class DataParallel:
    """This process's place in a data-parallel run (from torchrun's environment)."""

    rank: int
    world_size: int
    local_rank: int

    @staticmethod
    def from_env() -> "DataParallel | None":
        """The run torchrun set up (WORLD_SIZE, RANK, LOCAL_RANK), or None for one process."""
        import os

        size = int(os.environ.get("WORLD_SIZE", "1"))
        if size <= 1:
            return None
        return DataParallel(int(os.environ["RANK"]), size, int(os.environ.get("LOCAL_RANK", os.environ["RANK"])))

    @staticmethod
    def reports() -> bool:
        """Whether this process draws the progress bars: the only one, or rank 0 of a run."""
        dp = DataParallel.from_env()
        return dp is None or dp.rank == 0

    def share(self, n: int, what: str) -> tuple[int, int]:
        """(first, last + 1) of this rank's windows among a task's n."""
        if n % self.world_size:
            raise TTError(
                f"{what} of {n} windows does not split over {self.world_size} data-parallel processes; "
                f"choose a batch_size divisible by {self.world_size} (by k x {self.world_size} for k tasks)"
            )
        k = n // self.world_size
        return self.rank * k, (self.rank + 1) * k


def _start_process_group(dp: DataParallel, device: torch.device) -> None:
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=dp.rank, world_size=dp.world_size)


def _resolve_device(device: str | None) -> torch.device:
    if device is None:
        from tt.kernels.device import default_device

        device = default_device()
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise TTError(f"device {device!r} requested but torch sees no CUDA device; use 'cpu'")
    return torch.device(device)


#: TrainConfig fields a resumed run must share with the run it continues (named by `flag_of`).
#: (steps may grow, checkpoints and devices may change: none of these change a step's result.)
RUN_FIELDS = (
    "data",
    "task",
    "size",
    "batch_size",
    "lr",
    "seed",
    "online",
    "window",
    "warmup_steps",
    "weight_decay",
    "grad_clip",
    "ema_power",
    "ema_max_decay",
    "robot_diffusion_steps",
    "control_diffusion_steps",
    "future_states",
    "loss",
    "prediction",
    "weighting",
    "min_snr_gamma",
    "type_weights",
    "anchor_track",
    "anchor_control",
    "known_command",
    "control_target_offset",
    "dynamics_start",
    "time_ids",
)


def check_same_run(stored: dict, config: TrainConfig, out: Path) -> None:
    """Refuse to resume run `out` (trained with TrainConfig dict `stored`) with other arguments,
    as `tt generate` refuses to resume a dataset with other arguments; `ValueError` naming the flag."""
    if not stored:
        return
    saved = TrainConfig.from_dict(stored)
    for name in RUN_FIELDS:
        flag = "--online ..." if name == "online" else flag_of(name)
        if name not in stored and name != "lr":
            continue  # a field newer than the run: the network's own description is checked instead
        before, now = getattr(saved, name), getattr(config, name)
        if name == "lr":
            before, now = saved.learning_rate, config.learning_rate
        elif name == "data":
            before, now = (str(Path(v).resolve()) if v else "" for v in (before, now))
            if bool(before) != bool(now):  # one run on a dataset, the other online

                def source(path):
                    return f"--data {path}" if path else "--online"

                raise TTError(
                    f"run {out} was trained with {source(before)}, this run asks for {source(now)}; resume "
                    "it with its own arguments, or give another --out (or --no-resume to start it over)"
                )
        elif name == "online":
            if before is None or now is None:
                continue  # one of them trains on --data: said above
            a, b = asdict(before), asdict(now)
            changed = [k for k in a if a[k] != b.get(k)]
            if changed:
                named = ", ".join(f"{ONLINE_FLAGS.get(k, k)} {a[k]} (now {b.get(k)})" for k in changed)
                raise TTError(
                    f"run {out} was trained online with {named}; resume it with its own arguments, or "
                    "give another --out (or --no-resume to start it over)"
                )
            continue
        if before != now:

            def shown(v):
                return (
                    " ".join(map(str, v))
                    if isinstance(v, (list, tuple))
                    else ", ".join(f"{k}={w}" for k, w in v.items())
                    if isinstance(v, dict)
                    else v
                )

            raise TTError(
                f"run {out} was trained with {flag} {shown(before)!r}, this run asks for {shown(now)!r}; "
                "resume it with its own arguments, or give another --out (or --no-resume to start it over)"
            )


def layout_difference(a, b) -> str:
    """How token layout `a` (a model's) differs from `b` (the data's), in a few words."""
    sa, sb = {s.name: s for s in a.specs}, {s.name: s for s in b.specs}
    parts = []
    if set(sa) - set(sb):
        parts.append(f"types only the model has: {', '.join(sorted(set(sa) - set(sb)))}")
    if set(sb) - set(sa):
        parts.append(f"types only the data has: {', '.join(sorted(set(sb) - set(sa)))}")
    longer = [f"{n} {sa[n].length} vs {sb[n].length}" for n in sa if n in sb and sa[n].length != sb[n].length]
    if longer:
        parts.append(f"tokens per type (model vs data): {', '.join(longer[:4])}")
    wider = [f"{n} {sa[n].dim} vs {sb[n].dim}" for n in sa if n in sb and sa[n].dim != sb[n].dim]
    if wider:
        parts.append(f"values per token (model vs data): {', '.join(wider[:4])}")
    if a.steps != b.steps:
        parts.append(f"window steps {a.steps} vs {b.steps}")
    if dict(a.id_sizes) != dict(b.id_sizes):
        ids = [
            f"{k} {a.id_sizes.get(k)} vs {b.id_sizes.get(k)}"
            for k in sorted(set(a.id_sizes) | set(b.id_sizes))
            if a.id_sizes.get(k) != b.id_sizes.get(k)
        ]
        parts.append(f"ID ranges (model vs data): {', '.join(ids[:4])}")
    return "; ".join(parts) or "another token order or schema version"


def check_network(model: RoboDiT, layout, config: TrainConfig, where: str) -> None:
    """Refuse to train `model` (of a run being resumed, or of --init; `where` names it) under
    `config` on data of `layout` when the network is not the one `config` would build:
    LayoutError for another layout, ValueError naming the differing choice otherwise."""
    if model.layout != layout:
        raise LayoutError(
            f"{where} was trained on other tokens than the data's ({layout_difference(model.layout, layout)}): "
            "a model trained on another design space"
        )
    if model.config != config.model_config():
        import dataclasses

        sizes = [
            s for s, c in DIT_CONFIGS.items() if dataclasses.replace(c, time_ids=model.config.time_ids) == model.config
        ]
        size = (
            f"--size {sizes[0]}"
            if sizes
            else f"a network of {model.config.depth} blocks of width {model.config.hidden}"
        )
        raise TTError(
            f"{where} holds a {size} model with time_ids {model.config.time_ids}, this run asks for "
            f"--size {config.size} with time_ids {config.time_ids}"
        )
    if model.prediction != config.prediction:
        raise TTError(f"{where} predicts {model.prediction!r}, this run asks for prediction {config.prediction}")
    for flag, name, on in (
        ("anchor_track", "track_link_obs", config.anchor_track),
        ("anchor_control", "control", bool(config.anchor_control)),
    ):
        if (name in model.anchors) != on:
            was = "with" if name in model.anchors else "without"
            now = "gives" if on else "does not give"
            raise TTError(f"{where} was trained {was} {flag}, this run {now} it")


def newest_intact_checkpoint(out: Path) -> tuple[Path | None, dict | None]:
    """(path, state) of the newest checkpoint of run `out` that reads completely, or (None, None).

    A damaged newer checkpoint (truncated by a full disk, say) is renamed ``*.pt.damaged``,
    out of the run's list but kept, and the next older one is used; a warning says so.
    """
    folder = out / "checkpoints"
    if folder.is_dir():
        for tmp in folder.glob(".step_*.pt.tmp-*"):  # left by a process killed while writing
            tmp.unlink(missing_ok=True)
    damaged = []
    for path in reversed(list_checkpoints(out)):
        try:
            return path, load_checkpoint(path, need=RESUME_KEYS)
        except CorruptFileError as e:
            damaged.append(path)
            keep = path.with_name(path.name + ".damaged")
            os.replace(path, keep)
            log.warning("%s; moved it to %s and resuming from the checkpoint before it", e, keep.name)
    if damaged:
        raise CorruptFileError(
            f"run {out}: every checkpoint is damaged ({', '.join(p.name for p in damaged)}, now "
            "*.pt.damaged); start it over with --no-resume or give another --out"
        )
    return None, None


#: Files of a run folder that a run started over (``--no-resume``) removes, beside its checkpoints.
RUN_FILES = ("loss.csv", "loss.png")


def start_over(out: Path) -> list[str]:
    """Empty run folder `out` for a run that starts over (``--no-resume``): its checkpoints
    (damaged ones and unfinished writes too) and loss curve, so no later resume or
    ``--checkpoint RUN`` loads the earlier run's step. Other files stay. Returns the names
    removed."""
    removed = []
    folder = out / "checkpoints"
    if folder.is_dir():
        for pattern in ("step_*.pt", "step_*.pt.damaged", ".step_*.pt.tmp-*"):
            for path in sorted(folder.glob(pattern)):
                path.unlink(missing_ok=True)
                removed.append(f"checkpoints/{path.name}")
    for name in RUN_FILES:
        if (out / name).is_file():
            (out / name).unlink()
            removed.append(name)
    return removed


def train(
    config: TrainConfig,
    *,
    episodes: EpisodeTokens | None = None,
    space: str | None = None,
    on_step: Callable[[int, float], None] | None = None,
    on_checkpoint: Callable[[int, Path], None] | None = None,
    on_start_over: Callable[[], None] | None = None,
) -> TrainResult:
    """Train (or resume) a DiT; see the module docstring.

    episodes: training data in memory (else loaded from ``config.data``); space: the design
    space the episodes are of, recorded in the checkpoint (None: the source's
    ``design_space``, if it has one); on_step: called after every optimizer step with
    (step, loss), e.g. to drive a progress bar; on_checkpoint: called with (step, path) after
    each checkpoint is written, on the process that writes it (e.g. `tt.selection`'s
    held-out scoring), while a data-parallel run's other processes wait at the barrier;
    on_start_over: called, holding the run's lock, when a run without ``resume`` has emptied
    its folder (`start_over`), to remove files of its own (`tt.selection`'s).

    One process writes a run folder: the writing process holds ``OUT/.lock``
    (`tt.tokens.lock.DatasetLock`, as `tt generate` does its dataset) for the whole run, and
    a second writer is refused. A resumed run checks its data's identity
    (`tt.dit.loader.data_identity`), not only its path.
    """
    from contextlib import nullcontext

    from tt.tokens.lock import DatasetLock

    dp = DataParallel.from_env()
    device = _resolve_device(config.device)
    if dp is not None and device.type == "cuda":
        device = torch.device("cuda", dp.local_rank)  # one GPU per process
        torch.cuda.set_device(device)
    if dp is not None:
        _start_process_group(dp, device)
    writer = dp is None or dp.rank == 0
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    with DatasetLock(out, what="run folder") if writer else nullcontext():
        if writer and not config.resume:
            removed = start_over(out)
            if removed:
                log.warning(
                    "--no-resume: removed %d file(s) of the earlier run from %s (%s)",
                    len(removed),
                    out,
                    ", ".join(removed[:3]) + (" ..." if len(removed) > 3 else ""),
                )
            if on_start_over is not None:
                on_start_over()
        return _train(config, out, dp, device, writer, episodes, space, on_step, on_checkpoint)


def _train(
    config: TrainConfig,
    out: Path,
    dp: DataParallel | None,
    device: torch.device,
    writer: bool,
    episodes,
    space: str | None,
    on_step,
    on_checkpoint,
) -> TrainResult:
    """`train`'s work, with the run folder locked."""
    identity = None
    if episodes is None and config.online is not None:
        episodes = OnlineTokenSource(config.online, device=str(device))
    elif episodes is None:
        if not config.data:
            raise TTError("no training data: give --data DATASET (or an episode token file) or --online")
        from tt.dit.loader import data_identity, open_token_source

        episodes = open_token_source(config.data, verify="full")  # a chunk failing its CRC is skipped, with a warning
        identity = data_identity(config.data)
    layout = episodes.layout(config.window)
    space = space if space is not None else getattr(episodes, "design_space", None)
    resume_from, state = newest_intact_checkpoint(out) if config.resume else (None, None)

    if resume_from is not None:
        stored = state.get("train_config") or {}
        check_same_run(stored, config, out)
        if config.init and config.init != stored.get("init"):
            raise TTError(
                f"--init {config.init} starts a new run, but run {out} has checkpoints to resume (step "
                f"{int(state['step'])}{', started from --init ' + stored['init'] if stored.get('init') else ''}); "
                "give --no-resume to start it over from --init, or another --out"
            )
        if identity is not None and state.get("data_identity") is not None:
            from tt.dit.loader import describe_data_change

            why = describe_data_change(state["data_identity"], identity)
            if why is not None:
                raise TTError(
                    f"run {out} was trained on --data {config.data}, but {why}; resume it on the data it "
                    "was trained on, or start it over with --no-resume (or give another --out)"
                )
        model = RoboDiT.from_description(state["model"])
        check_network(model, layout, config, f"run {out}")
        model.load_state_dict(state["state_dict"])
        normalizer = Normalizer.from_state_dict(state["normalizer"])
    elif config.init:
        state = None
        start = load_model(config.init, ema=True)
        model, normalizer = start.model, start.normalizer
        check_network(model, layout, config, f"--init {config.init}")
        log.info("starting from the EMA weights of %s (step %d)", config.init, start.step)
    else:
        state = None
        normalizer = episodes.fit_normalizer()
        anchors = pose_anchors(layout, normalizer) if config.anchor_track else {}
        if config.anchor_control:
            # The residuals' spread sets the head's gain: windows from a generator of their own,
            # so the training draws are those of a run without the anchor.
            windows = episodes.sample(1024, layout.steps, "consecutive", torch.Generator().manual_seed(config.seed + 2))
            anchors.update(control_anchors(layout, normalizer, windows, config.anchor_control))
        with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's RNG
            torch.manual_seed(config.seed)
            model = RoboDiT(layout, config.model_config(), prediction=config.prediction, anchors=anchors)
    layout.check_normalizer(normalizer)
    model.to(device).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    ema = EMA(model, power=config.ema_power, max_decay=config.ema_max_decay)
    data_gen = torch.Generator().manual_seed(config.seed)
    noise_gen = torch.Generator(device=device).manual_seed(config.seed + 1)
    step, losses = 0, []
    if state is not None:
        optimizer.load_state_dict(state["optimizer"])
        ema.load_state_dict(state["ema"])
        data_gen.set_state(state["rng"]["data"])
        noise_gen.set_state(state["rng"]["noise"])
        step = int(state["step"])
        losses = state["losses"].tolist()
        log.info("resumed %s at step %d", resume_from, step)
    del state

    tasks = config.tasks()
    shares = {t.name: (dp.share(n, f"task {t.name}'s batch") if dp is not None else (0, n)) for t, n in tasks}
    forward, global_count = model, None
    if dp is not None:
        import torch.distributed as dist
        from torch.nn.parallel import DistributedDataParallel

        # A task trains only some heads, so some parameters get no gradient in a step.
        forward = DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None, find_unused_parameters=True
        )

        def global_count(count: torch.Tensor) -> torch.Tensor:
            # DDP averages gradients over ranks; scaling by K makes that average the sum of
            # the ranks' shares of the whole batch's mean.
            total = count.detach().clone()
            dist.all_reduce(total)
            return total / dp.world_size

    if config.compile:
        forward = torch.compile(forward)
    schedulers = {t.name: CosineDDIM(t.diffusion_steps) for t, _ in tasks}
    autocast = torch.autocast(
        device_type=device.type,
        dtype=torch.bfloat16,
        enabled=config.bf16 and (device.type == "cuda" or config.bf16_cpu),
    )
    log.info(
        "training %s DiT (%d parameters) on %s, task %s, from step %d to %d",
        config.size,
        model.parameter_count(),
        device,
        config.task,
        step,
        config.steps,
    )
    last = latest_checkpoint(out)
    start_step = getattr(episodes, "start_step", None)  # sources whose data changes with the step (online)
    while step < config.steps:
        if start_step is not None:
            start_step(step)
        parts = []
        for task, n in tasks:
            first, end = shares[task.name]
            part = None if dp is None else (first, end)
            raw = task_windows(episodes, layout, n, task, data_gen, part=part)
            layout.check(raw)
            tokens = normalizer.normalize(raw).to(device)
            noised = noise_tokens(
                task,
                schedulers[task.name],
                layout,
                tokens,
                noise_gen,
                prediction=config.prediction,
                weighting=config.weighting,
                gamma=config.min_snr_gamma,
                part=(first, n),
            )
            parts.append((task, noised))
        for g in optimizer.param_groups:
            g["lr"] = config.learning_rate * lr_factor(step, config.warmup_steps, config.steps)
        with autocast:
            loss, per_type = diffusion_loss(
                model,
                parts,
                loss=config.loss,
                type_weights=config.type_weights,
                forward=forward,
                global_count=global_count,
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        optimizer.step()
        ema.update(model)
        step += 1
        reported = loss.detach()
        if dp is not None:  # the ranks' losses sum to K times the whole batch's (see global_count)
            dist.all_reduce(reported)
            reported = reported / dp.world_size
        value = float(reported)
        if not math.isfinite(value):
            terms = {k: float(v) for k, v in per_type.items()}
            raise DivergedError(f"training loss is {value} at step {step}; per type: {terms}")
        losses.append(value)
        if step % config.checkpoint_every == 0 or step == config.steps:
            last = checkpoint_path(out, step)
            if writer:
                save_checkpoint(
                    last,
                    {
                        "schema_version": layout.schema_version,
                        "space": space,
                        "model": model.describe(),
                        "state_dict": model.state_dict(),
                        "ema": ema.state_dict(),
                        "optimizer": optimizer.state_dict(),
                        "normalizer": normalizer.state_dict(),
                        "train_config": config.to_dict(),
                        "step": step,
                        "rng": {"data": data_gen.get_state(), "noise": noise_gen.get_state()},
                        "losses": torch.tensor(losses, dtype=torch.float32),
                        "data_identity": identity,
                    },
                )
                for old in list_checkpoints(out)[: -config.keep_checkpoints]:
                    old.unlink()
                write_loss_curve(torch.tensor(losses), out)
                if on_checkpoint is not None:
                    on_checkpoint(step, last)
            if dp is not None:
                dist.barrier()  # the checkpoint is on disk before any rank goes on (or ends)
        if on_step is not None:
            on_step(step, value)
    if last is None:
        raise TTError(
            f"run {out} has nothing to do: it is at step {step} and --steps is {config.steps}; give a "
            "larger --steps to train on, or --no-resume to start it over"
        )
    return TrainResult(step, torch.tensor(losses, dtype=torch.float32), last, model.parameter_count())
