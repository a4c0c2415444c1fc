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

# torch's OpenMP workers spin after every parallel region, 300,000 turns by default: drjit's LLVM
# kernels then share the cores with spinning threads, which triples the time of a render between
# two torch ops on a small machine (benchmarks/render.py). Not spinning at all (passive waiting)
# makes every op of a network pass wake its threads: a capture's prediction took a quarter longer.
# A short spin serves both (measured on 2 cores; a user's own setting of either variable wins).
if "OMP_WAIT_POLICY" not in os.environ:
    os.environ.setdefault("GOMP_SPINCOUNT", "1000")

from .startup import collection_paused, deferring_command, tracing_modules_deferred  # noqa: E402

with collection_paused(), tracing_modules_deferred(deferring_command()):  # torch's import among them
    from .errors import InputError, MideepbasisError  # noqa: E402
    from .imageio import ImageIOError, read_image, write_image  # noqa: E402
    from .material import Material, MaterialError  # noqa: E402

__version__ = "0.1.0"

__all__ = ["Material", "MaterialError", "ImageIOError", "InputError", "MideepbasisError", "read_image",
           "write_image", "render_material", "render_flash", "load_model", "capture", "__version__"]

# Loaded on first use: these import torch's network, drjit and Mitsuba, which take a moment to start.
_LAZY = {"render_material": "mideepbasis.render.api", "render_flash": "mideepbasis.render",
         "load_model": "mideepbasis.model.checkpoint", "capture": "mideepbasis.capturing.pipeline"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mideepbasis' has no attribute {name!r}")
