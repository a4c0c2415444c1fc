"""Area resampling of images and material maps, shared by capture, training synthesis and the
reports: a photo and its maps are made smaller the same way wherever they are."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from . import constants
from .geometry import unit_vectors


def downsample(image: torch.Tensor, size: int | tuple[int, int]) -> torch.Tensor:
    """Area-average (..., C, H, W) to size x size, or to (height, width) (no-op when already there)."""
    height, width = (size, size) if isinstance(size, int) else size
    if tuple(image.shape[-2:]) == (height, width):
        return image
    shape = image.shape
    flat = image.reshape(-1, *shape[-3:])
    return F.interpolate(flat, size=(height, width), mode="area").reshape(*shape[:-2], height, width)


def downsample_maps(maps: torch.Tensor, size: int | tuple[int, int]) -> torch.Tensor:
    """Maps (B, 10, H, W) area-averaged to size x size (or (height, width)), their normals renormalised."""
    small = downsample(maps, size)
    return torch.cat([unit_vectors(small[:, constants.NORMAL], dim=1), small[:, constants.REFLECTANCE]], dim=1)
