"""The script builder of the skill library: smooth keyframed end-effector trajectories.

A `Script` is a trajectory of A end effectors built phase by phase: holds, minimum-jerk
moves (with optional offsets that vanish with two derivatives at the phase ends), and
minimum-jerk-timed paths. Each phase starts and ends at rest, or adds offsets that vanish
with their first two derivatives at its ends, so every trajectory is C2 in position and
orientation. `Script.build` samples it at 50 Hz.

Frames. Positions are in the world frame [m], z up. The end-effector frame has its x axis
along the approach direction (the way the gripper points); the identity quaternion means
"pointing forward (+x), level". Orientations are scripted as intrinsic yaw-pitch-roll,
q = Rz(yaw) Ry(pitch) Rx(roll): pitch +90 deg points the gripper straight down, roll turns
it about its own approach axis (a screw, a pour). Poses are given as dicts in degrees for
angles (`DEG` converts), holding only the keys that change.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from tt.sim.motions.base import MOTION_DT, MotionError, quat_mul

#: Degrees to radians (scripts give angles in degrees).
DEG = np.pi / 180.0
_POSE_KEYS = ("x", "y", "z", "pitch", "yaw", "roll")


def min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk profile 10s^3 - 15s^4 + 6s^5 on s in [0, 1] (clipped); zero slope and curvature at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def bump(s: np.ndarray) -> np.ndarray:
    """Smooth bump 64 s^3 (1-s)^3 on [0, 1]: 0 at the ends with two vanishing derivatives, 1 at s = 0.5."""
    s = np.clip(s, 0.0, 1.0)
    return 64.0 * s**3 * (1.0 - s) ** 3


def envelope(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Plateau of height 1 with minimum-jerk ramps of `ramp` [s] at both ends of [0, duration] [s]."""
    return min_jerk(t / ramp) * min_jerk((duration - t) / ramp)


def pose_quat(pitch: np.ndarray, yaw: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) of Rz(yaw) Ry(pitch) Rx(roll), angles [rad] of shape (...)."""
    pitch, yaw, roll = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (pitch, yaw, roll)))
    zero = np.zeros_like(pitch)
    qz = np.stack([np.cos(yaw / 2), zero, zero, np.sin(yaw / 2)], axis=-1)
    qy = np.stack([np.cos(pitch / 2), zero, np.sin(pitch / 2), zero], axis=-1)
    qx = np.stack([np.cos(roll / 2), np.sin(roll / 2), zero, zero], axis=-1)
    return quat_mul(quat_mul(qz, qy), qx)


def mirror_pose(pose: dict[str, float]) -> dict[str, float]:
    """The pose mirrored through the world xz plane (y, yaw and roll change sign)."""
    flip = {"y", "yaw", "roll"}
    return {k: (-v if k in flip else v) for k, v in pose.items()}


# A phase maps local times t (n,) [s] and fractions tau = t / duration (n,) to poses (n, A, 6).
_PhaseFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class Script:
    """Keyframed trajectory of A end effectors, built phase by phase; all arms share phase times.

    A pose is (x, y, z [m], pitch, yaw, roll [rad]); poses are given as dicts in degrees
    for angles, holding only the keys that change.
    """

    def __init__(self, *starts: dict[str, float]):
        self._pose = np.array([self._vector(s, None) for s in starts])  # (A, 6)
        self._phases: list[tuple[float, _PhaseFn]] = []

    @staticmethod
    def _vector(update: dict[str, float] | None, base: np.ndarray | None) -> np.ndarray:
        out = np.zeros(6) if base is None else base.copy()
        for k, v in (update or {}).items():
            i = _POSE_KEYS.index(k)
            out[i] = v * DEG if i >= 3 else v
        return out

    @property
    def arms(self) -> int:
        return self._pose.shape[0]

    def pose(self, arm: int = 0) -> dict[str, float]:
        """The current keyframe pose of `arm` (angles in degrees)."""
        return {k: float(v / DEG if i >= 3 else v) for i, (k, v) in enumerate(zip(_POSE_KEYS, self._pose[arm]))}

    def hold(self, duration: float) -> None:
        """Stay at the current pose for `duration` [s]."""
        self.move(duration)

    def move(self, duration: float, *targets: dict[str, float] | None, wave: _PhaseFn | None = None) -> None:
        """Minimum-jerk move of each arm to its updated pose over `duration` [s].

        targets: one pose update per arm (None keeps that arm still); wave: optional
        offsets (n, A, 6) added on top, which must vanish with two derivatives at the ends.
        """
        if targets and len(targets) != self.arms:
            raise MotionError(f"move needs {self.arms} targets, got {len(targets)}")
        start = self._pose.copy()
        end = np.array([self._vector(tg, start[a]) for a, tg in enumerate(targets or [None] * self.arms)])

        def phase(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
            out = start + (end - start) * min_jerk(tau)[:, None, None]
            return out if wave is None else out + wave(t, tau)

        self._phases.append((float(duration), phase))
        self._pose = end

    def path(self, duration: float, fn: Callable[[np.ndarray], np.ndarray]) -> None:
        """Follow `fn(s) -> poses (n, A, 6)` for s = min_jerk(tau), starting at rest at the current pose."""
        first = fn(np.zeros(1))[0]
        if not np.allclose(first, self._pose, atol=1e-9):
            raise MotionError(f"path starts at {first}, the script is at {self._pose}")
        self._phases.append((float(duration), lambda t, tau: fn(min_jerk(tau))))
        self._pose = fn(np.ones(1))[0]

    def build(self, dt: float = MOTION_DT) -> tuple[np.ndarray, np.ndarray]:
        """Sample at period `dt` [s] from 0 to the end of the last phase: pos (T, A, 3), quat (T, A, 4)."""
        durations = np.array([d for d, _ in self._phases])
        bounds = np.concatenate([[0.0], np.cumsum(durations)])
        t = np.arange(int(round(bounds[-1] / dt)) + 1) * dt
        which = np.clip(np.searchsorted(bounds, t, side="right") - 1, 0, len(self._phases) - 1)
        poses = np.empty((t.size, self.arms, 6))
        for i, (d, fn) in enumerate(self._phases):
            sel = which == i
            local = np.minimum(t[sel] - bounds[i], d)
            poses[sel] = fn(local, local / d)
        quat = pose_quat(poses[..., 3], poses[..., 4], poses[..., 5])
        return poses[..., :3], quat


def azimuth(x: float, y: float, mount_y: float = 0.0) -> float:
    """Yaw [deg] that points a gripper from an arm's mount at (0, mount_y) towards (x, y)."""
    return float(np.degrees(np.arctan2(y - mount_y, x)))


def bezier(points: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Cubic Bezier through control points (4, D) at parameters u (n,): (n, D).

    A Bezier curve stays in the convex hull of its control points, so control points
    inside the workspace box keep the whole curve inside it.
    """
    u = u[:, None]
    b = np.concatenate([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3], axis=1)
    return b @ points


__all__ = ["DEG", "Script", "azimuth", "bezier", "bump", "envelope", "min_jerk", "mirror_pose", "pose_quat"]
