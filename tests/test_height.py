"""Height maps integrated from normal maps (``mideepbasis.height``)."""

from __future__ import annotations

import math

import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.procedural.core import height_to_normal
from mideepbasis.height import height_from_normals


def normals_from_height(height: torch.Tensor, tileable: bool = False) -> torch.Tensor:
    """The generator's own normals of a height field (1, H, W) (central differences): the
    independent reference the integration must invert."""
    return torch.from_numpy(height_to_normal(height[0].numpy(), tileable)).permute(2, 0, 1).float()

#: Largest RMSE of the normals given back by the height's central differences: procedural normals
#: are the central differences of a height field, so the integration gives it back to float rounding.
ROUND_TRIP_RMSE = 1e-4


@pytest.mark.parametrize("tileable", [True, False])
@pytest.mark.parametrize("seed", [0, 3, 5])
def test_the_heights_slopes_give_back_a_procedural_normal_map(seed, tileable):
    normal = generate(seed, config=GeneratorConfig(size=64, tileable=tileable)).to_tensor()[:3]
    height = height_from_normals(normal, tileable)
    assert height.shape == (1, 64, 64) and abs(float(height.mean())) < 1e-6
    back = normals_from_height(height, tileable)
    assert float(((back - normal) ** 2).mean().sqrt()) < ROUND_TRIP_RMSE


def test_a_tilted_plane_and_a_bump_have_the_heights_they_should():
    size = 64
    # A plane rising along +x by 0.1 per half-width: h = 0.1 x, its normal (-0.1, 0, 1) / |.|.
    normal = torch.tensor([-0.1, 0.0, 1.0]).view(3, 1, 1).expand(3, size, size)
    normal = normal / normal.norm(dim=0, keepdim=True)
    height = height_from_normals(normal)[0]
    x = (2 * torch.arange(size) + 1) / size - 1
    # (Within half a pixel's rise, 0.0016: the mirrored field's slope turns at the edges, where the
    # central differences see half of it.)
    torch.testing.assert_close(height[10], 0.1 * x - (0.1 * x).mean(), atol=2e-3, rtol=0)
    assert float(height[10].diff().mean()) == pytest.approx(0.1 * 2 / size, rel=0.02)
    # A bump: its heights from its normals are the bump, up to a constant.
    y, x = torch.meshgrid(1 - (2 * torch.arange(size) + 1) / size, (2 * torch.arange(size) + 1) / size - 1,
                          indexing="ij")
    bump = 0.05 * torch.exp(-(x**2 + y**2) / 0.1)
    recovered = height_from_normals(normals_from_height(bump[None]))[0]
    torch.testing.assert_close(recovered, bump - bump.mean(), atol=2e-4, rtol=0)


def test_a_normal_map_with_no_height_behind_it_gets_the_closest_one():
    # A pure curl (a rotation field of slopes) has no height: the least-squares height is flat.
    size = 32
    angle = torch.linspace(0, 2 * math.pi, size + 1)[:-1]
    normal = torch.zeros(3, size, size)
    normal[0] = 0.1 * torch.sin(angle)[:, None]  # slope along x varies with the row
    normal[2] = 1.0
    normal = normal / normal.norm(dim=0, keepdim=True)
    height = height_from_normals(normal, tileable=True)
    assert float(height.abs().max()) < 1e-5


def test_a_capture_folder_gets_the_height_as_exr_and_16_bit_png(tmp_path):
    import json

    import cv2

    from mideepbasis.export import write_height
    from mideepbasis.imageio import read_image

    material = generate(4, config=GeneratorConfig(size=64))
    record = write_height(tmp_path, material)
    height = read_image(tmp_path / "height.exr")[..., 0]
    back = normals_from_height(torch.from_numpy(height)[None])
    assert float(((back - material.normal) ** 2).mean().sqrt()) < ROUND_TRIP_RMSE
    png = cv2.imread(str(tmp_path / "height.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype.name == "uint16" and png.min() == 0 and png.max() == 65535
    written = json.loads((tmp_path / "height.json").read_text())
    assert written == record and written["png_black"] == pytest.approx(float(height.min()), abs=1e-6)
    # The PNG holds the same heights between its black and white.
    scale = written["png_white"] - written["png_black"]
    assert abs(png.astype(float) / 65535 * scale + written["png_black"] - height).max() < scale / 60000
    assert not written["tileable"]
