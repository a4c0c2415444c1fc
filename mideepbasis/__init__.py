"""mideepbasis: SVBRDF capture from one hand-held flash photograph (DeepBasis, SIGGRAPH Asia 2023).

Public API::

    from mideepbasis import Material, capture, load_model, render_material
    material = Material.load("my_material/")
    image = render_material(material, light="env")          # (H, W, 3) linear, path traced
    model = load_model()                                    # the shipped DeepBasisNet

Rendering imports drjit and Mitsuba on first use (``mideepbasis.render``), not at import.
"""

from __future__ import annotations

import os

# torch's OpenMP workers spin after every parallel region by default; drjit's LLVM kernels then
# share the cores with spinning threads, which doubles the time of a render between two torch
# ops on a small machine. Passive waiting frees the cores at once (a user's own setting wins).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import InputError, MideepbasisError  # noqa: E402
from .imageio import ImageIOError, read_image, write_image  # noqa: E402
from .material import Material, MaterialError  # noqa: E402

__version__ = "0.1.0"

__all__ = ["Material", "MaterialError", "ImageIOError", "InputError", "MideepbasisError", "read_image",
           "write_image", "render_material", "render_flash", "load_model", "capture", "__version__"]

# Loaded on first use: these import drjit and Mitsuba, which take a moment to start.
_RENDERING = {"render_material": "mideepbasis.render.api", "render_flash": "mideepbasis.render",
              "load_model": "mideepbasis.model.checkpoint"}


def __getattr__(name):
    if name == "capture":  # the submodule, callable as its capture function (see capture/__init__.py)
        import importlib

        return importlib.import_module("mideepbasis.capture")
    if name in _RENDERING:
        import importlib

        return getattr(importlib.import_module(_RENDERING[name]), name)
    raise AttributeError(f"module 'mideepbasis' has no attribute {name!r}")
