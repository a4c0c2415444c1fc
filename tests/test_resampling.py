"""The shared Gaussian blur against a direct 2D sum with explicit edge extension."""

import math

import numpy as np
import pytest
import torch

from mideepbasis.resampling import gaussian_blur


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
