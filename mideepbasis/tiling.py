"""Seamless maps: a material made to wrap around its edges, all four maps alike.

The maps are cross-faded with a copy of themselves shifted by half their width, whose left and
right edges meet (the copy's left edge is the original's middle column, its right edge the column
just before it): near those edges the result is the shifted copy, inside it is the original, and
in between a smooth weight blends the two; then the same along the height. Nothing is blurred; the blend band shows both copies at once, as
texture tools' offset-and-blend does. Normals are blended as vectors and renormalised.

Shapes: maps (10, H, W) [normal 3, diffuse 3, roughness 1, specular 3].
"""

from __future__ import annotations

import torch

from . import constants
from .errors import InputError
from .geometry import unit_vectors

#: Smallest map side that can be made tileable [pixels]: the blend bands need room.
MIN_TILEABLE_SIZE = 32

#: Width of the blend band at each edge, as a fraction of the map's side.
DEFAULT_BAND = 0.25


def edge_weight(size: int, band: float = DEFAULT_BAND) -> torch.Tensor:
    """(size,) weight of the original along one axis: 0 at both ends, 1 inside, smoothstep between."""
    position = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    distance = torch.minimum(position, 1.0 - position) / band  # 0 at an edge, 1 at the band's inner end
    distance = distance.clamp(0.0, 1.0)
    return (distance * distance * (3.0 - 2.0 * distance)).float()


def make_tileable(maps: torch.Tensor, band: float = DEFAULT_BAND, source: str = "maps",
                  in_place: bool = False) -> torch.Tensor:
    """Maps (10, H, W) that wrap without a seam (see the module docstring); ``in_place``: written
    over ``maps`` (each channel is read whole before it is written), which is returned.

    Raises:
        InputError: maps smaller than ``MIN_TILEABLE_SIZE`` on a side.
    """
    height, width = maps.shape[-2:]
    if min(height, width) < MIN_TILEABLE_SIZE:
        raise InputError(f"{source}: {width}x{height} pixels is too small to make tileable "
                         f"(at least {MIN_TILEABLE_SIZE} a side)")
    if not 0.0 < band <= 0.5:
        raise InputError(f"tileable blend band must lie in (0, 0.5] of the size, got {band}")
    # One axis at a time: a copy shifted along both at once would bring its own seam (where the
    # original's top and bottom edges meet) into the side bands, where the copy is used.
    # Channel by channel: at 4096 px the ten channels' shifted copies and products would take 2 GB.
    blended = maps if in_place else torch.empty_like(maps)
    for channel in range(maps.shape[0]):
        value = maps[channel]
        for dim, size in ((-1, width), (-2, height)):
            weight = edge_weight(size, band).to(maps)
            weight = weight.view(1, size) if dim == -1 else weight.view(size, 1)
            value = weight * value + (1.0 - weight) * torch.roll(value, shifts=size // 2, dims=dim)
        blended[channel] = value
    blended[constants.NORMAL] = unit_vectors(blended[constants.NORMAL], dim=0)
    blended[constants.REFLECTANCE] = blended[constants.REFLECTANCE].clamp(0.0, 1.0)
    return blended


def tiled(image: torch.Tensor, count: int = 3) -> torch.Tensor:
    """``image`` (..., H, W) repeated ``count`` x ``count`` times."""
    return image.repeat(*([1] * (image.ndim - 2)), count, count)
