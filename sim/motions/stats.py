"""Statistics of target motions: how fast, how far and how much the tool turns.

They say where a motion sits among human demonstrations (tosses and flings peak at 2-3 m/s)
and whether it asks anything of a design. `tt motions --stats` prints them per skill.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from tt.sim.motions.base import Motion, MotionError


@dataclass(frozen=True)
class MotionStats:
    """Kinematic statistics of one motion; each is the largest over its end effectors.

    peak_speed, p95_speed: largest and 95th-percentile end-effector speed [m/s];
    peak_accel: largest end-effector acceleration [m/s^2] (central differences);
    extent: largest side of the axis-aligned box the path spans [m];
    orn_range: largest rotation between any two of its orientations [deg].
    """

    name: str
    arms: int
    duration: float
    peak_speed: float
    p95_speed: float
    peak_accel: float
    extent: float
    orn_range: float

    def row(self) -> dict:
        return asdict(self)


def _largest_rotation_deg(quat: np.ndarray) -> float:
    """Largest geodesic angle [deg] between any two unit quaternions of (T, 4)."""
    dots = np.clip(np.abs(quat @ quat.T), 0.0, 1.0)  # (T, T); q and -q are one rotation
    return float(np.degrees(2.0 * np.arccos(dots.min())))


def motion_stats(motions: Sequence[Motion]) -> list[MotionStats]:
    """The `MotionStats` of each motion."""
    out = []
    for m in motions:
        if m.steps < 3:
            raise MotionError(f"motion {m.name!r} has {m.steps} samples; speed and acceleration need at least 3")
        vel = np.gradient(m.pos, m.dt, axis=0)  # (T, A, 3) [m/s]
        acc = np.gradient(vel, m.dt, axis=0)  # (T, A, 3) [m/s^2]
        speed = np.linalg.norm(vel, axis=-1)  # (T, A)
        extent = (m.pos.max(axis=0) - m.pos.min(axis=0)).max()
        out.append(
            MotionStats(
                name=m.name,
                arms=m.arms,
                duration=m.duration,
                peak_speed=float(speed.max()),
                p95_speed=float(np.percentile(speed, 95, axis=0).max()),
                peak_accel=float(np.linalg.norm(acc, axis=-1).max()),
                extent=float(extent),
                orn_range=max(_largest_rotation_deg(m.quat[:, a]) for a in range(m.arms)),
            )
        )
    return out
