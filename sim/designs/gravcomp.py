"""Gravity-compensated variants of the fixed-base spaces, as the paper's code evaluates its arms.

The paper's evaluation (repository dividurga/transformer-transformer, ``detokenize(...,
gravcomp=...)`` in ``t2/robotok/tokenizer.py``) builds every body of a fixed-base arm with
MuJoCo's ``gravcomp="1"`` and every joint with ``actuatorgravcomp="true"``: MuJoCo then
adds a force that cancels each body's weight (``qfrc_gravcomp``, minus gravity's
generalized force on those bodies), so the position servos track without holding the arm
up. ``actuatorgravcomp`` only books that force as actuation (``qfrc_actuator``) instead of a
passive force; with no joint-level actuator force limits (tt's robots have none) the motion
is the same, and the actuators' own forces (``actuator_force``, what the torque reward
reads) never include it.

A variant is a design space of its own, named ``<base>-gravcomp`` (`gravcomp_name`):
``viperx-gravcomp``, ``viperx-nominal-gravcomp``, ``aloha-gravcomp``. Its designs have the
base space's parameters, nominal design, rewards and motions; its MJCF is the base's with
the two attributes added, so every backend that reads MJCF (the oracle, MuJoCo C, MuJoCo-Warp)
and tt's Warp kernels (`tt.kernels.model.TreeArrays.body_gravcomp`) simulate the same
compensated robot. ``get_space("viperx", gravcomp=True)`` is ``get_space("viperx-gravcomp")``.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Sequence

import numpy as np

from tt.sim.designs.base import ContinuousParam, Design, DesignError, DesignSpace, DiscreteParam

if TYPE_CHECKING:
    from tt.sim.designs.trees import DesignTrees

#: Suffix of a gravity-compensated variant's name.
GRAVCOMP_SUFFIX = "-gravcomp"
#: The fixed-base spaces that have a gravity-compensated variant.
GRAVCOMP_BASES: tuple[str, ...] = ("viperx", "viperx-nominal", "aloha")
#: The compensated share of each body's weight (the paper's ``gravcomp="1"``: all of it).
GRAVCOMP = 1.0


def gravcomp_name(base: str) -> str:
    """The name of the gravity-compensated variant of space `base` ("viperx" -> "viperx-gravcomp")."""
    return base + GRAVCOMP_SUFFIX


def add_gravcomp(xml: str, gravcomp: float = GRAVCOMP) -> str:
    """MJCF text `xml` with ``gravcomp`` on every body and ``actuatorgravcomp="true"`` on
    every joint (defaults included), as the paper's detokenizer writes them. Raises
    `DesignError` where `xml` already sets either attribute."""
    if re.search(r"\b(gravcomp|actuatorgravcomp)\s*=", xml):
        raise DesignError("the MJCF already sets gravcomp or actuatorgravcomp; add_gravcomp adds them itself")
    xml = re.sub(r"<body(?=[\s/>])", f'<body gravcomp="{gravcomp:.17g}"', xml)
    return re.sub(r"<joint(?=[\s/>])", '<joint actuatorgravcomp="true"', xml)


class GravcompSpace(DesignSpace):
    """Space `base` with gravity compensation on every body (see the module docstring).

    base: a fixed-base space without contacts; gravcomp: the compensated share of each
    body's weight (`GRAVCOMP`).
    """

    def __init__(self, base: DesignSpace, gravcomp: float = GRAVCOMP):
        if base.has_contacts:
            raise DesignError(
                f"space {base.name!r} has contacts; gravity compensation variants are for fixed-base arms"
            )
        self.name = gravcomp_name(base.name)
        self.base = base
        self.gravcomp = float(gravcomp)
        self.has_contacts = base.has_contacts
        self.ee_count = base.ee_count
        self.motion_offset = base.motion_offset
        self.places_motions = base.places_motions

    @property
    def family(self) -> str:
        return self.base.family

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        return self.base.discrete_params(discrete)

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        return self.base.continuous_params(discrete)

    def nominal(self) -> Design:
        base = self.base.nominal()
        return Design(self.name, base.discrete, base.continuous)

    def _mjcf(self, discrete, values, options) -> str:
        return add_gravcomp(self.base._mjcf(discrete, values, options), self.gravcomp)

    def to_base(self, design: Design) -> Design:
        """The same design in `base` (the robot without compensation)."""
        self.validate(design)
        return Design(self.base.name, tuple(design.discrete), tuple(design.continuous))

    def from_base(self, design: Design) -> Design:
        """A design of `base` as a design of this variant (the same robot, compensated)."""
        self.base.validate(design)
        return Design(self.name, tuple(design.discrete), tuple(design.continuous))

    def trees(self, designs: Sequence[Design]) -> "DesignTrees | None":
        """`base`'s tree fields of the same robots with ``body_gravcomp`` set on every body
        (what `tt.kernels.model.tree_fields` reads from this space's compiled MJCF)."""
        from dataclasses import replace

        from tt.kernels.model import TreeFields

        designs = list(designs)
        self.validate_many(designs)
        out = self.base.trees([Design(self.base.name, tuple(d.discrete), tuple(d.continuous)) for d in designs])
        if out is None:
            return None
        groups = []
        for members, fields in out.groups:
            values = dict(fields.values)
            gravcomp = np.zeros_like(values["body_gravcomp"])
            gravcomp[:, 1:] = self.gravcomp
            values["body_gravcomp"] = gravcomp
            groups.append((members, TreeFields(fields.topology, values)))
        return replace(out, space=self.name, groups=tuple(groups))


__all__ = ["GRAVCOMP", "GRAVCOMP_BASES", "GRAVCOMP_SUFFIX", "GravcompSpace", "add_gravcomp", "gravcomp_name"]
