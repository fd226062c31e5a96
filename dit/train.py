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
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import torch

from tt.dit.checkpoint import (
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
from tt.dit.layout import LayoutError, with_slot_ids
from tt.dit.model import RoboDiT, get_config
from tt.dit.online import OnlineConfig, OnlineTokenSource
from tt.tokens.normalize import Normalizer
from tt.dit.tasks import TaskSpec, diffusion_loss, noise_tokens

log = logging.getLogger(__name__)

#: Learning rate when none is given: the paper's 5e-3, and 1e-4 for the large model.
DEFAULT_LR = {"tiny": 5e-3, "mini": 1e-3, "small": 5e-3, "large": 1e-4}


@dataclass
class TrainConfig:
    """One training run.

    data: episode token file (`EpisodeTokens.save`); out: run folder; task: "robot",
    "control" or "both" (a unified model; each batch is half robot, half control
    windows); size: "tiny", "mini", "small" or "large"; steps: total optimizer steps; lr: None
    for `DEFAULT_LR`; window: control steps per training window; *_diffusion_steps: T of
    each task's DDIM process; future_states: the control task also diffuses the states
    after the current step; loss: "huber" or "mse"; bf16: autocast to bfloat16 on CUDA;
    device: None for `tt.kernels.device.default_device()`; keep_checkpoints: how many of the
    newest checkpoints to keep; init: a checkpoint to start a new run from (its EMA weights
    and normaliser; a fresh optimizer, learning-rate schedule and EMA from step 0), e.g. to
    fine-tune after a change of the training data; ignored when the run resumes; online:
    train on episodes the batched sim generates as training goes (`tt.dit.online`) instead
    of `data` (a dict is read as `OnlineConfig` fields).

    Sample-efficiency choices (defaults: the paper's recipe): prediction: what the network
    predicts, "eps", "x0" or "v" (`tt.dit.ddim.PREDICTIONS`); weighting: noise-level loss
    weighting "none", "min_snr" (gamma `min_snr_gamma`) or "edm" (`CosineDDIM.loss_weight`);
    type_weights: token type -> factor on its loss term (e.g. more on ``track_link_obs``, what
    the rewards read); bf16_cpu: autocast to bfloat16 on the CPU too (``bf16`` alone autocasts
    on CUDA only).
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
    online: OnlineConfig | None = None
    prediction: str = "eps"
    weighting: str = "none"
    min_snr_gamma: float = 5.0
    type_weights: dict[str, float] = field(default_factory=dict)
    bf16_cpu: bool = False

    def __post_init__(self) -> None:
        from tt.dit.ddim import PREDICTIONS, WEIGHTINGS

        if isinstance(self.online, dict):
            self.online = OnlineConfig(**self.online)
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"prediction {self.prediction!r} does not exist; predictions: {list(PREDICTIONS)}")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting {self.weighting!r} does not exist; weightings: {list(WEIGHTINGS)}")
        if not self.min_snr_gamma > 0:
            raise ValueError(f"min_snr_gamma must be > 0, got {self.min_snr_gamma}")
        self.type_weights = {str(k): float(v) for k, v in dict(self.type_weights).items()}
        bad = {k: v for k, v in self.type_weights.items() if not (math.isfinite(v) and v >= 0)}
        if bad:
            raise ValueError(f"type_weights must be finite and >= 0, got {bad}")
        if self.robot_diffusion_steps < 1 or self.control_diffusion_steps < 1:
            raise ValueError(f"robot_diffusion_steps and control_diffusion_steps must be >= 1, got "
                             f"{self.robot_diffusion_steps}, {self.control_diffusion_steps}")
        if self.online is not None and self.data:
            raise ValueError(f"give training data either as a dataset (data={self.data!r}) or online, not both")
        if self.task not in ("robot", "control", "both"):
            raise ValueError(f"task {self.task!r} does not exist; tasks: robot, control, both")
        get_config(self.size)
        if self.loss not in ("huber", "mse"):
            raise ValueError(f"loss {self.loss!r} does not exist; losses: huber, mse")
        for name in ("steps", "batch_size", "window", "checkpoint_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.task == "both" and self.batch_size < 2:
            raise ValueError(f"task 'both' needs batch_size >= 2, got {self.batch_size}")
        if self.warmup_steps < 0 or self.grad_clip <= 0 or self.weight_decay < 0:
            raise ValueError(f"need warmup_steps >= 0, grad_clip > 0, weight_decay >= 0; got {self.warmup_steps}, "
                             f"{self.grad_clip}, {self.weight_decay}")

    @property
    def learning_rate(self) -> float:
        return DEFAULT_LR[self.size] if self.lr is None else self.lr

    def tasks(self) -> list[tuple[TaskSpec, int]]:
        """(task, windows per batch) of each task trained."""
        robot = TaskSpec("robot", self.robot_diffusion_steps, "random")
        control = TaskSpec("control", self.control_diffusion_steps, "consecutive", self.future_states)
        if self.task == "robot":
            return [(robot, self.batch_size)]
        if self.task == "control":
            return [(control, self.batch_size)]
        half = self.batch_size // 2
        return [(robot, half), (control, self.batch_size - half)]

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        names = {f.name for f in fields(TrainConfig)}
        return TrainConfig(**{k: v for k, v in d.items() if k in names})


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
    (folder / "loss.csv").write_text("step,loss\n" + "".join(f"{s},{v:.6g}\n" for s, v in zip(steps, y)))
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
    fig.savefig(path)
    plt.close(fig)
    return path


def _resolve_device(device: str | None) -> torch.device:
    if device is None:
        from tt.kernels.device import default_device

        device = default_device()
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but torch sees no CUDA device; use 'cpu'")
    return torch.device(device)


def train(config: TrainConfig, *, episodes: EpisodeTokens | None = None, space: str | None = None,
          on_step: Callable[[int, float], None] | None = None) -> TrainResult:
    """Train (or resume) a DiT; see the module docstring.

    episodes: training data in memory (else loaded from ``config.data``); space: the design
    space the episodes are of, recorded in the checkpoint (None: the source's
    ``design_space``, if it has one); on_step: called after every optimizer step with
    (step, loss), e.g. to drive a progress bar.
    """
    device = _resolve_device(config.device)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    if episodes is None and config.online is not None:
        episodes = OnlineTokenSource(config.online, device=str(device))
    elif episodes is None:
        if not config.data:
            raise ValueError("TrainConfig.data is empty: give a dataset or an episode token file, online=, or episodes=")
        from tt.dit.loader import open_token_source

        episodes = open_token_source(config.data)
    layout = episodes.layout(config.window)
    space = space if space is not None else getattr(episodes, "design_space", None)
    resume_from = latest_checkpoint(out) if config.resume else None

    if resume_from is not None:
        state = load_checkpoint(resume_from)
        model = RoboDiT.from_description(state["model"])
        if model.layout != layout:
            raise LayoutError(f"run {out} was trained on layout {model.layout.to_dict()}, the data has {layout.to_dict()}")
        if model.config != get_config(config.size):
            raise ValueError(f"run {out} holds a {model.config} model, config asks for size {config.size!r}")
        if model.prediction != config.prediction:
            raise ValueError(f"run {out} predicts {model.prediction!r}, config asks for prediction {config.prediction!r}")
        model.load_state_dict(state["state_dict"])
        normalizer = Normalizer.from_state_dict(state["normalizer"])
    elif config.init:
        state = None
        start = load_model(config.init, ema=True)
        model, normalizer = start.model, start.normalizer
        if model.layout != layout:
            raise LayoutError(f"--init {config.init} was trained on layout {model.layout.to_dict()}, the data has {layout.to_dict()}")
        if model.config != get_config(config.size):
            raise ValueError(f"--init {config.init} holds a {model.config} model, config asks for size {config.size!r}")
        if model.prediction != config.prediction:
            raise ValueError(f"--init {config.init} predicts {model.prediction!r}, config asks for prediction "
                             f"{config.prediction!r}")
        log.info("starting from the EMA weights of %s (step %d)", config.init, start.step)
    else:
        state = None
        with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's RNG
            torch.manual_seed(config.seed)
            model = RoboDiT(layout, get_config(config.size), prediction=config.prediction)
        normalizer = episodes.fit_normalizer()
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
    schedulers = {t.name: CosineDDIM(t.diffusion_steps) for t, _ in tasks}
    autocast = torch.autocast(device_type=device.type, dtype=torch.bfloat16,
                              enabled=config.bf16 and (device.type == "cuda" or config.bf16_cpu))
    log.info("training %s DiT (%d parameters) on %s, task %s, from step %d to %d",
             config.size, model.parameter_count(), device, config.task, step, config.steps)
    last = latest_checkpoint(out)
    start_step = getattr(episodes, "start_step", None)  # sources whose data changes with the step (online)
    while step < config.steps:
        if start_step is not None:
            start_step(step)
        parts = []
        for task, n in tasks:
            raw = with_slot_ids(layout, episodes.sample(n, config.window, task.window, data_gen))
            layout.check(raw)
            tokens = normalizer.normalize(raw).to(device)
            parts.append((task, noise_tokens(task, schedulers[task.name], layout, tokens, noise_gen,
                                             prediction=config.prediction, weighting=config.weighting,
                                             gamma=config.min_snr_gamma)))
        for g in optimizer.param_groups:
            g["lr"] = config.learning_rate * lr_factor(step, config.warmup_steps, config.steps)
        with autocast:
            loss, per_type = diffusion_loss(model, parts, loss=config.loss, type_weights=config.type_weights)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        optimizer.step()
        ema.update(model)
        step += 1
        value = float(loss.detach())
        if not math.isfinite(value):
            terms = {k: float(v) for k, v in per_type.items()}
            raise FloatingPointError(f"training loss is {value} at step {step}; per type: {terms}")
        losses.append(value)
        if step % config.checkpoint_every == 0 or step == config.steps:
            last = checkpoint_path(out, step)
            save_checkpoint(last, {
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
            })
            for old in list_checkpoints(out)[:-config.keep_checkpoints]:
                old.unlink()
            write_loss_curve(torch.tensor(losses), out)
        if on_step is not None:
            on_step(step, value)
    if last is None:
        raise ValueError(f"run {out} has nothing to do: it is at step {step} and config.steps is {config.steps}")
    return TrainResult(step, torch.tensor(losses, dtype=torch.float32), last, model.parameter_count())
