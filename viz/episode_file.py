"""Episode files: what the viewer needs from a rollout, in one ``.npz``.

An episode file holds W worlds (one robot each) over T frames at the control rate. Each
world's design travels with it as JSON, so a file opens without the design file it came
from, and the body count of each world's model is recorded, so a file that no longer
matches its design (a changed design space, a hand-edited file) is caught on load
instead of animating the wrong bodies.

Keys (format ``tt.episode.v1``); worlds whose models have fewer joints than the widest
use the first ``nq[w]`` columns of ``qpos``:

=============  ================  ===================================================
key            shape / type      meaning
=============  ================  ===================================================
format         str               ``tt.episode.v1``
designs        str (JSON)        list of W design dicts (`DesignSpace.to_dict`)
labels         str (JSON)        list of W labels
motion_name    str               name of the target motion ('' if none)
dt             float             frame period [s]
qpos           (W, T, nq_max)    joint positions [m, rad; quaternions for free joints]
nq             (W,) int          joint-position count of each world's model
nbody          (W,) int          body count of each world's model (world body included)
alive          (W, T) bool       step executed before termination
target_pos     (W, T, A, 3)      end-effector targets [m] (absent: no targets)
target_quat    (W, T, A, 4)      target orientations (w, x, y, z)
=============  ================  ===================================================
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import mujoco
import numpy as np

from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, atomic_write, read_npz
from tt.sim.designs import Design, DesignError, get_space
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion, MotionError
from tt.viz.scene import Scene, SceneOptions, build_scene

FORMAT = "tt.episode.v1"


class EpisodeFileError(TTError):
    """An episode file (or record) that is malformed or does not match its designs."""


def _numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


@dataclass(frozen=True)
class EpisodeRecord:
    """Joint trajectories and targets of W robots, with the designs that produced them.

    designs: the design of each world, length W.
    qpos: joint positions, (W, T, nq_max); world w uses columns ``[:nq[w]]``.
    nq: joint-position count per world, (W,).
    nbody: body count per world's model (world body included), (W,).
    alive: step executed before termination, (W, T).
    target_pos: end-effector targets [m], (W, T, A, 3), or None.
    target_quat: target orientations (w, x, y, z), (W, T, A, 4), or None.
    labels: one label per world.
    motion_name: name of the target motion ('' when unknown).
    dt: frame period [s].
    """

    designs: tuple[Design, ...]
    qpos: np.ndarray
    nq: np.ndarray
    nbody: np.ndarray
    alive: np.ndarray
    target_pos: np.ndarray | None
    target_quat: np.ndarray | None
    labels: tuple[str, ...]
    motion_name: str
    dt: float

    def __post_init__(self) -> None:
        q = np.asarray(self.qpos, dtype=np.float64)
        if q.ndim != 3:
            raise EpisodeFileError(f"qpos must have shape (W, T, nq), got {q.shape}")
        w, t = q.shape[:2]
        if w == 0 or t == 0:
            raise EpisodeFileError(f"qpos has shape {q.shape}; an episode needs at least one world and one frame")
        nq = np.asarray(self.nq, dtype=np.int64).reshape(-1)
        nbody = np.asarray(self.nbody, dtype=np.int64).reshape(-1)
        for name, arr in (("nq", nq), ("nbody", nbody)):
            if arr.shape != (w,):
                raise EpisodeFileError(
                    f"{name} has shape {arr.shape}; qpos has W = {w} worlds, so {name} must be ({w},)"
                )
        if np.any(nq < 0) or np.any(nq > q.shape[2]):
            bad = int(np.argmax((nq < 0) | (nq > q.shape[2])))
            raise EpisodeFileError(f"nq[{bad}] = {nq[bad]}; valid: 0..{q.shape[2]} (the width of qpos)")
        alive = np.asarray(self.alive, dtype=bool)
        if alive.shape != (w, t):
            raise EpisodeFileError(f"alive has shape {alive.shape}; expected (W, T) = ({w}, {t})")
        if len(self.designs) != w:
            raise EpisodeFileError(f"{len(self.designs)} designs for W = {w} worlds; give one design per world")
        if len(self.labels) != w:
            raise EpisodeFileError(f"{len(self.labels)} labels for W = {w} worlds; give one label per world")
        if (self.target_pos is None) != (self.target_quat is None):
            raise EpisodeFileError("target_pos and target_quat must both be given or both be absent")
        tp = tq = None
        if self.target_pos is not None:
            tp = np.asarray(self.target_pos, dtype=np.float64)
            tq = np.asarray(self.target_quat, dtype=np.float64)
            if tp.ndim != 4 or tp.shape[:2] != (w, t) or tp.shape[3] != 3:
                raise EpisodeFileError(
                    f"target_pos has shape {tp.shape}; expected (W, T, A, 3) with (W, T) = ({w}, {t})"
                )
            if tq.shape != tp.shape[:3] + (4,):
                raise EpisodeFileError(f"target_quat has shape {tq.shape}; expected {tp.shape[:3] + (4,)}")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise EpisodeFileError(f"dt = {self.dt}; valid: a positive number of seconds")
        object.__setattr__(self, "qpos", q)
        object.__setattr__(self, "nq", nq)
        object.__setattr__(self, "nbody", nbody)
        object.__setattr__(self, "alive", alive)
        object.__setattr__(self, "target_pos", tp)
        object.__setattr__(self, "target_quat", tq)
        object.__setattr__(self, "designs", tuple(self.designs))
        object.__setattr__(self, "labels", tuple(str(s) for s in self.labels))
        object.__setattr__(self, "dt", float(self.dt))

    @property
    def worlds(self) -> int:
        return self.qpos.shape[0]

    @property
    def steps(self) -> int:
        return self.qpos.shape[1]

    # ------------------------------------------------------------ construction
    @classmethod
    def from_episode(
        cls,
        episode: Episode,
        designs: Sequence[Design],
        *,
        labels: Sequence[str] | None = None,
        motion_name: str = "",
    ) -> "EpisodeRecord":
        """The record of a rollout; `designs` are the rollout's input designs, indexed by
        ``episode.design_index``."""
        qpos = _numpy(episode.qpos).astype(np.float64)
        index = _numpy(episode.design_index).astype(np.int64).reshape(-1)
        if index.shape != (qpos.shape[0],):
            raise EpisodeFileError(f"episode.design_index has shape {index.shape}; expected ({qpos.shape[0]},)")
        if np.any(index < 0) or np.any(index >= len(designs)):
            bad = int(index[(index < 0) | (index >= len(designs))][0])
            raise EpisodeFileError(f"episode.design_index holds {bad}; only {len(designs)} designs were given")
        world_designs = tuple(designs[i] for i in index)
        models = [get_space(d.space).model(d) for d in world_designs]
        for w, m in enumerate(models):
            # Batches of mixed DoF pad qpos with zeros to the widest model.
            if m.nq > qpos.shape[2]:
                raise EpisodeFileError(
                    f"world {w}: episode qpos has {qpos.shape[2]} columns but design {int(index[w])} builds a "
                    f"model with nq = {m.nq}"
                )
        if labels is None:
            motion_index = _numpy(episode.motion_index).astype(np.int64).reshape(-1)
            labels = [f"{d.space} #{i}" for d, i in zip(world_designs, index)]
            if len(set(motion_index.tolist())) > 1:
                labels = [f"{s}, motion {m}" for s, m in zip(labels, motion_index)]
        return cls(
            designs=world_designs,
            qpos=qpos,
            nq=np.array([m.nq for m in models]),
            nbody=np.array([m.nbody for m in models]),
            alive=_numpy(episode.alive).astype(bool),
            target_pos=_numpy(episode.target_pos),
            target_quat=_numpy(episode.target_quat),
            labels=tuple(labels),
            motion_name=motion_name,
            dt=float(episode.dt),
        )

    @classmethod
    def concat(cls, records: Sequence["EpisodeRecord"]) -> "EpisodeRecord":
        """One record with the worlds of all `records` (e.g. the winners of several
        optimizers on one motion). Shorter episodes hold their last frame."""
        records = list(records)
        if not records:
            raise EpisodeFileError("nothing to concatenate: records is empty")
        dts = {r.dt for r in records}
        if len(dts) != 1:
            raise EpisodeFileError(f"records have different frame periods dt = {sorted(dts)} s")
        has_targets = {r.target_pos is not None for r in records}
        if len(has_targets) != 1:
            raise EpisodeFileError("either every record has targets or none does")
        if records[0].target_pos is not None:
            arms = {r.target_pos.shape[2] for r in records}
            if len(arms) != 1:
                raise EpisodeFileError(f"records have different end-effector counts {sorted(arms)}")
        t = max(r.steps for r in records)
        nq = max(r.qpos.shape[2] for r in records)

        def pad(x: np.ndarray, width: int | None = None) -> np.ndarray:
            x = np.concatenate([x, np.repeat(x[:, -1:], t - x.shape[1], axis=1)], axis=1)
            if width is not None and x.shape[2] < width:
                x = np.concatenate([x, np.zeros(x.shape[:2] + (width - x.shape[2],))], axis=2)
            return x

        def pad_alive(a: np.ndarray) -> np.ndarray:
            return np.concatenate([a, np.zeros((a.shape[0], t - a.shape[1]), dtype=bool)], axis=1)

        names = {r.motion_name for r in records} - {""}
        return cls(
            designs=tuple(d for r in records for d in r.designs),
            qpos=np.concatenate([pad(r.qpos, nq) for r in records]),
            nq=np.concatenate([r.nq for r in records]),
            nbody=np.concatenate([r.nbody for r in records]),
            alive=np.concatenate([pad_alive(r.alive) for r in records]),
            target_pos=None if records[0].target_pos is None else np.concatenate([pad(r.target_pos) for r in records]),
            target_quat=None
            if records[0].target_quat is None
            else np.concatenate([pad(r.target_quat) for r in records]),
            labels=tuple(s for r in records for s in r.labels),
            motion_name=names.pop() if len(names) == 1 else "",
            dt=records[0].dt,
        )

    def select(self, worlds: Sequence[int]) -> "EpisodeRecord":
        """The record of some worlds only (negative indices count from the end)."""
        idx = []
        for k in worlds:
            if not -self.worlds <= int(k) < self.worlds:
                raise EpisodeFileError(f"world index {k} out of range: the episode has {self.worlds} worlds")
            idx.append(int(k) % self.worlds)
        return EpisodeRecord(
            designs=tuple(self.designs[k] for k in idx),
            qpos=self.qpos[idx],
            nq=self.nq[idx],
            nbody=self.nbody[idx],
            alive=self.alive[idx],
            target_pos=None if self.target_pos is None else self.target_pos[idx],
            target_quat=None if self.target_quat is None else self.target_quat[idx],
            labels=tuple(self.labels[k] for k in idx),
            motion_name=self.motion_name,
            dt=self.dt,
        )

    # ------------------------------------------------------------ use
    def models(self) -> list[mujoco.MjModel]:
        """The MuJoCo model of each world, checked against the recorded nq and body count."""
        models = []
        for w, d in enumerate(self.designs):
            who = f"world {w} ({self.labels[w]!r})"
            try:
                model = get_space(d.space).model(d)
            except DesignError as e:
                raise EpisodeFileError(f"{who}: its design does not load: {e}") from None
            except ValueError as e:  # MuJoCo's compiler
                raise EpisodeFileError(f"{who}: MuJoCo cannot compile its design: {e}") from None
            if model.nbody != self.nbody[w]:
                raise EpisodeFileError(
                    f"{who}: the episode has poses for {self.nbody[w]} bodies but its design builds a model with "
                    f"{model.nbody} bodies; the episode does not belong to this design"
                )
            if model.nq != self.nq[w]:
                raise EpisodeFileError(
                    f"{who}: the episode has nq = {self.nq[w]} joint positions per frame but its design builds a "
                    f"model with nq = {model.nq}"
                )
            models.append(model)
        return models

    def world_qpos(self, w: int) -> np.ndarray:
        """Joint positions of world `w`, (T, nq[w])."""
        return self.qpos[w, :, : self.nq[w]]

    def world_motion(self, w: int) -> Motion | None:
        """The targets of world `w` as a Motion (None when the record has no targets)."""
        if self.target_pos is None:
            return None
        try:
            return Motion(self.motion_name or "targets", self.target_pos[w], self.target_quat[w], self.dt)
        except MotionError as e:
            raise EpisodeFileError(f"world {w} ({self.labels[w]!r}): bad targets: {e}") from None

    def scene(self, *, motion: Motion | None = None, options: SceneOptions | None = None) -> Scene:
        """A scene animating every world side by side; `motion` replaces the recorded targets."""
        models = self.models()
        motions = [motion] * self.worlds if motion is not None else [self.world_motion(w) for w in range(self.worlds)]
        return build_scene(
            models,
            qpos=[self.world_qpos(w) for w in range(self.worlds)],
            motions=motions,
            labels=self.labels,
            dt=self.dt,
            options=options,
        )


# ---------------------------------------------------------------- files
def save_episode_npz(
    path: str | Path,
    episode: Episode | EpisodeRecord,
    designs: Sequence[Design] | None = None,
    *,
    labels: Sequence[str] | None = None,
    motion_name: str = "",
) -> Path:
    """Write an episode file. Give an `Episode` with its input `designs` (and optionally
    labels and the motion's name), or a ready `EpisodeRecord`. Returns the path."""
    if isinstance(episode, EpisodeRecord):
        if designs is not None or labels is not None:
            raise EpisodeFileError("an EpisodeRecord carries its designs and labels; do not pass them again")
        record = episode
    else:
        if designs is None:
            raise EpisodeFileError("saving an Episode needs the designs it ran (designs=...)")
        record = EpisodeRecord.from_episode(episode, designs, labels=labels, motion_name=motion_name)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {
        "format": np.array(FORMAT),
        "designs": np.array(json.dumps([get_space(d.space).to_dict(d) for d in record.designs])),
        "labels": np.array(json.dumps(list(record.labels))),
        "motion_name": np.array(record.motion_name),
        "dt": np.array(record.dt),
        "qpos": record.qpos,
        "nq": record.nq,
        "nbody": record.nbody,
        "alive": record.alive,
    }
    if record.target_pos is not None:
        arrays["target_pos"] = record.target_pos
        arrays["target_quat"] = record.target_quat
    # np.savez appends .npz to names without it; write through a handle to keep the name.
    with atomic_write(path) as f:
        np.savez_compressed(f, **arrays)
    return path


def load_episode_npz(path: str | Path) -> EpisodeRecord:
    """Read an episode file written by `save_episode_npz`; errors name the bad key."""
    path = Path(path)
    try:
        data = read_npz(path, "episode file")
    except CorruptFileError as e:
        raise EpisodeFileError(str(e)) from None
    required = ("format", "designs", "labels", "motion_name", "dt", "qpos", "nq", "nbody", "alive")
    missing = [k for k in required if k not in data]
    if missing:
        raise EpisodeFileError(f"{path}: missing keys {missing}; an episode file ({FORMAT}) has {list(required)}")
    fmt = str(data["format"])
    if fmt != FORMAT:
        raise EpisodeFileError(f"{path}: format is {fmt!r}; this version of tt reads {FORMAT!r}")
    try:
        design_dicts = json.loads(str(data["designs"]))
        labels = json.loads(str(data["labels"]))
    except json.JSONDecodeError as e:
        raise EpisodeFileError(f"{path}: 'designs' or 'labels' is not valid JSON: {e}") from None
    if not isinstance(design_dicts, list):
        raise EpisodeFileError(f"{path}: 'designs' must be a JSON list of designs")
    designs = []
    for w, item in enumerate(design_dicts):
        if not isinstance(item, dict) or "space" not in item:
            raise EpisodeFileError(f"{path}: design of world {w} has no 'space' field")
        try:
            designs.append(get_space(item["space"]).from_dict(item))
        except DesignError as e:
            raise EpisodeFileError(f"{path}: design of world {w} does not load: {e}") from None
    has_targets = "target_pos" in data and "target_quat" in data
    try:
        return EpisodeRecord(
            designs=tuple(designs),
            qpos=data["qpos"],
            nq=data["nq"],
            nbody=data["nbody"],
            alive=data["alive"],
            target_pos=data["target_pos"] if has_targets else None,
            target_quat=data["target_quat"] if has_targets else None,
            labels=tuple(labels),
            motion_name=str(data["motion_name"]),
            dt=float(data["dt"]),
        )
    except (TypeError, ValueError) as e:  # an entry of the wrong shape or type
        raise EpisodeFileError(f"{path}: {e}") from None
