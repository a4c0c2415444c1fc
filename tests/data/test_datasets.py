"""Material readers on fixtures made here, and on ../shared/data when it is present."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from mideepbasis.data.datasets import (DeschaintreDataset, MaterialFolderDataset, PBRFolderDataset, ProceduralMaterials,
                                       ProceduralStream, classify_map_file)
from mideepbasis.data.procedural import GeneratorConfig
from mideepbasis.imageio import write_image
from mideepbasis.material import Material


def strip(path, layout=(1440, 288, 5, 288, 16), seed=0):
    """A synthetic Deschaintre strip with known panels; returns the central crops it stores."""
    width, height, panels, panel, crop = layout
    rng = np.random.default_rng(seed)
    image = np.zeros((height, width, 3), np.float32)
    crops = []
    for index in range(panels):
        content = rng.uniform(0.1, 0.9, (256 if panel == 288 else panel,) * 2 + (3,)).astype(np.float32)
        if index == panels - 4:  # the normal panel: encode a unit normal
            n = np.stack([content[..., 0] - 0.5, content[..., 1] - 0.5, np.ones_like(content[..., 0])], -1)
            content = (n / np.linalg.norm(n, axis=-1, keepdims=True) + 1) / 2
        block = np.zeros((panel, panel, 3), np.float32)
        block[crop:crop + content.shape[0], crop:crop + content.shape[1]] = content
        image[:, index * panel:(index + 1) * panel] = block
        crops.append(content)
    write_image(path, image)
    return crops


def test_deschaintre_reader_uses_stored_values(tmp_path):
    crops = strip(tmp_path / "a.png")
    strip(tmp_path / "b.png", layout=(2048, 512, 4, 512, 0), seed=1)
    reader = DeschaintreDataset(tmp_path)
    materials = list(reader)
    assert len(materials) == 2 and reader.skipped == 0 and reader.encoding == "stored-as-is"
    first = materials[0]
    assert (first.height, first.width) == (256, 256)
    quantised = np.round(crops[2] * 255) / 255  # the diffuse panel, used as stored (no sRGB decoding)
    np.testing.assert_allclose(first.diffuse.permute(1, 2, 0).numpy(), quantised, atol=1e-6)
    np.testing.assert_allclose(first.roughness[0].numpy(), (np.round(crops[3] * 255) / 255).mean(-1), atol=1e-6)
    assert materials[1].height == 512


def test_corrupt_and_odd_files_are_skipped_and_counted(tmp_path):
    strip(tmp_path / "good.png")
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    write_image(tmp_path / "wrong_size.png", np.zeros((100, 300, 3), np.float32))
    reader = DeschaintreDataset(tmp_path)
    with pytest.warns(UserWarning, match="skipping"):
        materials = list(reader)
    assert len(materials) == 1 and reader.skipped == 2
    assert {s.split("/")[-1] for s, _ in reader.skipped_sources} == {"corrupt.png", "wrong_size.png"}


def test_shared_deschaintre_test_set(shared_data):
    reader = DeschaintreDataset(shared_data / "deschaintre2018-test", with_photo=True)
    count = 0
    for material, photo in reader:
        count += 1
        assert (material.height, material.width) == (256, 256) and photo.shape == (3, 256, 256)
        assert material.convention == "deepbasis"
    assert count == 84 and reader.skipped == 0


def pbr_files(folder, names, size=16, seed=0):
    """Write per-map images under ``names`` {kind: file name}; returns the linear values written."""
    rng = np.random.default_rng(seed)
    values = {}
    folder.mkdir(parents=True, exist_ok=True)
    for kind, name in names.items():
        if kind in ("base_color", "diffuse", "specular"):
            linear = rng.uniform(0.05, 0.9, (size, size, 3)).astype(np.float32)
            write_image(folder / name, linear, encode_srgb=True, bit_depth=16)
        elif kind == "normal":
            n = np.stack([rng.uniform(-0.3, 0.3, (size, size)), rng.uniform(-0.3, 0.3, (size, size)),
                          np.ones((size, size))], -1).astype(np.float32)
            linear = n / np.linalg.norm(n, axis=-1, keepdims=True)
            write_image(folder / name, (linear + 1) / 2, bit_depth=16)
        else:
            linear = rng.uniform(0.0, 1.0, (size, size, 1)).astype(np.float32)
            if kind == "metallic":
                linear = (linear > 0.5).astype(np.float32)
            write_image(folder / name, linear, bit_depth=16)
        values[kind] = linear
    return values


def test_file_names_of_public_libraries_are_recognised(tmp_path):
    assert classify_map_file(tmp_path / "Bricks075_2K_Color.jpg")[1:] == ("base_color", "opengl")
    assert classify_map_file(tmp_path / "Bricks075_2K_NormalDX.jpg")[1:] == ("normal", "directx")
    assert classify_map_file(tmp_path / "wood_floor_nor_gl_2k.png")[1:] == ("normal", "opengl")
    assert classify_map_file(tmp_path / "wood_floor_diff_2k.png")[1:] == ("diffuse", "opengl")
    assert classify_map_file(tmp_path / "rock_rough_4k.exr")[1] == "roughness"
    assert classify_map_file(tmp_path / "Bricks075_2K_Color.jpg")[0] == classify_map_file(
        tmp_path / "Bricks075_2K_Roughness.jpg")[0]
    assert classify_map_file(tmp_path / "readme.png") is None


def test_pbr_folders_in_both_workflows(tmp_path):
    metal = pbr_files(tmp_path / "lib", {"base_color": "Metal01_2K_Color.png", "normal": "Metal01_2K_NormalDX.png",
                                         "roughness": "Metal01_2K_Roughness.png", "metallic": "Metal01_2K_Metalness.png"})
    spec = pbr_files(tmp_path / "lib" / "painted", {"diffuse": "albedo.png", "specular": "specular.png",
                                                    "roughness": "roughness.png"}, seed=1)
    reader = PBRFolderDataset(tmp_path / "lib")
    materials = {m.provenance["workflow"]: m for m in reader}
    assert reader.skipped == 0 and set(materials) == {"metallic-roughness", "specular"}

    metallic_material = materials["metallic-roughness"]
    base, m = metal["base_color"], metal["metallic"]
    expected_specular = 0.04 * (1 - m) + base * m
    np.testing.assert_allclose(metallic_material.specular.permute(1, 2, 0).numpy(), expected_specular, atol=2e-3)
    np.testing.assert_allclose(metallic_material.diffuse.permute(1, 2, 0).numpy(), base * (1 - m), atol=2e-3)
    flipped = metal["normal"] * np.array([1, -1, 1], np.float32)  # DirectX green points down
    np.testing.assert_allclose(metallic_material.normal.permute(1, 2, 0).numpy(), flipped, atol=2e-3)

    specular_material = materials["specular"]
    np.testing.assert_allclose(specular_material.diffuse.permute(1, 2, 0).numpy(), spec["diffuse"], atol=2e-3)
    np.testing.assert_allclose(specular_material.normal[2].numpy(), 1.0)  # no normal map: flat


def test_pbr_folder_with_a_missing_map_is_skipped(tmp_path):
    pbr_files(tmp_path, {"base_color": "stone_basecolor.png", "normal": "stone_normal.png"})
    reader = PBRFolderDataset(tmp_path)
    with pytest.warns(UserWarning, match="roughness"):
        assert list(reader) == []
    assert reader.skipped == 1


def test_material_folders(tmp_path):
    for index in range(2):
        Material.constant(8, 8, diffuse=0.2 * (index + 1), provenance={"index": index}).save(tmp_path / f"m{index}")
    materials = list(MaterialFolderDataset(tmp_path))
    assert [m.provenance["index"] for m in materials] == [0, 1]
    assert materials[1].diffuse.mean().item() == pytest.approx(0.4, abs=5e-3)


def test_procedural_stream_is_seeded_endless_and_safe_with_workers():
    config = GeneratorConfig(size=16)
    materials = ProceduralMaterials(seed=4, config=config)
    assert torch.equal(materials[7]["maps"], ProceduralMaterials(seed=4, config=config)[7]["maps"])
    assert not torch.equal(materials[7]["maps"], ProceduralMaterials(seed=5, config=config)[7]["maps"])

    loader = DataLoader(ProceduralStream(seed=4, config=config), batch_size=3, num_workers=2)
    iterator = iter(loader)
    batches = [next(iterator) for _ in range(6)]
    indices = [i for batch in batches for i in batch["index"].tolist()]
    assert sorted(indices) == list(range(18))  # every number once, none twice
    for batch in batches:
        for index, maps in zip(batch["index"].tolist(), batch["maps"]):
            assert torch.equal(maps, materials[index]["maps"])


def test_procedural_streams_of_two_processes_do_not_overlap():
    config = GeneratorConfig(size=16)
    first = iter(ProceduralStream(seed=1, config=config, rank=0, world_size=2))
    second = iter(ProceduralStream(seed=1, config=config, rank=1, world_size=2))
    assert [next(first)["index"] for _ in range(4)] == [0, 2, 4, 6]
    assert [next(second)["index"] for _ in range(4)] == [1, 3, 5, 7]
