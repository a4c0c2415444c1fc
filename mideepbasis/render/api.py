"""Rendering a whole material for people to look at: flash or environment, to EXR and PNG."""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from .. import constants, geometry
from ..configs import positive_int
from ..errors import InputError

#: The example material shipped with the package (a glazed tile), used by ``mideepbasis demo``.
EXAMPLE_MATERIAL = "example_material"


def example_material_dir() -> Path:
    """Folder of the bundled example material."""
    return Path(str(resources.files("mideepbasis") / "assets" / EXAMPLE_MATERIAL))


def example_capture_dir() -> Path:
    """Folder of the bundled example capture: ``photo.jpg``, ``truth/`` (its material) and ``truth.json``."""
    return Path(str(resources.files("mideepbasis") / "assets" / "example_capture"))


def _resized(maps: torch.Tensor, resolution: int | None) -> torch.Tensor:
    """(10, H, W) maps resampled to resolution x resolution (normals renormalised)."""
    if resolution is None or tuple(maps.shape[-2:]) == (resolution, resolution):
        return maps
    resized = torch.nn.functional.interpolate(maps[None], size=(resolution, resolution), mode="bilinear",
                                              align_corners=False, antialias=True)[0]
    resized[:3] = geometry.unit_vectors(resized[:3], dim=0)
    return resized


@dataclass(frozen=True)
class RenderConfig:
    """How ``mideepbasis render`` draws a material folder (``render_material``'s settings)."""

    light: str = field(default="flash", metadata={"choices": ("flash", "env")})
    """``flash``: the capture's flash; ``env``: the preview under an environment."""

    fov: float = constants.DEFAULT_FOV_DEG
    """Field of view of the flash camera [deg]."""

    offset: tuple[float, float] = field(default=(0.0, 0.0), metadata={"metavar": "TX,TY"})
    """Hand-held offset of camera and flash [patch half-widths]."""

    spp: int | None = field(default=None, metadata={"parse": positive_int})
    """Samples per pixel (path tracing); None: the flash's per-pixel formula, or the preview's default."""

    convention: str | None = field(default=None, metadata={"choices": constants.CONVENTIONS})
    """Shading convention (None: the material's own)."""

    env: str = field(default="studio", metadata={"metavar": "studio|sunsky|FILE"})
    """Environment of ``light`` env: ``studio``, ``sunsky`` or an EXR/HDR file."""

    resolution: int | None = field(default=None, metadata={"parse": positive_int})
    """Image size [pixels] (None: the material's for the flash, 256 for the environment)."""

    seed: int = 0
    """Seed of the path tracer."""

    shape: str = field(default="plane", metadata={"choices": constants.PREVIEW_SHAPES})
    """Object of ``light`` env: the sample on a table, a ball, or a cloth draped over one."""

    tiles: float = 2.0
    """Times the maps repeat across a sphere or cloth."""


def render_with(material, config: RenderConfig, progress: bool = True) -> np.ndarray:
    """``render_material`` with a ``RenderConfig``."""
    return render_material(material, light=config.light, fov=config.fov, offset=config.offset, spp=config.spp,
                           convention=config.convention, environment=config.env, resolution=config.resolution,
                           seed=config.seed, progress=progress, shape=config.shape, tiles=config.tiles)


def render_material(material, light: str = "flash", fov: float = constants.DEFAULT_FOV_DEG,
                    offset: tuple[float, float] = (0.0, 0.0), spp: int | None = None,
                    convention: str | None = None, environment: str = "studio", resolution: int | None = None,
                    seed: int = 0, progress: bool = True, shape: str = "plane", tiles: float = 2.0) -> np.ndarray:
    """Render a Material under the flash or in the environment preview.

    Args:
        material: the Material.
        light: ``flash`` (the capture) or ``env`` (the preview).
        fov: field of view of the flash camera [deg].
        offset: hand-held offset (tx, ty) of camera and flash [patch half-widths].
        spp: samples per pixel. For the flash, None renders the per-pixel formula of docs/ARCHITECTURE.md section 4
            exactly (no ray tracing) and a number path traces the flash scene.
        convention: shading convention; default the material's.
        environment: ``studio``, ``sunsky`` or an EXR/HDR file, for ``env``.
        resolution: output size [pixels]; default the material's width (flash) or 256 (env).
        seed: seed of the path tracer.
        progress: show a progress bar for long path-traced renders.
        shape: for ``env``: ``plane`` (the sample on a table), ``sphere`` or ``cloth``.
        tiles: for a sphere or cloth: how many times the maps repeat across it [count].

    Returns:
        linear radiance, (H, W, 3) float32.
    """
    from . import render_flash, scenes

    convention = convention or material.convention
    maps = material.to_tensor()
    if light == "env":
        scene = scenes.shape_scene(maps, shape=shape, environment=environment, tiles=tiles,
                                   spp=spp or constants.DEFAULT_SPP, resolution=resolution or constants.PREVIEW_RESOLUTION,
                                   convention=convention, rfilter=constants.PREVIEW_FILM_FILTER)
        return scenes.render_preview(scene, seed=seed, progress=progress)
    if shape != "plane":
        raise InputError(f"--shape {shape} needs --light env (the flash capture sees the sample plane)")
    if light != "flash":
        raise InputError(f"unknown light {light!r}: expected 'flash' or 'env'")
    angle = float(geometry.offset_angle_deg(torch.tensor(offset), fov))
    if angle > constants.MAX_OFFSET_DEG + 1e-6:
        import warnings
        warnings.warn(f"offset {offset} is {angle:.1f} deg from the centred capture, beyond the "
                      f"{constants.MAX_OFFSET_DEG} deg a hand-held capture reaches")
    if spp is not None:
        scene = scenes.flash_scene(maps, offset=offset, fov=fov, spp=spp, resolution=resolution, convention=convention)
        return scenes.render(scene, seed=seed, progress=progress)
    maps = _resized(maps, resolution)
    lights = geometry.light_positions(torch.tensor(offset, dtype=torch.float32), fov).view(1, 1, 3)
    with torch.no_grad():
        image = render_flash(maps[None], lights, fov=fov, convention=convention)
    return image[0, 0].permute(1, 2, 0).numpy()


def write_render(image: np.ndarray, exr_path: Path) -> tuple[Path, Path]:
    """Write a linear render as EXR and, beside it, as an 8-bit sRGB PNG (clipped); both atomic."""
    from ..imageio import write_image

    exr_path = Path(exr_path)
    png_path = exr_path.with_suffix(".png")
    write_image(exr_path, image)
    write_image(png_path, np.clip(image, 0.0, 1.0), encode_srgb=True)
    return exr_path, png_path
