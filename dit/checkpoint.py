"""Training checkpoints: everything needed to resume training or to sample.

A checkpoint is one ``torch.save`` file (``RUN/checkpoints/step_0001000.pt``) holding a
dict:

    format           "tt.dit.checkpoint/1"
    schema_version   RoboToken schema version of the layout (None: not a schema layout)
    space            design space of the training episodes (None: not recorded)
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

Shipped checkpoints. The repository's ``checkpoints/`` folder (installed as
``tt.checkpoints``) holds the checkpoints tt ships, one file per design space named
``<space>.pt`` or ``<space>_<size>.pt`` (``viperx_mini.pt``), and specialists of one task
``<space>_<size>_<task>.pt`` (``viperx_mini_control.pt``); `default_checkpoint` finds a
space's.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from tt.dit.ema import EMA
from tt.dit.layout import Layout
from tt.dit.model import RoboDiT
from tt.dit.tasks import ROBOT, TASK_NAMES, task_names
from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, atomic_write, check_readable, reason
from tt.tokens.normalize import Normalizer

#: Format tag of checkpoint files.
CHECKPOINT_FORMAT = "tt.dit.checkpoint/1"

_NAME = re.compile(r"^step_(\d+)\.pt$")
#: Model sizes, the one preferred when a space ships several first.
_SIZE_PREFERENCE = ("large", "small", "mini", "tiny")


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


def checkpoint_file(path: str | Path) -> Path:
    """A checkpoint file: `path` itself, or a run folder's latest checkpoint."""
    path = Path(path)
    if not path.is_dir():
        return path
    found = latest_checkpoint(path)
    if found is None:
        raise FileNotFoundError(f"run folder {path} has no checkpoints under {path / 'checkpoints'}")
    return found


def shipped_folder() -> Path:
    """The folder of shipped checkpoints: ``checkpoints/`` beside the package's ``dit/``
    (the repository root in an editable install, ``tt/checkpoints`` in an installed one)."""
    return Path(__file__).resolve().parent.parent / "checkpoints"


def _shipped_name(p: Path) -> tuple[str, str, str | None]:
    """(space, size, task) of a shipped file name ``<space>[_<size>][_<task>].pt``; task is
    None for a generalist, or a task name (`tt.dit.tasks.TASK_NAMES`) for a specialist."""
    space, _, rest = p.stem.partition("_")
    size, _, last = rest.rpartition("_")
    if last in TASK_NAMES:
        return space, size, last
    return space, rest, None


def shipped_checkpoints(folder: str | Path | None = None) -> dict[str, list[Path]]:
    """Shipped checkpoint files by design space, the preferred one first (see `default_checkpoint`):
    generalists by size, then task specialists by size.

    folder: where to look (None: `shipped_folder()`); a missing folder holds none.
    """
    folder = shipped_folder() if folder is None else Path(folder)
    found: dict[str, list[tuple[bool, int, str, Path]]] = {}
    if folder.is_dir():
        for p in folder.iterdir():
            if p.suffix != ".pt" or not p.is_file():
                continue
            space, size, task = _shipped_name(p)
            rank = _SIZE_PREFERENCE.index(size) if size in _SIZE_PREFERENCE else len(_SIZE_PREFERENCE)
            found.setdefault(space, []).append((task is not None, rank, p.name, p))
    return {space: [p for *_, p in sorted(files)] for space, files in sorted(found.items())}


class NoCheckpointError(FileNotFoundError):
    """No shipped checkpoint for a design space."""


def default_checkpoint(space: str, folder: str | Path | None = None, *, task: str | None = None) -> Path:
    """The shipped checkpoint of design space `space` in `folder` (None: `shipped_folder()`).

    A generalist is ``<space>.pt`` or ``<space>_<size>.pt``; a specialist of one task
    ``<space>_<size>_<task>.pt`` (``viperx_mini_control.pt``). task None: the generalist of
    the largest model (large, small, mini, tiny, then any other suffix by name); a task: its
    specialist of the largest model if one is shipped, else the generalist.

    Raises NoCheckpointError (a FileNotFoundError) naming the spaces that have one.
    """
    folder = shipped_folder() if folder is None else Path(folder)
    shipped = shipped_checkpoints(folder)
    if task is not None and task not in TASK_NAMES:
        raise TTError(f"task {task!r} does not exist; tasks: {', '.join(TASK_NAMES)}")
    files = shipped.get(space, [])
    for p in [p for p in files if _shipped_name(p)[2] == task] + [p for p in files if _shipped_name(p)[2] is None]:
        return p
    have = ", ".join(f"{s} ({', '.join(p.name for p in ps)})" for s, ps in shipped.items()) or "none"
    if files:
        raise NoCheckpointError(
            f"design space {space!r} ships only checkpoints of other tasks in {folder} "
            f"({', '.join(p.name for p in files)}), none {'for task ' + repr(task) if task else 'for every task'} "
            f"(expected {space}_<size>.pt); pass --checkpoint RUN"
        )
    raise NoCheckpointError(
        f"no shipped DiT checkpoint for design space {space!r} in {folder} (expected {space}.pt or "
        f"{space}_<size>.pt; spaces with one: {have}); train one with `tt train` and pass --checkpoint RUN"
    )


def shipped_critic(space: str, checkpoint: str | Path, folder: str | Path | None = None) -> Path | None:
    """The critic to rank the samples of `checkpoint` by: the space's shipped dynamics
    specialist when `checkpoint` is the space's shipped generalist or generator (robot
    specialist) and a dynamics specialist ships beside it, else None (the sampling model's own
    dynamics task; a user's own checkpoint is not paired with a shipped critic it was not
    trained beside)."""
    shipped = set()
    for task in (None, "robot"):  # a space may ship a generator without a generalist (ALOHA)
        try:
            shipped.add(default_checkpoint(space, folder, task=task).resolve())
        except NoCheckpointError:
            pass
    try:
        critic = default_checkpoint(space, folder, task="dynamics")
    except NoCheckpointError:
        return None
    if critic.resolve() in shipped or Path(checkpoint).resolve() not in shipped:
        return None
    return critic


#: Entries a checkpoint needs to sample (`load_model`) and, in addition, to resume training.
SAMPLE_KEYS = ("model", "state_dict", "ema", "normalizer", "step")
RESUME_KEYS = SAMPLE_KEYS + ("optimizer", "train_config", "rng", "losses")


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write `state` (see the module docstring) atomically and durably: written beside the
    target, fsync'ed, renamed, the folder fsync'ed (`tt.kernels.files.atomic_write`), so a
    crash at any point leaves the old file or the complete new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        torch.save({"format": CHECKPOINT_FORMAT, **state}, f)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu", *, need: tuple[str, ...] = ()) -> dict:
    """Read a checkpoint; raises FileNotFoundError, `CorruptFileError` (empty, truncated,
    not a tt checkpoint, or lacking one of the entries `need`) or
    `tt.tokens.schema.SchemaVersionError` (written for another RoboToken schema)."""
    path = check_readable(path, "checkpoint")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols of foreign files
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises RuntimeError, EOFError, UnpicklingError, ... for damaged files
        raise CorruptFileError(f"checkpoint {path} cannot be read: {reason(e, path)}") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise CorruptFileError(f"{path} is not a tt DiT checkpoint (format {found!r}, expected {CHECKPOINT_FORMAT!r})")
    version = state.get("schema_version")
    if version is not None:
        from tt.tokens.schema import check_version

        check_version(version, f"checkpoint {path}")
    missing = [k for k in need if k not in state]
    if missing:
        raise CorruptFileError(f"checkpoint {path} lacks the entries {missing} (a damaged or partial tt checkpoint)")
    return state


@dataclass
class TrainedModel:
    """A network ready to sample: model (EMA weights unless asked otherwise, eval mode),
    its normaliser, layout, the step it was saved at, the design space it was trained on
    (None: not recorded, as in checkpoints written before spaces were), its file, the
    names of the tasks it was trained on and the DDIM training steps of its robot and
    dynamics tasks (the paper's defaults where the checkpoint records no train config);
    dynamics_start: its dynamics task is told the episode's first step (window "start")."""

    model: RoboDiT
    normalizer: Normalizer
    layout: Layout
    step: int
    space: str | None = None
    path: Path | None = None
    tasks: tuple[str, ...] = ("robot",)
    robot_diffusion_steps: int = ROBOT.diffusion_steps
    dynamics_start: bool = False

    def trained_on(self, task: str) -> bool:
        """Whether the model was trained on `task` ("robot", "dynamics" or "control")."""
        return task in self.tasks


def load_model(path: str | Path, *, ema: bool = True, device: str | torch.device = "cpu") -> TrainedModel:
    """The network of a checkpoint (a file, or a run folder: its latest checkpoint)."""
    path = checkpoint_file(path)
    state = load_checkpoint(path, need=SAMPLE_KEYS)
    try:
        model = RoboDiT.from_description(state["model"])
        model.load_state_dict(state["state_dict"])
        if ema:
            averaged = EMA(model)
            averaged.load_state_dict(state["ema"])
            averaged.copy_to(model)
        normalizer = Normalizer.from_state_dict(state["normalizer"])
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as e:
        raise CorruptFileError(f"checkpoint {path}: its network does not load ({reason(e)})") from None
    model.to(device).eval()
    tasks, robot_steps, start = _trained_tasks(state.get("train_config"))
    return TrainedModel(
        model, normalizer, model.layout, int(state["step"]), state.get("space"), path, tasks, robot_steps, start
    )


def _trained_tasks(config) -> tuple[tuple[str, ...], int, bool]:
    """(task names, robot DDIM steps, dynamics_start) of a checkpoint's train config (a dict,
    or absent)."""
    if not isinstance(config, dict):
        return ("robot",), ROBOT.diffusion_steps, False
    try:
        names = tuple(task_names(str(config.get("task", "robot"))))
    except ValueError:
        names = ("robot",)
    return (
        names,
        int(config.get("robot_diffusion_steps", ROBOT.diffusion_steps)),
        bool(config.get("dynamics_start", False)),
    )
