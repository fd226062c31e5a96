"""Training checkpoints: everything needed to resume training or to sample.

A checkpoint is one ``torch.save`` file (``RUN/checkpoints/step_0001000.pt``) holding a
dict:

    format           "tt.dit.checkpoint/1"
    schema_version   RoboToken schema version of the layout (None: not a schema layout)
    model            layout and DiTConfig (`RoboDiT.describe`)
    state_dict       network weights
    ema              EMA weights and update count (`EMA.state_dict`)
    optimizer        AdamW state
    normalizer       per-type feature ranges (`Normalizer.state_dict`)
    train_config     the TrainConfig as a dict
    step             optimizer steps taken
    rng              states of the data and noise generators
    losses           (step,) float32 training loss per step so far

Loading checks the format and the schema version first, so a checkpoint of another
RoboToken schema fails with `SchemaVersionError` before any weight is read.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch

from tt.dit.ema import EMA
from tt.dit.layout import Layout
from tt.dit.model import RoboDiT
from tt.dit.normalization import Normalizer

#: Format tag of checkpoint files.
CHECKPOINT_FORMAT = "tt.dit.checkpoint/1"

_NAME = re.compile(r"^step_(\d+)\.pt$")


def checkpoint_path(run: str | Path, step: int) -> Path:
    return Path(run) / "checkpoints" / f"step_{step:07d}.pt"


def list_checkpoints(run: str | Path) -> list[Path]:
    """Checkpoints of a run folder, oldest first."""
    folder = Path(run) / "checkpoints"
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(run: str | Path) -> Path | None:
    found = list_checkpoints(run)
    return found[-1] if found else None


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write `state` (see the module docstring) atomically: a crash leaves the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".pt.tmp")
    torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint; raises FileNotFoundError, ValueError (not a tt checkpoint) or
    `tt.tokens.schema.SchemaVersionError` (written for another RoboToken schema)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    state = torch.load(path, map_location=map_location, weights_only=True)
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise ValueError(f"{path} is not a tt DiT checkpoint (format {found!r}, expected {CHECKPOINT_FORMAT!r})")
    version = state.get("schema_version")
    if version is not None:
        from tt.tokens.schema import check_version

        check_version(version, f"checkpoint {path}")
    return state


@dataclass
class TrainedModel:
    """A network ready to sample: model (EMA weights unless asked otherwise, eval mode),
    its normaliser, layout and the step it was saved at."""

    model: RoboDiT
    normalizer: Normalizer
    layout: Layout
    step: int


def load_model(path: str | Path, *, ema: bool = True, device: str | torch.device = "cpu") -> TrainedModel:
    """The network of a checkpoint (a file, or a run folder: its latest checkpoint)."""
    path = Path(path)
    if path.is_dir():
        found = latest_checkpoint(path)
        if found is None:
            raise FileNotFoundError(f"run folder {path} has no checkpoints under {path / 'checkpoints'}")
        path = found
    state = load_checkpoint(path)
    model = RoboDiT.from_description(state["model"])
    model.load_state_dict(state["state_dict"])
    if ema:
        averaged = EMA(model)
        averaged.load_state_dict(state["ema"])
        averaged.copy_to(model)
    model.to(device).eval()
    return TrainedModel(model, Normalizer.from_state_dict(state["normalizer"]), model.layout, int(state["step"]))
