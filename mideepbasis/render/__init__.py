"""Rendering: the one place that picks the Mitsuba variant, finds LLVM and registers plugins.

Importing this package

1. makes sure drjit's LLVM backend gets a compatible ``libLLVM`` (drjit 1.5 aborts the
   process with LLVM 15 and 16, and cannot load LLVM 14 or older): ``DRJIT_LIBLLVM_PATH``
   is set to the newest compatible library found when it is unset, and a clear
   ``LLVMNotFoundError`` is raised where only incompatible ones exist;
2. sets the Mitsuba variant, unless one is set already: ``$MIDEEPBASIS_VARIANT`` if given,
   else ``cuda_ad_rgb`` where torch sees a CUDA device, else ``llvm_ad_rgb``;
3. registers the ``svbrdf`` BSDF plugin.

Where Mitsuba is not installed (a training machine that has only torch, such as a lent GPU
server), the package still imports: the ``torch`` backend of ``render_flash`` works, and the
``mitsuba`` backend raises ``MitsubaMissingError`` naming the fix. ``set_render_backend``
chooses the backend that calls without an explicit ``backend`` use (``mitsuba`` by default).
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import os
import re
import sys
from pathlib import Path

from .. import constants
from ..errors import MideepbasisError
from ..startup import collection_paused

#: Oldest LLVM major version drjit 1.5 runs with here; 15 and 16 crash it, 14 does not load.
MIN_LLVM_MAJOR = 17

#: Folders searched for libLLVM, in order (Debian/Ubuntu multiarch, Fedora, Homebrew, ...).
LLVM_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
    "/usr/local/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib",
)

_LLVM_NAME = re.compile(r"^libLLVM(?:-(\d+))?(?:\.so|\.dylib)(?:\.(\d+))?(?:\.[\d.]+)?$")

_FIX = "install LLVM 19 (Debian/Ubuntu: `apt-get install libllvm19`) or set DRJIT_LIBLLVM_PATH to a libLLVM of version 17 or newer"


class LLVMNotFoundError(MideepbasisError):
    """No libLLVM that drjit's LLVM backend can use was found."""


class MitsubaMissingError(MideepbasisError):
    """The ``mitsuba`` render backend was asked for where Mitsuba is not installed."""


#: Backends of ``render_flash``: the ``svbrdf`` plugin through the bridge, or the torch reference.
RENDER_BACKENDS = ("mitsuba", "torch")

_default_backend = "mitsuba"


def set_render_backend(name: str) -> None:
    """Choose the backend of every ``render_flash`` call that names none (training on a GPU
    machine without Mitsuba uses ``torch``)."""
    global _default_backend
    if name not in RENDER_BACKENDS:
        raise ValueError(f"unknown render backend {name!r}; expected one of {RENDER_BACKENDS}")
    if name == "mitsuba":
        _require_mitsuba()
    _default_backend = name


def _require_mitsuba() -> None:
    if _MITSUBA_MISSING is not None:
        raise MitsubaMissingError(f"the mitsuba render backend needs Mitsuba 3 ({_MITSUBA_MISSING}); "
                                  "install the package's dependencies or choose the torch backend")


def render_backend() -> str:
    """The backend ``render_flash`` uses when a call names none."""
    return _default_backend


def llvm_major_version(path: str | os.PathLike) -> int | None:
    """Major LLVM version of a libLLVM file, read from its (resolved) name; None if unknown."""
    for candidate in (Path(path), Path(os.path.realpath(path))):
        match = _LLVM_NAME.match(candidate.name)
        if match and (match.group(1) or match.group(2)):
            return int(match.group(1) or match.group(2))
    return None


def find_libllvm(search_dirs=LLVM_SEARCH_DIRS) -> list[tuple[int, Path]]:
    """All libLLVM libraries in ``search_dirs`` and ``/usr/lib/llvm-*/lib``, newest first.

    Returns:
        (major version, path) pairs, one per version.
    """
    folders = [Path(d) for d in search_dirs]
    folders += sorted(Path("/usr/lib").glob("llvm-*/lib")) if tuple(search_dirs) == LLVM_SEARCH_DIRS else []
    found: dict[int, Path] = {}
    for folder in folders:
        if not folder.is_dir():
            continue
        for entry in sorted(folder.iterdir()):
            if _LLVM_NAME.match(entry.name) and entry.exists():
                version = llvm_major_version(entry)
                if version is not None and version not in found:
                    found[version] = entry
    return sorted(found.items(), reverse=True)


def ensure_llvm(search_dirs=LLVM_SEARCH_DIRS) -> Path:
    """Point drjit at a compatible libLLVM, or raise ``LLVMNotFoundError`` naming the fix.

    Returns:
        the library drjit will load.
    """
    chosen = os.environ.get("DRJIT_LIBLLVM_PATH")
    if chosen:
        if not Path(chosen).is_file():
            raise LLVMNotFoundError(f"DRJIT_LIBLLVM_PATH={chosen} does not exist: {_FIX}")
        version = llvm_major_version(chosen)
        if version is not None and version < MIN_LLVM_MAJOR:
            raise LLVMNotFoundError(f"DRJIT_LIBLLVM_PATH={chosen} is LLVM {version}, which drjit 1.5 cannot use: {_FIX}")
        return Path(chosen)
    found = find_libllvm(search_dirs)
    compatible = [(version, path) for version, path in found if version >= MIN_LLVM_MAJOR]
    if not compatible:
        seen = ", ".join(f"LLVM {version} ({path})" for version, path in found) or "no libLLVM at all"
        raise LLVMNotFoundError(f"found {seen}, none usable by drjit 1.5: {_FIX}")
    os.environ["DRJIT_LIBLLVM_PATH"] = str(compatible[0][1])
    return compatible[0][1]


def _choose_variant() -> str:
    requested = os.environ.get("MIDEEPBASIS_VARIANT")
    if requested:
        return requested
    try:
        import torch
        if torch.cuda.is_available():
            return "cuda_ad_rgb"
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    return "llvm_ad_rgb"


#: Set to ``1`` (the console command does), Mitsuba's switch to the variant leaves out its Python
#: AD integrators (``prb``, ``prb_projective``, ...), which nothing in mideepbasis uses: importing
#: them parses their source for ``dr.syntax``, 0.06 - 0.1 s of every command on two cores.
#: A program of its own that renders with them keeps the default.
SKIP_PYTHON_INTEGRATORS = constants.SKIP_MITSUBA_PYTHON_INTEGRATORS_ENV

_PYTHON_INTEGRATORS = "mitsuba.python.ad.integrators"


class _SkippedModule(importlib.abc.Loader, importlib.abc.MetaPathFinder):
    """A finder whose module ``_PYTHON_INTEGRATORS`` runs nothing when (re)loaded."""

    def find_spec(self, name, path, target=None):
        return importlib.machinery.ModuleSpec(name, self, is_package=True) if name == _PYTHON_INTEGRATORS else None

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        pass


def _set_variant(mi, variant: str) -> None:
    """``mi.set_variant``; with ``SKIP_PYTHON_INTEGRATORS`` set, without the reload of the Python
    integrators that Mitsuba does on a switch to an LLVM or CUDA variant."""
    if os.environ.get(SKIP_PYTHON_INTEGRATORS) != "1":
        mi.set_variant(variant)
        return
    finder = _SkippedModule()
    sys.meta_path.insert(0, finder)
    try:
        mi.set_variant(variant)
    finally:
        sys.meta_path.remove(finder)


def _initialise() -> None:
    import mitsuba as mi

    if mi.variant() is None:
        variant = _choose_variant()
        if variant.startswith("llvm"):
            ensure_llvm()
        _set_variant(mi, variant)


with collection_paused():  # drjit's and Mitsuba's imports
    try:
        import mitsuba as _mitsuba  # noqa: F401
    except ImportError as _error:  # only the torch backend is available
        _MITSUBA_MISSING: ImportError | None = _error
    else:
        _MITSUBA_MISSING = None
        _initialise()
        from . import bsdf  # noqa: E402, F401  (registers the plugin once the variant is set)


def _flash_settings(fov, convention, intensity, backend) -> tuple[str, float, str]:
    """The convention, intensity and backend of a flash render call, defaults filled in and the backend checked."""
    from .. import constants, geometry

    convention = convention or constants.DEFAULT_CONVENTION
    backend = backend or _default_backend
    if intensity is None:
        intensity = geometry.flash_intensity(fov or constants.DEFAULT_FOV_DEG, convention)
    if backend not in RENDER_BACKENDS:
        raise ValueError(f"unknown render backend {backend!r}; expected one of {list(RENDER_BACKENDS)}")
    return convention, intensity, backend


def render_flash(maps, lights, *, fov: float | None = None, convention: str | None = None,
                 intensity: float | None = None, backend: str | None = None, views=None, extent: float = 1.0):
    """The flash renderer every part of the pipeline calls: per pixel, batched, differentiable.

    Args:
        maps: (B, 10, H, W) torch tensor [normal 3, diffuse 3, roughness 1, specular 3].
        lights: (B, K, 3) co-located camera and flash positions [patch half-widths].
        fov: field of view [deg] that sets the default intensity (default 45).
        convention: ``physical`` (default) or ``deepbasis``.
        intensity: radiant intensity [W/sr]; default ``geometry.flash_intensity(fov, convention)``.
        backend: ``mitsuba`` (the ``svbrdf`` plugin through the bridge) or ``torch`` (the
            independent reference, for cross-checks and machines without Mitsuba); None: the
            one ``set_render_backend`` chose (``mitsuba`` unless changed).
        views: (B, K, 3) viewpoints apart from the lights (re-rendering metrics), or None: the
            camera sits at the light, as in a flash capture.
        extent: half-width of the framed sample [patch half-widths] (1 here; the authors'
            networks see 384 / 383).

    Returns:
        linear radiance, (B, K, 3, H, W).
    """
    from . import reference

    convention, intensity, backend = _flash_settings(fov, convention, intensity, backend)
    if backend == "torch":
        return reference.render_flash(maps, lights, intensity, convention, views=views, extent=extent)
    _require_mitsuba()
    from . import bridge

    return bridge.render_flash(maps, lights, intensity, convention, views=views, extent=extent)


#: Side of the square tiles ``render_flash_tiled`` renders a large image in [pixels].
RENDER_TILE = 1024


def render_flash_tiled(maps, light, *, fov: float | None = None, convention: str | None = None,
                       extent: float = 1.0, tile: int = RENDER_TILE):
    """``render_flash`` of one material under one co-located flash, without gradients, in square
    tiles of ``tile`` pixels where the image is a square of whole tiles: the render's own memory
    (1.6 GB at 4096 px at once) stays that of one tile. Exact: the flash and the camera are moved
    by minus the tile's centre and the tile framed as a sample of its own (``extent`` scaled), and
    a pixel's radiance depends only on its maps and its offsets to the light and camera.

    Args:
        maps: (1, 10, N, N) or (1, 10, H, W); light: (3,) [patch half-widths].

    Returns:
        linear radiance, (3, H, W).
    """
    import torch

    height, width = maps.shape[-2:]
    light = torch.as_tensor(light, dtype=torch.float32).view(1, 1, 3)
    with torch.no_grad():
        if height != width or height <= tile or height % tile:
            return render_flash(maps, light, fov=fov, convention=convention, extent=extent)[0, 0]
        count = height // tile
        image = torch.empty(3, height, width)
        tile_extent = extent / count
        for row in range(count):
            for col in range(count):
                centre = torch.tensor([extent * (-1 + (2 * col + 1) / count), extent * (1 - (2 * row + 1) / count), 0.0])
                rows, cols = slice(row * tile, (row + 1) * tile), slice(col * tile, (col + 1) * tile)
                image[:, rows, cols] = render_flash(maps[..., rows, cols], light - centre, fov=fov,
                                                    convention=convention, extent=tile_extent)[0, 0]
    return image


def release_memory() -> None:
    """Free what the Mitsuba renderer holds of the last render (``bridge.release_memory``);
    nothing to do for the torch backend or before Mitsuba is loaded."""
    import sys

    bridge = sys.modules.get(f"{__name__}.bridge")
    if bridge is not None:
        bridge.release_memory()


def flash_l1(maps, photo, lights, *, fov: float | None = None, convention: str | None = None,
             intensity: float | None = None, backend: str | None = None, extent: float = 1.0):
    """Mean L1 between a photo and the clipped flash render of one material under each of K
    lights: the lighting search's objective. The ``mitsuba`` backend renders and reduces in one
    kernel of the plugin (no K images are made); ``torch`` is ``render_flash``'s reference and a
    mean. Not differentiable.

    Args:
        maps: (1, 10, H, W); photo: (1, 3, H, W) linear; lights: (K, 3) [patch half-widths].
        fov, convention, intensity, backend, extent: as ``render_flash``.

    Returns:
        (K,).
    """
    from . import reference

    convention, intensity, backend = _flash_settings(fov, convention, intensity, backend)
    if backend == "torch":
        import torch

        errors = []
        with torch.no_grad():
            for chunk in lights.split(64):  # 64 lights' images at a time
                rendered = reference.render_flash(maps, chunk[None], intensity, convention, extent=extent)[0]
                errors.append((rendered.clamp(0.0, 1.0) - photo).abs().mean(dim=(1, 2, 3)))
        return torch.cat(errors)
    _require_mitsuba()
    from . import bridge

    return bridge.flash_l1(maps, photo, lights, intensity, convention, extent=extent)
