"""MJCF building blocks shared by tt's design spaces: serial chains of primitive geoms.

Masses and inertias are never written by hand: every geom carries a density and MuJoCo
derives body masses and inertias from the geometry, so they always follow the shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Effective density of links [kg/m^3]: aluminium tubes with motors, averaged over the
#: solid primitive volume; puts the nominal ViperX near its real 3.6 kg.
LINK_DENSITY = 1000.0


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


def chain_xml(prefix: str, joints: list[JointSpec], segments: list[Segment], ee_site: str,
              housing_radius: float = 0.03, indent: str = "    ") -> str:
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
                f'{pad}  <geom name="{prefix}{j.name}_motor" type="cylinder" size="{housing_radius!r} {housing_radius!r}" '
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
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def axis_angle_quat(axis, angle: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation by `angle` [rad] about `axis`."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
