"""Capture geometry by hand: pixel points, flash positions, offset angles, the lighting-mark material."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mideepbasis import constants, geometry


def test_pixel_points_are_the_pixel_centres_of_design_section_2():
    points = geometry.pixel_points(2, 4)
    # Row 0 is the top edge (+y), column 0 the left edge (-x): x = -1 + (2j + 1) / w, y = 1 - (2i + 1) / h.
    assert points[:, 0, 0].tolist() == pytest.approx([-0.75, 0.5, 0.0])
    assert points[:, 1, 3].tolist() == pytest.approx([0.75, -0.5, 0.0])
    assert points[0, 0].tolist() == pytest.approx([-0.75, -0.25, 0.25, 0.75])


def test_flash_positions_and_offset_angles():
    height = 1 / math.tan(math.radians(45.0) / 2)
    assert constants.camera_height(45.0) == pytest.approx(height)
    offsets = torch.tensor([[0.3, -0.4]])
    assert geometry.light_positions(offsets)[0].tolist() == pytest.approx([0.3, -0.4, height])
    assert float(geometry.offset_angle_deg(offsets)) == pytest.approx(math.degrees(math.atan(0.5 / height)))
    assert geometry.max_offset() == pytest.approx(height * math.tan(math.radians(constants.MAX_OFFSET_DEG)))
    assert geometry.flash_intensity() == pytest.approx(math.pi * height**2)
    with pytest.raises(ValueError, match="field of view"):
        constants.camera_height(180.0)


def test_the_lighting_mark_material():
    maps = geometry.lighting_mark_material(3, 5)
    assert maps.shape == (1, 10, 3, 5)
    assert torch.equal(maps[0, :3, 1, 2], torch.tensor([0.0, 0.0, 1.0]))
    assert maps[0, 3:6].unique().tolist() == pytest.approx([constants.LIGHTING_MARK_DIFFUSE])
    assert maps[0, 6].unique().tolist() == pytest.approx([constants.LIGHTING_MARK_ROUGHNESS])
    assert maps[0, 7:10].unique().tolist() == pytest.approx([constants.LIGHTING_MARK_SPECULAR])


@pytest.mark.parametrize("dim", [0, 1, 2, -1])
def test_vector_lengths_and_unit_vectors_along_any_dimension(dim):
    torch.manual_seed(0)
    vectors = torch.randn(3, 4, 5, 6)
    vectors.select(3 if dim != -1 else 0, 0).zero_()  # whole zero vectors: unit_vectors leaves them zero, as F.normalize does
    reference = np.sqrt((vectors.double().numpy() ** 2).sum(axis=dim, keepdims=True))
    np.testing.assert_allclose(geometry.vector_length(vectors, dim, keepdim=True).numpy(), reference, rtol=1e-6)
    assert geometry.vector_length(vectors, dim).shape == reference.squeeze(axis=dim).shape
    unit = geometry.unit_vectors(vectors, dim)
    expected = vectors.double().numpy() / np.maximum(reference, 1e-12)
    np.testing.assert_allclose(unit.numpy(), expected, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("strength", [0.0, 0.5, 1.0, 2.0])
def test_scaled_slopes_scale_a_height_field_s_gradient(strength):
    """Normals of h(x, y) = a x + b y are (-a, -b, 1) / |.|: their slopes -n_x / n_z, -n_y / n_z are the
    gradient, which a strength s makes s a, s b."""
    gradients = torch.tensor([[0.3, -0.7], [0.0, 0.0], [2.0, 1.0]])
    normals = torch.cat([-gradients, torch.ones(3, 1)], dim=1)
    normals = normals / normals.norm(dim=1, keepdim=True)
    scaled = geometry.scaled_slopes(normals.T[:, None], strength, dim=0)[:, 0].T  # components along dim 0
    torch.testing.assert_close(scaled.norm(dim=1), torch.ones(3))
    torch.testing.assert_close(-scaled[:, :2] / scaled[:, 2:], strength * gradients, rtol=1e-5, atol=1e-6)
