"""Area resampling and blurring of images and material maps, shared by capture, training synthesis
and the reports: a photo and its maps are made smaller (and blurred) the same way wherever they are."""

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


def separable_filter(image: torch.Tensor, kernel: torch.Tensor, padding: str = "reflect") -> torch.Tensor:
    """(B, C, H, W) convolved by ``kernel`` (2k + 1,) along the rows and then the columns, the
    edges extended by torch's ``padding`` (``reflect``, ``replicate``, or ``constant``: zeros)."""
    radius = kernel.shape[0] // 2
    kernel = kernel.to(image).view(1, 1, 1, -1).expand(image.shape[1], 1, 1, -1)
    padded = F.pad(image, (radius, radius, 0, 0), mode=padding)
    image = F.conv2d(padded, kernel, groups=image.shape[1])
    padded = F.pad(image, (0, 0, radius, radius), mode=padding)
    return F.conv2d(padded, kernel.transpose(-1, -2), groups=image.shape[1])


def gaussian_blur(image: torch.Tensor, sigma: float, padding: str = "reflect", radius: int | None = None) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W).

    Args:
        sigma: the Gaussian's standard deviation [pixels].
        padding: how the edges are extended, torch's ``reflect`` or ``replicate``.
        radius: taps each side of the centre [pixels]; default ``max(1, int(3 * sigma))``.
    """
    radius = max(1, int(3 * sigma)) if radius is None else radius
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-(offsets**2) / (2 * sigma**2))
    return separable_filter(image, kernel / kernel.sum(), padding)
