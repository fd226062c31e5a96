"""Procedural design spaces, by name: ``get_space("viperx")``; the gravity-compensated
variants of the fixed-base ones (`tt.sim.designs.gravcomp`): ``get_space("viperx-gravcomp")``
or ``get_space("viperx", gravcomp=True)``."""

from __future__ import annotations

import importlib

from tt.sim.designs.base import (
    ContinuousParam,
    Design,
    DesignError,
    DesignSpace,
    DiscreteParam,
    FixedStructureSpace,
    load_designs,
    save_designs,
)
from tt.sim.designs.gravcomp import GRAVCOMP_BASES, gravcomp_name

#: space name -> (module, attribute) that defines it
_MODULES = {
    "viperx": ("tt.sim.designs.viperx", "SPACE"),
    "viperx-nominal": ("tt.sim.designs.viperx", "NOMINAL_SPACE"),
    "aloha": ("tt.sim.designs.aloha", "SPACE"),
    "bimanual": ("tt.sim.designs.bimanual", "SPACE"),
    "quadruped": ("tt.sim.designs.quadruped", "SPACE"),
}
#: gravity-compensated variant -> the space it compensates
_GRAVCOMP_OF = {gravcomp_name(base): base for base in GRAVCOMP_BASES}
_VARIANTS: dict[str, DesignSpace] = {}

SPACE_NAMES: tuple[str, ...] = tuple(_MODULES) + tuple(_GRAVCOMP_OF)


def get_space(name: str, *, gravcomp: bool = False) -> DesignSpace:
    """The design space called `name`; raises `DesignError` listing the valid names.

    gravcomp: the space's gravity-compensated variant (``get_space("viperx", gravcomp=True)``
    is ``get_space("viperx-gravcomp")``, `tt.sim.designs.gravcomp`); a variant's own name
    is returned as it is. Raises `DesignError` for a space without one (the quadruped, the
    mobile bimanual).
    """
    if not isinstance(name, str) or name not in SPACE_NAMES:
        raise DesignError(f"unknown design space {name!r}; valid: {list(SPACE_NAMES)}")
    if gravcomp and name not in _GRAVCOMP_OF:
        if name not in GRAVCOMP_BASES:
            raise DesignError(
                f"design space {name!r} has no gravity-compensated variant; the fixed-base arms do: "
                f"{list(GRAVCOMP_BASES)}"
            )
        name = gravcomp_name(name)
    if name in _GRAVCOMP_OF:
        if name not in _VARIANTS:
            from tt.sim.designs.gravcomp import GravcompSpace

            _VARIANTS[name] = GravcompSpace(get_space(_GRAVCOMP_OF[name]))
        return _VARIANTS[name]
    module, attribute = _MODULES[name]
    return getattr(importlib.import_module(module), attribute)


__all__ = [
    "ContinuousParam",
    "Design",
    "DesignError",
    "DesignSpace",
    "DiscreteParam",
    "FixedStructureSpace",
    "SPACE_NAMES",
    "get_space",
    "load_designs",
    "save_designs",
]
