"""Target motions: end-effector SE(3) trajectories sampled at 50 Hz."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tt.kernels.errors import TTError

#: Control and motion rate of tt [Hz]; every motion is resampled to it.
MOTION_HZ = 50.0
MOTION_DT = 1.0 / MOTION_HZ


class MotionError(TTError):
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
            raise MotionError(
                f"motion {self.name!r}: quat shape {quat.shape} does not match pos {pos.shape[:2]} + (4,)"
            )
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
                f"motion {self.name!r}: quaternion at step {bad} has norm "
                f"{norms.flat[np.argmax(np.abs(norms - 1))]:.4f}; "
                "quaternions must be unit (w, x, y, z)"
            )
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise MotionError(f"motion {self.name!r}: dt must be a positive number of seconds, got {self.dt}")
        # Quaternions already unit to rounding are kept bit for bit, so that saving and
        # reloading a motion reproduces it exactly (renormalising is not idempotent).
        unit = (np.abs(norms - 1.0) <= 1e-12)[..., None]
        object.__setattr__(self, "pos", pos)
        object.__setattr__(self, "quat", np.where(unit, quat, quat / norms[..., None]))

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


# ------------------------------------------------------------------ quaternion helpers
# (w, x, y, z), Hamilton convention, batched over any leading dimensions; float64 numpy.


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of quaternions, shapes (..., 4) broadcast together."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion), shape (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors v (..., 3) rotated by unit quaternions q (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) from rotation vectors (axis * angle [rad]), shape (..., 3)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    # sin(angle/2)/angle written with np.sinc stays exact as angle -> 0.
    half_sinc = 0.5 * np.sinc(angle / (2.0 * np.pi))
    return np.concatenate([np.cos(angle / 2.0), rotvec * half_sinc], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3), angle in [0, pi] [rad], from unit quaternions (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    q = np.where(q[..., :1] < 0.0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    # angle / s -> 2 / w as s -> 0 (w -> 1); both forms agree to rounding at s = 1e-8.
    scale = np.where(s > 1e-8, angle / np.maximum(s, 1e-300), 2.0 / q[..., :1])
    return q[..., 1:] * scale


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle [rad] from a to b, in [0, pi], shape (...)."""
    d = np.abs(np.sum(np.asarray(a, dtype=np.float64) * np.asarray(b, dtype=np.float64), axis=-1))
    return 2.0 * np.arccos(np.clip(d, 0.0, 1.0))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc.

    q0, q1: unit quaternions (..., 4); s: fractions in [0, 1], shape (...) broadcast with them.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)[..., None]
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(d < 0.0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    sin_t = np.sin(theta)
    # Below ~1e-6 rad apart, normalised linear interpolation equals slerp to rounding.
    near = sin_t < 1e-6
    safe = np.where(near, 1.0, sin_t)
    w0 = np.where(near, 1.0 - s, np.sin((1.0 - s) * theta) / safe)
    w1 = np.where(near, s, np.sin(s * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_continuous(q: np.ndarray) -> np.ndarray:
    """Sign-flip samples of a trajectory (T, ..., 4) so consecutive quaternions have q_t · q_t-1 >= 0.

    q and -q are the same rotation; a continuous sign makes a trajectory smooth as a curve in R^4.
    """
    q = np.array(q, dtype=np.float64, copy=True)
    if q.shape[0] < 2:
        return q
    flips = np.sum(q[1:] * q[:-1], axis=-1) < 0.0
    sign = np.concatenate([np.ones((1,) + flips.shape[1:]), np.where(np.cumsum(flips, axis=0) % 2 == 1, -1.0, 1.0)])
    return q * sign[..., None]
