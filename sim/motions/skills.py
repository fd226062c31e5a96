"""The skill library: 10 single-arm and 5 bimanual procedural manipulation skills, and
their seeds' train / validation split.

Every skill is a short `tt.sim.motions.script.Script` of phases sized for the workspaces
of `tt.sim.motions.workspace`; a `Skill` holds its script and its continuous parameters.

Seeds. A skill has a few continuous parameters, each with a nominal value and a range.
Seed 0 is the canonical motion (all nominal); any other seed draws every parameter not
given explicitly uniformly from its range with a generator seeded by (skill, seed), so a
(skill, seed) pair always yields the same motion. `TRAIN_SEEDS` and `VAL_SEEDS` split the
seeds; the registry by name is `tt.sim.motions.registry`.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from tt.sim.motions.base import MOTION_DT, Motion, MotionError
from tt.sim.motions.io import place_at_base
from tt.sim.motions.script import DEG, Script, azimuth, bezier, bump, envelope, mirror_pose
from tt.sim.motions.workspace import BIMANUAL_MOUNT_Y

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
    script: Callable[..., Script]

    def draw(self, seed: int) -> dict[str, float]:
        """Parameter values for `seed`: nominal for 0, else uniform in each range."""
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise MotionError(f"seed must be an integer >= 0, got {seed!r}")
        if seed == 0:
            return {p.name: p.nominal for p in self.params}
        rng = np.random.default_rng([zlib.crc32(self.name.encode()), int(seed)])
        return {p.name: float(rng.uniform(p.low, p.high)) for p in self.params}

    def motion(self, seed: int = 0, *, placed: bool = True, **overrides: float) -> Motion:
        """The motion for `seed`, with any parameters in `overrides` fixed to the given values.

        Skills are written in front of the nominal arm (`tt.sim.motions.workspace`); the
        library motion is then placed to start over the robot's base (`place_at_base`),
        as the paper places its demonstrations. placed=False returns the script's own frame.
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
        motion = Motion(name, pos, quat, MOTION_DT, meta=meta)
        return place_at_base(motion) if placed else motion


def _p(name: str, nominal: float, low: float, high: float, unit: str, doc: str) -> SkillParam:
    return SkillParam(name, nominal, low, high, unit, doc)


# ---- single arm


def _toss(y, pivot_z, radius, back, forward, swing_time, flick) -> Script:
    # Underhand swing: the hand moves on a circle below a pivot, like an arm swinging from
    # the shoulder; min-jerk timing puts the peak speed (the release) mid-swing, where the
    # velocity points forward and up by (forward - back) / 2.
    px = 0.32
    yaw = azimuth(px, y)
    pitch0 = 80.0

    def arc(psi_deg: float) -> tuple[float, float]:
        psi = psi_deg * DEG
        return px + radius * np.sin(psi), pivot_z - radius * np.cos(psi)

    wx, wz = arc(-back)
    s = Script({"x": 0.32, "y": y, "z": pivot_z - radius + 0.06, "pitch": 70.0, "yaw": yaw})
    s.hold(0.4)
    s.move(1.0, {"x": wx, "z": wz, "pitch": pitch0})
    s.hold(0.25)

    def swing(u: np.ndarray) -> np.ndarray:
        psi = (-back + (forward + back) * u) * DEG
        out = np.empty((u.size, 1, 6))
        out[:, 0, 0] = px + radius * np.sin(psi)
        out[:, 0, 1] = y
        out[:, 0, 2] = pivot_z - radius * np.cos(psi)
        out[:, 0, 3] = (pitch0 - flick * u) * DEG
        out[:, 0, 4] = yaw * DEG
        out[:, 0, 5] = 0.0
        return out

    s.path(swing_time, swing)
    s.hold(0.4)
    s.move(1.2, {"x": 0.32, "z": pivot_z - radius + 0.06, "pitch": 70.0})
    s.hold(0.5)
    return s


TOSS = Skill(
    "toss",
    1,
    "underhand toss: wind back, swing forward-up on an arc with a wrist flick, return",
    (
        _p("y", 0.0, -0.15, 0.15, "m", "lateral position of the swing plane"),
        _p("pivot_z", 0.34, 0.30, 0.38, "m", "height of the swing circle's centre"),
        _p("radius", 0.23, 0.21, 0.25, "m", "radius of the swing circle"),
        _p("back", 38.0, 30.0, 40.0, "deg", "wind-up angle behind the pivot"),
        _p("forward", 62.0, 55.0, 65.0, "deg", "follow-through angle in front of the pivot"),
        # A person's underhand toss releases at 2-3 m/s; min-jerk timing peaks at 1.875x
        # the mean speed, so a 0.40 m arc in 0.30 s peaks at 2.5 m/s.
        _p("swing_time", 0.30, 0.28, 0.37, "s", "duration of the swing"),
        _p("flick", 55.0, 40.0, 65.0, "deg", "wrist pitch-up during the swing"),
    ),
    _toss,
)


def _scrub(cx, cy, z, amplitude, frequency, direction, drift, scrub_time) -> Script:
    # Strokes along `direction` in the table plane, the wrist rolling a little with each
    # stroke, while the hand drifts sideways to cover a patch.
    d = direction * DEG
    yaw = azimuth(cx, cy)
    s = Script({"x": cx, "y": cy - drift / 2, "z": z + 0.15, "pitch": 80.0, "yaw": yaw})
    s.hold(0.4)
    s.move(0.9, {"z": z})

    def strokes(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        env = envelope(t, scrub_time, 0.5)
        phase = np.sin(2 * np.pi * frequency * t)
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 0] = env * amplitude * np.cos(d) * phase
        out[:, 0, 1] = env * amplitude * np.sin(d) * phase
        out[:, 0, 2] = env * 0.005 * np.cos(4 * np.pi * frequency * t)  # pressure pulses twice per stroke
        out[:, 0, 5] = env * 8.0 * DEG * phase
        return out

    s.move(scrub_time, {"y": cy + drift / 2}, wave=strokes)
    s.move(0.9, {"z": z + 0.15})
    s.hold(0.4)
    return s


SCRUB = Skill(
    "scrub",
    1,
    "table scrub: descend, back-and-forth strokes with sideways drift, retract",
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


def _drawer_open(hx, hy, hz, pull, pull_time, handle_roll, pitch) -> Script:
    yaw = azimuth(hx, hy)
    s = Script({"x": 0.30, "y": hy, "z": hz + 0.08, "pitch": 35.0, "yaw": yaw})
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
    "drawer_open",
    1,
    "open a drawer: approach the handle, grasp, pull straight back, release, retreat",
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


def _screw(sx, sy, sz, turn, drop, turn_time) -> Script:
    # Ratchet: grip, turn about the approach axis while the thread pulls the hand down,
    # release, turn back lifted a little, repeat.
    yaw = azimuth(sx, sy)
    s = Script({"x": sx, "y": sy, "z": sz + 0.10, "pitch": 90.0, "yaw": yaw, "roll": -turn / 2})
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
    "screw",
    1,
    "screw in: three ratchet turns about the downward approach axis, descending with the thread",
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


def _wipe(wx, wy, wz, radius, period, sweep, wipe_time) -> Script:
    # Circles on a vertical surface (a whiteboard facing the robot) while sweeping sideways.
    s = Script({"x": 0.30, "y": wy - sweep / 2, "z": wz, "pitch": 20.0})
    s.hold(0.3)
    s.move(1.0, {"x": wx, "pitch": 0.0})

    def circles(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        env = envelope(t, wipe_time, 0.5)
        w = 2 * np.pi / period
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 1] = env * radius * np.sin(w * t)
        out[:, 0, 2] = env * radius * (1.0 - np.cos(w * t)) - env * radius
        out[:, 0, 5] = env * 10.0 * DEG * np.sin(w * t)
        return out

    s.move(wipe_time, {"y": wy + sweep / 2}, wave=circles)
    s.move(0.8, {"x": 0.30, "pitch": 20.0})
    s.hold(0.3)
    return s


WIPE = Skill(
    "wipe",
    1,
    "wipe a vertical surface: press in, circular strokes sweeping sideways, pull back",
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


def _pour(sx, sy, gx, gy, gz, tilt, tilt_time, pour_time) -> Script:
    # A cup held from the side, gripper level: carry it over the target, roll about the
    # approach axis to pour, roll back, carry it home.
    s = Script({"x": sx, "y": sy, "z": 0.12, "pitch": 10.0, "yaw": azimuth(sx, sy)})
    s.hold(0.3)
    s.move(1.4, {"x": gx, "y": gy, "z": gz, "yaw": azimuth(gx, gy)})
    s.move(tilt_time, {"roll": tilt, "pitch": 20.0, "z": gz - 0.02})
    s.hold(pour_time)
    s.move(tilt_time, {"roll": 0.0, "pitch": 10.0, "z": gz})
    s.move(1.4, {"x": sx, "y": sy, "z": 0.12, "yaw": azimuth(sx, sy)})
    s.hold(0.3)
    return s


POUR = Skill(
    "pour",
    1,
    "pour: lift a cup, carry it over a target, tilt it about the approach axis, return it",
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


def _reach_place(ax, ay, bx, by, bz, lift, turn, transfer_time) -> Script:
    # Pick with the gripper pointing down, carry along an arc over the table, turn the
    # object about the vertical on the way, set it down.
    az = 0.06
    s = Script({"x": ax, "y": ay, "z": az + lift, "pitch": 90.0})
    s.hold(0.3)
    s.move(0.8, {"z": az})
    s.hold(0.4)  # grasp

    def carry(u: np.ndarray) -> np.ndarray:
        out = np.zeros((u.size, 1, 6))
        out[:, 0, 0] = ax + (bx - ax) * u
        out[:, 0, 1] = ay + (by - ay) * u
        out[:, 0, 2] = az + (bz - az) * u + 4.0 * lift * u * (1.0 - u)
        out[:, 0, 3] = 90.0 * DEG
        out[:, 0, 4] = turn * u * DEG
        return out

    s.path(transfer_time, carry)
    s.hold(0.4)  # release
    s.move(0.8, {"z": bz + lift})
    s.hold(0.3)
    return s


REACH_PLACE = Skill(
    "reach_place",
    1,
    "pick and place: descend, grasp, carry on an arc while turning, place, lift",
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


def _fling_script(y: float, depth: float, height: float, fling_time: float, arms: int, mount_y: float) -> Script:
    """Cloth fling for one arm or a mirrored pair; `y` is arm 0's lateral position."""
    grab_x = 0.40
    back = {"x": 0.22, "z": height, "pitch": 20.0}
    start = {"x": grab_x, "y": y, "z": 0.08, "pitch": 90.0, "yaw": azimuth(grab_x, y, mount_y) * 0.5}
    s = Script(*([start, mirror_pose(start)][:arms]))
    s.hold(0.3)
    s.hold(0.3)  # grasp the corner
    s.move(1.2, *([back, mirror_pose(back)][:arms]))
    # Fling: over the top and forward, then lay the cloth down while pulling back.
    ctrl = np.array(
        [
            [0.22, height, 20.0],
            [0.22 + depth * 0.9, height + 0.02, -10.0],
            [0.22 + depth, 0.22, 40.0],
            [0.42, 0.09, 75.0],
        ]
    )
    yaw0 = s.pose(0)["yaw"]

    def fling(u: np.ndarray) -> np.ndarray:
        c = bezier(ctrl, u)  # (n, 3): x, z, pitch
        out = np.zeros((u.size, arms, 6))
        out[:, 0, 0] = c[:, 0]
        out[:, 0, 1] = y
        out[:, 0, 2] = c[:, 1]
        out[:, 0, 3] = c[:, 2] * DEG
        out[:, 0, 4] = yaw0 * DEG
        if arms == 2:
            out[:, 1] = out[:, 0] * np.array([1, -1, 1, 1, -1, -1])
        return out

    s.path(fling_time, fling)
    s.hold(0.4)  # release
    up = {"x": 0.40, "z": 0.20, "pitch": 80.0}
    s.move(0.8, *([up, mirror_pose(up)][:arms]))
    s.hold(0.4)
    return s


def _fling(y, depth, height, fling_time) -> Script:
    return _fling_script(y, depth, height, fling_time, 1, 0.0)


FLING = Skill(
    "fling",
    1,
    "cloth fling with one corner: grab low, lift back, fling over and forward, lay down",
    (
        _p("y", 0.0, -0.15, 0.15, "m", "lateral position"),
        _p("depth", 0.30, 0.25, 0.33, "m", "forward reach of the fling from the lifted pose"),
        _p("height", 0.42, 0.36, 0.46, "m", "height of the lifted pose"),
        # Human cloth flings peak at 2-3 m/s (see `tt motions --stats`).
        _p("fling_time", 0.34, 0.30, 0.40, "s", "duration of the fling"),
    ),
    _fling,
)


def _stir(cx, cy, z, radius, period, tilt, stir_time) -> Script:
    yaw = azimuth(cx, cy)
    s = Script({"x": cx, "y": cy, "z": z + 0.12, "pitch": 90.0 - tilt, "yaw": yaw})
    s.hold(0.3)
    s.move(0.8, {"z": z})

    def circles(t: np.ndarray, tau: np.ndarray) -> np.ndarray:
        env = envelope(t, stir_time, 0.6)
        w = 2 * np.pi / period
        out = np.zeros((t.size, 1, 6))
        out[:, 0, 0] = env * radius * np.cos(w * t) - env * radius
        out[:, 0, 1] = env * radius * np.sin(w * t)
        # The spoon tilts into the direction of travel.
        out[:, 0, 3] = env * 6.0 * DEG * np.sin(w * t)
        return out

    s.move(stir_time, wave=circles)
    s.move(0.8, {"z": z + 0.12})
    s.hold(0.3)
    return s


STIR = Skill(
    "stir",
    1,
    "stir a pot: dip a held spoon, circle with the tip, lift out",
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


def _hammer(nx, ny, nz, raise_height, swing, strike_time) -> Script:
    # The held hammer points forward; each blow raises the hand while pitching the wrist
    # up, then strikes down, pitching the head into the nail.
    yaw = azimuth(nx, ny)
    s = Script({"x": nx - 0.05, "y": ny, "z": nz + 0.10, "pitch": 15.0, "yaw": yaw})
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
    "hammer",
    1,
    "hammer a nail: four blows, each a raise with the wrist cocked back and a fast strike",
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


def _bi_fling(y, depth, height, fling_time) -> Script:
    return _fling_script(y, depth, height, fling_time, 2, BIMANUAL_MOUNT_Y)


BI_FLING = Skill(
    "bi_fling",
    2,
    "two-arm cloth fling: grab two corners, lift back, fling over and forward, lay down",
    (
        _p("y", 0.20, 0.15, 0.25, "m", "half the distance between the held corners"),
        _p("depth", 0.24, 0.20, 0.26, "m", "forward reach of the fling from the lifted pose"),
        _p("height", 0.40, 0.35, 0.44, "m", "height of the lifted pose"),
        _p(
            "fling_time",
            0.38,
            0.33,
            0.45,
            "s",
            "duration of the fling (two arms with a cloth between them: a little slower)",
        ),
    ),
    _bi_fling,
)


def _bi_lift(cx, cy, half_width, lift, carry, hold_time) -> Script:
    # Grippers point at each other and squeeze a box from its sides.
    z = 0.10
    a0 = {"x": cx, "y": cy + half_width + 0.08, "z": z, "pitch": 20.0, "yaw": -90.0}
    a1 = mirror_pose(a0) | {"y": cy - half_width - 0.08}
    s = Script(a0, a1)
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
    "bi_lift",
    2,
    "two-arm box lift: squeeze a box from both sides, lift and carry it, set it down",
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


def _bi_handover(px, py, hx, hz, gap, qx, qy) -> Script:
    # Arm 0 picks an object on its side and presents it sideways at the middle; arm 1 takes
    # it there and places it on its own side. Asymmetric, so the arms are scripted apart.
    a0 = {"x": px, "y": py, "z": 0.16, "pitch": 90.0}
    a1 = {"x": 0.30, "y": -0.25, "z": 0.25, "pitch": 60.0, "yaw": 30.0}
    s = Script(a0, a1)
    s.hold(0.3)
    s.move(0.8, {"z": 0.06}, None)
    s.hold(0.4)  # arm 0 grasps
    # Arm 1 sets off towards the handover while arm 0 is still on its way.
    s.move(
        1.6,
        {"x": hx, "y": gap / 2, "z": hz, "pitch": 30.0, "yaw": -90.0},
        {"x": hx, "y": -gap / 2 - 0.06, "z": hz, "pitch": 30.0, "yaw": 90.0},
    )
    s.move(0.6, None, {"y": -gap / 2})
    s.hold(0.4)  # arm 1 grasps, arm 0 lets go
    s.move(1.0, {"x": 0.30, "y": 0.25, "z": 0.25, "pitch": 60.0, "yaw": -30.0}, {"y": -gap / 2 - 0.06})
    s.move(1.4, None, {"x": qx, "y": qy, "z": 0.07, "pitch": 90.0, "yaw": 0.0})
    s.hold(0.4)  # arm 1 places
    s.move(0.6, None, {"z": 0.16})
    s.hold(0.3)
    return s


BI_HANDOVER = Skill(
    "bi_handover",
    2,
    "handover: arm 0 picks and presents an object at the middle, arm 1 takes and places it",
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


def _bi_fold(fx, width, length, height, fold_time) -> Script:
    # Fold a cloth in half towards the robot: grab the far corners, carry them up and over
    # on a Bezier arc, lay them on the near edge.
    z0 = 0.06
    a0 = {"x": fx, "y": width, "z": z0 + 0.10, "pitch": 90.0}
    s = Script(a0, mirror_pose(a0))
    s.hold(0.3)
    s.move(0.8, {"z": z0}, {"z": z0})
    s.hold(0.4)
    ctrl = np.array(
        [
            [fx, z0, 90.0],
            [fx, z0 + height, 80.0],
            [fx - length, z0 + height, 55.0],
            [fx - length, z0 + 0.01, 60.0],
        ]
    )

    def fold(u: np.ndarray) -> np.ndarray:
        c = bezier(ctrl, u)
        out = np.zeros((u.size, 2, 6))
        out[:, 0, 0] = c[:, 0]
        out[:, 0, 1] = width
        out[:, 0, 2] = c[:, 1]
        out[:, 0, 3] = c[:, 2] * DEG
        out[:, 1] = out[:, 0] * np.array([1, -1, 1, 1, -1, -1])
        return out

    s.path(fold_time, fold)
    s.hold(0.4)
    up = {"z": z0 + 0.12, "pitch": 80.0}
    s.move(0.8, up, up)
    s.hold(0.3)
    return s


BI_FOLD = Skill(
    "bi_fold",
    2,
    "two-arm cloth fold: grab the far corners, carry them over on an arc, lay them on the near edge",
    (
        _p("fx", 0.45, 0.42, 0.48, "m", "x of the far corners"),
        _p("width", 0.15, 0.10, 0.22, "m", "half the cloth width (y of arm 0)"),
        _p("length", 0.22, 0.18, 0.25, "m", "fold length towards the robot"),
        _p("height", 0.22, 0.16, 0.28, "m", "height of the fold arc's control points"),
        _p("fold_time", 2.0, 1.6, 2.5, "s", "duration of the fold"),
    ),
    _bi_fold,
)


def _bi_jar(jx, jz, turn, turn_time, hold_pitch) -> Script:
    # Arm 1 holds a jar from its side; arm 0 grips the lid from above and unscrews it with
    # ratchet turns, then lifts it off and sets it aside.
    jy = 0.03  # jar axis, on arm 0's side so the lid stays in its half
    lid_z = jz + 0.07
    a0 = {"x": jx, "y": jy, "z": lid_z + 0.08, "pitch": 90.0, "roll": turn / 2}
    a1 = {"x": jx, "y": jy - 0.14, "z": jz, "pitch": hold_pitch, "yaw": 90.0}
    s = Script(a0, a1)
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
    "bi_jar",
    2,
    "open a jar: arm 1 holds the jar, arm 0 unscrews the lid with two ratchet turns and sets it aside",
    (
        _p("jx", 0.33, 0.30, 0.37, "m", "jar x"),
        _p("jz", 0.13, 0.10, 0.16, "m", "height where arm 1 holds the jar"),
        _p("turn", 80.0, 60.0, 95.0, "deg", "rotation per ratchet turn"),
        _p("turn_time", 0.75, 0.65, 0.9, "s", "duration of one turn"),
        _p("hold_pitch", 15.0, 0.0, 30.0, "deg", "downward tilt of the holding gripper"),
    ),
    _bi_jar,
)


__all__ = [
    "BI_FLING",
    "BI_FOLD",
    "BI_HANDOVER",
    "BI_JAR",
    "BI_LIFT",
    "DRAWER_OPEN",
    "FLING",
    "HAMMER",
    "POUR",
    "REACH_PLACE",
    "SCREW",
    "SCRUB",
    "SPLITS",
    "STIR",
    "TOSS",
    "TRAIN_SEEDS",
    "VAL_SEEDS",
    "WIPE",
    "Skill",
    "SkillParam",
    "split_of",
]
