"""Plain-argument entry points for the ``tt`` command line (the typer app wires them)."""

from __future__ import annotations

from pathlib import Path

from tt.dit.online import OnlineConfig
from tt.dit.train import DataParallel, TrainConfig, TrainResult, train


def train_cmd(
    data: str | Path | None,
    *,
    task: str = "robot",
    size: str = "small",
    out: str | Path = "runs/dit",
    steps: int = 10_000,
    batch_size: int = 64,
    lr: float | None = None,
    device: str | None = None,
    seed: int = 0,
    checkpoint_every: int = 1000,
    resume: bool = True,
    init: str | Path | None = None,
    online: OnlineConfig | None = None,
    progress: bool = True,
    on_checkpoint=None,
    on_start_over=None,
    episodes=None,
    **recipe,
) -> TrainResult:
    """``tt train``: train a DiT on an episode token file, with a tqdm bar showing the loss.

    data: episode token file (`tt.dit.data.EpisodeTokens.save`); task: robot | control |
    both; size: tiny | mini | small | large; out: run folder (checkpoints, loss.csv, loss.png);
    lr: None for the paper's value of the size; device: None for the default device;
    resume: continue from the run folder's latest checkpoint if it has one; init: start a new
    run (step 0) from this checkpoint's EMA weights and normaliser; online: generate the
    training episodes with the batched sim instead of reading `data` (`tt.dit.online`);
    on_checkpoint: called with (step, path) after each checkpoint, on_start_over: when a run
    started over has emptied its folder (`tt.dit.train.train`); episodes: the training data
    in memory or a token source built by the caller (`tt.dit.train.train`; the online source
    with proposals, `tt.guidance.proposer.online_source`);
    recipe: further `TrainConfig` fields (prediction, weighting, type_weights, bf16_cpu,
    robot_diffusion_steps, ...).
    Raises ValueError (bad arguments, mismatched run folder), FileNotFoundError and
    `tt.tokens.schema.SchemaVersionError`.
    """
    from tqdm import tqdm

    progress = progress and DataParallel.reports()  # one bar for a data-parallel run

    config = TrainConfig(
        data=str(data) if data is not None else "",
        out=str(out),
        task=task,
        size=size,
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        device=device,
        seed=seed,
        checkpoint_every=checkpoint_every,
        resume=resume,
        init=str(init) if init else "",
        online=online,
        **recipe,
    )
    bar = tqdm(total=steps, desc=f"train {size} {task}", unit="step", disable=not progress, dynamic_ncols=True)
    state = {"first": True}

    def on_step(step: int, loss: float) -> None:
        if state["first"]:
            bar.update(step - 1 - bar.n)  # a resumed run starts past 0
            state["first"] = False
        bar.update(1)
        if step % 10 == 0 or step == steps:
            bar.set_postfix(loss=f"{loss:.4f}", refresh=False)

    try:
        return train(
            config, episodes=episodes, on_step=on_step, on_checkpoint=on_checkpoint, on_start_over=on_start_over
        )
    finally:
        bar.close()
