"""Height maps integrated from normal maps (``mideepbasis.height``)."""

from __future__ import annotations

import math

import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.procedural.core import height_to_normal
from mideepbasis.height import (cosine_transform, height_from_normals, inverse_cosine_transform, slopes,
                                sine_transform)


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


@pytest.mark.parametrize("size", [1, 2, 7, 16])
def test_the_cosine_and_sine_transforms_are_their_sums(size):
    # Against their definitions, summed as a matrix product in float64, along either dimension.
    values = torch.randn(size, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(size))
    n = torch.arange(size, dtype=torch.float64)
    angles = math.pi * n[:, None] * (n[None, :] + 0.5) / size  # [k, n]
    tolerance = {"atol": 1e-12, "rtol": 0.0}
    torch.testing.assert_close(cosine_transform(values, 0), torch.cos(angles) @ values, **tolerance)
    torch.testing.assert_close(sine_transform(values, 0), torch.sin(angles) @ values, **tolerance)
    torch.testing.assert_close(cosine_transform(values.T, 1), (torch.cos(angles) @ values).T, **tolerance)
    torch.testing.assert_close(inverse_cosine_transform(cosine_transform(values, 0), 0), values, **tolerance)


def mirrored_height(normal: torch.Tensor) -> torch.Tensor:
    """The least-squares height of the periodic field of twice the size that mirrors the slopes
    (each odd along its own axis, even across it), by FFTs in float64, cropped: the reference the
    cosine-transform solve must equal."""
    along_columns, along_rows = (s.double() for s in slopes(normal))
    height, width = along_columns.shape
    gx = torch.cat([torch.cat([along_columns, -along_columns.flip(1)], 1),
                    torch.cat([along_columns.flip(0), -along_columns.flip(0).flip(1)], 1)], 0)
    gy = torch.cat([torch.cat([along_rows, along_rows.flip(1)], 1),
                    torch.cat([-along_rows.flip(0), -along_rows.flip(0).flip(1)], 1)], 0)
    u = torch.sin(2 * math.pi * torch.fft.fftfreq(2 * width, dtype=torch.float64))[None, :]
    v = torch.sin(2 * math.pi * torch.fft.fftfreq(2 * height, dtype=torch.float64))[:, None]
    denominator = u * u + v * v
    spectrum = (-1j * u * torch.fft.fft2(gx) - 1j * v * torch.fft.fft2(gy)) / denominator.clamp(min=1e-12)
    spectrum[denominator <= 1e-12] = 0
    field = torch.fft.ifft2(spectrum).real[:height, :width]
    return (field - field.mean())[None]


@pytest.mark.parametrize("shape", [(64, 64), (37, 50)])
def test_a_map_that_does_not_tile_is_integrated_as_its_mirrored_field(shape):
    tilt = torch.tensor([0.3, 0.3, 1.0]).view(3, 1, 1)
    normal = torch.randn(3, *shape, generator=torch.Generator().manual_seed(1)) * tilt
    normal = normal / normal.norm(dim=0, keepdim=True)
    reference = mirrored_height(normal)
    # float32 against float64: within a millionth of the height's range.
    atol = 1e-6 * float(reference.max() - reference.min())
    torch.testing.assert_close(height_from_normals(normal).double(), reference, atol=atol, rtol=0.0)
