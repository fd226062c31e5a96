"""Batched rigid transforms in numpy: a pose is a rotation (..., 3, 3) and a translation (..., 3).

``T_ab`` is the pose of frame b in frame a; composing ``T_ab`` with ``T_bc`` gives ``T_ac``.
Quaternions are (w, x, y, z), MuJoCo's order.
"""

from __future__ import annotations

import numpy as np


def compose(ra: np.ndarray, pa: np.ndarray, rb: np.ndarray, pb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_ab * T_bc``: (ra, pa) is T_ab, (rb, pb) is T_bc; returns T_ac."""
    return ra @ rb, (ra @ pb[..., None])[..., 0] + pa


def invert(r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse pose: ``T_ba`` from ``T_ab``."""
    rt = np.swapaxes(r, -1, -2)
    return rt, -(rt @ p[..., None])[..., 0]


def z_to_axis(axis: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) whose z column is the unit `axis` (..., 3): the smallest rotation
    taking +z to the axis (for -z, a half turn about x)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    x, y, z = np.moveaxis(a, -1, 0)
    # Rodrigues for the rotation from e_z to a: R = I + [v]x + [v]x^2 / (1 + c), v = e_z x a.
    c = z
    denom = np.where(c > -1 + 1e-12, 1 + c, 1.0)
    out = np.empty(a.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - x * x / denom
    out[..., 0, 1] = -x * y / denom
    out[..., 0, 2] = x
    out[..., 1, 0] = -x * y / denom
    out[..., 1, 1] = 1 - y * y / denom
    out[..., 1, 2] = y
    out[..., 2, 0] = -x
    out[..., 2, 1] = -y
    out[..., 2, 2] = c
    flip = c <= -1 + 1e-12
    out[flip] = np.diag([1.0, -1.0, -1.0])
    return out


def skew_parallel_axis(r: np.ndarray) -> np.ndarray:
    """``(r . r) E - r r^T`` (..., 3, 3): the parallel-axis term per unit mass for offset r."""
    r = np.asarray(r, dtype=np.float64)
    rr = (r * r).sum(-1)
    return rr[..., None, None] * np.eye(3) - r[..., :, None] * r[..., None, :]
