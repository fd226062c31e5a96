"""The float64 SO(3) / SE(3) functions of `tt.kernels.lie` near zero angle, against float64
math whose coefficients are exact.

The functions switch to Taylor series below 0.5 rad; their float64 versions must carry
float64 coefficients (a float literal in a Warp function is float32, ~1e-8 relative off,
which shows here as 1e-10 to 1e-9 on the Jacobian blocks at 0.2 rad). The reference: the
rotation vector from MuJoCo (`mju_quat2Vel`), the Jacobian coefficients from their closed
forms evaluated in 40-digit arithmetic (mpmath; float64 closed forms cancel
catastrophically at these angles), assembled in float64 numpy. Angles up to 0.2 rad keep
the series' truncation error (~1e-10 t2^5 relative) below 1e-16, so what remains is
float64 round-off on entries of order 1: held to 1e-14.
"""

import mpmath
import mujoco
import numpy as np
import warp as wp

from tt.kernels.lie import MINK_JLOG_EPS, lie_funcs

TOL64 = 1e-14  # float64 round-off on O(1) entries (see the module docstring)

_L = lie_funcs(wp.float64)


@wp.kernel
def _lie64(
    # In:
    quat_in: wp.array(dtype=wp.vec4d),
    trans_in: wp.array(dtype=wp.vec3d),
    # Out:
    w_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
    a_out: wp.array(dtype=wp.mat33d),
    b_out: wp.array(dtype=wp.mat33d),
    jlog_a_out: wp.array(dtype=wp.mat33d),
    jlog_b_out: wp.array(dtype=wp.mat33d),
):
    i = wp.tid()
    v, w = _L.se3_log(_L.quat_wxyz(quat_in[i]), trans_in[i])
    A, B = _L.se3_ljacinv(v, w)
    JA, JB = _L.se3_jlog(v, w)
    w_out[i] = w
    v_out[i] = v
    a_out[i] = A
    b_out[i] = B
    jlog_a_out[i] = JA
    jlog_b_out[i] = JB


def _run(quat: np.ndarray, trans: np.ndarray) -> dict[str, np.ndarray]:
    n = len(quat)
    outs = {
        "w": wp.array(np.full((n, 3), np.inf), dtype=wp.vec3d, device="cpu"),
        "v": wp.array(np.full((n, 3), np.inf), dtype=wp.vec3d, device="cpu"),
        "A": wp.array(np.full((n, 3, 3), np.inf), dtype=wp.mat33d, device="cpu"),
        "B": wp.array(np.full((n, 3, 3), np.inf), dtype=wp.mat33d, device="cpu"),
        "JA": wp.array(np.full((n, 3, 3), np.inf), dtype=wp.mat33d, device="cpu"),
        "JB": wp.array(np.full((n, 3, 3), np.inf), dtype=wp.mat33d, device="cpu"),
    }
    wp.launch(
        _lie64,
        dim=n,
        inputs=[wp.array(quat, dtype=wp.vec4d, device="cpu"), wp.array(trans, dtype=wp.vec3d, device="cpu")],
        outputs=list(outs.values()),
        device="cpu",
    )
    return {k: a.numpy() for k, a in outs.items()}


def _coefficients(theta: float) -> tuple[float, float, float, float]:
    """beta (of Jl^-1), and b, c, d (of Q) at angle theta [rad], to 40 digits, rounded to float64."""
    if theta == 0.0:
        return 1.0 / 12.0, 1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0
    with mpmath.workdps(40):
        t = mpmath.mpf(theta)
        s, co = mpmath.sin(t), mpmath.cos(t)
        beta = (1 - t * s / (2 * (1 - co))) / t**2
        b = (t - s) / t**3
        c = (t**2 + 2 * co - 2) / (2 * t**4)
        d = (2 * t - 3 * s + t * co) / (2 * t**5)
        return float(beta), float(b), float(c), float(d)


def _skew(x: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def _reference(quat: np.ndarray, trans: np.ndarray) -> dict[str, np.ndarray]:
    ref: dict[str, list] = {"w": [], "v": [], "A": [], "B": []}
    for q, t in zip(quat, trans):
        w = np.zeros(3)
        mujoco.mju_quat2Vel(w, q, 1.0)
        beta, b, c, d = _coefficients(float(np.linalg.norm(w)))
        W = _skew(w)
        A = np.eye(3) - 0.5 * W + beta * W @ W
        v = A @ t
        V = _skew(v)
        WVW = W @ V @ W
        Q = 0.5 * V + b * (W @ V + V @ W + WVW) + c * (W @ W @ V + V @ W @ W - 3.0 * WVW) + d * (WVW @ W + W @ WVW)
        ref["w"].append(w)
        ref["v"].append(v)
        ref["A"].append(A)
        ref["B"].append(-A @ Q @ A)
    return {k: np.stack(x) for k, x in ref.items()}


def _poses(angles: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions (w >= 0) of the given angles about random axes, and random translations [m]."""
    rng = np.random.default_rng(seed)
    axis = rng.standard_normal((len(angles), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    quat = np.concatenate([np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None] * axis], axis=1)
    return quat, rng.normal(0.0, 0.5, (len(angles), 3))


def test_float64_series_match_exact_coefficients_near_zero_angle():
    rng = np.random.default_rng(0)
    # Zero, tiny angles (1e-8 to 1e-2 rad) and the upper end of the range (0.01 to 0.2 rad).
    angles = np.concatenate([[0.0], 10.0 ** rng.uniform(-8.0, -2.0, 31), rng.uniform(0.01, 0.2, 32)])  # [rad]
    quat, trans = _poses(angles, seed=1)
    out, ref = _run(quat, trans), _reference(quat, trans)
    for key in ("w", "v", "A", "B"):
        np.testing.assert_allclose(out[key], ref[key], atol=TOL64, rtol=0, err_msg=key)
    # The angles that a float32 coefficient would put off by more than the tolerance.
    assert np.sum(angles > 0.05) > 10


def test_se3_jlog_is_the_identity_below_minks_threshold():
    # |w|^2 at half and twice mink's threshold: (I, 0) below it, se3_ljacinv above it.
    angles = np.sqrt(MINK_JLOG_EPS) * np.array([0.0, 0.5, 0.7, 1.4, 2.0])
    quat, trans = _poses(angles, seed=2)
    out = _run(quat, trans)
    below = np.sum(out["w"] ** 2, axis=1) < MINK_JLOG_EPS
    assert below.tolist() == [True, True, True, False, False]
    np.testing.assert_array_equal(out["JA"][below], np.broadcast_to(np.eye(3), (3, 3, 3)))
    np.testing.assert_array_equal(out["JB"][below], 0.0)
    np.testing.assert_array_equal(out["JA"][~below], out["A"][~below])
    np.testing.assert_array_equal(out["JB"][~below], out["B"][~below])
    # Above the threshold the coupling block is about -[v]/2, the term mink drops below it.
    np.testing.assert_allclose(out["B"][~below], [-0.5 * _skew(v) for v in out["v"][~below]], atol=1e-4)
