"""Area resampling, bilinear upsampling and blurring of images and material maps, shared by capture,
training synthesis, the network's outputs and the reports: a photo and its maps are made smaller
(and blurred) the same way wherever they are."""

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


def upsample_maps(maps: torch.Tensor, size: int | tuple[int, int]) -> torch.Tensor:
    """Maps (B, 10, h, w) bilinearly to size x size (or (height, width)), their normals renormalised:
    a smaller capture's answer, plainly upsampled."""
    height, width = (size, size) if isinstance(size, int) else size
    if maps.shape[-2:] == (height, width):
        return maps
    big = upsample_bilinear(maps, height, width)
    return torch.cat([unit_vectors(big[:, constants.NORMAL], dim=1), big[:, constants.REFLECTANCE]], dim=1)


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


def upsample_bilinear(value: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(..., h, w) to (..., height, width), bilinear (half-pixel centres), every leading entry apart."""
    flat = value.reshape(value.shape[0], -1, *value.shape[-2:])
    big = F.interpolate(flat, size=(height, width), mode="bilinear", align_corners=False)
    return big.reshape(*value.shape[:-2], height, width)


def exact_in_bands(rows: int, height: int) -> bool:
    """Whether ``upsampled_rows`` can upsample ``rows`` rows to ``height``: the output rows' source
    positions, (y + 1/2) rows / height - 1/2, and so their weights, lose nothing to rounding when a
    band shifts them by whole input rows where ``height`` is a power-of-two multiple of ``rows``."""
    factor = height // rows
    return factor * rows == height and factor & (factor - 1) == 0


def upsampled_rows(value: torch.Tensor, height: int, width: int, start: int, stop: int) -> torch.Tensor:
    """Rows ``start:stop`` of ``upsample_bilinear(value, height, width)`` for (B, C, h, w) with
    ``exact_in_bands(h, height)``, interpolated from the input rows they need alone. The same
    weights times the same values, but torch's kernel does not always round its sums alike in
    outputs of other shapes: equal to float rounding (1e-7), to the bit for a band of every row."""
    rows = value.shape[-2]
    factor = height // rows
    # One input row more on each side: a band's first and last output rows interpolate from it.
    first, last = max(0, start // factor - 1), min(rows, -(-stop // factor) + 1)
    band = F.interpolate(value[..., first:last, :].contiguous(), size=((last - first) * factor, width),
                         mode="bilinear", align_corners=False)
    return band[..., start - first * factor:stop - first * factor, :]
