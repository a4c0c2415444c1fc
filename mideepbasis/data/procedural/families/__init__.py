"""The procedural families; importing this package registers all of them (see ``registry``)."""

from . import (  # noqa: F401
    ceramic, concrete, fabric, leather, metal, organic, paper, plastic, sparkle, stone, tiles, wood,
)
