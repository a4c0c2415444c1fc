"""``benchmarks/detail.py``'s shading_visibility: a matte surface's fine relief shows in its flash
photo as the first-order shading ``(l_xy / l_z) . dn_xy``, with slope 1."""

import torch

from mideepbasis import constants
from mideepbasis.evaluation import flash_photos

from ..helpers import benchmark_module, matte_egg_crate


def test_matte_relief_shows_with_slope_one():
    detail = benchmark_module("detail")
    maps = matte_egg_crate(256, cycles=24, slope=0.15)
    photos, lights = flash_photos(maps, torch.tensor([[0.3, -0.2]]), constants.DEFAULT_FOV_DEG, "physical", 1.0)
    seen = detail.shading_visibility(maps, photos, lights[0], band=64)
    assert seen["correlation"] > 0.9
    assert 0.85 < seen["slope"] < 1.15
    assert 0.3 < seen["along_light"] < 0.7
    assert abs(seen["explained"] - seen["correlation"] ** 2 * seen["along_light"]) < 1e-9
    # The shading shows the slope along the light; the window's filter integrates it into the height,
    # whose gradient gives back the slope across the light too: more than the pixel-wise estimate.
    assert seen["window_explained"] > 0.6
    assert seen["window_explained"] > seen["explained"] + 0.1


def test_the_window_oracle_explains_nothing_of_unrelated_contrast():
    detail = benchmark_module("detail")
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(256, 256, generator=generator)
    tilt = torch.randn(2, 256, 256, generator=generator)
    fine = torch.randn(2, 256, 256, generator=generator)
    assert abs(detail.window_explained(noise, tilt, fine)) < 0.05  # 676 taps fitted on 40,000 pixels


def test_a_swapped_reflectance_keeps_the_relief_and_takes_the_other_albedo():
    detail = benchmark_module("detail")
    relief = matte_egg_crate(32, cycles=4, slope=0.15)
    other = torch.rand(1, constants.BASIS_CHANNELS, 32, 32, generator=torch.Generator().manual_seed(5))
    swapped = detail.with_reflectance_of(relief, other)
    assert torch.equal(swapped[:, constants.NORMAL], relief[:, constants.NORMAL])
    assert torch.equal(swapped[:, constants.REFLECTANCE], other[:, constants.REFLECTANCE])
    # Under a plain albedo the egg-crate shows as before; under the other's noise its shading is swamped.
    lights = torch.tensor([[0.3, -0.2]])
    seen = {}
    for name, maps in (("plain", relief), ("swapped", swapped)):
        photos, flashes = flash_photos(maps, lights)
        seen[name] = detail.shading_visibility(maps, photos, flashes[0], band=8)["correlation"]
    assert seen["swapped"] < seen["plain"] - 0.3


def test_photo_jitter_is_a_seeded_relative_noise_of_the_asked_spread():
    detail = benchmark_module("detail")
    photos = torch.full((1, 3, 128, 128), 0.25)
    first = detail.jittered(photos, 1e-3, seed=7)
    relative = first / photos - 1.0
    assert abs(float(relative.std()) - 1e-3) < 5e-5  # 49,152 draws: the spread's error about 3e-6
    assert abs(float(relative.mean())) < 2e-5
    assert torch.equal(first, detail.jittered(photos, 1e-3, seed=7))
    assert not torch.equal(first, detail.jittered(photos, 1e-3, seed=8))
    assert torch.equal(detail.jittered(photos, 0.0, seed=7), photos)
