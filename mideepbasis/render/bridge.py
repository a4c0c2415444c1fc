"""The only crossing between torch and drjit: ``dr.wrap`` around the per-pixel flash render.

Torch tensors are (B, C, H, W); the plugin's textures are (B*H, W, C). The layout changes
happen here, on the torch side of the crossing, so that torch's autograd handles them and
drjit sees contiguous textures. Gradients flow to all four maps and to the light positions.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import torch

from .. import constants
from .flash import FlashRenderer

_renderers: dict[str, FlashRenderer] = {}


def flash_renderer(convention: str) -> FlashRenderer:
    """The shared ``FlashRenderer`` of a convention (one plugin instance per convention)."""
    if convention not in constants.CONVENTIONS:
        raise ValueError(f"unknown shading convention {convention!r}; expected one of {constants.CONVENTIONS}")
    if convention not in _renderers:
        _renderers[convention] = FlashRenderer(convention)
    return _renderers[convention]


@dr.wrap(source="torch", target="drjit")
def _render_flash_drjit(normal, diffuse, roughness, specular, lights, views, intensity, batch, convention, extent):
    renderer = flash_renderer(convention)
    renderer.set_maps(normal, diffuse, roughness, specular)
    height, width = normal.shape[0] // batch, normal.shape[1]
    positions = dr.unravel(mi.Point3f, lights.array)
    viewpoints = None if views is None else dr.unravel(mi.Point3f, views.array)
    return renderer.render(positions, batch, height, width, mi.Float(intensity.array), viewpoints, extent)


@dr.wrap(source="torch", target="drjit")
def _mean_l1_drjit(normal, diffuse, roughness, specular, photo, lights, intensity, convention, extent):
    renderer = flash_renderer(convention)
    renderer.set_maps(normal, diffuse, roughness, specular)
    return renderer.mean_l1(dr.unravel(mi.Point3f, lights.array), photo, mi.Float(intensity.array), extent)


def release_memory() -> None:
    """Let go of the last render's textures and of drjit's cached allocations (which it keeps for
    the next kernel): after a large one-off render, such as a 4096 px capture's re-rendering."""
    for renderer in _renderers.values():
        renderer.release_maps()
    dr.flush_malloc_cache()


def _to_texture(maps: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) -> (B*H, W, C), contiguous."""
    batch, channels, height, width = maps.shape
    return maps.permute(0, 2, 3, 1).reshape(batch * height, width, channels).contiguous()


def render_flash(maps: torch.Tensor, lights: torch.Tensor, intensity: float,
                 convention: str = constants.DEFAULT_CONVENTION, views: torch.Tensor | None = None,
                 extent: float = 1.0) -> torch.Tensor:
    """Per-pixel flash render through the Mitsuba ``svbrdf`` plugin, differentiable in torch.

    Args:
        maps: (B, 10, H, W) float32 stacked [normal 3, diffuse 3, roughness 1, specular 3].
        lights: (B, K, 3) camera and flash positions [patch half-widths].
        views: (B, K, 3) viewpoints apart from the lights, or None (co-located).
        intensity: radiant intensity [W/sr] (``physical``) or lamp intensity (``deepbasis``).
        convention: ``physical`` or ``deepbasis``.

    Returns:
        linear radiance, (B, K, 3, H, W), on the device and with the dtype of ``maps``.
    """
    if maps.ndim != 4 or maps.shape[1] != constants.BASIS_CHANNELS:
        raise ValueError(f"maps must have shape (B, {constants.BASIS_CHANNELS}, H, W), got {tuple(maps.shape)}")
    if lights.ndim != 3 or lights.shape[0] != maps.shape[0] or lights.shape[2] != 3:
        raise ValueError(f"lights must have shape (B, K, 3) with B = {maps.shape[0]}, got {tuple(lights.shape)}")
    batch, n_lights = lights.shape[:2]
    normal, diffuse, roughness, specular = torch.split(maps.float(), [3, 3, 1, 3], dim=1)
    # The light tensor is always handed over so that its gradient exists whenever asked for.
    flat_views = None if views is None else views.float().reshape(batch * n_lights, 3)
    image = _render_flash_drjit(_to_texture(normal), _to_texture(diffuse), _to_texture(roughness),
                                _to_texture(specular), lights.float().reshape(batch * n_lights, 3), flat_views,
                                torch.tensor([float(intensity)], device=maps.device), batch, convention,
                                float(extent))
    return image.permute(0, 1, 4, 2, 3).to(maps.dtype)


def flash_l1(maps: torch.Tensor, photo: torch.Tensor, lights: torch.Tensor, intensity: float,
             convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> torch.Tensor:
    """Mean L1 between ``photo`` and the clipped flash render of ``maps`` under each light, the
    render and the reduction in one kernel of the ``svbrdf`` plugin (``FlashRenderer.mean_l1``).
    Not differentiable.

    Args:
        maps: (1, 10, H, W); photo: (1, 3, H, W) linear; lights: (K, 3) [patch half-widths].

    Returns:
        (K,).
    """
    if maps.ndim != 4 or maps.shape[:2] != (1, constants.BASIS_CHANNELS):
        raise ValueError(f"maps must have shape (1, {constants.BASIS_CHANNELS}, H, W), got {tuple(maps.shape)}")
    if photo.shape != (1, 3, *maps.shape[-2:]):
        raise ValueError(f"photo must have shape (1, 3, {maps.shape[-2]}, {maps.shape[-1]}), got {tuple(photo.shape)}")
    normal, diffuse, roughness, specular = torch.split(maps.detach().float(), [3, 3, 1, 3], dim=1)
    with torch.no_grad():
        return _mean_l1_drjit(_to_texture(normal), _to_texture(diffuse), _to_texture(roughness),
                              _to_texture(specular), _to_texture(photo.detach().float()),
                              lights.detach().float().reshape(-1, 3), torch.tensor([float(intensity)]),
                              convention, float(extent)).to(maps.dtype)
