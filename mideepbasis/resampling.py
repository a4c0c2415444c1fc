"""Area resampling and blurring of images and material maps, shared by capture, training synthesis
and the reports: a photo and its maps are made smaller (and blurred) the same way wherever they are."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from . import constants
from .geometry import unit_vectors


def downsample(image: torch.Tensor, size: int | tuple[int, int]) -> torch.Tensor:
    """Area-average (..., C, H, W) to size x size, or to (height, width) (no-op when already there).

    Where both sides shrink by whole factors, as nearly always here, torch's average pooling over
    those blocks: the same result as its adaptive (``area``) pooling to the bit (tested), and
    quicker on two AVX2 cores (10 x 1024 x 1024 to 256 px: 15 -> 12 ms, 3 x 1024 x 1024 to 512 px:
    15 -> 8 ms)."""
    height, width = (size, size) if isinstance(size, int) else size
    if tuple(image.shape[-2:]) == (height, width):
        return image
    shape = image.shape
    flat = image.reshape(-1, *shape[-3:])
    rows, columns = shape[-2] // height, shape[-1] // width
    if rows * height == shape[-2] and columns * width == shape[-1]:
        small = F.avg_pool2d(flat, (rows, columns))
    else:
        small = F.interpolate(flat, size=(height, width), mode="area")
    return small.reshape(*shape[:-2], height, width)


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
