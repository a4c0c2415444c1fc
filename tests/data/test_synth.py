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


# --- photos as phones take them (SynthesisConfig's phone levers) -----------------------------------


def test_the_phone_levers_are_off_by_default_and_draw_nothing():
    config = synth.SynthesisConfig()
    assert all(getattr(config, name) == getattr(synth.SynthesisConfig, name) for name in synth.PHONE_LEVERS)
    generator = torch.Generator().manual_seed(5)
    state = generator.get_state()
    assert synth.sample_fov(generator, config) == constants.DEFAULT_FOV_DEG
    assert torch.equal(generator.get_state(), state)
    drawing, reference = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    camera = synth.sample_camera(3, drawing, config)
    assert (camera.tone is None and camera.vignetting is None and camera.jpeg_quality is None
            and camera.white_point is None)
    torch.testing.assert_close(camera.gains, synth.sample_gains(3, reference, config))
    assert torch.equal(drawing.get_state(), reference.get_state())  # the gains' draws and nothing after


def test_fields_of_view_come_from_log_uniform_camera_distances():
    config = synth.SynthesisConfig(fov_range=(20.0, 75.0))
    generator = torch.Generator().manual_seed(0)
    fovs = np.array([synth.sample_fov(generator, config) for _ in range(4000)])
    assert 20.0 <= fovs.min() and fovs.max() <= 75.0
    heights = 1.0 / np.tan(np.radians(fovs) / 2.0)
    low, high = np.log(1.0 / math.tan(math.radians(37.5))), np.log(1.0 / math.tan(math.radians(10.0)))
    position = np.sort((np.log(heights) - low) / (high - low))  # uniform on [0, 1] if log-uniform
    assert np.abs(position - np.arange(1, len(position) + 1) / len(position)).max() < 0.03


def test_a_batch_is_photographed_at_its_drawn_field_of_view():
    maps = random_maps(2, 16)
    config = synth.SynthesisConfig(fov_range=(20.0, 75.0), quantize=False, shot_noise=(1e-12, 1e-12),
                                   read_noise=(1e-12, 1e-12))
    batch = synth.synthesize(maps, torch.Generator().manual_seed(2), config)
    assert 20.0 <= batch.fov <= 75.0 and abs(batch.fov - 45.0) > 1e-3
    # The lights stand at the camera's height for that field of view, the photo is their render.
    torch.testing.assert_close(batch.lights[:, 2], torch.full((2,), constants.camera_height(batch.fov)))
    gains = synth.sample_gains(2, torch.Generator().manual_seed(0), config)  # any gains: compare ratios
    expected = render_flash(maps, batch.lights.view(2, 1, 3), fov=batch.fov)[:, 0].clamp(0, 1)
    ratio = (batch.photos / expected.clamp(min=1e-3))[expected < 0.9]
    assert ratio.std() / ratio.mean() < 0.2, gains  # one gain per photo and channel, nothing else
    # The lighting mark of the input is the one of that field of view (the network reads it there).
    from mideepbasis.model.inputs import LIGHTING_MARK, lighting_mark

    mark = lighting_mark(batch.lights, 16, 16, batch.fov) * 2 - 1
    torch.testing.assert_close(batch.inputs[:, LIGHTING_MARK], mark)


def test_the_lighting_mark_tells_fields_of_view_apart():
    # The network knows the field of view only through the lighting mark (its input): the glossy
    # reference's highlight covers more of a narrow view (each pixel sees the flash closer to the
    # mirror direction), and the falloff to the corners is gentler.
    from mideepbasis.model.inputs import lighting_mark

    highlight, corners = [], []
    for fov in (20.0, 45.0, 75.0):
        light = torch.tensor([[0.0, 0.0, constants.camera_height(fov)]])
        mark = lighting_mark(light, 64, 64, fov)[0].mean(0)
        highlight.append((mark > 0.5).float().mean().item())
        corners.append(mark[0, 0].item())
    assert highlight[0] > 2 * highlight[1] > 4 * highlight[2] > 0
    assert corners[0] > corners[1] > corners[2]


def test_a_colour_cast_goes_into_the_diffuse_target_not_the_specular():
    maps = random_maps(3, 16)
    maps[:, constants.DIFFUSE] *= 0.5  # room for a cast without clipping
    config = synth.SynthesisConfig(cast_in_diffuse=True, white_balance_sigma=0.2, exposure_sigma=0.0,
                                   quantize=False, shot_noise=(1e-12, 1e-12), read_noise=(1e-12, 1e-12))
    batch = synth.synthesize(maps, torch.Generator().manual_seed(4), config)
    # The target keeps the specular and the normals; its diffuse is the material's times one cast.
    torch.testing.assert_close(batch.maps[:, constants.SPECULAR], maps[:, constants.SPECULAR])
    torch.testing.assert_close(batch.maps[:, constants.NORMAL], maps[:, constants.NORMAL])
    cast = (batch.maps[:, constants.DIFFUSE] / maps[:, constants.DIFFUSE]).mean(dim=(2, 3))
    assert cast.std(dim=1).min() > 0.02  # a real colour cast
    torch.testing.assert_close(torch.log(cast).mean(1), torch.zeros(3), atol=1e-5, rtol=0)  # no brightness
    # The photo is the material itself seen through that cast: diffuse and highlight alike.
    # (times one brightness per photo: the white balance's mean gain, as exposure).
    seen = render_flash(maps, batch.lights.view(3, 1, 3))[:, 0] * cast.view(3, 3, 1, 1)
    keep = (seen < 0.8).all(dim=1, keepdim=True).expand_as(seen)
    for photo, expected, mask in zip(batch.photos, seen, keep):
        brightness = (photo[mask] * expected[mask]).sum() / (expected[mask] ** 2).sum()
        assert abs(brightness.item() - 1.0) < 0.5
        torch.testing.assert_close(photo[mask], brightness * expected[mask], atol=2e-4, rtol=1e-3)


def test_tone_curve_keeps_black_grey_white_and_order():
    values = torch.linspace(0, 1, 101)
    for strength in (0.0, 0.3, 1.0):
        curve = synth.tone_curve(values, torch.tensor(strength))
        torch.testing.assert_close(curve[[0, 50, 100]], torch.tensor([0.0, 0.5, 1.0]))
        assert (curve.diff() >= 0).all()
    torch.testing.assert_close(synth.tone_curve(values, torch.tensor(0.0)), values)
    strong = synth.tone_curve(values, torch.tensor(1.0))
    assert strong[25] < values[25] and strong[75] > values[75]  # shadows darker, highlights brighter


def test_highlight_compression_keeps_mid_grey_maps_its_white_point_to_one_and_is_off_at_one():
    values = torch.tensor([0.0, 0.02, 0.18, 0.5, 1.0, 3.0, 10.0])
    torch.testing.assert_close(synth.compress_highlights(values, torch.tensor(1.0)), values)
    for white in (2.0, 8.0):
        # The reference gain: bisection on y(g m) = m, the extended Reinhard curve written out.
        def curve(x):
            return x * (1 + x / white**2) / (1 + x)

        low, high = 1.0, 2.0
        for _ in range(60):
            gain = 0.5 * (low + high)
            low, high = (gain, high) if curve(gain * 0.18) < 0.18 else (low, gain)
        compressed = synth.compress_highlights(values, torch.tensor(white))
        torch.testing.assert_close(compressed, curve(gain * values), atol=1e-6, rtol=1e-5)
        assert float(compressed[2]) == pytest.approx(0.18, abs=1e-6)
        assert float(synth.compress_highlights(torch.tensor(white / gain), torch.tensor(white))) == pytest.approx(1.0)
        assert (compressed.diff() > 0).all() and compressed[1] > values[1] and compressed[4] < 1.0


def test_compressed_highlights_clip_less_and_keep_the_target():
    maps = random_maps(2, 32, seed=5)
    maps[:, constants.ROUGHNESS] = 0.1
    maps[:, constants.SPECULAR] = 0.9
    plain = synth.synthesize(maps, torch.Generator().manual_seed(2), _noiseless())
    compressed = synth.synthesize(maps, torch.Generator().manual_seed(2), _noiseless(highlight_compression=(8.0, 8.0)))
    assert (compressed.photos >= 0.999).float().mean() < 0.5 * (plain.photos >= 0.999).float().mean()
    assert torch.equal(compressed.maps, plain.maps)  # the target is the material as it is
    with pytest.raises(ValueError, match="highlight_compression"):
        synth.SynthesisConfig(highlight_compression=(0.5, 2.0))


def test_vignetting_darkens_the_corners_by_its_strength():
    factor = synth.vignette(torch.tensor([0.0, 0.3]), 64, 64)
    torch.testing.assert_close(factor[0], torch.ones(1, 64, 64))
    corner = 1 - 0.3 * ((1 - 1 / 64) ** 2)  # the corner pixel's centre sits half a pixel inside
    assert factor[1, 0, 0, 0].item() == pytest.approx(corner, abs=1e-6)
    assert factor[1, 0, 31, 31].item() > 0.999


def test_flash_cone_falloff_is_the_cosine_from_the_axis_to_a_power():
    lights = torch.tensor([[0.3, -0.2, 2.0]])
    falloff = synth.flash_cone_falloff(lights, torch.tensor([2.5]), 8, 8)
    x, y = -1 + 1 / 8, 1 - 1 / 8  # the top-left pixel's point
    cosine = 2.0 / math.sqrt((x - 0.3) ** 2 + (y + 0.2) ** 2 + 4.0)
    assert falloff[0, 0, 0, 0].item() == pytest.approx(cosine**2.5, rel=1e-5)
    torch.testing.assert_close(synth.flash_cone_falloff(lights, torch.tensor([0.0]), 8, 8), torch.ones(1, 1, 8, 8))


def test_tilted_normals_turn_by_the_angle_about_the_axis():
    maps = random_maps(2, 4)
    maps[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    angle, azimuth = torch.tensor([0.1, 0.05]), torch.tensor([0.0, math.pi / 2])
    tilted = synth.tilt_normals(maps, angle, azimuth)
    normals = tilted[:, constants.NORMAL, 0, 0]
    torch.testing.assert_close(normals.norm(dim=1), torch.ones(2))
    torch.testing.assert_close(normals[:, 2], torch.cos(angle))
    # About +x the normal leans in the y-z plane, about +y in the x-z plane.
    assert abs(normals[0, 0]) < 1e-6 and abs(normals[1, 1]) < 1e-6
    torch.testing.assert_close(tilted[:, 3:], maps[:, 3:])


def test_jpeg_round_trip_keeps_colours_and_loses_more_at_lower_quality():
    flat = torch.tensor([0.8, 0.2, 0.4]).view(1, 3, 1, 1).expand(1, 3, 32, 32)
    flat = torch.round(flat * 255) / 255
    torch.testing.assert_close(synth.jpeg_round_trip(flat, [90]), flat, atol=2.5 / 255, rtol=0)  # RGB order kept
    generator = torch.Generator().manual_seed(0)
    image = torch.nn.functional.interpolate(torch.rand(1, 3, 8, 8, generator=generator), size=64, mode="bicubic")
    image = torch.round(image.clamp(0, 1) * 255) / 255
    errors = [(synth.jpeg_round_trip(image, [quality]) - image).abs().mean().item() for quality in (95, 70)]
    assert errors[0] < 3 / 255 and errors[1] > errors[0] * 1.3, errors


def test_phone_photos_make_valid_inputs_and_keep_the_pair_consistent():
    maps = random_maps(2, 32)
    batch = synth.synthesize(maps, torch.Generator().manual_seed(1), synth.SynthesisConfig(**synth.PHONE_PHOTOS))
    assert torch.isfinite(batch.inputs).all() and batch.inputs.abs().max() <= 1.0
    assert 20.0 <= batch.fov <= 75.0
    # M + xi is the variation of the target (the diffuse with its cast), as the consistency loss needs.
    torch.testing.assert_close(batch.varied_maps, batch.variation.apply(batch.maps))


def test_a_share_of_batches_is_photographed_by_the_plain_camera():
    config = synth.SynthesisConfig(**synth.PHONE_PHOTOS, plain_probability=0.4)
    assert config.plain().fov_range is None and config.plain().jpeg_quality is None
    assert config.plain().white_balance_sigma == config.white_balance_sigma  # the levers alone
    generator = torch.Generator().manual_seed(3)
    fovs = [synth.synthesize(random_maps(1, 8), generator, config).fov for _ in range(200)]
    plain = sum(fov == constants.DEFAULT_FOV_DEG for fov in fovs) / len(fovs)
    assert 0.3 < plain < 0.5


def test_a_hazy_photo_is_the_sum_of_two_lobes_whose_specular_adds_up():
    maps = random_maps(2, 32, seed=4)
    maps[:, constants.ROUGHNESS] = 0.3
    config = _noiseless(specular_haze=(0.4, 0.4), haze_spread=(0.25, 0.25))
    batch = synth.synthesize(maps, torch.Generator().manual_seed(6), config)
    # The independent reference: the material with 60 % of its specular, plus a diffuse-free
    # material with the other 40 % at roughness 0.55, each rendered by the torch renderer.
    sharp, haze = maps.clone(), maps.clone()
    sharp[:, constants.SPECULAR] *= 0.6
    haze[:, constants.DIFFUSE] = 0.0
    haze[:, constants.SPECULAR] *= 0.4
    haze[:, constants.ROUGHNESS] = 0.55
    lights = batch.lights.view(2, 1, 3)
    expected = (render_flash(sharp, lights, backend="torch") + render_flash(haze, lights, backend="torch"))[:, 0]
    torch.testing.assert_close(batch.photos, expected.clamp(0, 1), atol=1e-4, rtol=0)
    assert torch.equal(batch.maps, maps)  # the target keeps one lobe of the whole specular
    one_lobe = render_flash(maps, lights, backend="torch")[:, 0]
    assert (batch.photos < one_lobe.clamp(0, 1) - 1e-3).any() and (batch.photos > one_lobe + 1e-3).any()


def test_without_haze_the_synthesis_draws_the_same_numbers():
    maps = random_maps(2, 16, seed=2)
    plain = synth.synthesize(maps, torch.Generator().manual_seed(8), _noiseless())
    spread_only = synth.synthesize(maps, torch.Generator().manual_seed(8), _noiseless(haze_spread=(0.3, 0.5)))
    assert torch.equal(plain.photos, spread_only.photos) and torch.equal(plain.lights, spread_only.lights)


@pytest.mark.parametrize("field, value", [("specular_haze", (0.5, 1.5)), ("specular_haze", (0.6, 0.2)),
                                          ("haze_spread", (-0.1, 0.2))])
def test_haze_ranges_are_checked(field, value):
    with pytest.raises(ValueError, match=field):
        synth.SynthesisConfig(**{field: value})
