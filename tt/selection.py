"""Choosing a run's checkpoint by held-out r: early stopping on what the critic is for.

The training loss does not say when the model stops improving as a critic. On the full
ViperX space (`benchmarks/results/dit_ladder_r2c.md`) the dynamics task's held-out r peaked
at step 2,000-2,500 and then fell to a third of that by step 6,000 while the loss kept
falling. `tt train selection.designs N` therefore scores every checkpoint the run writes as
`tt predict` would use it (`tt.ladder.score_designs`: predicted against simulated reward of
N held-out designs x validation motions) and keeps the best one as ``RUN/best.pt``.

The selection designs are drawn with seed ``HELDOUT_SEED + SELECTION_SEED``: neither a
training draw nor the ladder's report designs (seed ``HELDOUT_SEED``), so a checkpoint
chosen here is still reported on designs it was not chosen on. The criterion is the mean
within-motion r (a motion where the predictions do not spread counts 0), what ranking
candidates for one motion needs; pooled r is recorded beside it. Sixteen designs rank runs
far apart but are noisy within one run (`benchmarks/results/dit_ladder_r2g.md`): give 32 or
more. ``RUN/selection.csv`` holds one row per scored checkpoint and ``RUN/selection.png``
plots them, ``RUN/selection.json`` the settings; a resumed run reads them back (and refuses
other settings), so its best is the best over the whole run. In a data-parallel run the
scoring runs on the writing process while the others wait at the checkpoint's barrier.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from tt.guidance.predicted import CRITIC_DDIM_STEPS
from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, atomic_write, read_json, reason, write_text

log = logging.getLogger(__name__)

#: Offset (on `tt.ladder.HELDOUT_SEED`) of the designs checkpoints are chosen on; the ladder
#: reports on offset 0.
SELECTION_SEED = 1

_COLUMNS = ("step", "within_r", "pooled_r", "seconds")


@dataclass(frozen=True)
class SelectionConfig:
    """How `CheckpointSelector` scores a checkpoint.

    designs: held-out designs (seed `SELECTION_SEED`); motions: validation motions spread
    over the skills (`tt.ladder.validation_motions`); reward: the reward predicted and
    simulated; num_steps: DDIM steps of the prediction (the critic's default); samples: predictions averaged per
    pair; backend: the simulator's (None: the space's default, ``warp``, or ``mjbatch`` for a
    space with contacts); device: the model's during scoring (None: the default
    device, CUDA when present).
    """

    designs: int = 16
    motions: int = 5
    reward: str = "tracking"
    num_steps: int = CRITIC_DDIM_STEPS
    samples: int = 1
    backend: str | None = None
    device: str | None = None

    def __post_init__(self) -> None:
        for name in ("designs", "motions", "num_steps", "samples"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise TTError(f"selection.{name} = {value!r}; must be an integer >= 1")
        if self.designs < 3:
            raise TTError(f"selection.designs = {self.designs}; a correlation needs at least 3 designs")
        from tt.sim.rewards import REWARDS, reward_name

        try:
            object.__setattr__(self, "reward", reward_name(self.reward))  # the paper's names too
        except TTError:
            raise TTError(f"selection.reward = {self.reward!r} is not a reward; valid: {', '.join(REWARDS)}") from None


@dataclass(frozen=True)
class SelectionRow:
    """One scored checkpoint: its step, mean within-motion and pooled r, scoring seconds."""

    step: int
    within_r: float
    pooled_r: float
    seconds: float


class CheckpointSelector:
    """Score each checkpoint of a run and keep the best as ``RUN/best.pt`` (module docstring).

    Call it with (step, checkpoint path) after each checkpoint is written (`tt.dit.train.train`'s
    ``on_checkpoint``). The design space is the checkpoint's.
    """

    def __init__(self, run: str | Path, config: SelectionConfig | None = None, *, fresh: bool = False):
        """fresh: the run starts over (``--no-resume``): an earlier selection in `run` is not
        read, and `start_over` (which `tt.dit.train.train` calls holding the run's lock, as
        its ``on_start_over``) removes it. Otherwise it is read back, and refused
        (ValueError) if it was scored another way."""
        self.run = Path(run)
        self.config = config or SelectionConfig()
        self.rows: list[SelectionRow] = []
        if not fresh:
            self._check_config()
            self.rows = self._read()
        self._pairs = None  # (space, designs, motions), drawn at the first call

    def start_over(self) -> None:
        """Remove an earlier selection's files from the run folder."""
        for path in (self.csv_path, self.best_path, self.best_meta_path, self.config_path, self.run / "selection.png"):
            path.unlink(missing_ok=True)

    @property
    def config_path(self) -> Path:
        return self.run / "selection.json"

    def _check_config(self) -> None:
        if not self.config_path.exists():
            return
        # The device changes the sampling noise, not what r measures, so a run trained on
        # one device may be resumed and scored on another.
        stored = read_json(self.config_path, "selection settings")
        if not isinstance(stored, dict):
            raise CorruptFileError(
                f"selection settings {self.config_path} hold a {type(stored).__name__}, not the "
                "settings tt train writes; move it away, or start the run over with --no-resume"
            )
        before = {k: v for k, v in stored.items() if k != "device"}
        now = {k: v for k, v in json.loads(json.dumps(asdict(self.config))).items() if k != "device"}
        if before != now:
            raise TTError(
                f"{self.run} was selected with {before}, this run asks for {now}: their r values do not "
                "compare; give the same --select-* flags, or start the run over with --no-resume"
            )

    @property
    def csv_path(self) -> Path:
        return self.run / "selection.csv"

    @property
    def best_path(self) -> Path:
        return self.run / "best.pt"

    @property
    def best_meta_path(self) -> Path:
        return self.run / "best.json"

    @property
    def best(self) -> SelectionRow | None:
        """The row with the highest within-motion r (NaN rows never win), or None."""
        finite = [r for r in self.rows if math.isfinite(r.within_r)]
        return max(finite, key=lambda r: (r.within_r, -r.step)) if finite else None

    def _read(self) -> list[SelectionRow]:
        if not self.csv_path.exists():
            return []
        try:
            with self.csv_path.open(encoding="utf-8", newline="") as f:
                reader = csv.DictReader(f)
                if tuple(reader.fieldnames or ()) != _COLUMNS:
                    raise CorruptFileError(
                        f"selection table {self.csv_path} has columns {reader.fieldnames}, not "
                        f"{list(_COLUMNS)}; move it away to start the selection over"
                    )
                return [
                    SelectionRow(int(r["step"]), float(r["within_r"]), float(r["pooled_r"]), float(r["seconds"]))
                    for r in reader
                ]
        except UnicodeDecodeError as e:
            why = f"it is not text (byte {e.start} is not UTF-8)"
        except (ValueError, TypeError, KeyError, csv.Error) as e:
            why = f"a row is not step,within_r,pooled_r,seconds numbers ({reason(e)})"
        raise CorruptFileError(
            f"selection table {self.csv_path} is damaged: {why}; move it away to start the selection "
            "over, or start the run over with --no-resume"
        )

    def _pairs_for(self, space: str):
        from tt.ladder import heldout_designs, validation_motions

        if self._pairs is None or self._pairs[0] != space:
            cfg = self.config
            self._pairs = (
                space,
                heldout_designs(space, cfg.designs, seed=SELECTION_SEED),
                validation_motions(space, cfg.motions),
            )
        return self._pairs[1], self._pairs[2]

    def __call__(self, step: int, checkpoint: str | Path) -> SelectionRow:
        import time

        from tt.dit.checkpoint import load_model
        from tt.kernels.device import default_device
        from tt.ladder import score_designs

        t0 = time.perf_counter()
        trained = load_model(checkpoint, device=self.config.device or default_device())
        if trained.space is None:
            raise TTError(f"checkpoint {checkpoint} records no design space; selection needs one to draw designs")
        designs, motions = self._pairs_for(trained.space)
        cfg = self.config
        score = score_designs(  # backend None: the space's (evaluate_designs)
            trained, designs, motions, cfg.reward, samples=cfg.samples, num_steps=cfg.num_steps, backend=cfg.backend
        )
        # A motion whose predictions do not spread has no r; it counts 0, not left out, so a
        # degenerate checkpoint is not ranked on the motions where it happens to vary.
        within = float(np.mean([r if math.isfinite(r) else 0.0 for r in score.within]))
        row = SelectionRow(int(step), within, float(score.pooled), time.perf_counter() - t0)
        self.rows = sorted([r for r in self.rows if r.step != row.step] + [row], key=lambda r: r.step)
        self._write()
        best = self.best
        if best is row:
            self._keep(Path(checkpoint), row)
        elif best is not None and self.kept_step != best.step:
            log.warning(
                "selection: best.pt holds step %s but the best scored step is %d, whose checkpoint is no "
                "longer at hand",
                self.kept_step,
                best.step,
            )
        log.info(
            "selection: step %d within-motion r %.3f, pooled r %.3f (best: step %d, %.3f)",
            row.step,
            row.within_r,
            row.pooled_r,
            self.best.step if self.best else -1,
            self.best.within_r if self.best else float("nan"),
        )
        return row

    @property
    def kept_step(self) -> int | None:
        """The step whose checkpoint ``best.pt`` holds (``best.json``), or None."""
        meta = self.best_meta_path
        if not (meta.exists() and self.best_path.exists()):
            return None
        data = read_json(meta, "best-checkpoint record")
        try:
            return int(data["step"])
        except (KeyError, TypeError, ValueError):
            raise CorruptFileError(
                f"best-checkpoint record {meta} has no step number; move it away, or start the run "
                "over with --no-resume"
            ) from None

    def _keep(self, checkpoint: Path, row: SelectionRow) -> None:
        # Copied, not linked: the run prunes old checkpoints (`keep_checkpoints`).
        with open(checkpoint, "rb") as src, atomic_write(self.best_path) as dst:
            shutil.copyfileobj(src, dst)
        write_text(
            self.best_meta_path,
            json.dumps({**asdict(row), "checkpoint": checkpoint.name, "config": asdict(self.config)}, indent=1),
        )

    def _write(self) -> None:
        write_text(self.config_path, json.dumps(asdict(self.config), indent=1))
        with atomic_write(self.csv_path, "w") as f:
            w = csv.writer(f)
            w.writerow(_COLUMNS)
            for r in self.rows:
                w.writerow([r.step, f"{r.within_r:.6g}", f"{r.pooled_r:.6g}", f"{r.seconds:.3f}"])
        if len(self.rows) >= 2:
            from tt.viz.plots import save_curve

            save_curve(
                self.run / "selection.png",
                [r.step for r in self.rows],
                {"within-motion r": [r.within_r for r in self.rows], "pooled r": [r.pooled_r for r in self.rows]},
                title=f"held-out r per checkpoint (best: step {self.best.step})" if self.best else "held-out r",
                xlabel="training step",
                ylabel="predicted vs simulated reward, Pearson r",
            )


__all__ = ["SELECTION_SEED", "CheckpointSelector", "SelectionConfig", "SelectionRow"]
