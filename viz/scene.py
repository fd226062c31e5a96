"""Meshcat scenes of N robots side by side: geoms, end-effector sites, target paths, labels,
and the animation of their joint trajectories.

A `Scene` is a list of meshcat commands in their lowered (msgpack-ready) form. The same
list drives a live meshcat server (`tt.viz.live`) and a standalone HTML file
(`tt.viz.html`), so what one shows the other shows too.

Scene tree (under ``/meshcat/tt``, translated so that the framed centre is the viewer's
origin, see `tt.viz.camera`)::

    robot_03/                      one grid cell per robot, translated to its place
        bodies/02_shoulder/        world pose of a body (animated)
            05_shoulder_link       a geom, fixed in its body
            07_ee_0/               an end-effector site: sphere + axes
        target/path_0              the target trajectory of end effector 0, a line
        target/frame_0             the current target of end effector 0, a small frame (animated)
        label                      a text sprite above the cell
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import mujoco
import numpy as np
import umsgpack

from tt.kernels.errors import TTError
from tt.kernels.rotations import quat_to_mat
from tt.sim.motions.base import MOTION_DT, Motion
from tt.viz.camera import CameraOptions, CameraView, frame_points
from tt.viz.poses import BodyPoses, body_poses, pose_matrix
from tt.viz.shapes import (
    ee_site_ids,
    frame_triad,
    geom_visuals,
    ground_grid,
    marker_sphere,
    path_name,
    polyline,
    text_sprite,
)

#: Root of tt's content in the meshcat scene tree.
ROOT = "/meshcat/tt"

_CAMERA_OBJECT = "/Cameras/default/rotated/<object>"
_FLOAT32_EXT = 0x17  # msgpack extension code meshcat's viewer decodes as a Float32Array


class SceneError(TTError):
    """Inputs that cannot make a scene; the message names the argument and the robot."""


@dataclass(frozen=True)
class SceneOptions:
    """Look of a scene.

    camera: framing (direction, field of view, window aspect).
    geom_groups: MuJoCo geom groups drawn (MuJoCo's viewer default: 0, 1, 2).
    plane_extent: half size [m] drawn for infinite planes (floors).
    target_rgba: colour of target trajectories.
    target_frame_scale: axis length [m] of the current-target frame and the end-effector axes.
    grid_spacing, grid_rgba: the floor grid at z = 0 under all robots: line spacing [m]
        (None: the finest of 0.1, 0.25, 0.5, 1 m that keeps it under 40 lines), colour.
    label_height: height of the text labels as a fraction of the window height.
    cell_gap: free space [m] between neighbouring robots in the grid.
    background: (top, bottom) background colours, each (r, g, b) in [0, 1].
    loop: replay the animation forever (True) or once (False).
    """

    camera: CameraOptions = field(default_factory=CameraOptions)
    geom_groups: tuple[int, ...] = (0, 1, 2)
    plane_extent: float = 1.0
    target_rgba: tuple[float, float, float, float] = (0.85, 0.1, 0.6, 1.0)
    target_frame_scale: float = 0.06
    label_height: float = 0.045
    cell_gap: float = 0.3
    background: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.97, 0.97, 0.98), (0.72, 0.75, 0.8))
    grid_spacing: float | None = None
    grid_rgba: tuple[float, float, float, float] = (0.55, 0.57, 0.62, 1.0)
    loop: bool = True


@dataclass
class Scene:
    """Meshcat commands that draw (and animate) robots, and how they were framed.

    commands: lowered meshcat commands in the order they must be applied.
    view: the camera framing; `view.center` is the world point at the viewer's origin.
    cell_offsets: world translation of each robot's grid cell [m], (N, 3).
    labels: one label per robot.
    dt: animation frame period [s].
    frames: number of animation frames (1 for a still scene).
    """

    commands: list[dict]
    view: CameraView
    cell_offsets: np.ndarray
    labels: tuple[str, ...]
    dt: float
    frames: int

    @property
    def duration(self) -> float:
        """Length of the animation [s] (0 for a still scene)."""
        return (self.frames - 1) * self.dt

    def pack(self) -> list[bytes]:
        """Each command as the msgpack bytes the meshcat viewer decodes."""
        return [umsgpack.packb(c) for c in self.commands]


# ---------------------------------------------------------------- lowered commands
def _matrix(m: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(m, dtype=np.float64).T.reshape(-1)]  # column-major


def set_object(path: str, obj: dict) -> dict:
    return {"type": "set_object", "path": path, "object": obj}


def set_transform(path: str, matrix: np.ndarray) -> dict:
    return {"type": "set_transform", "path": path, "matrix": _matrix(matrix)}


def set_property(path: str, key: str, value) -> dict:
    return {"type": "set_property", "path": path, "property": key, "value": value}


def delete(path: str) -> dict:
    return {"type": "delete", "path": path}


def _float32(values: np.ndarray) -> umsgpack.Ext:
    return umsgpack.Ext(_FLOAT32_EXT, np.ascontiguousarray(values, dtype=np.float32).tobytes())


def _pose_clip(path: str, pos: np.ndarray, quat_wxyz: np.ndarray, fps: float) -> dict:
    """Animation clip moving the node at `path` through poses (T, 3) and (T, 4) (w, x, y, z)."""
    times = _float32(np.arange(pos.shape[0]))  # in frames; three.js divides by fps
    xyzw = np.asarray(quat_wxyz)[:, [1, 2, 3, 0]]
    return {
        "path": path,
        "clip": {
            "fps": fps,
            "name": "default",
            "tracks": [
                {"name": ".position", "type": "vector3", "times": times, "values": _float32(pos.reshape(-1))},
                {"name": ".quaternion", "type": "quaternion", "times": times, "values": _float32(xyzw.reshape(-1))},
            ],
        },
    }


# ---------------------------------------------------------------- inputs
def _per_robot(value, n: int, what: str) -> list:
    if value is None:
        return [None] * n
    value = list(value)
    if len(value) != n:
        raise SceneError(f"{what} has {len(value)} entries; there are {n} robots, give one per robot")
    return value


def _motions(motions, n: int) -> list[Motion | None]:
    if motions is None or isinstance(motions, Motion):
        return [motions] * n
    out = _per_robot(motions, n, "motions")
    for i, m in enumerate(out):
        if m is not None and not isinstance(m, Motion):
            raise SceneError(f"motions[{i}] is a {type(m).__name__}; expected a tt Motion or None")
    return out


def _hold_last(x: np.ndarray, frames: int) -> np.ndarray:
    """Pad axis 0 to `frames` by repeating the last entry (a finished episode holds still)."""
    if x.shape[0] == frames:
        return x
    return np.concatenate([x, np.repeat(x[-1:], frames - x.shape[0], axis=0)], axis=0)


@dataclass
class _Robot:
    model: mujoco.MjModel
    label: str
    poses: BodyPoses
    motion: Motion | None
    visuals: list
    sites: list[int]

    def local_points(self, frames: int, target_radius: float) -> tuple[np.ndarray, np.ndarray]:
        """Points (K, 3) [m] and radii (K,) [m] that bound the robot and its targets over all frames."""
        rot = quat_to_mat(self.poses.quat)  # (T, nbody, 3, 3)
        pts, rad = [], []
        for v in self.visuals:
            if v.radius <= 0:
                continue
            pts.append(self.poses.pos[:, v.body_id] + rot[:, v.body_id] @ v.center)
            rad.append(np.full(frames, v.radius))
        if self.motion is not None:
            pts.append(self.motion.pos.reshape(-1, 3))
            rad.append(np.full(self.motion.pos.shape[0] * self.motion.pos.shape[1], target_radius))
        if not pts:
            # Nothing drawable: keep the body origins in view.
            pts.append(self.poses.pos.reshape(-1, 3))
            rad.append(np.full(pts[0].shape[0], 0.05))
        return np.concatenate(pts).reshape(-1, 3), np.concatenate(rad)


# ---------------------------------------------------------------- the builder
def build_scene(
    models: Sequence[mujoco.MjModel],
    *,
    qpos: Sequence[np.ndarray | None] | None = None,
    motions: Motion | Sequence[Motion | None] | None = None,
    labels: Sequence[str] | None = None,
    dt: float = MOTION_DT,
    options: SceneOptions | None = None,
) -> Scene:
    """A scene with N robots in a grid, each optionally moving and with its target motion.

    models: the N robots.
    qpos: per robot, its joint positions, (T_i, nq_i) for an animation or (nq_i,) for one
        pose; None (or a None entry) draws the model at ``qpos0``.
    motions: one target motion for every robot, or one (or None) per robot; drawn as a line
        per end effector with the current target as a small frame.
    labels: one text label per robot (default ``robot 0``, ``robot 1``, ...).
    dt: frame period [s] of `qpos` and of the motions (tt's control period, 50 Hz).
    The animation lasts as long as the longest trajectory or motion; shorter ones hold
    their last frame.
    """
    options = options or SceneOptions()
    models = list(models)
    n = len(models)
    if n == 0:
        raise SceneError("models is empty; give at least one mujoco.MjModel")
    for i, m in enumerate(models):
        if not isinstance(m, mujoco.MjModel):
            raise SceneError(f"models[{i}] is a {type(m).__name__}; expected a mujoco.MjModel")
    if not (math.isfinite(dt) and dt > 0):
        raise SceneError(f"dt = {dt}; valid: a positive number of seconds")
    qpos_list = _per_robot(qpos, n, "qpos")
    motion_list = _motions(motions, n)
    label_list = (
        [f"robot {i}" for i in range(n)] if labels is None else [str(s) for s in _per_robot(labels, n, "labels")]
    )

    robots: list[_Robot] = []
    for i, (model, q, motion, label) in enumerate(zip(models, qpos_list, motion_list, label_list)):
        who = f"robot {i} ({label!r})"
        poses = body_poses(model, model.qpos0 if q is None else q, name=who)
        sites = ee_site_ids(model)
        if motion is not None:
            if abs(motion.dt - dt) > 1e-9 * dt:
                raise SceneError(
                    f"motion {motion.name!r} of {who} has dt = {motion.dt} s; the scene's frames are dt = {dt} s"
                )
            if sites and motion.arms != len(sites):
                raise SceneError(
                    f"motion {motion.name!r} of {who} has {motion.arms} end effectors; the model has "
                    f"{len(sites)} end-effector sites (ee_0..ee_{len(sites) - 1})"
                )
        visuals = geom_visuals(model, groups=options.geom_groups, plane_extent=options.plane_extent)
        robots.append(_Robot(model, label, poses, motion, visuals, sites))

    frames = max([r.poses.pos.shape[0] for r in robots] + [r.motion.steps for r in robots if r.motion is not None])
    for r in robots:
        r.poses = BodyPoses(_hold_last(r.poses.pos, frames), _hold_last(r.poses.quat, frames))
        if r.motion is not None and r.motion.steps != frames:
            m = r.motion
            r.motion = Motion(m.name, _hold_last(m.pos, frames), _hold_last(m.quat, frames), m.dt, m.meta)

    # Grid cells sized by the union of everyone's bounds, laid out along the camera's
    # horizontal right and away directions so cells do not hide one another.
    local = [r.local_points(frames, options.target_frame_scale) for r in robots]
    all_pts = np.concatenate([p for p, _ in local])
    all_rad = np.concatenate([rd for _, rd in local])
    lo = (all_pts - all_rad[:, None]).min(0)
    hi = (all_pts + all_rad[:, None]).max(0)
    fwd = options.camera.forward()
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    away = np.array([fwd[0], fwd[1], 0.0]) / np.linalg.norm(fwd[:2])
    span = hi - lo
    step_right = float(np.abs(right) @ span) + options.cell_gap
    step_away = float(np.abs(away) @ span) + options.cell_gap
    cols = math.ceil(math.sqrt(n))
    offsets = np.zeros((n, 3))
    for i in range(n):
        row, col = divmod(i, cols)
        row_cols = min(cols, n - row * cols)
        offsets[i] = (col - (row_cols - 1) / 2.0) * step_right * right + row * step_away * away

    sprites = [text_sprite(label, options.label_height, options.camera.fov_deg) for label in label_list]
    label_local = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + 0.05])
    frame_pts = [p + offsets[i] for i, (p, _) in enumerate(local)] + [label_local + offsets]
    frame_rad = [rd for _, rd in local] + [np.full(n, 0.05)]
    view = frame_points(np.concatenate(frame_pts), np.concatenate(frame_rad), options.camera)

    shift = pose_matrix(-view.center)
    top, bottom = options.background
    eye = view.eye
    cmds: list[dict] = [
        delete(ROOT),
        set_property("/Background", "top_color", [float(c) for c in top]),
        set_property("/Background", "bottom_color", [float(c) for c in bottom]),
        # The axes helper marks the viewer's origin, which is the framed centre here, not
        # the world origin; it would mislead.
        set_property("/Axes", "visible", False),
        # meshcat's own 20 m grid is replaced by one fitted to the robots (see `ground_grid`).
        set_property("/Grid", "visible", False),
        set_transform("/Cameras/default", np.eye(4)),
        # The camera object lives in a y-up frame: world (x, y, z) is (x, z, -y) there.
        set_property(_CAMERA_OBJECT, "position", [float(eye[0]), float(eye[2]), float(-eye[1])]),
        set_property(_CAMERA_OBJECT, "fov", float(view.fov_deg)),
        set_transform(ROOT, shift),
    ]
    floor_lo = np.concatenate(frame_pts).min(0) - 0.3
    floor_hi = np.concatenate(frame_pts).max(0) + 0.3
    spacing = options.grid_spacing
    if spacing is None:
        extent = float(np.max(floor_hi[:2] - floor_lo[:2]))
        spacing = next((s for s in (0.1, 0.25, 0.5) if extent / s <= 40), 1.0)
    cmds.append(set_object(f"{ROOT}/floor_grid", ground_grid(floor_lo, floor_hi, spacing, options.grid_rgba)))
    clips = []
    for i, r in enumerate(robots):
        cell = f"{ROOT}/robot_{i:02d}"
        cmds.append(set_transform(cell, pose_matrix(offsets[i])))
        cmds += _robot_commands(r, cell, options, clips, frames, dt)
        cmds.append(set_object(f"{cell}/label", sprites[i]))
        cmds.append(set_transform(f"{cell}/label", pose_matrix(label_local)))
    if frames > 1:
        reps = 1_000_000 if options.loop else 1
        cmds.append(
            {
                "type": "set_animation",
                "path": "",
                "animations": clips,
                "options": {"play": True, "repetitions": reps, "clampWhenFinished": True},
            }
        )
    return Scene(cmds, view, offsets, tuple(label_list), float(dt), int(frames))


def _robot_commands(r: _Robot, cell: str, options: SceneOptions, clips: list, frames: int, dt: float) -> list[dict]:
    model = r.model
    cmds: list[dict] = []
    by_body: dict[int, list] = {}
    for v in r.visuals:
        by_body.setdefault(v.body_id, []).append(v)
    site_body = {int(model.site_bodyid[s]): [] for s in r.sites}
    for s in r.sites:
        site_body[int(model.site_bodyid[s])].append(s)
    fps = 1.0 / dt
    for b in sorted(set(by_body) | set(site_body)):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or ""
        bpath = f"{cell}/bodies/{path_name(b, name, 'body')}"
        cmds.append(set_transform(bpath, pose_matrix(r.poses.pos[0, b], r.poses.quat[0, b])))
        for v in by_body.get(b, []):
            cmds.append(set_object(f"{bpath}/{v.name}", v.object))
            cmds.append(set_transform(f"{bpath}/{v.name}", v.local))
        for s in site_body.get(b, []):
            sname = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, s) or ""
            spath = f"{bpath}/{path_name(s, sname, 'site')}"
            radius = max(float(model.site_size[s][0]), 0.008)
            cmds.append(set_object(spath, marker_sphere(radius, model.site_rgba[s])))
            cmds.append(set_object(f"{spath}/axes", frame_triad(options.target_frame_scale)))
            cmds.append(set_transform(spath, pose_matrix(model.site_pos[s], model.site_quat[s])))
        # The world body never moves; every other body gets a track, fixed ones included,
        # which keeps the scene correct for floating bases.
        if frames > 1 and b != 0:
            clips.append(_pose_clip(bpath, r.poses.pos[:, b], r.poses.quat[:, b], fps))
    if r.motion is not None:
        for a in range(r.motion.arms):
            cmds.append(set_object(f"{cell}/target/path_{a}", polyline(r.motion.pos[:, a], options.target_rgba)))
            fpath = f"{cell}/target/frame_{a}"
            cmds.append(set_object(fpath, frame_triad(options.target_frame_scale)))
            cmds.append(set_transform(fpath, pose_matrix(r.motion.pos[0, a], r.motion.quat[0, a])))
            if frames > 1:
                clips.append(_pose_clip(fpath, r.motion.pos[:, a], r.motion.quat[:, a], fps))
    return cmds
