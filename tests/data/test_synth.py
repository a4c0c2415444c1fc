"""Training-input synthesis: the offset distribution, the variation xi, the camera, the network input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mideepbasis import constants, geometry
from mideepbasis.data import synth
from mideepbasis.imageio import linear_to_srgb
from mideepbasis.render import render_flash


def random_maps(batch, size, seed=0):
    generator = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(batch, 3, size, size, generator=generator) * 0.3
                                           + torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1), dim=1)
    return torch.cat([normal, torch.rand(batch, 7, size, size, generator=generator)], 1)


def normal_cdf(x, sigma):
    return 0.5 * (1 + math.erf(x / (sigma * math.sqrt(2))))


def test_offsets_follow_the_clipped_normal_distribution():
    fov, delta = 45.0, constants.MAX_OFFSET_DEG
    offsets = synth.sample_offsets(40_000, torch.Generator().manual_seed(0), fov=fov)
    height = constants.camera_height(fov)
    angles = geometry.offset_angle_deg(offsets, fov)
    assert angles.max().item() <= delta + 1e-4
    # Per axis the angle is N(0, (delta/3)^2); radial clipping touches only the ~1.1% beyond 3 sigma.
    per_axis = torch.rad2deg(torch.atan(offsets / height)).flatten().numpy()
    sigma = delta / 3
    assert abs(per_axis.mean()) < 0.02 * sigma
    assert per_axis.std() == pytest.approx(sigma, rel=0.02)
    values = np.sort(per_axis)
    empirical = np.arange(1, len(values) + 1) / len(values)
    theoretical = np.array([normal_cdf(v, sigma) for v in values[::50]])
    ks = np.abs(empirical[::50] - theoretical).max()
    assert ks < 0.015, ks
    clipped = (angles > delta - 1e-3).float().mean().item()
    assert 0.005 < clipped < 0.02  # P(|angle| > 3 sigma) for a 2-D normal is exp(-4.5) = 1.1%


def test_variation_has_the_stated_properties():
    generator = torch.Generator().manual_seed(1)
    variation = synth.sample_variation(5000, generator)
    assert 0 <= variation.rotation.min() and variation.rotation.max() <= math.pi / 6
    assert variation.rotation.max() > 0.95 * math.pi / 6  # uniform over the whole range
    assert 0 <= variation.shift.min() and variation.shift.max() <= 0.3 and variation.shift.std(0).min() > 0.08
    assert variation.shift.shape == (5000, 7)  # a different shift for every channel

    maps = random_maps(4, 8)
    small = synth.Variation(rotation=variation.rotation[:4], shift=variation.shift[:4])
    varied = small.apply(maps)
    assert torch.allclose((varied[:, :3] ** 2).sum(1), torch.ones(4, 8, 8), atol=1e-5)  # normals stay unit
    assert torch.equal(varied[:, 2], maps[:, 2])  # a rotation about +z keeps the tilt
    assert varied[:, 3:].min() >= 0 and varied[:, 3:].max() <= 1
    # Uniform over the pixels: the same input value gives the same output value everywhere.
    flat = torch.full((1, 10, 4, 4), 0.5)
    out = synth.Variation(variation.rotation[:1], variation.shift[:1]).apply(flat)
    assert torch.allclose(out, out[..., :1, :1].expand_as(out))


def test_variation_by_hand_and_on_bases():
    variation = synth.Variation(rotation=torch.tensor([math.pi / 2]), shift=torch.full((1, 7), 0.25))
    maps = torch.zeros(1, 10, 1, 1)
    maps[0, 0] = 1.0  # normal +x
    maps[0, 3:] = 0.5
    varied = variation.apply(maps)[0, :, 0, 0]
    assert varied[:3].tolist() == pytest.approx([0.0, 1.0, 0.0], abs=1e-6)  # +x turned to +y
    assert varied[3:].tolist() == pytest.approx([(0.5 + 0.25) / 1.25] * 7)
    bases = maps[:, None, :, 0, 0].expand(1, 10, 10).contiguous()  # (B, N, 10): the same xi on bases
    assert torch.allclose(variation.apply(bases.transpose(1, 2)).transpose(1, 2)[0, 3], varied)


def test_photo_is_quantised_clipped_srgb():
    generator = torch.Generator().manual_seed(2)
    radiance = torch.rand(2, 3, 16, 16) * 1.5
    photo = synth.simulate_photo(radiance, generator)
    codes = linear_to_srgb(photo) * 255
    assert torch.allclose(codes, codes.round(), atol=2e-3)
    assert photo.min() >= 0 and photo.max() <= 1
    quiet = synth.SynthesisConfig(shot_noise=(1e-12, 1e-12), read_noise=(1e-12, 1e-12), quantize=False)
    gains = torch.ones(2, 3)
    assert torch.allclose(synth.simulate_photo(radiance, generator, quiet, gains=gains), radiance.clamp(0, 1), atol=1e-5)


def test_synthesize_renders_both_materials_under_the_same_flash():
    maps = random_maps(3, 32)
    config = synth.SynthesisConfig(shot_noise=(1e-12, 1e-12), read_noise=(1e-12, 1e-12), quantize=False,
                                   exposure_sigma=0.0, white_balance_sigma=0.0)
    batch = synth.synthesize(maps, torch.Generator().manual_seed(3), config)
    assert batch.inputs.shape == batch.varied_inputs.shape == (3, 9, 32, 32)
    assert batch.inputs.min() >= -1 and batch.inputs.max() <= 1
    assert torch.allclose(batch.varied_maps, batch.variation.apply(maps))
    expected = render_flash(batch.varied_maps, batch.lights.view(3, 1, 3), backend="torch")[:, 0].clamp(0, 1)
    assert torch.allclose(batch.varied_photos, expected, atol=1e-4)
    assert torch.equal(batch.inputs[:, 6:], batch.varied_inputs[:, 6:])  # one flash, one lighting mark


def _noiseless(**overrides):
    # Noise far below the tolerances (its ranges are log-uniform: they cannot be zero).
    return synth.SynthesisConfig(exposure_sigma=0.0, white_balance_sigma=0.0, shot_noise=(1e-14, 1e-14),
                                 read_noise=(1e-9, 1e-9), quantize=False, **overrides)


def test_supersampled_photos_are_the_pixel_centre_photos_of_a_smooth_material():
    # A uniform material photographed at twice the size and area-averaged must be the photo taken at
    # the small size (each small pixel's centre is the centre of its four sub-pixels): the same to
    # the curvature of the flash's smooth falloff over a sub-pixel.
    small = torch.zeros(2, 10, 16, 16)
    small[:, 2] = 1.0
    small[:, 3:6] = 0.6
    small[:, 6] = 0.7
    small[:, 7:10] = 0.04
    large = torch.nn.functional.interpolate(small, scale_factor=2, mode="nearest")
    plain = synth.synthesize(small, torch.Generator().manual_seed(4), _noiseless())
    supersampled = synth.synthesize(large, torch.Generator().manual_seed(4), _noiseless(supersample=2))
    assert supersampled.photos.shape == plain.photos.shape == (2, 3, 16, 16)
    torch.testing.assert_close(supersampled.offsets, plain.offsets)  # the same draws, in the same order
    torch.testing.assert_close(supersampled.maps, small, atol=1e-6, rtol=0)
    # 4e-4 seen; a downsample off by one large pixel gives 1e-2.
    torch.testing.assert_close(supersampled.photos, plain.photos, atol=1e-3, rtol=0)
    torch.testing.assert_close(supersampled.inputs, plain.inputs, atol=2e-3, rtol=0)


def test_supersampled_maps_are_area_averaged_with_unit_normals():
    large = random_maps(1, 32, seed=3)
    batch = synth.synthesize(large, torch.Generator().manual_seed(0), _noiseless(supersample=2))
    blocks = large.unfold(2, 2, 2).unfold(3, 2, 2).mean(dim=(-1, -2))  # (1, 10, 16, 16) by hand
    normal = blocks[:, :3] / blocks[:, :3].norm(dim=1, keepdim=True)
    torch.testing.assert_close(batch.maps[:, 3:], blocks[:, 3:], atol=1e-6, rtol=0)
    torch.testing.assert_close(batch.maps[:, :3], normal, atol=1e-6, rtol=0)
    assert batch.varied_maps.shape == batch.photos.shape[:1] + (10, 16, 16)


def test_supersample_is_checked():
    with pytest.raises(ValueError, match="at least 1"):
        synth.SynthesisConfig(supersample=0)
    with pytest.raises(ValueError, match="cannot be supersampled by 2"):
        synth.synthesize(torch.zeros(1, 10, 15, 15), torch.Generator(), synth.SynthesisConfig(supersample=2))
