"""The network input (model.inputs): its layout by hand, the lighting mark, the optional channels."""

from __future__ import annotations

import math

import pytest
import torch

from mideepbasis import constants, geometry
from mideepbasis.model import inputs
from mideepbasis.render import render_flash


def test_network_input_by_hand():
    photo = torch.tensor([0.0, 1.0, 0.2]).view(1, 3, 1, 1)
    mark = torch.full((1, 3, 1, 1), 0.5)
    x = inputs.network_input(photo, mark)[0, :, 0, 0]
    eps = inputs.LOG_EPS
    log_02 = (math.log(0.2 + eps) - math.log(eps)) / (math.log(1 + eps) - math.log(eps))
    assert x.tolist() == pytest.approx([-1, 1, -0.6, -1, 1, 2 * log_02 - 1, 0, 0, 0], abs=1e-6)


def test_lighting_mark_is_the_reference_material_render():
    lights = geometry.light_positions(torch.tensor([[0.0, 0.0], [0.3, -0.2]]))
    mark = inputs.lighting_mark(lights, 33, 33)
    expected = render_flash(geometry.lighting_mark_material(33, 33).expand(2, -1, -1, -1), lights.view(2, 1, 3),
                            backend="torch")[:, 0].clamp(0, 1)
    assert torch.allclose(mark, expected, atol=1e-5)
    # Diffuse 0.1, specular 0.5 at the centre under the centred flash: 0.1 + D(1) G(1)^2 F / 4 * pi,
    # D(1) = 1 / (pi alpha^2), G(1) = 1: clipped to 1 by the highlight.
    assert mark[0, :, 16, 16].tolist() == pytest.approx([1.0, 1.0, 1.0])
    assert mark[0, 0, 0, 0] < 0.2 and mark[1].argmax() != mark[0].argmax()


def test_flash_falloff_is_the_white_lambertian_of_the_physical_convention():
    lights = geometry.light_positions(torch.tensor([[0.3, -0.2]]))
    falloff = inputs.flash_falloff(lights, 8, 8)
    points = geometry.pixel_points(8, 8)
    distance = torch.linalg.vector_norm(lights[0].view(3, 1, 1) - points, dim=0)
    height = constants.camera_height()
    # (1 / pi) cos * pi H^2 / d^2 with cos = H / d, for a flash at height H.
    torch.testing.assert_close(falloff[0, 0], (height / distance) ** 3, rtol=1e-5, atol=1e-6)


def test_extra_inputs_are_bounded_and_mean_what_they_say():
    photo = torch.rand(2, 3, 32, 32) * 0.8
    falloff = torch.full((2, 1, 32, 32), 0.5)
    channels = inputs.extra_input_channels(photo, ("shading", "highpass"), falloff)
    assert channels.shape == (2, 6, 32, 32) and channels.abs().max() <= 1.0
    # shading: a photo equal to the falloff (a white Lambertian) gives a ratio of 1 everywhere.
    flat = inputs.extra_input_channels(falloff.expand(2, 3, 32, 32), ("shading",), falloff)
    assert torch.allclose(flat, flat[0, 0, 0, 0].expand_as(flat))
    # highpass: a constant photo has no detail.
    assert inputs.extra_input_channels(torch.full((1, 3, 16, 16), 0.3), ("highpass",)).abs().max() < 1e-5
    encoded = inputs.network_input(photo, torch.rand(2, 3, 32, 32), ("shading", "highpass"), falloff)
    assert encoded.shape == (2, 15, 32, 32)
    assert torch.equal(encoded[:, :9], inputs.network_input(photo, encoded[:, inputs.LIGHTING_MARK] * 0.5 + 0.5))


def test_decode_photo_inverts_the_photo_channels_and_the_layout_counts_channels():
    photo = torch.rand(2, 3, 8, 8)
    encoded = inputs.network_input(photo, torch.rand(2, 3, 8, 8))
    torch.testing.assert_close(inputs.decode_photo(encoded), photo, rtol=0, atol=1e-6)
    assert encoded.shape[1] == inputs.input_channels() == 9
    assert inputs.input_channels(("shading", "highpass")) == 15
    # The log photo sits where the layout says: log_compress of the photo, mapped to [-1, 1].
    torch.testing.assert_close(encoded[:, inputs.LOG_PHOTO], inputs.log_compress(photo) * 2 - 1)


def test_relief_inputs_by_hand():
    lights = geometry.light_positions(torch.tensor([[0.3, -0.2], [0.0, 0.0]]))
    falloff = inputs.flash_falloff(lights, 16, 16)
    # A white Lambertian photographed under its own flash has no shading left, nor detail.
    relief = inputs.relief_inputs(falloff.expand(2, 3, 16, 16), lights)
    assert relief.shape == (2, inputs.RELIEF_CHANNELS, 16, 16)
    assert relief[:, 3:5].abs().max() < 1e-5
    torch.testing.assert_close(relief[:, :3], inputs.log_compress(falloff.expand(2, 3, 16, 16)) * 2 - 1)
    # Twice as bright a photo: the shading channel rises by 0.3 log 2 (up to the log's epsilon).
    darker = falloff.expand(2, 3, 16, 16) * 0.25
    rise = inputs.relief_inputs(darker * 2, lights)[:, 3] - inputs.relief_inputs(darker, lights)[:, 3]
    expected = 0.3 * (torch.log(darker[:, 0] * 2 + inputs.LOG_EPS) - torch.log(darker[:, 0] + inputs.LOG_EPS))
    torch.testing.assert_close(rise, expected, rtol=1e-5, atol=1e-6)
    # The last two channels: 3 times the x and y of the unit vector from the pixel's point to the flash.
    row, col = 3, 12
    point = torch.tensor([(2 * col + 1) / 16 - 1, 1 - (2 * row + 1) / 16, 0.0])
    towards = lights[0] - point
    torch.testing.assert_close(relief[0, 5:, row, col], 3 * (towards / towards.norm())[:2])
    # Under a centred flash the pixels left of the centre see the flash to their right (+x).
    assert (relief[1, 5, :, :8] > 0).all() and (relief[1, 5, :, 8:] < 0).all()


def test_the_view_input_is_the_cosine_to_the_flash_and_the_field_of_view():
    """Against hand geometry: the flash 2.4 above the point (0.5, -0.25), a pixel at distance d sees
    it at cos = 2.4 / d; the constant channel codes the field of view within VIEW_FOV_RANGE."""
    light = torch.tensor([[0.5, -0.25, 2.4]])
    view = inputs.view_channels(light, 8, 8, fov=30.0)
    points = geometry.pixel_points(8, 8)
    distance = (light.view(3, 1, 1) - points).norm(dim=0)
    cosine = 2.4 / distance
    torch.testing.assert_close(view[0, 0], 2 * cosine - 1)
    torch.testing.assert_close(view[0, 2], 2 * cosine**3 - 1)
    low, high = inputs.VIEW_FOV_RANGE
    assert float(view[0, 1].unique()) == pytest.approx(2 * (30.0 - low) / (high - low) - 1)
    assert float(inputs.view_channels(light, 4, 4, fov=90.0)[0, 1].max()) == 1.0
    # It turns with the image: the flash mirrored left-right gives the mirrored channels.
    mirrored = inputs.view_channels(light * torch.tensor([-1.0, 1.0, 1.0]), 8, 8, fov=30.0)
    torch.testing.assert_close(mirrored, view.flip(-1))
    photos = torch.rand(1, 3, 8, 8)
    encoded = inputs.encode_inputs(photos, light, 30.0, extra_inputs=("view",))
    assert encoded.shape == (1, inputs.input_channels(("view",)), 8, 8)
    torch.testing.assert_close(encoded[:, -3:], view)
