"""Reporting: the validation sheet's layout and the map tiles' encodings."""

from __future__ import annotations

import numpy as np
import torch

from mideepbasis.imageio import linear_to_srgb, read_image
from mideepbasis.reporting import map_tiles, validation_sheet


def test_map_tiles_encode_each_map_as_people_look_at_it():
    maps = torch.zeros(10, 2, 2)
    maps[2] = 1.0
    maps[3:6], maps[6], maps[7:10] = 0.25, 0.5, 0.04
    normal, diffuse, roughness, specular = map_tiles(maps)
    assert np.allclose(normal[0, 0], [0.5, 0.5, 1.0])  # (n + 1) / 2
    assert np.allclose(diffuse[0, 0], linear_to_srgb(np.float32(0.25)))  # colour: sRGB
    assert np.allclose(roughness[0, 0], [0.5, 0.5, 0.5])  # data: as it is, grey
    assert np.allclose(specular[0, 0], linear_to_srgb(np.float32(0.04)))


def test_validation_sheet_rows_and_columns(tmp_path):
    photos, maps = torch.rand(3, 3, 8, 8), torch.rand(3, 10, 8, 8)
    path = validation_sheet(photos, maps, maps, tmp_path / "sheet.png")
    sheet = read_image(path)
    assert sheet.shape == (3 * 8, 9 * 8, 3)  # a photo, then four predicted-true pairs, per row
    assert np.allclose(sheet[:8, 8:16], sheet[:8, 16:24], atol=1 / 255)  # prediction equals truth here
