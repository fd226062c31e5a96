"""Procedural design spaces, by name: ``get_space("viperx")``."""

from __future__ import annotations

import importlib

from tt.sim.designs.base import (
    ContinuousParam,
    Design,
    DesignError,
    DesignSpace,
    DiscreteParam,
    load_designs,
    save_designs,
)

#: space name -> module that defines ``SPACE``
_MODULES = {
    "viperx": "tt.sim.designs.viperx",
    "aloha": "tt.sim.designs.aloha",
    "bimanual": "tt.sim.designs.bimanual",
    "quadruped": "tt.sim.designs.quadruped",
}

SPACE_NAMES: tuple[str, ...] = tuple(_MODULES)


def get_space(name: str) -> DesignSpace:
    """The design space called `name`; raises `DesignError` listing the valid names."""
    if not isinstance(name, str) or name not in _MODULES:
        raise DesignError(f"unknown design space {name!r}; valid: {list(_MODULES)}")
    return importlib.import_module(_MODULES[name]).SPACE


__all__ = [
    "ContinuousParam",
    "Design",
    "DesignError",
    "DesignSpace",
    "DiscreteParam",
    "SPACE_NAMES",
    "get_space",
    "load_designs",
    "save_designs",
]
