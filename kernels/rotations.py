"""Host-side (numpy, float64) rotation conversions that every layer shares.

Quaternions are (w, x, y, z), MuJoCo's order. The bottom layer holds them so that the
model builders (`tt.kernels.model`, `tt.sim.designs.chain_tree`), the tokenizer and the
viewer use one definition.
"""

from __future__ import annotations

import numpy as np


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) -> rotation matrices (..., 3, 3); the input is normalised."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def mat_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) with w >= 0.

    Uses the largest of the four candidate pivots per matrix, so it is accurate for every
    rotation (no branch loses precision near 180 degrees).
    """
    r = np.asarray(r, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = np.argmax(cand, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300)) * 2
    q = np.empty(r.shape[:-2] + (4,))
    qw = np.stack(
        [
            s / 4,
            (r[..., 2, 1] - r[..., 1, 2]) / s,
            (r[..., 0, 2] - r[..., 2, 0]) / s,
            (r[..., 1, 0] - r[..., 0, 1]) / s,
        ],
        -1,
    )
    qx = np.stack(
        [
            (r[..., 2, 1] - r[..., 1, 2]) / s,
            s / 4,
            (r[..., 0, 1] + r[..., 1, 0]) / s,
            (r[..., 0, 2] + r[..., 2, 0]) / s,
        ],
        -1,
    )
    qy = np.stack(
        [
            (r[..., 0, 2] - r[..., 2, 0]) / s,
            (r[..., 0, 1] + r[..., 1, 0]) / s,
            s / 4,
            (r[..., 1, 2] + r[..., 2, 1]) / s,
        ],
        -1,
    )
    qz = np.stack(
        [
            (r[..., 1, 0] - r[..., 0, 1]) / s,
            (r[..., 0, 2] + r[..., 2, 0]) / s,
            (r[..., 1, 2] + r[..., 2, 1]) / s,
            s / 4,
        ],
        -1,
    )
    for i, cand_q in enumerate((qw, qx, qy, qz)):
        sel = k == i
        q[sel] = cand_q[sel]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


__all__ = ["mat_to_quat", "quat_to_mat"]
