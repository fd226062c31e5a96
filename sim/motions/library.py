"""Procedural manipulation skills: seeded end-effector trajectories at 50 Hz.

Every skill is a short script of phases (holds, minimum-jerk moves, oscillations under a
smooth envelope, minimum-jerk-timed paths). Each phase starts and ends at rest, or adds
offsets that vanish with their first two derivatives at its ends, so every trajectory is
C2 in position and orientation.

Frames. Positions are in the world frame [m], z up. The end-effector frame has its x axis
along the approach direction (the way the gripper points); the identity quaternion means
"pointing forward (+x), level". Orientations are scripted as intrinsic yaw-pitch-roll,
q = Rz(yaw) Ry(pitch) Rx(roll): pitch +90 deg points the gripper straight down, roll turns
it about its own approach axis (a screw, a pour).

Geometry. Single-arm skills are sized for a ViperX-300S-like arm standing upright at the
world origin (`SINGLE_ARM`); bimanual skills for two such arms mounted at y = +-0.3 m
(`BIMANUAL`), end effector 0 on the +y arm. `Workspace.contains` is the reachability
check the tests apply to every library motion.

Seeds. A skill has a few continuous parameters, each with a nominal value and a range.
Seed 0 is the canonical motion (all nominal); any other seed draws every parameter not
given explicitly uniformly from its range with a generator seeded by (skill, seed), so a
(skill, seed) pair always yields the same motion.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from tt.sim.motions.base import MOTION_DT, Motion, MotionError, quat_mul, quat_rotate

# ------------------------------------------------------------------ workspaces


@dataclass(frozen=True)
class Workspace:
    """Where one arm's end-effector targets may go.

    mount: arm base position [m]; shoulder: shoulder joint position [m] (the arm's centre
    of reach); low, high: axis-aligned box for target positions [m]; center: middle of
    the region the skills work in [m]; reach: largest target distance from the shoulder
    [m] (below the arm's full stretch, so the wrist keeps some bend); hand: wrist-centre to
    gripper-tip length [m]; wrist_reach: largest wrist-centre distance from the shoulder
    [m] (upper arm + forearm less a margin); max_approach_z: largest upward component of
    the approach axis (grippers point forward or down, not up).
    """

    mount: tuple[float, float, float]
    shoulder: tuple[float, float, float]
    low: tuple[float, float, float]
    high: tuple[float, float, float]
    center: tuple[float, float, float]
    reach: float = 0.62
    hand: float = 0.17
    wrist_reach: float = 0.58
    max_approach_z: float = 0.5

    def contains(self, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """Whether each target pose is inside this workspace.

        pos: positions [m], shape (..., 3); quat: (w, x, y, z), shape (..., 4).
        Returns a bool array of shape (...).
        """
        pos = np.asarray(pos, dtype=np.float64)
        approach = quat_rotate(quat, np.array([1.0, 0.0, 0.0]))
        in_box = np.all((pos >= np.array(self.low) - 1e-9) & (pos <= np.array(self.high) + 1e-9), axis=-1)
        tip = np.linalg.norm(pos - np.array(self.shoulder), axis=-1) <= self.reach
        wrist = np.linalg.norm(pos - self.hand * approach - np.array(self.shoulder), axis=-1) <= self.wrist_reach
        upright = approach[..., 2] <= self.max_approach_z
        return in_box & tip & wrist & upright


#: Height of the nominal ViperX shoulder joint above its mount [m].
SHOULDER_HEIGHT = 0.127

#: The single arm: upright at the world origin, working in front of it.
SINGLE_ARM = Workspace(
    mount=(0.0, 0.0, 0.0),
    shoulder=(0.0, 0.0, SHOULDER_HEIGHT),
    low=(0.15, -0.35, 0.05),
    high=(0.55, 0.35, 0.55),
    center=(0.35, 0.0, 0.25),
)

#: Middle of the single arm's working region [m].
SINGLE_ARM_CENTER = SINGLE_ARM.center

#: Lateral mount offset of the bimanual arms [m]: arm 0 at +y, arm 1 at -y.
BIMANUAL_MOUNT_Y = 0.3

#: The two arms of the bimanual robot; targets of arm 0 stay at y >= 0, of arm 1 at y <= 0.
BIMANUAL = (
    Workspace(
        mount=(0.0, BIMANUAL_MOUNT_Y, 0.0),
        shoulder=(0.0, BIMANUAL_MOUNT_Y, SHOULDER_HEIGHT),
        low=(0.15, 0.0, 0.05),
        high=(0.5, 0.55, 0.5),
        center=(0.33, 0.15, 0.25),
    ),
    Workspace(
        mount=(0.0, -BIMANUAL_MOUNT_Y, 0.0),
        shoulder=(0.0, -BIMANUAL_MOUNT_Y, SHOULDER_HEIGHT),
        low=(0.15, -0.55, 0.05),
        high=(0.5, 0.0, 0.5),
        center=(0.33, -0.15, 0.25),
    ),
)

#: Middle of the shared bimanual workspace [m] (between the arms).
BIMANUAL_CENTER = (0.33, 0.0, 0.25)


def workspaces(arms: int) -> tuple[Workspace, ...]:
    """The workspace of each end effector of a robot with `arms` (1 or 2) end effectors."""
    if arms == 1:
        return (SINGLE_ARM,)
    if arms == 2:
        return BIMANUAL
    raise MotionError(f"arms must be 1 or 2, got {arms}")


# ------------------------------------------------------------------ smooth building blocks

_DEG = np.pi / 180.0
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


class _Script:
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
            out[i] = v * _DEG if i >= 3 else v
        return out

    @property
    def arms(self) -> int:
        return self._pose.shape[0]

    def pose(self, arm: int = 0) -> dict[str, float]:
        """The current keyframe pose of `arm` (angles in degrees)."""
        return {k: float(v / _DEG if i >= 3 else v) for i, (k, v) in enumerate(zip(_POSE_KEYS, self._pose[arm]))}

    def hold(self, duration: float) -> None:
        """Stay at the current pose for `duration` [s]."""
        self.move(duration)

    def move(self, duration: float, *targets: dict[str, float] | None, wave: _PhaseFn | None = None) -> None:
        """Minimum-jerk move of each arm to its updated pose over `duration` [s].

        targets: one pose update per arm (None keeps that arm still); wave: optional
        offsets (n, A, 6) added on top, which must vanish with two derivatives at the ends.
        """
        if targets and len(targets) != self.arms:
            raise ValueError(f"move needs {self.arms} targets, got {len(targets)}")
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
            raise ValueError(f"path starts at {first}, the script is at {self._pose}")
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


def _azimuth(x: float, y: float, mount_y: float = 0.0) -> float:
    """Yaw [deg] that points a gripper from an arm's mount at (0, mount_y) towards (x, y)."""
    return float(np.degrees(np.arctan2(y - mount_y, x)))


# ------------------------------------------------------------------ skills


@dataclass(frozen=True)
class SkillParam:
    """One continuous skill parameter: nominal value (seed 0) and the range seeds draw from."""

    name: str
    nominal: float
    low: float
    high: float
    unit: str
    doc: str


@dataclass(frozen=True)
class Skill:
    """A procedural skill: `script(**params)` returns the phases of one trajectory."""

    name: str
    arms: int
    summary: str
    params: tuple[SkillParam, ...]
    script: Callable[..., _Script]

    def draw(self, seed: int) -> dict[str, float]:
        """Parameter values for `seed`: nominal for 0, else uniform in each range."""
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise MotionError(f"seed must be an integer >= 0, got {seed!r}")
        if seed == 0:
            return {p.name: p.nominal for p in self.params}
        rng = np.random.default_rng([zlib.crc32(self.name.encode()), int(seed)])
        return {p.name: float(rng.uniform(p.low, p.high)) for p in self.params}

    def motion(self, seed: int = 0, **overrides: float) -> Motion:
        """The motion for `seed`, with any parameters in `overrides` fixed to the given values.

        ``meta`` records skill, seed, split ("train", "val", "extra", or "custom" when
        parameters were overridden) and every parameter value.
        """
        values = self.draw(seed)
        by_name = {p.name: p for p in self.params}
        for k, v in overrides.items():
            if k not in by_name:
                raise MotionError(f"skill {self.name!r} has no parameter {k!r}; valid: {list(by_name)}")
            p = by_name[k]
            if not (np.isfinite(v) and p.low <= v <= p.high):
                raise MotionError(f"skill {self.name!r}: {k} = {v!r} is outside [{p.low}, {p.high}] {p.unit}")
            values[k] = float(v)
        pos, quat = self.script(**values).build()
        name = self.name if seed == 0 else f"{self.name}:{seed}"
        # A motion with hand-set parameters belongs to no split, whatever its seed.
        split = split_of(seed) if not overrides else "custom"
        meta = {"skill": self.name, "seed": int(seed), "split": split, "params": values}
        return Motion(name, pos, quat, MOTION_DT, meta=meta)


def _p(name: str, nominal: float, low: float, high: float, unit: str, doc: str) -> SkillParam:
    return SkillParam(name, nominal, low, high, unit, doc)


# ---- single arm


def _toss(y, pivot_z, radius, back, forward, swing_time, flick) -> _Script:
    # Underhand swing: the hand moves on a circle below a pivot, like an arm swinging from
    # the shoulder; min-jerk timing puts the peak speed (the release) mid-swing, where the
    # velocity points forward and up by (forward - back) / 2.
    px = 0.32
    yaw = _azimuth(px, y)
    pitch0 = 80.0

    def arc(psi_deg: float) -> tuple[float, float]:
        psi = psi_deg * _DEG
        return px + radius * np.sin(psi), pivot_z - radius * np.cos(psi)

    wx, wz = arc(-back)
    s = _Script({"x": 0.32, "y": y, "z": pivot_z - radius + 0.06, "pitch": 70.0, "yaw": yaw})
    s.hold(0.4)
    s.move(1.0, {"x": wx, "z": wz, "pitch": pitch0})
    s.hold(0.25)

    def swing(u: np.ndarray) -> np.ndarray:
        psi = (-back + (forward + back) * u) * _DEG
        out = np.empty((u.size, 1, 6))
        out[:, 0, 0] = px + radius * np.sin(psi)
        out[:, 0, 1] = y
        out[:, 0, 2] = pivot_z - radius * np.cos(psi)
        out[:, 0, 3] = (pitch0 - flick * u) * _DEG
        out[:, 0, 4] = yaw * _DEG
        out[:, 0, 5] = 0.0
        return out

    s.path(swing_time, swing)
    s.hold(0.4)
    s.move(1.2, {"x": 0.32, "z": pivot_z - radius + 0.06, "pitch": 70.0})
    s.hold(0.5)
    return s


TOSS = Skill(
    "toss", 1, "underhand toss: wind back, swing forward-up on an arc with a wrist flick, return",
    (
        _p("y", 0.0, -0.15, 0.15, "m", "lateral position of the swing plane"),
        _p("pivot_z", 0.34, 0.30, 0.38, "m", "height of the swing circle's centre"),
        _p("radius", 0.21, 0.18, 0.23, "m", "radius of the swing circle"),
        _p("back", 40.0, 30.0, 45.0, "deg", "wind-up angle behind the pivot"),
        _p("forward", 65.0, 55.0, 70.0, "deg", "follow-through angle in front of the pivot"),
        _p("swing_time", 0.7, 0.65, 0.9, "s", "duration of the swing"),
        _p("flick", 55.0, 40.0, 65.0, "deg", "wrist pitch-up during the swing"),
    ),
    _toss,
)


def _scrub(cx, cy, z, amplitude, frequency, direction, drift, scrub_time) -> _Script:
    # Strokes along `direction` in the table plane, the wrist rolling a little with each
    # stroke, while the hand drifts sideways to cover a patch.
    d = direction * _DEG
    yaw = _azimuth(cx, cy)
    s = _Script({"x": cx, "y": cy - drift / 2, "z": z + 0.15, "pitch": 80.0, "yaw": yaw})
    s.hold(0.4)
    s.move(0.9, {"z": z})

    def strokes(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        env = envelope(t, scrub_time, 0.5)
        phase = np.sin(2 * np.pi * frequency * t)
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 0] = env * amplitude * np.cos(d) * phase
        out[:, 0, 1] = env * amplitude * np.sin(d) * phase
        out[:, 0, 2] = env * 0.005 * np.cos(4 * np.pi * frequency * t)  # pressure pulses twice per stroke
        out[:, 0, 5] = env * 8.0 * _DEG * phase
        return out

    s.move(scrub_time, {"y": cy + drift / 2}, wave=strokes)
    s.move(0.9, {"z": z + 0.15})
    s.hold(0.4)
    return s


SCRUB = Skill(
    "scrub", 1, "table scrub: descend, back-and-forth strokes with sideways drift, retract",
    (
        _p("cx", 0.38, 0.32, 0.44, "m", "x of the scrubbed patch"),
        _p("cy", 0.0, -0.15, 0.15, "m", "y of the scrubbed patch"),
        _p("z", 0.07, 0.06, 0.10, "m", "height of the gripper tip while scrubbing"),
        _p("amplitude", 0.06, 0.04, 0.08, "m", "stroke amplitude (half the stroke length)"),
        _p("frequency", 1.2, 0.8, 1.6, "Hz", "strokes per second"),
        _p("direction", 0.0, -30.0, 30.0, "deg", "stroke direction from the x axis"),
        _p("drift", 0.08, -0.12, 0.12, "m", "sideways travel during the scrub"),
        _p("scrub_time", 3.0, 2.5, 4.0, "s", "duration of the scrubbing"),
    ),
    _scrub,
)


def _drawer_open(hx, hy, hz, pull, pull_time, handle_roll, pitch) -> _Script:
    yaw = _azimuth(hx, hy)
    s = _Script({"x": 0.30, "y": hy, "z": hz + 0.08, "pitch": 35.0, "yaw": yaw})
    s.hold(0.4)
    s.move(1.2, {"x": hx - 0.07, "z": hz, "pitch": pitch, "roll": handle_roll})
    s.move(0.7, {"x": hx})
    s.hold(0.5)  # close the gripper on the handle
    s.move(pull_time, {"x": hx - pull})
    s.hold(0.5)  # release
    s.move(0.7, {"x": hx - pull - 0.04, "z": hz + 0.05})
    s.move(1.0, {"x": 0.30, "z": hz + 0.08, "pitch": 35.0, "roll": 0.0})
    s.hold(0.4)
    return s


DRAWER_OPEN = Skill(
    "drawer_open", 1, "open a drawer: approach the handle, grasp, pull straight back, release, retreat",
    (
        _p("hx", 0.46, 0.43, 0.50, "m", "handle x (closed drawer)"),
        _p("hy", 0.0, -0.15, 0.15, "m", "handle y"),
        _p("hz", 0.20, 0.12, 0.30, "m", "handle height"),
        _p("pull", 0.18, 0.12, 0.22, "m", "opening distance"),
        _p("pull_time", 1.5, 1.2, 2.0, "s", "duration of the pull"),
        _p("handle_roll", 0.0, -90.0, 90.0, "deg", "gripper roll matching the handle direction"),
        _p("pitch", 5.0, 0.0, 20.0, "deg", "downward tilt of the gripper at the handle"),
    ),
    _drawer_open,
)


def _screw(sx, sy, sz, turn, drop, turn_time) -> _Script:
    # Ratchet: grip, turn about the approach axis while the thread pulls the hand down,
    # release, turn back lifted a little, repeat.
    yaw = _azimuth(sx, sy)
    s = _Script({"x": sx, "y": sy, "z": sz + 0.10, "pitch": 90.0, "yaw": yaw, "roll": -turn / 2})
    s.hold(0.3)
    s.move(0.8, {"z": sz})
    z = sz

    def lift(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 2] = 0.015 * bump(tau)
        return out

    for _ in range(3):
        s.hold(0.15)  # grip
        z -= drop
        s.move(turn_time, {"z": z, "roll": turn / 2})
        s.hold(0.15)  # release
        s.move(0.65, {"roll": -turn / 2}, wave=lift)
    s.move(0.8, {"z": sz + 0.10, "roll": 0.0})
    s.hold(0.3)
    return s


SCREW = Skill(
    "screw", 1, "screw in: three ratchet turns about the downward approach axis, descending with the thread",
    (
        _p("sx", 0.35, 0.28, 0.42, "m", "screw x"),
        _p("sy", 0.0, -0.15, 0.15, "m", "screw y"),
        _p("sz", 0.12, 0.08, 0.20, "m", "gripper height at the screw head"),
        _p("turn", 80.0, 60.0, 95.0, "deg", "rotation per ratchet turn"),
        _p("drop", 0.004, 0.002, 0.006, "m", "thread advance per turn"),
        _p("turn_time", 0.75, 0.65, 0.9, "s", "duration of one turn"),
    ),
    _screw,
)


def _wipe(wx, wy, wz, radius, period, sweep, wipe_time) -> _Script:
    # Circles on a vertical surface (a whiteboard facing the robot) while sweeping sideways.
    s = _Script({"x": 0.30, "y": wy - sweep / 2, "z": wz, "pitch": 20.0})
    s.hold(0.3)
    s.move(1.0, {"x": wx, "pitch": 0.0})

    def circles(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        env = envelope(t, wipe_time, 0.5)
        w = 2 * np.pi / period
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 1] = env * radius * np.sin(w * t)
        out[:, 0, 2] = env * radius * (1.0 - np.cos(w * t)) - env * radius
        out[:, 0, 5] = env * 10.0 * _DEG * np.sin(w * t)
        return out

    s.move(wipe_time, {"y": wy + sweep / 2}, wave=circles)
    s.move(0.8, {"x": 0.30, "pitch": 20.0})
    s.hold(0.3)
    return s


WIPE = Skill(
    "wipe", 1, "wipe a vertical surface: press in, circular strokes sweeping sideways, pull back",
    (
        _p("wx", 0.44, 0.40, 0.47, "m", "x of the surface (gripper tip)"),
        _p("wy", 0.0, -0.08, 0.08, "m", "y of the wiped patch"),
        _p("wz", 0.28, 0.22, 0.34, "m", "height of the wiped patch"),
        _p("radius", 0.055, 0.04, 0.07, "m", "radius of the wiping circles"),
        _p("period", 1.2, 1.0, 1.6, "s", "time per circle"),
        _p("sweep", 0.18, 0.12, 0.22, "m", "sideways travel while wiping"),
        _p("wipe_time", 3.6, 3.0, 4.5, "s", "duration of the wiping"),
    ),
    _wipe,
)


def _pour(sx, sy, gx, gy, gz, tilt, tilt_time, pour_time) -> _Script:
    # A cup held from the side, gripper level: carry it over the target, roll about the
    # approach axis to pour, roll back, carry it home.
    s = _Script({"x": sx, "y": sy, "z": 0.12, "pitch": 10.0, "yaw": _azimuth(sx, sy)})
    s.hold(0.3)
    s.move(1.4, {"x": gx, "y": gy, "z": gz, "yaw": _azimuth(gx, gy)})
    s.move(tilt_time, {"roll": tilt, "pitch": 20.0, "z": gz - 0.02})
    s.hold(pour_time)
    s.move(tilt_time, {"roll": 0.0, "pitch": 10.0, "z": gz})
    s.move(1.4, {"x": sx, "y": sy, "z": 0.12, "yaw": _azimuth(sx, sy)})
    s.hold(0.3)
    return s


POUR = Skill(
    "pour", 1, "pour: lift a cup, carry it over a target, tilt it about the approach axis, return it",
    (
        _p("sx", 0.33, 0.28, 0.38, "m", "x where the cup stands"),
        _p("sy", -0.15, -0.22, -0.08, "m", "y where the cup stands"),
        _p("gx", 0.42, 0.36, 0.46, "m", "x above the target container"),
        _p("gy", 0.08, 0.0, 0.18, "m", "y above the target container"),
        _p("gz", 0.28, 0.22, 0.34, "m", "height of the pour"),
        _p("tilt", 100.0, 70.0, 115.0, "deg", "roll at full pour"),
        _p("tilt_time", 1.2, 0.9, 1.5, "s", "duration of tilting (and of tilting back)"),
        _p("pour_time", 0.9, 0.5, 1.3, "s", "time held at full tilt"),
    ),
    _pour,
)


def _reach_place(ax, ay, bx, by, bz, lift, turn, transfer_time) -> _Script:
    # Pick with the gripper pointing down, carry along an arc over the table, turn the
    # object about the vertical on the way, set it down.
    az = 0.06
    s = _Script({"x": ax, "y": ay, "z": az + lift, "pitch": 90.0})
    s.hold(0.3)
    s.move(0.8, {"z": az})
    s.hold(0.4)  # grasp

    def carry(u: np.ndarray) -> np.ndarray:
        out = np.zeros((u.size, 1, 6))
        out[:, 0, 0] = ax + (bx - ax) * u
        out[:, 0, 1] = ay + (by - ay) * u
        out[:, 0, 2] = az + (bz - az) * u + 4.0 * lift * u * (1.0 - u)
        out[:, 0, 3] = 90.0 * _DEG
        out[:, 0, 4] = turn * u * _DEG
        return out

    s.path(transfer_time, carry)
    s.hold(0.4)  # release
    s.move(0.8, {"z": bz + lift})
    s.hold(0.3)
    return s


REACH_PLACE = Skill(
    "reach_place", 1, "pick and place: descend, grasp, carry on an arc while turning, place, lift",
    (
        _p("ax", 0.38, 0.30, 0.45, "m", "pick x"),
        _p("ay", 0.15, 0.08, 0.22, "m", "pick y"),
        _p("bx", 0.32, 0.25, 0.42, "m", "place x"),
        _p("by", -0.15, -0.22, -0.08, "m", "place y"),
        _p("bz", 0.10, 0.06, 0.15, "m", "place height"),
        _p("lift", 0.15, 0.10, 0.22, "m", "height of the carrying arc above the pick/place"),
        _p("turn", 30.0, -45.0, 45.0, "deg", "rotation of the object about the vertical"),
        _p("transfer_time", 1.6, 1.3, 2.0, "s", "duration of the carry"),
    ),
    _reach_place,
)


def _bezier(points: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Cubic Bezier through control points (4, D) at parameters u (n,): (n, D).

    A Bezier curve stays in the convex hull of its control points, so control points
    inside the workspace box keep the whole curve inside it.
    """
    u = u[:, None]
    b = np.concatenate([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3], axis=1)
    return b @ points


def _fling_script(y: float, depth: float, height: float, fling_time: float, arms: int, mount_y: float) -> _Script:
    """Cloth fling for one arm or a mirrored pair; `y` is arm 0's lateral position."""
    grab_x = 0.40
    back = {"x": 0.22, "z": height, "pitch": 20.0}
    start = {"x": grab_x, "y": y, "z": 0.08, "pitch": 90.0, "yaw": _azimuth(grab_x, y, mount_y) * 0.5}
    s = _Script(*([start, mirror_pose(start)][:arms]))
    s.hold(0.3)
    s.hold(0.3)  # grasp the corner
    s.move(1.2, *([back, mirror_pose(back)][:arms]))
    # Fling: over the top and forward, then lay the cloth down while pulling back.
    ctrl = np.array([
        [0.22, height, 20.0],
        [0.22 + depth * 0.9, height + 0.02, -10.0],
        [0.22 + depth, 0.22, 40.0],
        [0.42, 0.09, 75.0],
    ])
    yaw0 = s.pose(0)["yaw"]

    def fling(u: np.ndarray) -> np.ndarray:
        c = _bezier(ctrl, u)  # (n, 3): x, z, pitch
        out = np.zeros((u.size, arms, 6))
        out[:, 0, 0] = c[:, 0]
        out[:, 0, 1] = y
        out[:, 0, 2] = c[:, 1]
        out[:, 0, 3] = c[:, 2] * _DEG
        out[:, 0, 4] = yaw0 * _DEG
        if arms == 2:
            out[:, 1] = out[:, 0] * np.array([1, -1, 1, 1, -1, -1])
        return out

    s.path(fling_time, fling)
    s.hold(0.4)  # release
    up = {"x": 0.40, "z": 0.20, "pitch": 80.0}
    s.move(0.8, *([up, mirror_pose(up)][:arms]))
    s.hold(0.4)
    return s


def _fling(y, depth, height, fling_time) -> _Script:
    return _fling_script(y, depth, height, fling_time, 1, 0.0)


FLING = Skill(
    "fling", 1, "cloth fling with one corner: grab low, lift back, fling over and forward, lay down",
    (
        _p("y", 0.0, -0.15, 0.15, "m", "lateral position"),
        _p("depth", 0.30, 0.25, 0.33, "m", "forward reach of the fling from the lifted pose"),
        _p("height", 0.42, 0.36, 0.46, "m", "height of the lifted pose"),
        _p("fling_time", 1.1, 0.95, 1.3, "s", "duration of the fling"),
    ),
    _fling,
)


def _stir(cx, cy, z, radius, period, tilt, stir_time) -> _Script:
    yaw = _azimuth(cx, cy)
    s = _Script({"x": cx, "y": cy, "z": z + 0.12, "pitch": 90.0 - tilt, "yaw": yaw})
    s.hold(0.3)
    s.move(0.8, {"z": z})

    def circles(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        env = envelope(t, stir_time, 0.6)
        w = 2 * np.pi / period
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 0] = env * radius * np.cos(w * t) - env * radius
        out[:, 0, 1] = env * radius * np.sin(w * t)
        # The spoon tilts into the direction of travel.
        out[:, 0, 3] = env * 6.0 * _DEG * np.sin(w * t)
        return out

    s.move(stir_time, wave=circles)
    s.move(0.8, {"z": z + 0.12})
    s.hold(0.3)
    return s


STIR = Skill(
    "stir", 1, "stir a pot: dip a held spoon, circle with the tip, lift out",
    (
        _p("cx", 0.38, 0.32, 0.44, "m", "x where the spoon dips in (the circle's far edge)"),
        _p("cy", 0.0, -0.12, 0.12, "m", "y of the pot centre"),
        _p("z", 0.12, 0.09, 0.16, "m", "gripper height while stirring"),
        _p("radius", 0.05, 0.03, 0.07, "m", "radius of the stirring circle"),
        _p("period", 1.2, 0.9, 1.5, "s", "time per circle"),
        _p("tilt", 15.0, 0.0, 25.0, "deg", "tilt of the spoon from vertical"),
        _p("stir_time", 3.6, 3.0, 4.5, "s", "duration of the stirring"),
    ),
    _stir,
)


def _hammer(nx, ny, nz, raise_height, swing, strike_time) -> _Script:
    # The held hammer points forward; each blow raises the hand while pitching the wrist
    # up, then strikes down, pitching the head into the nail.
    yaw = _azimuth(nx, ny)
    s = _Script({"x": nx - 0.05, "y": ny, "z": nz + 0.10, "pitch": 15.0, "yaw": yaw})
    s.hold(0.3)
    s.move(0.8, {"x": nx, "z": nz})
    for _ in range(4):
        s.move(0.5, {"z": nz + raise_height, "pitch": 15.0 - swing})
        s.hold(0.1)
        s.move(strike_time, {"z": nz, "pitch": 15.0})
        s.hold(0.25)
    s.move(0.8, {"x": nx - 0.05, "z": nz + 0.10})
    s.hold(0.3)
    return s


HAMMER = Skill(
    "hammer", 1, "hammer a nail: four blows, each a raise with the wrist cocked back and a fast strike",
    (
        _p("nx", 0.42, 0.36, 0.48, "m", "x of the hand at impact"),
        _p("ny", 0.0, -0.15, 0.15, "m", "y of the hand at impact"),
        _p("nz", 0.12, 0.08, 0.18, "m", "height of the hand at impact"),
        _p("raise_height", 0.10, 0.07, 0.13, "m", "how far the hand rises before a blow"),
        _p("swing", 30.0, 20.0, 35.0, "deg", "wrist pitch during the raise"),
        _p("strike_time", 0.35, 0.30, 0.45, "s", "duration of a strike"),
    ),
    _hammer,
)


# ---- bimanual


def _bi_fling(y, depth, height, fling_time) -> _Script:
    return _fling_script(y, depth, height, fling_time, 2, BIMANUAL_MOUNT_Y)


BI_FLING = Skill(
    "bi_fling", 2, "two-arm cloth fling: grab two corners, lift back, fling over and forward, lay down",
    (
        _p("y", 0.20, 0.15, 0.25, "m", "half the distance between the held corners"),
        _p("depth", 0.24, 0.20, 0.26, "m", "forward reach of the fling from the lifted pose"),
        _p("height", 0.40, 0.35, 0.44, "m", "height of the lifted pose"),
        _p("fling_time", 1.1, 0.95, 1.3, "s", "duration of the fling"),
    ),
    _bi_fling,
)


def _bi_lift(cx, cy, half_width, lift, carry, hold_time) -> _Script:
    # Grippers point at each other and squeeze a box from its sides.
    z = 0.10
    a0 = {"x": cx, "y": cy + half_width + 0.08, "z": z, "pitch": 20.0, "yaw": -90.0}
    a1 = mirror_pose(a0) | {"y": cy - half_width - 0.08}
    s = _Script(a0, a1)
    s.hold(0.3)
    s.move(0.8, {"y": cy + half_width}, {"y": cy - half_width})
    s.hold(0.4)
    s.move(1.3, {"z": z + lift, "x": cx + carry}, {"z": z + lift, "x": cx + carry})
    s.hold(hold_time)
    s.move(1.3, {"z": z, "x": cx}, {"z": z, "x": cx})
    s.hold(0.4)
    s.move(0.8, {"y": cy + half_width + 0.08}, {"y": cy - half_width - 0.08})
    s.hold(0.3)
    return s


BI_LIFT = Skill(
    "bi_lift", 2, "two-arm box lift: squeeze a box from both sides, lift and carry it, set it down",
    (
        _p("cx", 0.34, 0.30, 0.38, "m", "box x"),
        _p("cy", 0.0, -0.04, 0.04, "m", "box y"),
        _p("half_width", 0.12, 0.08, 0.15, "m", "half the box width"),
        _p("lift", 0.18, 0.12, 0.24, "m", "lift height"),
        _p("carry", 0.0, -0.08, 0.08, "m", "forward carry while lifted"),
        _p("hold_time", 0.6, 0.3, 1.0, "s", "time held up"),
    ),
    _bi_lift,
)


def _bi_handover(px, py, hx, hz, gap, qx, qy) -> _Script:
    # Arm 0 picks an object on its side and presents it sideways at the middle; arm 1 takes
    # it there and places it on its own side. Asymmetric, so the arms are scripted apart.
    a0 = {"x": px, "y": py, "z": 0.16, "pitch": 90.0}
    a1 = {"x": 0.30, "y": -0.25, "z": 0.25, "pitch": 60.0, "yaw": 30.0}
    s = _Script(a0, a1)
    s.hold(0.3)
    s.move(0.8, {"z": 0.06}, None)
    s.hold(0.4)  # arm 0 grasps
    # Arm 1 sets off towards the handover while arm 0 is still on its way.
    s.move(1.6, {"x": hx, "y": gap / 2, "z": hz, "pitch": 30.0, "yaw": -90.0},
           {"x": hx, "y": -gap / 2 - 0.06, "z": hz, "pitch": 30.0, "yaw": 90.0})
    s.move(0.6, None, {"y": -gap / 2})
    s.hold(0.4)  # arm 1 grasps, arm 0 lets go
    s.move(1.0, {"x": 0.30, "y": 0.25, "z": 0.25, "pitch": 60.0, "yaw": -30.0}, {"y": -gap / 2 - 0.06})
    s.move(1.4, None, {"x": qx, "y": qy, "z": 0.07, "pitch": 90.0, "yaw": 0.0})
    s.hold(0.4)  # arm 1 places
    s.move(0.6, None, {"z": 0.16})
    s.hold(0.3)
    return s


BI_HANDOVER = Skill(
    "bi_handover", 2, "handover: arm 0 picks and presents an object at the middle, arm 1 takes and places it",
    (
        _p("px", 0.35, 0.30, 0.42, "m", "pick x (arm 0's side)"),
        _p("py", 0.22, 0.15, 0.28, "m", "pick y"),
        _p("hx", 0.36, 0.32, 0.42, "m", "handover x"),
        _p("hz", 0.28, 0.22, 0.34, "m", "handover height"),
        _p("gap", 0.08, 0.06, 0.12, "m", "distance between the grippers at the handover"),
        _p("qx", 0.35, 0.30, 0.42, "m", "place x (arm 1's side)"),
        _p("qy", -0.22, -0.28, -0.15, "m", "place y"),
    ),
    _bi_handover,
)


def _bi_fold(fx, width, length, height, fold_time) -> _Script:
    # Fold a cloth in half towards the robot: grab the far corners, carry them up and over
    # on a Bezier arc, lay them on the near edge.
    z0 = 0.06
    a0 = {"x": fx, "y": width, "z": z0 + 0.10, "pitch": 90.0}
    s = _Script(a0, mirror_pose(a0))
    s.hold(0.3)
    s.move(0.8, {"z": z0}, {"z": z0})
    s.hold(0.4)
    ctrl = np.array([
        [fx, z0, 90.0],
        [fx, z0 + height, 80.0],
        [fx - length, z0 + height, 55.0],
        [fx - length, z0 + 0.01, 60.0],
    ])

    def fold(u: np.ndarray) -> np.ndarray:
        c = _bezier(ctrl, u)
        out = np.zeros((u.size, 2, 6))
        out[:, 0, 0] = c[:, 0]
        out[:, 0, 1] = width
        out[:, 0, 2] = c[:, 1]
        out[:, 0, 3] = c[:, 2] * _DEG
        out[:, 1] = out[:, 0] * np.array([1, -1, 1, 1, -1, -1])
        return out

    s.path(fold_time, fold)
    s.hold(0.4)
    up = {"z": z0 + 0.12, "pitch": 80.0}
    s.move(0.8, up, up)
    s.hold(0.3)
    return s


BI_FOLD = Skill(
    "bi_fold", 2, "two-arm cloth fold: grab the far corners, carry them over on an arc, lay them on the near edge",
    (
        _p("fx", 0.45, 0.42, 0.48, "m", "x of the far corners"),
        _p("width", 0.15, 0.10, 0.22, "m", "half the cloth width (y of arm 0)"),
        _p("length", 0.22, 0.18, 0.25, "m", "fold length towards the robot"),
        _p("height", 0.22, 0.16, 0.28, "m", "height of the fold arc's control points"),
        _p("fold_time", 2.0, 1.6, 2.5, "s", "duration of the fold"),
    ),
    _bi_fold,
)


def _bi_jar(jx, jz, turn, turn_time, hold_pitch) -> _Script:
    # Arm 1 holds a jar from its side; arm 0 grips the lid from above and unscrews it with
    # ratchet turns, then lifts it off and sets it aside.
    jy = 0.03  # jar axis, on arm 0's side so the lid stays in its half
    lid_z = jz + 0.07
    a0 = {"x": jx, "y": jy, "z": lid_z + 0.08, "pitch": 90.0, "roll": turn / 2}
    a1 = {"x": jx, "y": jy - 0.14, "z": jz, "pitch": hold_pitch, "yaw": 90.0}
    s = _Script(a0, a1)
    s.hold(0.3)
    s.move(0.8, {"z": lid_z}, {"y": jy - 0.05})
    s.hold(0.3)

    def lift(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        out = np.zeros((t.size, 2, 6))
        out[:, 0, 2] = 0.012 * bump(tau)
        return out

    for _ in range(2):
        s.hold(0.15)
        s.move(turn_time, {"roll": -turn / 2}, None)
        s.hold(0.15)
        s.move(0.65, {"roll": turn / 2}, None, wave=lift)
    s.move(0.8, {"z": lid_z + 0.06, "roll": 0.0}, None)
    s.move(1.0, {"x": jx - 0.05, "y": 0.22, "z": lid_z}, {"y": jy - 0.14})
    s.hold(0.3)
    return s


BI_JAR = Skill(
    "bi_jar", 2, "open a jar: arm 1 holds the jar, arm 0 unscrews the lid with two ratchet turns and sets it aside",
    (
        _p("jx", 0.33, 0.30, 0.37, "m", "jar x"),
        _p("jz", 0.13, 0.10, 0.16, "m", "height where arm 1 holds the jar"),
        _p("turn", 80.0, 60.0, 95.0, "deg", "rotation per ratchet turn"),
        _p("turn_time", 0.75, 0.65, 0.9, "s", "duration of one turn"),
        _p("hold_pitch", 15.0, 0.0, 30.0, "deg", "downward tilt of the holding gripper"),
    ),
    _bi_jar,
)


#: Every skill by name, single-arm first.
SKILLS: dict[str, Skill] = {
    s.name: s
    for s in (
        TOSS, SCRUB, DRAWER_OPEN, SCREW, WIPE, POUR, REACH_PLACE, FLING, STIR, HAMMER,
        BI_FLING, BI_LIFT, BI_HANDOVER, BI_FOLD, BI_JAR,
    )
}


# ------------------------------------------------------------------ public skill functions


def toss(seed: int = 0, **params: float) -> Motion:
    """Underhand toss (parameters: `TOSS.params`)."""
    return TOSS.motion(seed, **params)


def scrub(seed: int = 0, **params: float) -> Motion:
    """Table scrub (parameters: `SCRUB.params`)."""
    return SCRUB.motion(seed, **params)


def drawer_open(seed: int = 0, **params: float) -> Motion:
    """Open a drawer (parameters: `DRAWER_OPEN.params`)."""
    return DRAWER_OPEN.motion(seed, **params)


def screw(seed: int = 0, **params: float) -> Motion:
    """Ratchet screwing about the approach axis (parameters: `SCREW.params`)."""
    return SCREW.motion(seed, **params)


def wipe(seed: int = 0, **params: float) -> Motion:
    """Wipe a vertical surface (parameters: `WIPE.params`)."""
    return WIPE.motion(seed, **params)


def pour(seed: int = 0, **params: float) -> Motion:
    """Pour from a held cup (parameters: `POUR.params`)."""
    return POUR.motion(seed, **params)


def reach_place(seed: int = 0, **params: float) -> Motion:
    """Pick and place (parameters: `REACH_PLACE.params`)."""
    return REACH_PLACE.motion(seed, **params)


def fling(seed: int = 0, **params: float) -> Motion:
    """One-arm cloth fling (parameters: `FLING.params`)."""
    return FLING.motion(seed, **params)


def stir(seed: int = 0, **params: float) -> Motion:
    """Stir a pot (parameters: `STIR.params`)."""
    return STIR.motion(seed, **params)


def hammer(seed: int = 0, **params: float) -> Motion:
    """Hammer a nail (parameters: `HAMMER.params`)."""
    return HAMMER.motion(seed, **params)


def bi_fling(seed: int = 0, **params: float) -> Motion:
    """Two-arm cloth fling (parameters: `BI_FLING.params`)."""
    return BI_FLING.motion(seed, **params)


def bi_lift(seed: int = 0, **params: float) -> Motion:
    """Two-arm box lift (parameters: `BI_LIFT.params`)."""
    return BI_LIFT.motion(seed, **params)


def bi_handover(seed: int = 0, **params: float) -> Motion:
    """Handover between the arms (parameters: `BI_HANDOVER.params`)."""
    return BI_HANDOVER.motion(seed, **params)


def bi_fold(seed: int = 0, **params: float) -> Motion:
    """Two-arm cloth fold (parameters: `BI_FOLD.params`)."""
    return BI_FOLD.motion(seed, **params)


def bi_jar(seed: int = 0, **params: float) -> Motion:
    """Open a jar with two arms (parameters: `BI_JAR.params`)."""
    return BI_JAR.motion(seed, **params)


# ------------------------------------------------------------------ registry and splits

#: Seeds of the training variants of every skill (seed 0 is the canonical motion).
TRAIN_SEEDS: tuple[int, ...] = tuple(range(10))
#: Seeds of the validation variants of every skill; disjoint from `TRAIN_SEEDS`.
VAL_SEEDS: tuple[int, ...] = (100, 101, 102)
SPLITS: dict[str, tuple[int, ...]] = {"train": TRAIN_SEEDS, "val": VAL_SEEDS}


def split_of(seed: int) -> str:
    """``"train"``, ``"val"`` or ``"extra"`` (a seed in neither split)."""
    for split, seeds in SPLITS.items():
        if seed in seeds:
            return split
    return "extra"


def _seed_ranges(seeds: tuple[int, ...]) -> str:
    return f"{seeds[0]}-{seeds[-1]}" if seeds == tuple(range(seeds[0], seeds[-1] + 1)) else ",".join(map(str, seeds))


@dataclass(frozen=True)
class MotionInfo:
    """One row of `list_motions`: a skill, its canonical motion's size, and its split seeds."""

    name: str
    arms: int
    duration: float
    steps: int
    params: tuple[str, ...]
    train_seeds: tuple[int, ...]
    val_seeds: tuple[int, ...]
    summary: str

    def row(self) -> dict[str, str | int | float]:
        """Flat, printable columns: name, arms, duration_s, steps, train, val, params, summary."""
        return {
            "name": self.name,
            "arms": self.arms,
            "duration_s": round(self.duration, 2),
            "steps": self.steps,
            "train": f"seeds {_seed_ranges(self.train_seeds)}",
            "val": f"seeds {_seed_ranges(self.val_seeds)}",
            "params": ", ".join(self.params),
            "summary": self.summary,
        }


def list_motions(arms: int | None = None) -> list[MotionInfo]:
    """Every library skill (or those with `arms` end effectors), single-arm first."""
    if arms not in (None, 1, 2):
        raise MotionError(f"arms must be 1, 2 or None, got {arms!r}")
    out = []
    for sk in SKILLS.values():
        if arms is not None and sk.arms != arms:
            continue
        m = sk.motion(0)
        out.append(MotionInfo(sk.name, sk.arms, m.duration, m.steps, tuple(p.name for p in sk.params),
                              TRAIN_SEEDS, VAL_SEEDS, sk.summary))
    return out


def get_motion(name: str, seed: int | None = None) -> Motion:
    """The library motion `name` with `seed` (default 0, the canonical one).

    `name` may carry its seed as ``"toss:7"``; raises `MotionError` listing the valid
    names for an unknown one. The motion's ``meta`` holds skill, seed, split and params.
    """
    skill, sep, tail = str(name).partition(":")
    if sep:
        try:
            named_seed = int(tail)
        except ValueError:
            raise MotionError(f"motion {name!r}: the part after ':' must be an integer seed") from None
        if seed is not None and seed != named_seed:
            raise MotionError(f"motion {name!r} names seed {named_seed} but seed={seed} was passed")
        seed = named_seed
    if skill not in SKILLS:
        raise MotionError(f"unknown motion {skill!r}; valid: {', '.join(SKILLS)}")
    return SKILLS[skill].motion(0 if seed is None else seed)


def motion_set(split: str, arms: int | None = None) -> list[Motion]:
    """All motions of a split: every skill (with `arms` end effectors, or all) at every split seed.

    train: seeds `TRAIN_SEEDS` of every skill; val: seeds `VAL_SEEDS`. Ordered by skill
    (as in `SKILLS`), then seed; the same call always returns the same motions.
    """
    if split not in SPLITS:
        raise MotionError(f"unknown split {split!r}; valid: {list(SPLITS)}")
    if arms not in (None, 1, 2):
        raise MotionError(f"arms must be 1, 2 or None, got {arms!r}")
    return [get_motion(sk.name, seed) for sk in SKILLS.values() if arms in (None, sk.arms) for seed in SPLITS[split]]
