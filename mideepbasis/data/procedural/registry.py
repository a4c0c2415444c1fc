"""The families of the procedural generator, by name: each turns a Canvas into a Surface."""

from __future__ import annotations

from collections.abc import Callable

from .core import Canvas, Surface

FamilyFunction = Callable[[Canvas], Surface]

#: Every registered family, by name, in registration order.
FAMILIES: dict[str, FamilyFunction] = {}


def family(name: str) -> Callable[[FamilyFunction], FamilyFunction]:
    """Register ``function`` as the family ``name`` (a decorator)."""

    def register(function: FamilyFunction) -> FamilyFunction:
        if name in FAMILIES:
            raise ValueError(f"procedural family {name!r} is registered twice")
        FAMILIES[name] = function
        return function

    return register
