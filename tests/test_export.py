"""Exports: the glTF material carries our maps through the metallic-roughness conversion, output
folders are never replaced unasked."""

from __future__ import annotations

import json

import pytest
import torch

from mideepbasis import constants
from mideepbasis.errors import InputError
from mideepbasis.export import export_pbr, gltf_material
from mideepbasis.imageio import read_image
from mideepbasis.material import Material


def test_gltf_textures_hold_the_metallic_roughness_conversion(tmp_path):
    generator = torch.Generator().manual_seed(2)
    size = 8
    material = Material(torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, size, size).clone(),
                        torch.rand(3, size, size, generator=generator) * 0.8,
                        torch.rand(1, size, size, generator=generator), torch.full((3, size, size), 0.05))
    document = gltf_material(material, tmp_path)
    json.dumps(document)  # JSON-serialisable as it is
    pbr = export_pbr(material)
    base = read_image(tmp_path / "base_color.png", decode_srgb=True)
    packed = read_image(tmp_path / "metallic_roughness.png")
    assert torch.allclose(torch.from_numpy(base).permute(2, 0, 1), pbr["base_color"], atol=2 / 255)
    assert torch.allclose(torch.from_numpy(packed[..., 1]), pbr["roughness"][0], atol=1 / 255)  # G: roughness
    assert torch.allclose(torch.from_numpy(packed[..., 2]), pbr["metallic"][0], atol=1 / 255)  # B: metallic
    # KHR_materials_specular: F0 = 0.04 x factor x colour must give back our specular 0.05 (dielectric here).
    factor = document["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"][0]
    colour = read_image(tmp_path / "specular_color.png", decode_srgb=True)
    assert 0.04 * factor * colour.mean() == pytest.approx(0.05, rel=0.02)


def test_gltf_gives_back_the_specular_of_a_partly_metallic_material(tmp_path):
    """A glTF reader's F0 is (1 - metallic) x 0.04 x factor x colour + metallic x base colour; for a
    material made from metallic-roughness maps split where the export splits it, that is its specular."""
    generator = torch.Generator().manual_seed(3)
    size = 8
    base = 0.3 + 0.6 * torch.rand(3, size, size, generator=generator)
    metallic = torch.linspace(0.2, 0.9, size * size).view(1, size, size)
    material = Material.from_pbr(base, metallic, torch.full((1, size, size), 0.4),
                                 dielectric_f0=constants.EXPORT_METAL_F0)
    document = gltf_material(material, tmp_path)
    factor = document["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"][0]
    colour = torch.from_numpy(read_image(tmp_path / "specular_color.png", decode_srgb=True)).permute(2, 0, 1)
    read_base = torch.from_numpy(read_image(tmp_path / "base_color.png", decode_srgb=True)).permute(2, 0, 1)
    read_metallic = torch.from_numpy(read_image(tmp_path / "metallic_roughness.png")[..., 2])
    f0 = (1 - read_metallic) * 0.04 * factor * colour + read_metallic * read_base
    assert torch.allclose(f0, material.specular, atol=0.01), (f0 - material.specular).abs().max()


def test_an_occupied_output_folder_is_refused(tmp_path):
    from mideepbasis.outputs import OutputFolder

    (tmp_path / "out").mkdir()
    OutputFolder(tmp_path / "out", overwrite=False).abort()  # empty: fine
    (tmp_path / "out" / "mine.txt").write_text("keep")
    with pytest.raises(InputError, match="exists and is not empty"):
        OutputFolder(tmp_path / "out", overwrite=False)
    with pytest.raises(InputError, match="not written by mideepbasis"):  # not the tool's: kept
        OutputFolder(tmp_path / "out", overwrite=True)
    assert (tmp_path / "out" / "mine.txt").read_text() == "keep"
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        OutputFolder(tmp_path / "file", overwrite=True)
