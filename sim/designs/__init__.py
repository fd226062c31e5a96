"""Procedural design spaces, by name: ``get_space("viperx")``."""

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

#: space name -> (module, attribute) that defines it
_MODULES = {
    "viperx": ("tt.sim.designs.viperx", "SPACE"),
    "viperx-nominal": ("tt.sim.designs.viperx", "NOMINAL_SPACE"),
    "aloha": ("tt.sim.designs.aloha", "SPACE"),
    "bimanual": ("tt.sim.designs.bimanual", "SPACE"),
    "quadruped": ("tt.sim.designs.quadruped", "SPACE"),
}

SPACE_NAMES: tuple[str, ...] = tuple(_MODULES)


def get_space(name: str) -> DesignSpace:
    """The design space called `name`; raises `DesignError` listing the valid names."""
    if not isinstance(name, str) or name not in _MODULES:
        raise DesignError(f"unknown design space {name!r}; valid: {list(_MODULES)}")
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
