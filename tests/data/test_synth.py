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


def test_network_input_by_hand():
    photo = torch.tensor([0.0, 1.0, 0.2]).view(1, 3, 1, 1)
    mark = torch.full((1, 3, 1, 1), 0.5)
    x = synth.network_input(photo, mark)[0, :, 0, 0]
    eps = synth.LOG_EPS
    log_02 = (math.log(0.2 + eps) - math.log(eps)) / (math.log(1 + eps) - math.log(eps))
    assert x.tolist() == pytest.approx([-1, 1, -0.6, -1, 1, 2 * log_02 - 1, 0, 0, 0], abs=1e-6)


def test_lighting_mark_is_the_reference_material_render():
    lights = geometry.light_positions(torch.tensor([[0.0, 0.0], [0.3, -0.2]]))
    mark = synth.lighting_mark(lights, 33, 33)
    expected = render_flash(geometry.lighting_mark_material(33, 33).expand(2, -1, -1, -1), lights.view(2, 1, 3),
                            backend="torch")[:, 0].clamp(0, 1)
    assert torch.allclose(mark, expected, atol=1e-5)
    # Diffuse 0.1, specular 0.5 at the centre under the centred flash: 0.1 + D(1) G(1)^2 F / 4 * pi,
    # D(1) = 1 / (pi alpha^2), G(1) = 1: clipped to 1 by the highlight.
    assert mark[0, :, 16, 16].tolist() == pytest.approx([1.0, 1.0, 1.0])
    assert mark[0, 0, 0, 0] < 0.2 and mark[1].argmax() != mark[0].argmax()


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


def test_flash_falloff_is_the_white_lambertian_of_the_physical_convention():
    from mideepbasis import constants, geometry
    from mideepbasis.data.synth import flash_falloff

    lights = geometry.light_positions(torch.tensor([[0.3, -0.2]]))
    falloff = flash_falloff(lights, 8, 8)
    points = geometry.pixel_points(8, 8)
    distance = torch.linalg.vector_norm(lights[0].view(3, 1, 1) - points, dim=0)
    height = constants.camera_height()
    # (1 / pi) cos * pi H^2 / d^2 with cos = H / d, for a flash at height H.
    torch.testing.assert_close(falloff[0, 0], (height / distance) ** 3, rtol=1e-5, atol=1e-6)


def test_extra_inputs_are_bounded_and_mean_what_they_say():
    from mideepbasis.data.synth import extra_input_channels, network_input

    photo = torch.rand(2, 3, 32, 32) * 0.8
    falloff = torch.full((2, 1, 32, 32), 0.5)
    channels = extra_input_channels(photo, ("shading", "highpass"), falloff)
    assert channels.shape == (2, 6, 32, 32) and channels.abs().max() <= 1.0
    # shading: a photo equal to the falloff (a white Lambertian) gives a ratio of 1 everywhere.
    flat = extra_input_channels(falloff.expand(2, 3, 32, 32), ("shading",), falloff)
    assert torch.allclose(flat, flat[0, 0, 0, 0].expand_as(flat))
    # highpass: a constant photo has no detail.
    assert extra_input_channels(torch.full((1, 3, 16, 16), 0.3), ("highpass",)).abs().max() < 1e-5
    inputs = network_input(photo, torch.rand(2, 3, 32, 32), ("shading", "highpass"), falloff)
    assert inputs.shape == (2, 15, 32, 32)
    assert torch.equal(inputs[:, :9], network_input(photo, inputs[:, 6:9] * 0.5 + 0.5))
