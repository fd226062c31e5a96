"""Target motions: end-effector SE(3) trajectories sampled at 50 Hz."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Control and motion rate of tt [Hz]; every motion is resampled to it.
MOTION_HZ = 50.0
MOTION_DT = 1.0 / MOTION_HZ


class MotionError(ValueError):
    """A trajectory that cannot be tracked as given (NaN, bad quaternions, empty)."""


@dataclass(frozen=True, eq=False)
class Motion:
    """End-effector targets in the world frame.

    pos: positions [m], shape (T, A, 3), A end effectors (1 single arm, 2 bimanual).
    quat: orientations as unit quaternions (w, x, y, z), shape (T, A, 4).
    dt: sample period [s]; tt's own motions use `MOTION_DT`.
    """

    name: str
    pos: np.ndarray
    quat: np.ndarray
    dt: float = MOTION_DT
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        pos = np.asarray(self.pos, dtype=np.float64)
        quat = np.asarray(self.quat, dtype=np.float64)
        if pos.ndim == 2:
            pos = pos[:, None, :]
        if quat.ndim == 2:
            quat = quat[:, None, :]
        if pos.ndim != 3 or pos.shape[-1] != 3:
            raise MotionError(f"motion {self.name!r}: pos must have shape (T, 3) or (T, A, 3), got {pos.shape}")
        if quat.shape != pos.shape[:2] + (4,):
            raise MotionError(f"motion {self.name!r}: quat shape {quat.shape} does not match pos {pos.shape[:2]} + (4,)")
        if pos.shape[0] == 0:
            raise MotionError(f"motion {self.name!r} is empty (T = 0)")
        if not np.all(np.isfinite(pos)):
            bad = int(np.argwhere(~np.isfinite(pos))[0, 0])
            raise MotionError(f"motion {self.name!r}: pos has NaN/inf (first at step {bad})")
        if not np.all(np.isfinite(quat)):
            bad = int(np.argwhere(~np.isfinite(quat))[0, 0])
            raise MotionError(f"motion {self.name!r}: quat has NaN/inf (first at step {bad})")
        norms = np.linalg.norm(quat, axis=-1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            bad = int(np.argwhere(np.abs(norms - 1.0) > 1e-3)[0, 0])
            raise MotionError(
                f"motion {self.name!r}: quaternion at step {bad} has norm {norms.flat[np.argmax(np.abs(norms - 1))]:.4f}; "
                "quaternions must be unit (w, x, y, z)"
            )
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise MotionError(f"motion {self.name!r}: dt must be a positive number of seconds, got {self.dt}")
        object.__setattr__(self, "pos", pos)
        object.__setattr__(self, "quat", quat / norms[..., None])

    @property
    def steps(self) -> int:
        """Number of samples T."""
        return self.pos.shape[0]

    @property
    def arms(self) -> int:
        """Number of end effectors A."""
        return self.pos.shape[1]

    @property
    def duration(self) -> float:
        """Length in seconds."""
        return self.steps * self.dt
