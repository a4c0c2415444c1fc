"""The shared Gaussian blur against a direct 2D sum with explicit edge extension."""

import math

import numpy as np
import pytest
import torch

import torch.nn.functional as F

from mideepbasis import constants
from mideepbasis.resampling import downsample, gaussian_blur, upsample_maps


def _extended_index(index: np.ndarray, size: int, padding: str) -> np.ndarray:
    """Where a pixel index outside [0, size) reads from: mirrored without repeating the edge
    (``reflect``) or the edge itself (``replicate``)."""
    if padding == "replicate":
        return np.clip(index, 0, size - 1)
    period = 2 * (size - 1)
    index = np.abs(index) % period
    return np.where(index >= size, period - index, index)


def _reference_blur(image: np.ndarray, sigma: float, radius: int, padding: str) -> np.ndarray:
    """(H, W) blurred by the 2D sum over the (2 radius + 1)^2 taps exp(-(dx^2 + dy^2) / 2 sigma^2)."""
    height, width = image.shape
    rows, cols = np.arange(height), np.arange(width)
    total = np.zeros_like(image, dtype=np.float64)
    weights = 0.0
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            weight = math.exp(-(dx * dx + dy * dy) / (2 * sigma * sigma))
            source = image[np.ix_(_extended_index(rows + dy, height, padding), _extended_index(cols + dx, width, padding))]
            total += weight * source
            weights += weight
    return total / weights


@pytest.mark.parametrize("padding", ["reflect", "replicate"])
@pytest.mark.parametrize("sigma, radius", [(1.5, None), (1.5, 5), (0.7, None), (3.0, 4)])
def test_blur_matches_direct_sum(padding, sigma, radius):
    generator = torch.Generator().manual_seed(5)
    image = torch.rand(2, 3, 19, 23, generator=generator, dtype=torch.float64)
    blurred = gaussian_blur(image, sigma, padding=padding, radius=radius)
    taps = max(1, int(3 * sigma)) if radius is None else radius
    for batch in range(2):
        for channel in range(3):
            expected = _reference_blur(image[batch, channel].numpy(), sigma, taps, padding)
            np.testing.assert_allclose(blurred[batch, channel].numpy(), expected, rtol=0, atol=1e-12)


def test_default_radius_is_three_sigma_truncated():
    """A delta spreads exactly int(3 sigma) pixels each way (at least one)."""
    delta = torch.zeros(1, 1, 31, 31, dtype=torch.float64)
    delta[0, 0, 15, 15] = 1.0
    for sigma, reach in ((1.5, 4), (0.2, 1), (2.0, 6)):
        row = gaussian_blur(delta, sigma)[0, 0, 15]
        assert (row > 0).nonzero().flatten().tolist() == list(range(15 - reach, 16 + reach))


@pytest.mark.parametrize("shape, size", [((1, 3, 256, 256), 128), ((2, 10, 1024, 1024), 256), ((1, 3, 512, 384), (64, 96)),
                                         ((1, 10, 2048, 1024), 256), ((2, 4, 3, 96, 160), (24, 20))])
def test_downsampling_by_whole_factors_is_the_block_mean_and_torchs_area_resampling_to_the_bit(shape, size):
    torch.manual_seed(1)
    image = torch.rand(shape) * 3 - 1
    height, width = (size, size) if isinstance(size, int) else size
    small = downsample(image, size)
    flat = image.reshape(-1, *shape[-3:])
    area = F.interpolate(flat, size=(height, width), mode="area").reshape(*shape[:-2], height, width)
    assert torch.equal(small, area)
    blocks = image.reshape(*shape[:-2], height, shape[-2] // height, width, shape[-1] // width).mean(dim=(-3, -1))
    torch.testing.assert_close(small, blocks, atol=1e-6, rtol=0)
    if image.ndim == 4:
        assert torch.equal(downsample(image.contiguous(memory_format=torch.channels_last), size), area)


def test_downsampling_by_other_factors_is_torchs_area_resampling():
    image = torch.rand(1, 3, 100, 75)
    torch.testing.assert_close(downsample(image, 64), F.interpolate(image, size=(64, 64), mode="area"), atol=0, rtol=0)


def test_upsampled_maps_follow_a_linear_ramp_and_keep_unit_normals():
    # Bilinear interpolation between half-pixel centres is exact for a linear function: away from
    # the border, the maps of a ramp sampled at 32 px upsample to the ramp sampled at 64 px.
    def ramp(size):
        centres = (torch.arange(size, dtype=torch.float64) + 0.5) / size
        y, x = torch.meshgrid(centres, centres, indexing="ij")
        maps = torch.empty(1, 10, size, size, dtype=torch.float64)
        maps[0, constants.NORMAL] = F.normalize(torch.stack([0.3 * x - 0.1, 0.2 * y, torch.ones_like(x)]), dim=0)
        maps[0, constants.REFLECTANCE] = torch.stack([0.2 + 0.5 * x + 0.1 * y] * 7)
        return maps, x, y

    small, _, _ = ramp(32)
    big = upsample_maps(small, 64)
    truth, x, y = ramp(64)
    inner = (slice(None), slice(None), slice(1, -1), slice(1, -1))
    torch.testing.assert_close(big[:, constants.REFLECTANCE][inner], truth[:, constants.REFLECTANCE][inner])
    torch.testing.assert_close(big[:, constants.NORMAL].norm(dim=1),
                               torch.ones(1, 64, 64, dtype=torch.float64))
    # The normals' tilt is interpolated before renormalising: within 1e-3 of the ramp's own.
    assert (big[:, constants.NORMAL] - truth[:, constants.NORMAL])[inner].abs().max() < 1e-3
    assert upsample_maps(small, 32) is small and upsample_maps(small, (64, 96)).shape == (1, 10, 64, 96)
