"""SO(3) / SE(3) logarithms and their Jacobians as Warp functions, in mink's conventions.

mink (the oracle's IK) writes a pose error as the right-minus of SE(3), a twist
``(v, w)`` (translation first) expressed in the moving frame, and differentiates it with
the left Jacobian inverse of SE(3). These functions give the same quantities in float32:

* ``so3_log(q)``: rotation vector of a unit quaternion, taken on the hemisphere w >= 0
  (angle in [0, pi]).
* ``se3_log(q, t)``: twist ``(v, w)`` of the pose (q, t), ``v = V(w)^-1 t``.
* ``se3_ljacinv(v, w)``: the 6x6 left Jacobian inverse as its two distinct 3x3 blocks,
  ``[[A, B], [0, A]]`` with ``A = Jl(w)^-1`` and ``B = -A Q(v, w) A`` (Barfoot,
  "State Estimation for Robotics", eqs. 7.86, 7.95).
* ``se3_jlog(v, w)``: the Jacobian mink's frame task uses, ``se3_ljacinv`` but the identity
  when ``|w|^2 < MINK_JLOG_EPS``.

The closed forms cancel catastrophically in float32 at small angles, so below
`_SERIES_ANGLE` every coefficient is its Taylor series (terms to angle^8; the truncation
error there is below 1e-12 relative). Their coefficients are constants of the scalar type,
made in Python: a float literal inside a Warp function is float32 whatever it is cast to,
so ``S(1.0 / 720.0)`` written in a float64 function would be divided in float32 (~1e-8
relative off).

The functions exist for float32 (module-level names) and float64 (`lie_funcs(wp.float64)`),
the latter for computations whose result must not depend on round-off (the start posture).
"""

import functools
from types import SimpleNamespace

import warp as wp

#: Angle [rad] below which the coefficients use their Taylor series.
_SERIES_ANGLE = 0.5

#: mink 1.3's SE(3) ``jlog`` returns the identity when the squared rotation error is below
#: this [rad^2] (``EPS`` in ``mink/lie/_lie_ops_c.c``, as documented in `tt.sim.controller`),
#: dropping the coupling block ``-A Q A`` of ``Jl^-1``. That block is ``-1/2 [v]`` there, so
#: with a position error and an orientation already on target (a target taken from the
#: site's own pose) mink's Jacobian differs from the exact one by about ``|v| / 2`` on
#: rotational DoFs; `se3_jlog` follows mink.
MINK_JLOG_EPS = 1e-10


def lie_funcs(dtype=wp.float32) -> SimpleNamespace:
    """See `_lie_funcs` (one cache entry per precision, however `dtype` is passed)."""
    return _lie_funcs(dtype)


@functools.cache
def _lie_funcs(dtype) -> SimpleNamespace:
    """The functions for scalar type `dtype` (wp.float32 or wp.float64).

    quat_wxyz(v4) -> quat; wxyz(quat) -> v4; so3_log(quat) -> vec3;
    so3_ljacinv(vec3) -> mat33; se3_log(quat, vec3) -> (v, w); se3_ljacinv(v, w) -> (A, B);
    se3_jlog(v, w) -> (A, B).
    """
    S = dtype
    vec3 = wp.types.vector(3, S)
    vec4 = wp.types.vector(4, S)
    quat = wp.types.quaternion(S)
    mat33 = wp.types.matrix((3, 3), S)
    # Constants of type S, exact to its precision (see the module docstring).
    SERIES = S(_SERIES_ANGLE)
    JLOG_EPS = S(MINK_JLOG_EPS)
    LOG_SERIES_N2 = S(1.0e-8)
    BETA0, BETA1, BETA2, BETA3, BETA4 = (S(1.0 / k) for k in (12.0, 720.0, 30240.0, 1209600.0, 47900160.0))
    QB0, QB1, QB2, QB3, QB4 = (S(1.0 / k) for k in (6.0, 120.0, 5040.0, 362880.0, 39916800.0))
    QC0, QC1, QC2, QC3, QC4 = (S(1.0 / k) for k in (24.0, 720.0, 40320.0, 3628800.0, 479001600.0))
    QD0, QD1, QD2, QD3, QD4 = (S(1.0 / k) for k in (120.0, 2520.0, 120960.0, 9979200.0, 1245404160.0))

    @wp.func
    def quat_wxyz(v: vec4) -> quat:
        """Warp quaternion (x, y, z, w) of a (w, x, y, z) 4-vector."""
        return quat(v[1], v[2], v[3], v[0])

    @wp.func
    def wxyz(q: quat) -> vec4:
        """(w, x, y, z) 4-vector of a Warp quaternion."""
        return vec4(q[3], q[0], q[1], q[2])

    @wp.func
    def so3_log(q: quat) -> vec3:
        """Rotation vector [rad] of a unit quaternion, angle in [0, pi]."""
        v = vec3(q[0], q[1], q[2])
        w = q[3]
        if w < S(0.0):
            v = -v
            w = -w
        # atan2(n, w) / n -> 1 / w as n -> 0: the series (in n^2, no square root) keeps the
        # value and its adjoint finite at zero rotation.
        n2 = wp.dot(v, v)
        scale = S(0.0)
        if n2 < LOG_SERIES_N2:
            scale = S(2.0) / w * (S(1.0) - n2 / (S(3.0) * w * w))
        else:
            n = wp.sqrt(n2)
            scale = S(2.0) * wp.atan2(n, w) / n
        return v * scale

    @wp.func
    def beta(t2: S) -> S:
        """(1 - (theta/2) cot(theta/2)) / theta^2 at t2 = theta^2: the second-order
        coefficient of Jl^-1 and V^-1 (a function of theta^2, so no square root at zero)."""
        if t2 < SERIES * SERIES:
            return BETA0 + t2 * (BETA1 + t2 * (BETA2 + t2 * (BETA3 + t2 * BETA4)))
        theta = wp.sqrt(t2)
        return (S(1.0) - theta * wp.sin(theta) / (S(2.0) * (S(1.0) - wp.cos(theta)))) / t2

    @wp.func
    def so3_ljacinv(w: vec3) -> mat33:
        """Left Jacobian inverse of SO(3) at rotation vector w: I - w^/2 + beta w^ w^."""
        W = wp.skew(w)
        return wp.identity(n=3, dtype=S) - S(0.5) * W + beta(wp.dot(w, w)) * (W @ W)

    @wp.func
    def se3_log(q: quat, t: vec3):
        """Twist (v [m], w [rad]) of the pose with rotation q and translation t [m]."""
        w = so3_log(q)
        return so3_ljacinv(w) @ t, w

    @wp.func
    def q_block(v: vec3, w: vec3) -> mat33:
        """Q(v, w), the translation block of the SE(3) left Jacobian."""
        t2 = wp.dot(w, w)
        b = S(0.0)
        c = S(0.0)
        d = S(0.0)
        if t2 < SERIES * SERIES:
            b = QB0 - t2 * (QB1 - t2 * (QB2 - t2 * (QB3 - t2 * QB4)))
            c = QC0 - t2 * (QC1 - t2 * (QC2 - t2 * (QC3 - t2 * QC4)))
            d = QD0 - t2 * (QD1 - t2 * (QD2 - t2 * (QD3 - t2 * QD4)))
        else:
            theta = wp.sqrt(t2)
            s = wp.sin(theta)
            co = wp.cos(theta)
            t4 = t2 * t2
            b = (theta - s) / (t2 * theta)
            c = (t2 + S(2.0) * co - S(2.0)) / (S(2.0) * t4)
            d = (S(2.0) * theta - S(3.0) * s + theta * co) / (S(2.0) * t4 * theta)
        V = wp.skew(v)
        W = wp.skew(w)
        WV = W @ V
        VW = V @ W
        WVW = WV @ W
        WW = W @ W
        return S(0.5) * V + b * (WV + VW + WVW) + c * (WW @ V + VW @ W - S(3.0) * WVW) + d * (WVW @ W + W @ WVW)

    @wp.func
    def se3_ljacinv(v: vec3, w: vec3):
        """Blocks (A, B) of the SE(3) left Jacobian inverse [[A, B], [0, A]] at twist (v, w)."""
        A = so3_ljacinv(w)
        return A, -(A @ q_block(v, w) @ A)

    @wp.func
    def se3_jlog(v: vec3, w: vec3):
        """Blocks (A, B) of mink's SE(3) Jacobian at twist (v, w): those of `se3_ljacinv`, or
        (I, 0) when |w|^2 < MINK_JLOG_EPS (mink's switch, a discontinuity it has)."""
        if wp.dot(w, w) < JLOG_EPS:
            return wp.identity(n=3, dtype=S), mat33()
        return se3_ljacinv(v, w)

    return SimpleNamespace(
        quat_wxyz=quat_wxyz,
        wxyz=wxyz,
        so3_log=so3_log,
        so3_ljacinv=so3_ljacinv,
        se3_log=se3_log,
        se3_ljacinv=se3_ljacinv,
        se3_jlog=se3_jlog,
    )


_F32 = lie_funcs(wp.float32)
quat_wxyz = _F32.quat_wxyz
wxyz = _F32.wxyz
so3_log = _F32.so3_log
so3_ljacinv = _F32.so3_ljacinv
se3_log = _F32.se3_log
se3_ljacinv = _F32.se3_ljacinv
se3_jlog = _F32.se3_jlog
