"""`chain_xml`'s robots compiled straight to tree-model fields: MuJoCo's compiler arithmetic
for a serial chain of primitive geoms, batched over designs.

A batched rollout of N random designs spends most of its setup compiling N MJCF texts
(about 2.4 ms a design here), although within one topology only a few numbers change from
design to design: the base pose, the joint axes, the link vectors. `chain_fields` takes
one compiled design of the topology (the template, read by `tt.kernels.model.tree_fields`)
and recomputes, for all N designs at once with numpy, every field a chain's choices
change: body offsets and the base pose, joint axes, each link body's mass, center of mass
and principal inertia from its geoms (MuJoCo's primitive formulas, density
`LINK_DENSITY`), the end-effector site, and MuJoCo's ``dof_invweight0``. Fields the chain
does not change (gains, ranges, solver parameters, the base's own geoms) are the
template's. tests/test_chain_tree.py compares every field with MuJoCo's compile of the
same designs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from tt.kernels.model import TreeFields, dof_invweight0
from tt.kernels.rotations import mat_to_quat
from tt.sim.designs.mjcf import LINK_DENSITY

#: Link vectors shorter than this [m] carry no capsule (`chain_xml` skips them).
MIN_LINK = 1e-9


@dataclass(frozen=True)
class ChainBatch:
    """N chains of one shape, as `chain_xml` and the base body it hangs from describe them.

    base_pos: base body position in its parent's frame [m], (N, 3).
    base_quat: base body orientation (w, x, y, z), (N, 4).
    axes: joint axis of each joint in its body frame, (N, J, 3).
    vectors: segment vector of each joint's link [m], (N, J, 3) (the next body's offset;
        the last one places the end-effector site).
    radii: capsule radius of each link [m], (N, J).
    hinge: whether each joint is a hinge (hinges carry a motor housing), (J,).
    housing_radius: radius and half-height of the motor housing cylinders [m].
    """

    base_pos: np.ndarray
    base_quat: np.ndarray
    axes: np.ndarray
    vectors: np.ndarray
    radii: np.ndarray
    hinge: tuple[bool, ...]
    housing_radius: float = 0.03

    @property
    def count(self) -> int:
        return len(self.base_pos)

    def take(self, index: Sequence[int]) -> "ChainBatch":
        """The chains `index`, in that order."""
        index = np.asarray(index, dtype=np.int64)
        return replace(
            self,
            base_pos=self.base_pos[index],
            base_quat=self.base_quat[index],
            axes=self.axes[index],
            vectors=self.vectors[index],
            radii=self.radii[index],
        )


def _cylinder(radius: float, half_height: float, density: float) -> tuple[float, float, float]:
    """Mass, transverse and axial moment of inertia about the center of a solid cylinder."""
    mass = density * np.pi * radius**2 * 2.0 * half_height
    return mass, mass * (3.0 * radius**2 + (2.0 * half_height) ** 2) / 12.0, mass * radius**2 / 2.0


def _capsules(radius: np.ndarray, length: np.ndarray, density: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass, transverse and axial moment about the center of capsules (a cylinder of
    `length` capped by two hemispheres), elementwise."""
    cyl = density * np.pi * radius**2 * length
    sph = density * 4.0 / 3.0 * np.pi * radius**3
    # Each hemisphere's center of mass sits 3r/8 beyond its flat face, which is length/2
    # from the center; its own moment about that face is the sphere's, 2/5 m r^2.
    transverse = cyl * (3.0 * radius**2 + length**2) / 12.0 + sph * (
        0.4 * radius**2 + length**2 / 4.0 + 3.0 * length * radius / 8.0
    )
    axial = cyl * radius**2 / 2.0 + sph * 0.4 * radius**2
    return cyl + sph, transverse, axial


def _axial_tensor(axis: np.ndarray, transverse: np.ndarray, axial: np.ndarray) -> np.ndarray:
    """Inertia tensors of bodies symmetric about unit `axis` (..., 3), (..., 3, 3)."""
    outer = axis[..., :, None] * axis[..., None, :]
    eye = np.eye(3)
    return transverse[..., None, None] * (eye - outer) + axial[..., None, None] * outer


def _shift(mass: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Parallel-axis term m (|d|^2 I - d d^T) for point masses at `offset` (..., 3)."""
    return mass[..., None, None] * (
        np.einsum("...i,...i->...", offset, offset)[..., None, None] * np.eye(3)
        - offset[..., :, None] * offset[..., None, :]
    )


def principal_frames(tensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal moments (..., 3) and the frames (w, x, y, z) (..., 4) of symmetric inertia
    tensors (..., 3, 3); any frame of a degenerate tensor is as good as MuJoCo's."""
    moments, vecs = np.linalg.eigh(tensor)
    flip = np.linalg.det(vecs) < 0
    vecs[flip, :, 2] *= -1.0
    return moments, mat_to_quat(vecs)


def chain_fields(
    template: TreeFields,
    chains: ChainBatch,
    *,
    base_body: int,
    chain_bodies: Sequence[int],
    ee: int = 0,
    density: float = LINK_DENSITY,
) -> TreeFields:
    """The tree fields of N chains hanging from a base body, from one compiled template.

    template: the `TreeFields` of one design of the same topology (one entry); it supplies
        every field the chains do not change. base_body: the tree body of the base;
        chain_bodies: the tree body of each joint, base to tip (J,); ee: the end-effector
        index whose site ends the chain.
    Returns N entries.
    """
    n, J = chains.count, len(chain_bodies)
    if chains.axes.shape != (n, J, 3) or chains.vectors.shape != (n, J, 3) or chains.radii.shape != (n, J):
        raise ValueError(
            f"chains of {J} joints need axes and vectors (N, {J}, 3) and radii (N, {J}); got "
            f"{chains.axes.shape}, {chains.vectors.shape}, {chains.radii.shape}"
        )
    if chains.base_pos.shape != (n, 3) or chains.base_quat.shape != (n, 4):
        raise ValueError(
            f"base_pos and base_quat need shapes ({n}, 3) and ({n}, 4); got "
            f"{chains.base_pos.shape}, {chains.base_quat.shape}"
        )
    if template.count != 1:
        raise ValueError(f"the template has {template.count} entries; chain_fields needs one compiled design")
    topo = template.topology
    jointless = [b for b in chain_bodies if topo.body_dof[b] < 0]
    if jointless:
        raise ValueError(f"chain bodies {jointless} carry no joint; every chain body holds one")
    out = template.take(np.zeros(n, dtype=np.int64))
    v = {k: np.array(a, copy=True) for k, a in out.values.items()}
    v["body_pos"][:, base_body] = chains.base_pos
    v["body_quat"][:, base_body] = chains.base_quat / np.linalg.norm(chains.base_quat, axis=-1, keepdims=True)
    axes = chains.axes / np.linalg.norm(chains.axes, axis=-1, keepdims=True)
    offsets = np.concatenate([np.zeros((n, 1, 3)), chains.vectors[:, :-1]], axis=1)
    bodies = np.asarray(chain_bodies)
    v["body_pos"][:, bodies] = offsets
    v["dof_axis"][:, [topo.body_dof[b] for b in chain_bodies]] = axes

    # Each link body: a motor housing (hinges; a cylinder along the joint axis at the body's
    # origin) and a capsule from the origin along the segment vector.
    length = np.linalg.norm(chains.vectors, axis=-1)
    has_link = length > MIN_LINK
    cap_mass, cap_t, cap_a = _capsules(chains.radii, length, density)
    cap_mass = np.where(has_link, cap_mass, 0.0)
    direction = np.where(has_link[..., None], chains.vectors / np.maximum(length, MIN_LINK)[..., None], 0.0)
    cap_center = chains.vectors / 2.0
    hinge = np.asarray(chains.hinge, dtype=float)
    h_mass, h_t, h_a = _cylinder(chains.housing_radius, chains.housing_radius, density)
    house_mass = np.broadcast_to(h_mass * hinge, (n, J))
    mass = cap_mass + house_mass
    com = cap_mass[..., None] * cap_center / np.maximum(mass, 1e-300)[..., None]
    tensor = (
        np.where(has_link, 1.0, 0.0)[..., None, None] * _axial_tensor(direction, cap_t, cap_a)
        + _shift(cap_mass, cap_center - com)
        + hinge[None, :, None, None] * _axial_tensor(axes, np.full((n, J), h_t), np.full((n, J), h_a))
        + _shift(house_mass, -com)
    )
    moments, frames = principal_frames(tensor)
    v["body_mass"][:, bodies] = mass
    v["body_ipos"][:, bodies] = com
    v["body_iquat"][:, bodies] = frames
    v["body_inertia"][:, bodies] = moments
    v["ee_pos"][:, ee] = chains.vectors[:, -1]
    fields = TreeFields(topo, v)
    fields.values["dof_invweight0"] = dof_invweight0(fields)
    return fields


def chain_sizes(chains: ChainBatch) -> np.ndarray:
    """Each chain's share of `tt.sim.rewards.robot_size` [m], (N,): every geom's longest
    dimension, housings (2 r) and capsules (length + 2 r)."""
    length = np.linalg.norm(chains.vectors, axis=-1)
    links = np.where(length > MIN_LINK, length + 2.0 * chains.radii, 0.0).sum(axis=-1)
    return links + 2.0 * chains.housing_radius * float(np.sum(chains.hinge))


__all__ = ["ChainBatch", "chain_fields", "chain_sizes", "principal_frames"]
