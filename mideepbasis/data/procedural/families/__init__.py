"""The procedural families; importing this package registers all of them (see ``registry``)."""

from . import tiles  # noqa: F401
