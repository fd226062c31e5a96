"""MJCF building blocks shared by tt's design spaces: serial chains of primitive geoms.

Masses and inertias are never written by hand: every geom carries a density and MuJoCo
derives body masses and inertias from the geometry, so they always follow the shape.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import mujoco
import numpy as np

#: Effective density of links [kg/m^3]: hollow aluminium tubes with motors, averaged over
#: the solid primitive volume. Chosen so that random ViperX designs weigh 3.2 kg on average,
#: as the paper's Random row reports (its mass target is 3.2 kg as well).
LINK_DENSITY = 620.0


@dataclass(frozen=True)
class JointSpec:
    """A hinge (or slide) joint and the position actuator that drives it.

    axis: unit axis in the body frame; range: limits [rad or m]; kp [N m/rad], kv [N m s/rad]
    position-actuator gains; force: actuator force limit [N m]; armature: reflected rotor
    inertia [kg m^2]; damping: joint damping [N m s/rad].
    """

    name: str
    axis: tuple[float, float, float]
    range: tuple[float, float]
    kp: float
    kv: float
    force: float
    armature: float = 0.05
    damping: float = 0.5
    kind: str = "hinge"


@dataclass(frozen=True)
class Segment:
    """The rigid link from one joint to the next: a capsule of `radius` [m] along `vector` [m]."""

    vector: tuple[float, float, float]
    radius: float


def fmt(values) -> str:
    """Space-separated numbers with round-trip precision (MJCF attributes)."""
    return " ".join(repr(float(v)) for v in np.atleast_1d(values))


def chain_xml(
    prefix: str,
    joints: list[JointSpec],
    segments: list[Segment],
    ee_site: str,
    housing_radius: float = 0.03,
    indent: str = "    ",
) -> str:
    """Nested bodies of a serial chain: body i holds joint i, a motor housing along the joint
    axis, and the capsule of segment i; the end-effector site sits at the end of the last
    segment with the identity orientation of the last body's frame.

    The caller places the returned text inside a parent body (the mount).
    """
    if len(joints) != len(segments):
        raise ValueError(f"{len(joints)} joints need {len(joints)} segments, got {len(segments)}")
    lines: list[str] = []
    offset = (0.0, 0.0, 0.0)
    for i, (j, s) in enumerate(zip(joints, segments)):
        pad = indent * (i + 1)
        lines.append(f'{pad}<body name="{prefix}{j.name}" pos="{fmt(offset)}">')
        lines.append(
            f'{pad}  <joint name="{prefix}{j.name}" type="{j.kind}" axis="{fmt(j.axis)}" range="{fmt(j.range)}" '
            f'armature="{j.armature!r}" damping="{j.damping!r}"/>'
        )
        if j.kind == "hinge":
            lines.append(
                f'{pad}  <geom name="{prefix}{j.name}_motor" type="cylinder" size="{housing_radius!r} '
                f'{housing_radius!r}" '
                f'zaxis="{fmt(j.axis)}" rgba="0.15 0.15 0.15 1"/>'
            )
        if np.linalg.norm(s.vector) > 1e-9:
            lines.append(
                f'{pad}  <geom name="{prefix}{j.name}_link" type="capsule" fromto="0 0 0 {fmt(s.vector)}" '
                f'size="{s.radius!r}" rgba="0.55 0.6 0.7 1"/>'
            )
        offset = s.vector
    pad = indent * (len(joints) + 1)
    lines.append(f'{pad}<site name="{ee_site}" pos="{fmt(offset)}" size="0.015" rgba="1 0.3 0.1 1"/>')
    for i in reversed(range(len(joints))):
        lines.append(f"{indent * (i + 1)}</body>")
    return "\n".join(lines)


def actuators_xml(prefix: str, joints: list[JointSpec], indent: str = "    ") -> str:
    """One position actuator per joint, control range = joint range, force limited."""
    return "\n".join(
        f'{indent}<position name="{prefix}{j.name}" joint="{prefix}{j.name}" kp="{j.kp!r}" kv="{j.kv!r}" '
        f'ctrlrange="{fmt(j.range)}" forcerange="{-j.force!r} {j.force!r}"/>'
        for j in joints
    )


def header_xml(model: str, contacts: bool, timestep: float = 0.002) -> str:
    """Compiler, options and defaults shared by tt's robots (Euler integrator, gravity on)."""
    flag = "" if contacts else '\n    <flag contact="disable"/>'
    contact_attr = "" if contacts else ' contype="0" conaffinity="0"'
    return f"""<mujoco model="{model}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep!r}" integrator="Euler" gravity="0 0 -9.81">{flag}
  </option>
  <default>
    <geom density="{LINK_DENSITY!r}"{contact_attr}/>
  </default>"""


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_mul_batch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`quat_mul` of (..., 4) arrays of (w, x, y, z) quaternions, broadcast."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=float), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=float), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def axis_angle_quat(axis, angle: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation by `angle` [rad] about `axis`."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def servo(
    name: str,
    axis,
    range: tuple[float, float],
    kp: float,
    force: float,
    armature: float,
    *,
    kind: str = "hinge",
    damping: float = 0.1,
) -> JointSpec:
    """A joint with a position servo whose derivative gain is critical for the rotor alone.

    kv = 2 sqrt(kp armature): the servo never rings on its own reflected inertia; the
    link inertia on top only slows it. Units as in `JointSpec` (N and m for slides).
    """
    kv = 2.0 * np.sqrt(kp * armature)
    return JointSpec(
        name,
        tuple(float(a) for a in axis),
        (float(range[0]), float(range[1])),
        kp=float(kp),
        kv=float(round(kv, 4)),
        force=float(force),
        armature=float(armature),
        damping=float(damping),
        kind=kind,
    )


# Mirror images through the world XZ plane (y -> -y), for left/right symmetric robots.
# A mirrored body frame is R' = M R M with M = diag(1, -1, 1), a proper rotation, so a
# mirrored chain stays an ordinary MJCF chain: local offsets map by M, slide axes (true
# vectors) by M, and hinge axes (pseudovectors) by -M. The same joint values then give the
# mirrored pose: p' = M p and R' = M R M for every body and site.
_MIRROR = np.array([1.0, -1.0, 1.0])


def mirror_joint_xz(joint: JointSpec) -> JointSpec:
    """The joint of the mirror-image chain: same range and gains, mirrored axis."""
    axis = _MIRROR * np.asarray(joint.axis, dtype=float)
    if joint.kind == "hinge":
        axis = -axis
    return replace(joint, axis=tuple(float(a) + 0.0 for a in axis))


def mirror_segment_xz(segment: Segment) -> Segment:
    """The segment of the mirror-image chain."""
    return replace(segment, vector=tuple(float(v) + 0.0 for v in _MIRROR * np.asarray(segment.vector, dtype=float)))


def mirror_quat_xz(quat) -> np.ndarray:
    """Quaternion (w, x, y, z) of the mirrored frame M R M: (w, -x, y, -z)."""
    w, x, y, z = np.asarray(quat, dtype=float)
    return np.array([w, -x, y, -z]) + 0.0


def stiffen_for_gravity(
    model: mujoco.MjModel, joints: dict[str, JointSpec], ee_sites: Sequence[str], sag: float
) -> dict[str, JointSpec]:
    """Raise servo stiffness where needed so the home posture sags at most `sag` [m].

    A position servo holding gravity torque tau_j deflects by tau_j / kp_j, which moves an
    end effector by about s_j = a_j / kp_j with a_j = |tau_j| max_site |J_j| (J_j: column j
    of the site's position Jacobian), all at ``model.qpos0``. If sum_j s_j exceeds `sag`,
    the largest contributions are capped at a common level c with sum_j min(s_j, c) = sag
    and those joints get kp_j = a_j / c; joints already stiff enough keep their gains. kv
    follows `servo`'s rule; the force limit is raised to twice the home torque where it is
    lower, so every design holds its home posture with margin to move.

    joints: the specs to adjust, keyed by the model's joint name (other joints keep their
    gains and take no share of the budget). Returns the adjusted specs under the same keys.
    """
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)  # qpos0, zero velocity: qfrc_bias is the gravity load
    jacs = []
    for site in ee_sites:
        jacp = np.zeros((3, model.nv))
        mujoco.mj_jacSite(model, data, jacp, None, model.site(site).id)
        jacs.append(jacp)
    names = list(joints)
    dofs = [int(model.jnt_dofadr[model.joint(n).id]) for n in names]
    load = np.abs(data.qfrc_bias[dofs])
    a = load * np.array([max(float(np.linalg.norm(j[:, d])) for j in jacs) for d in dofs])
    s = a / np.array([joints[n].kp for n in names])
    cap = np.inf
    if s.sum() > sag:
        # Water-filling: with contributions sorted high to low, the cap that leaves the
        # k largest at c and the rest as they are is c = (sag - sum of the rest) / k.
        order = np.sort(s)[::-1]
        for k in range(1, len(order) + 1):
            cap = (sag - order[k:].sum()) / k
            if k == len(order) or cap >= order[k]:
                break
    out = {}
    for n, load_n, a_n, s_n in zip(names, load, a, s):
        spec = joints[n]
        kp = spec.kp if s_n <= cap else float(a_n / cap)
        out[n] = replace(
            spec,
            kp=float(kp),
            kv=float(round(2.0 * np.sqrt(kp * spec.armature), 4)),
            force=float(max(spec.force, 2.0 * load_n)),
        )
    return out
