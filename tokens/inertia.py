"""Mass properties of primitives and the split of a body's lumped inertia over its links.

Formulas follow MuJoCo's compiler (uniform-density solids; a capsule is a cylinder plus a
sphere split into two hemispheres), so a primitive's inertia here equals what MuJoCo
derives from the same geom (checked in tests/test_tokens.py).

Geometry codes are indices into `tt.tokens.schema.GEOM_TYPES`; sizes follow MuJoCo's
``geom_size`` convention (radius, half-length, half-sizes) [m].
"""

from __future__ import annotations

import numpy as np

from tt.tokens.frames import skew_parallel_axis
from tt.tokens.schema import GEOM_TYPES

SPHERE, CAPSULE, ELLIPSOID, CYLINDER, BOX = (
    GEOM_TYPES.index(n) for n in ("sphere", "capsule", "ellipsoid", "cylinder", "box")
)

#: Number of meaningful size entries per geometry code.
SIZE_DIMS = {0: 0, SPHERE: 1, CAPSULE: 2, ELLIPSOID: 3, CYLINDER: 2, BOX: 3}


def primitive_volume(code: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Volume [m^3] of primitives: code (...), size (..., 3) -> (...); 0 for code "none"."""
    code = np.asarray(code)
    s = np.asarray(size, dtype=np.float64)
    r, h, c = s[..., 0], s[..., 1], s[..., 2]
    sphere = 4.0 / 3.0 * np.pi * r**3
    vol = np.zeros(code.shape)
    vol = np.where(code == SPHERE, sphere, vol)
    vol = np.where(code == CAPSULE, np.pi * r**2 * 2 * h + sphere, vol)
    vol = np.where(code == ELLIPSOID, 4.0 / 3.0 * np.pi * r * h * c, vol)
    vol = np.where(code == CYLINDER, np.pi * r**2 * 2 * h, vol)
    vol = np.where(code == BOX, 8 * r * h * c, vol)
    return vol


def primitive_inertia(code: np.ndarray, size: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Principal moments [kg m^2] about the centre, in the geom frame: (..., 3).

    code (...), size (..., 3) [m], mass (...) [kg]; zeros for code "none".
    """
    code = np.asarray(code)
    s = np.asarray(size, dtype=np.float64)
    m = np.asarray(mass, dtype=np.float64)
    a, b, c = s[..., 0], s[..., 1], s[..., 2]
    out = np.zeros(code.shape + (3,))

    def put(sel, ixx, iyy, izz):
        nonlocal out
        out = np.where(sel[..., None], np.stack(np.broadcast_arrays(ixx, iyy, izz), -1), out)

    put(code == SPHERE, 0.4 * m * a**2, 0.4 * m * a**2, 0.4 * m * a**2)
    # Capsule: mass split between the cylinder and the two hemispheres by volume; the
    # hemispheres' term is MuJoCo's (about the capsule centre).
    r, height = a, 2 * b
    vcyl = np.pi * r**2 * height
    vsph = 4.0 / 3.0 * np.pi * r**3
    total = np.where(vcyl + vsph > 0, vcyl + vsph, 1.0)
    mcyl, msph = m * vcyl / total, m * vsph / total
    ixx_cap = mcyl * (3 * r**2 + height**2) / 12 + msph * (2 * r**2 / 5 + height**2 / 4 + 3 * height * r / 8)
    izz_cap = mcyl * r**2 / 2 + msph * 2 * r**2 / 5
    put(code == CAPSULE, ixx_cap, ixx_cap, izz_cap)
    put(code == ELLIPSOID, m * (b**2 + c**2) / 5, m * (a**2 + c**2) / 5, m * (a**2 + b**2) / 5)
    ixx_cyl = m * (3 * a**2 + (2 * b) ** 2) / 12
    put(code == CYLINDER, ixx_cyl, ixx_cyl, m * a**2 / 2)
    put(code == BOX, m * (b**2 + c**2) / 3, m * (a**2 + c**2) / 3, m * (a**2 + b**2) / 3)
    return out


def principal_axes(inertia: np.ndarray, rtol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Inertia tensors (..., 3, 3) -> (rotation (..., 3, 3), principal moments (..., 3)).

    A tensor that is already diagonal (off-diagonal terms below ``rtol`` times its trace)
    keeps the identity rotation and its diagonal in order, so primitives stay canonical.
    Otherwise the eigenvectors, each with its largest component positive and the last one
    flipped if needed for a right-handed frame.
    """
    i = 0.5 * (inertia + np.swapaxes(inertia, -1, -2))
    diag = np.diagonal(i, axis1=-2, axis2=-1).copy()
    off = np.abs(i - diag[..., None] * np.eye(3)).max((-1, -2))
    scale = np.maximum(np.abs(diag).sum(-1), 1e-300)
    is_diag = off <= rtol * scale
    rot = np.broadcast_to(np.eye(3), i.shape).copy()
    moments = diag
    if np.any(~is_diag):
        w, v = np.linalg.eigh(i[~is_diag])
        idx = np.argmax(np.abs(v), axis=-2)  # (k, 3): row of the largest entry per column
        sign = np.sign(np.take_along_axis(v, idx[..., None, :], axis=-2))
        v = v * np.where(sign == 0, 1.0, sign)
        v[..., :, 2] *= np.sign(np.linalg.det(v))[..., None]
        rot[~is_diag] = v
        moments[~is_diag] = w
    return rot, moments


def valid_moments(moments: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Principal moments (..., 3) that are non-negative and satisfy the triangle inequality."""
    d = np.asarray(moments)
    tol = rtol * np.abs(d).sum(-1)
    tri = (
        (d[..., 0] + d[..., 1] >= d[..., 2] - tol)
        & (d[..., 0] + d[..., 2] >= d[..., 1] - tol)
        & (d[..., 1] + d[..., 2] >= d[..., 0] - tol)
    )
    return tri & np.all(d >= -tol[..., None], axis=-1)


def repair_moments(moments: np.ndarray, margin: float = 1e-6) -> np.ndarray:
    """Valid principal moments: negatives to 0, then, where the triangle inequality fails,
    the smallest blend towards the mean moment that satisfies it with a relative ``margin``
    (so it survives printing in float32). Valid input comes back unchanged.

    The blend keeps the total (the trace) and moves each moment as little as the worst
    violated inequality requires; MuJoCo's ``balanceinertia`` jumps to the mean instead.
    """
    d = np.maximum(np.asarray(moments, dtype=np.float64), 0.0)
    gap = d.sum(-1, keepdims=True) - 2 * d  # d_j + d_k - d_i for each i
    bad = gap < 0
    if not bad.any():
        return d
    mean = d.mean(-1, keepdims=True)
    need = np.where(bad, (margin * mean - gap) / np.maximum(mean - gap, 1e-300), 0.0).max(-1, keepdims=True)
    alpha = np.clip(need, 0.0, 1.0)
    return (1 - alpha) * d + alpha * mean


def fit_masses(
    mass: np.ndarray,
    com: np.ndarray,
    inertia: np.ndarray,
    codes: np.ndarray,
    sizes: np.ndarray,
    centers: np.ndarray,
    rotations: np.ndarray,
) -> np.ndarray:
    """Non-negative primitive masses whose solids best reproduce B bodies' lumped mass,
    centre of mass and inertia (all in the body frame; inertia about the com).

    When a lumped inertia is the solids' inertia for some per-primitive densities (a CAD
    export of parts in different materials), this recovers those masses exactly; the
    uniform-density split is its special case. Least squares on the 10 mass-moment
    equations, each scaled to be dimensionless; bodies whose unconstrained solution has a
    negative mass are solved again with masses >= 0. Each body's masses sum to its mass.

    mass (B,) [kg]; com (B, 3) [m]; inertia (B, 3, 3) [kg m^2]; codes (B, k); sizes,
    centers (B, k, 3) [m]; rotations (B, k, 3, 3). Returns (B, k) [kg].
    """
    from scipy.optimize import nnls

    mass = np.asarray(mass, dtype=np.float64)
    k = codes.shape[-1]
    unit = primitive_inertia(codes, sizes, np.ones(codes.shape))  # (B, k, 3) per kg
    j_unit = rotations @ (unit[..., :, None] * np.swapaxes(rotations, -1, -2)) + skew_parallel_axis(centers)
    j_total = inertia + mass[:, None, None] * skew_parallel_axis(com)
    iu = np.triu_indices(3)
    trace = np.trace(j_total, axis1=-2, axis2=-1)
    length = np.sqrt(np.maximum(trace / np.maximum(mass, 1e-300), 1e-12))
    scale = np.maximum(trace, 1e-300)
    a = np.concatenate(
        [
            np.ones((len(mass), 1, k)) / mass[:, None, None],
            np.swapaxes(centers, -1, -2) / (mass * length)[:, None, None],
            np.moveaxis(j_unit[:, :, iu[0], iu[1]], -1, -2) / scale[:, None, None],
        ],
        axis=1,
    )  # (B, 10, k)
    b = np.concatenate(
        [np.ones((len(mass), 1)), com / length[:, None], j_total[:, iu[0], iu[1]] / scale[:, None]], axis=1
    )
    m = (np.linalg.pinv(a) @ b[..., None])[..., 0]
    for i in np.flatnonzero((m < 0).any(-1)):
        m[i], _ = nnls(a[i], b[i])
    total = m.sum(-1, keepdims=True)
    return np.where(total > 0, m * (mass[:, None] / np.where(total > 0, total, 1.0)), mass[:, None] / k)


def split_lumped_inertia(
    mass: np.ndarray,
    com: np.ndarray,
    inertia: np.ndarray,
    codes: np.ndarray,
    sizes: np.ndarray,
    centers: np.ndarray,
    rotations: np.ndarray,
    masses: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split B bodies' lumped inertias over their k primitives each (paper, "Inertia Splitting").

    Masses follow a uniform density over the primitives' volumes, unless `masses` (B, k)
    gives them (`fit_masses`). Every primitive but the first gets its own solid inertia;
    the first takes the remainder (mass, centre of mass and inertia, by the parallel axis
    theorem), so each body's total mass, centre of mass and inertia are kept exactly.
    Where the remainder is not a physical inertia (a lumped inertia far from the
    primitives' shapes), every primitive of that body keeps its solid inertia instead and
    its entry of the returned ``exact`` is False.

    mass (B,) [kg]; com (B, 3) [m] and inertia (B, 3, 3) [kg m^2] about the com, in the body
    frame; codes (B, k), sizes (B, k, 3), centers (B, k, 3) [m] and rotations (B, k, 3, 3) of
    the primitives in the body frame. Returns per-primitive masses (B, k), centres of mass
    (B, k, 3) and inertia tensors about them (B, k, 3, 3) in the body frame, and exact (B,).
    """
    mass = np.asarray(mass, dtype=np.float64)
    vol = primitive_volume(codes, sizes)
    total = vol.sum(-1, keepdims=True)
    k = vol.shape[-1]
    frac = np.where(total > 0, vol / np.where(total > 0, total, 1.0), 1.0 / k)
    masses = mass[:, None] * frac if masses is None else np.array(masses, dtype=np.float64)
    solid = primitive_inertia(codes, sizes, masses)  # (B, k, 3) in geom frames
    tensors = rotations @ (solid[..., :, None] * np.swapaxes(rotations, -1, -2))
    coms = np.array(centers, dtype=np.float64)
    if k == 1:
        return (
            mass[:, None],
            np.asarray(com, dtype=np.float64)[:, None].copy(),
            np.asarray(inertia, dtype=np.float64)[:, None].copy(),
            np.ones(len(mass), bool),
        )
    rest_m = masses[:, 1:]
    m0 = mass - rest_m.sum(-1)
    ok = m0 > 1e-12 * np.maximum(mass, 1e-300)
    m0_safe = np.where(ok, m0, 1.0)
    c0 = (mass[:, None] * com - (rest_m[..., None] * coms[:, 1:]).sum(1)) / m0_safe[:, None]
    # Everything about the body origin, then back to primitive 0's centre of mass.
    j_total = inertia + mass[:, None, None] * skew_parallel_axis(com)
    j_rest = (tensors[:, 1:] + rest_m[..., None, None] * skew_parallel_axis(coms[:, 1:])).sum(1)
    i0 = j_total - j_rest - m0_safe[:, None, None] * skew_parallel_axis(c0)
    _, moments = principal_axes(i0)
    exact = ok & valid_moments(moments, rtol=1e-6)
    massless = mass <= 0
    exact[massless] = True
    masses[exact, 0] = m0[exact]
    coms[exact, 0] = c0[exact]
    tensors[exact, 0] = i0[exact]
    return masses, coms, tensors, exact
