"""Body poses of MuJoCo models along joint trajectories, and the rigid-transform algebra
the viewer needs (quaternion (w, x, y, z) to 4x4 matrices).

Poses come from `mujoco.mj_kinematics`, the reference forward kinematics, one model at a
time: the designs a viewer compares usually differ in topology, so there is no common
batch to vectorise over, and the viewer runs once per scene, not in a training loop.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import mujoco
import numpy as np

from tt.kernels.errors import TTError
from tt.kernels.rotations import quat_to_mat


class PoseError(TTError):
    """A joint trajectory that does not fit its model; the message names the field."""


class BodyPoses(NamedTuple):
    """World poses of every body of one model over T frames.

    pos: body origin positions [m], (T, nbody, 3)
    quat: body orientations (w, x, y, z), (T, nbody, 4)
    """

    pos: np.ndarray
    quat: np.ndarray


def body_poses(model: mujoco.MjModel, qpos: np.ndarray, *, name: str = "model") -> BodyPoses:
    """World poses of all bodies (world body included, index 0) for each frame of `qpos`.

    qpos: joint positions, (T, nq) or (nq,) for a single frame.
    name: how error messages refer to the model (e.g. "design 2").
    """
    q = np.asarray(qpos, dtype=np.float64)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != model.nq:
        raise PoseError(
            f"qpos of {name} has shape {tuple(np.shape(qpos))}; its model has nq = {model.nq}, "
            f"so qpos must be (T, {model.nq}) or ({model.nq},)"
        )
    if not np.all(np.isfinite(q)):
        bad = int(np.argwhere(~np.isfinite(q))[0, 0])
        raise PoseError(f"qpos of {name} has NaN/inf (first at frame {bad})")
    data = mujoco.MjData(model)
    pos = np.empty((q.shape[0], model.nbody, 3))
    quat = np.empty((q.shape[0], model.nbody, 4))
    for t in range(q.shape[0]):
        data.qpos[:] = q[t]
        mujoco.mj_kinematics(model, data)
        pos[t] = data.xpos
        quat[t] = data.xquat
    return BodyPoses(pos, quat)


def pose_matrix(
    pos: Sequence[float] | np.ndarray, quat: Sequence[float] | np.ndarray | None = None, rot: np.ndarray | None = None
) -> np.ndarray:
    """4x4 homogeneous transform from a position [m] and a quaternion (w, x, y, z) or a 3x3
    rotation (identity when neither is given)."""
    m = np.eye(4)
    if quat is not None:
        m[:3, :3] = quat_to_mat(np.asarray(quat, dtype=np.float64))
    elif rot is not None:
        m[:3, :3] = rot
    m[:3, 3] = pos
    return m


def rotation_x(angle: float) -> np.ndarray:
    """4x4 rotation about the x axis by `angle` [rad]."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[1:3, 1:3] = [[c, -s], [s, c]]
    return m
