"""Tests of mideepbasis.material: validation, tensors, the material folder, Deschaintre strips, PBR."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch
from PIL import Image

from mideepbasis import constants
from mideepbasis.errors import InputError
from mideepbasis.imageio import read_image, write_image
from mideepbasis.material import MAP_NAMES, Material, MaterialError

# Largest error of a save/load round trip per format, per map [in-memory units]:
# 8-bit: normals lose up to 1/255 per component before renormalising, sRGB-encoded albedos up to
# half a step times the largest slope of the sRGB EOTF (2.4 / 1.055 at 1), roughness half a step;
# 16-bit the same with 65535 steps; float32 EXR only the renormalisation of the normals.
ROUND_TRIP_TOL = {
    #         normal   diffuse/specular  roughness
    "png": (6e-3, 0.5 / 255 * 2.4 / 1.055 + 1e-6, 0.5 / 255 + 1e-6),
    "png16": (5e-5, 0.5 / 65535 * 2.4 / 1.055 + 1e-6, 0.5 / 65535 + 1e-7),
    "exr": (1e-6, 0.0, 0.0),
}

#: The evaluation data of the project, read in place (never copied).
DESCHAINTRE_TEST = Path(__file__).resolve().parents[2] / "shared" / "data" / "deschaintre2018-test"


def random_material(h: int = 16, w: int = 12, seed: int = 0, **kwargs) -> Material:
    g = torch.Generator().manual_seed(seed)
    theta = torch.rand(1, h, w, generator=g) * math.radians(70)
    phi = torch.rand(1, h, w, generator=g) * 2 * math.pi
    normal = torch.cat([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()])
    return Material(
        normal,
        torch.rand(3, h, w, generator=g),
        torch.rand(1, h, w, generator=g),
        torch.rand(3, h, w, generator=g),
        **kwargs,
    )


def max_error(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max())


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# --- validation ------------------------------------------------------------------------------------


def test_valid_material_and_numpy_input():
    m = random_material()
    assert (m.height, m.width) == (16, 12)
    assert all(getattr(m, k).dtype == torch.float32 for k in MAP_NAMES)
    from_numpy = Material(*(getattr(m, k).double().numpy() for k in MAP_NAMES))
    assert isinstance(from_numpy.diffuse, torch.Tensor) and from_numpy.diffuse.dtype == torch.float32
    assert max_error(from_numpy.normal, m.normal) < 1e-7
    assert from_numpy.convention == "physical" and from_numpy.provenance == {}
    assert "12x16" in repr(m)


def test_tolerances_clamp_and_renormalise():
    m = random_material()
    slightly = Material(m.normal * (1 + 0.5 * constants.UNIT_NORMAL_TOLERANCE),
                        m.diffuse.clamp(max=0.9) + 0.5 * constants.RANGE_TOLERANCE + 0.1,
                        m.roughness * 0 - 0.5 * constants.RANGE_TOLERANCE, m.specular)
    assert max_error(torch.linalg.vector_norm(slightly.normal, dim=0), torch.ones(16, 12)) < 1e-6
    assert slightly.roughness.min() == 0.0
    assert slightly.diffuse.max() <= 1.0


def _bad(m: Material, **changes):
    fields = {k: getattr(m, k) for k in MAP_NAMES}
    fields.update(changes)
    return lambda: Material(**fields, source="bad.png")


def test_validation_errors():
    m = random_material()
    nan = m.diffuse.clone()
    nan[1, 2, 3] = float("nan")
    below = m.normal.clone()
    below[:, 0, 0] = torch.tensor([0.6, 0.0, -0.8])
    cases = [
        (_bad(m, diffuse=m.diffuse.permute(1, 2, 0)), r"diffuse must have shape \(3, H, W\), got \(16, 12, 3\)"),
        (_bad(m, roughness=m.specular), r"roughness must have shape \(1, H, W\)"),
        (_bad(m, specular=m.specular[0]), r"specular must have shape"),
        (_bad(m, diffuse=m.diffuse[:, :8]), "maps differ in size"),
        (_bad(m, normal=m.normal[:, :1], diffuse=m.diffuse[:, :1], roughness=m.roughness[:, :1],
              specular=m.specular[:, :1]), "at least 2x2"),
        (_bad(m, diffuse=nan), "diffuse contains NaN"),
        (_bad(m, specular=m.specular + 0.5), r"specular values lie in \[.*\], outside \[0, 1\]"),
        (_bad(m, roughness=m.roughness - 0.01), "roughness values lie in"),
        (_bad(m, normal=m.normal * 1.1), "not unit vectors"),
        (_bad(m, normal=below), "point into the surface"),
        (_bad(m, diffuse=[[0.5]]), "must be a tensor or array"),
        (lambda: Material(m.normal, m.diffuse, m.roughness, m.specular, convention="blender"), "unknown convention"),
        (lambda: Material(m.normal, m.diffuse, m.roughness, m.specular, provenance={"x": object()}),
         "not JSON-serialisable"),
    ]
    for make, message in cases:
        with pytest.raises(MaterialError, match=message) as exc:
            make()
        assert "\n" not in str(exc.value)
        assert isinstance(exc.value, InputError)
    with pytest.raises(MaterialError, match="^bad.png: diffuse contains NaN"):
        _bad(m, diffuse=nan)()


# --- tensors ---------------------------------------------------------------------------------------


def test_to_tensor_layout_and_from_tensor():
    m = random_material()
    t = m.to_tensor()
    assert t.shape == (10, 16, 12)
    torch.testing.assert_close(t[0:3], m.normal, rtol=0, atol=0)
    torch.testing.assert_close(t[3:6], m.diffuse, rtol=0, atol=0)
    torch.testing.assert_close(t[6:7], m.roughness, rtol=0, atol=0)
    torch.testing.assert_close(t[7:10], m.specular, rtol=0, atol=0)
    back = Material.from_tensor(t, convention="deepbasis", source="net")
    assert back.convention == "deepbasis" and back.source == "net"
    torch.testing.assert_close(back.to_tensor(), t, rtol=0, atol=1e-6)

    raw = t.clone()
    raw[0:3] *= 3.0  # unnormalised normals ...
    raw[2, 0, 0] = -0.1  # ... one slightly below the surface ...
    raw[3:] = raw[3:] * 1.4 - 0.2  # ... and albedos out of range
    repaired = Material.from_tensor(raw)
    assert max_error(torch.linalg.vector_norm(repaired.normal, dim=0), torch.ones(16, 12)) < 1e-6
    assert repaired.normal[2].min() >= 0.0
    torch.testing.assert_close(repaired.diffuse, (t[3:6] * 1.4 - 0.2).clamp(0, 1))
    with pytest.raises(MaterialError, match=r"must have shape \(10, H, W\)"):
        Material.from_tensor(t[:9])


def test_constant():
    m = Material.constant(4, 5, normal=(0, 1, 1), diffuse=(0.1, 0.2, 0.3), roughness=0.7)
    assert (m.height, m.width) == (4, 5)
    torch.testing.assert_close(m.normal[:, 3, 4], torch.tensor([0.0, 1.0, 1.0]) / math.sqrt(2))
    torch.testing.assert_close(m.diffuse[:, 0, 0], torch.tensor([0.1, 0.2, 0.3]))
    assert (m.roughness == 0.7).all() and (m.specular == constants.DIELECTRIC_F0).all()
    with pytest.raises(MaterialError, match="expected 1 or 3 values"):
        Material.constant(4, 5, diffuse=(0.1, 0.2))


# --- material folder -------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", list(ROUND_TRIP_TOL))
def test_save_load_round_trip(tmp_path, fmt):
    provenance = {"source": "unit test", "seed": 3, "nested": {"list": [1, 2]}}
    m = random_material(provenance=provenance, convention="deepbasis")
    folder = m.save(tmp_path / "mat", format=fmt)
    suffix = "exr" if fmt == "exr" else "png"
    assert listing(folder) == sorted(["material.json"] + [f"{n}.{suffix}" for n in MAP_NAMES])

    meta = json.loads((folder / "material.json").read_text())
    assert meta["format"] == "mideepbasis-material" and meta["version"] == 1
    assert meta["file_format"] == suffix
    depth = {"png": 8, "png16": 16, "exr": 32}[fmt]
    assert meta["bit_depth"] == {"normal": max(depth, 16) if suffix == "png" else depth, "diffuse": depth,
                                 "roughness": depth, "specular": depth}
    if suffix == "png":  # the files' own depths
        import cv2

        assert cv2.imread(str(folder / "normal.png"), cv2.IMREAD_UNCHANGED).dtype.name == "uint16"
        expected_colour = "uint16" if fmt == "png16" else "uint8"
        assert cv2.imread(str(folder / "diffuse.png"), cv2.IMREAD_UNCHANGED).dtype.name == expected_colour
    assert meta["size"] == {"width": 12, "height": 16}
    assert meta["convention"] == "deepbasis" and meta["provenance"] == provenance
    expected = ({"normal": "unsigned-opengl", "diffuse": "srgb", "roughness": "linear", "specular": "srgb"}
                if suffix == "png" else
                {"normal": "signed", "diffuse": "linear", "roughness": "linear", "specular": "linear"})
    assert meta["encoding"] == expected

    back = Material.load(folder)
    tol_normal, tol_albedo, tol_roughness = ROUND_TRIP_TOL[fmt]
    assert max_error(back.normal, m.normal) <= tol_normal
    assert max_error(back.diffuse, m.diffuse) <= tol_albedo
    assert max_error(back.specular, m.specular) <= tol_albedo
    assert max_error(back.roughness, m.roughness) <= tol_roughness
    assert back.convention == "deepbasis" and back.provenance == provenance
    assert back.source == str(folder)
    assert read_image(folder / f"roughness.{suffix}").shape == (16, 12, 1)  # grey on disk


def read_normal_png(path) -> np.ndarray:
    """A 16-bit RGB PNG's stored values (H, W, 3) (Pillow reads it as 8-bit; OpenCV as BGR)."""
    import cv2

    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert stored.dtype == np.uint16
    return stored[..., ::-1].astype(np.float64)


def test_png_encodings_on_disk(tmp_path):
    """Stored values against the closed-form encodings (independent of the reader)."""
    m = random_material()
    folder = m.save(tmp_path / "mat", format="png")
    lin = m.diffuse.permute(1, 2, 0).double().numpy()
    srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.maximum(lin, 0.0031308) ** (1 / 2.4) - 0.055)
    stored = np.asarray(Image.open(folder / "diffuse.png")).astype(np.float64)
    assert np.abs(stored - srgb * 255).max() <= 0.5 + 1e-3
    stored = read_normal_png(folder / "normal.png")  # 16-bit
    assert np.abs(stored - (m.normal.permute(1, 2, 0).double().numpy() + 1) / 2 * 65535).max() <= 0.5 + 1e-2
    stored = np.asarray(Image.open(folder / "roughness.png")).astype(np.float64)
    assert stored.ndim == 2 and np.abs(stored - m.roughness[0].double().numpy() * 255).max() <= 0.5 + 1e-3


def test_directx_normals_flip_green(tmp_path):
    m = random_material()
    gl = m.save(tmp_path / "gl", format="png")
    dx = m.save(tmp_path / "dx", format="png", normal_convention="directx")
    assert json.loads((dx / "material.json").read_text())["encoding"]["normal"] == "unsigned-directx"
    a = read_normal_png(gl / "normal.png").astype(int)
    b = read_normal_png(dx / "normal.png").astype(int)
    np.testing.assert_array_equal(a[..., [0, 2]], b[..., [0, 2]])
    assert np.abs(b[..., 1] - (65535 - a[..., 1])).max() <= 1  # (1 - y) / 2 = 1 - (1 + y) / 2, rounded
    assert max_error(Material.load(dx).normal, m.normal) <= ROUND_TRIP_TOL["png"][0]

    dx_exr = m.save(tmp_path / "dx_exr", format="exr", normal_convention="directx")
    assert json.loads((dx_exr / "material.json").read_text())["encoding"]["normal"] == "signed-directx"
    stored = read_image(dx_exr / "normal.exr")
    np.testing.assert_array_equal(stored[..., 1], -m.normal[1].numpy())
    assert max_error(Material.load(dx_exr).normal, m.normal) <= ROUND_TRIP_TOL["exr"][0]


def test_load_without_material_json(tmp_path):
    m = random_material()
    folder = m.save(tmp_path / "mat", format="png16")
    (folder / "material.json").unlink()
    back = Material.load(folder)
    assert max_error(back.diffuse, m.diffuse) <= ROUND_TRIP_TOL["png16"][1]
    assert back.convention == constants.DEFAULT_CONVENTION
    assert back.provenance["encoding"]["diffuse"] == "srgb" and "defaults assumed" in back.provenance["note"]

    m.save(tmp_path / "exr", format="exr")
    (tmp_path / "exr" / "material.json").unlink()
    assert max_error(Material.load(tmp_path / "exr").specular, m.specular) == 0.0

    for name in MAP_NAMES:  # both sets complete: ambiguous
        (tmp_path / "exr" / f"{name}.exr").rename(folder / f"{name}.exr")
    with pytest.raises(MaterialError, match="both .png and .exr"):
        Material.load(folder)


def test_load_errors_name_the_problem_and_write_nothing(tmp_path):
    m = random_material()

    def folder_with(name: str, change) -> Path:
        folder = m.save(tmp_path / name, format="exr" if "exr" in name else "png")
        change(folder)
        return folder

    def write_nan(folder: Path) -> None:
        nan = np.full((16, 12), 0.5, np.float32)
        nan[3, 4] = np.nan
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(header, {"R": nan, "G": nan, "B": nan}).write(str(folder / "diffuse.exr"))

    def edit_json(**changes):
        def change(folder: Path) -> None:
            meta = json.loads((folder / "material.json").read_text())
            meta.update(changes)
            (folder / "material.json").write_text(json.dumps(meta))
        return change

    cases = {
        "missing_map": (lambda f: (f / "roughness.png").unlink(), r"missing roughness map \(roughness.png\)"),
        "missing_map_no_json": (lambda f: [(f / "specular.png").unlink(), (f / "material.json").unlink()],
                                r"missing specular map \(specular.png\)"),
        "sizes": (lambda f: write_image(f / "diffuse.png", np.zeros((8, 8, 3), np.float32)), "maps differ in size"),
        "nan_exr": (write_nan, "diffuse.exr' contains NaN"),
        "range_exr": (lambda f: write_image(f / "diffuse.exr", np.full((16, 12, 3), 1.5, np.float32)),
                      "diffuse values lie in"),
        "normals_exr": (lambda f: write_image(f / "normal.exr", np.full((16, 12, 3), 0.2, np.float32)),
                        "not unit vectors"),
        "bad_json": (lambda f: (f / "material.json").write_text("{not json"), "material.json: not valid JSON"),
        "wrong_format": (edit_json(format="something-else"), "not a 'mideepbasis-material'"),
        "new_version": (edit_json(version=2), "unsupported version 2"),
        "bad_encoding": (edit_json(encoding={"diffuse": "gamma22"}), "unknown diffuse encoding 'gamma22'"),
        "bad_size": (edit_json(size={"width": 5, "height": 5}), "material.json says 5x5"),
        "not_image": (lambda f: (f / "normal.png").write_text("text"), "normal.png': not an image file"),
    }
    for name, (change, message) in cases.items():
        folder = folder_with(name, change)
        before = {p: p.read_bytes() for p in folder.iterdir()}
        with pytest.raises(MaterialError, match=message) as exc:
            Material.load(folder)
        assert "\n" not in str(exc.value) and name in str(exc.value), name
        assert {p: p.read_bytes() for p in folder.iterdir()} == before, name
    with pytest.raises(MaterialError, match="no such folder"):
        Material.load(tmp_path / "nowhere")


def test_save_errors_write_nothing(tmp_path):
    m = random_material()
    with pytest.raises(MaterialError, match="unknown material format 'tiff'"):
        m.save(tmp_path / "a", format="tiff")
    with pytest.raises(MaterialError, match="unknown normal convention 'vulkan'"):
        m.save(tmp_path / "a", normal_convention="vulkan")
    assert list(tmp_path.iterdir()) == []


# --- Deschaintre strips ----------------------------------------------------------------------------


def make_strip(path: Path, panels: int, size: int, crop: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Write a strip whose panels have known central contents and a junk border; return the centres."""
    rng = np.random.default_rng(seed)
    inner = size - 2 * crop
    normal = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    centres = {
        "photo": rng.integers(0, 256, (inner, inner, 3)),
        "normal": np.broadcast_to(np.round((normal + 1) / 2 * 255), (inner, inner, 3)).copy(),
        "diffuse": rng.integers(0, 256, (inner, inner, 3)),
        "roughness": np.broadcast_to([30, 60, 120], (inner, inner, 3)).copy(),
        "specular": rng.integers(0, 256, (inner, inner, 3)),
    }
    centres["diffuse"][0, 0] = [1, 2, 3]  # marks the top-left corner of the crop
    names = list(centres)[5 - panels:]
    strip = np.full((size, panels * size, 3), 7, np.uint8)  # the border that must be cropped away
    for i, name in enumerate(names):
        strip[crop:size - crop, i * size + crop:(i + 1) * size - crop] = centres[name]
    Image.fromarray(strip).save(path)
    return {name: centres[name] for name in names}


@pytest.mark.parametrize("width,height,panels,crop", [(1440, 288, 5, 16), (1280, 256, 5, 0), (2048, 512, 4, 0)])
def test_deschaintre_synthetic(tmp_path, width, height, panels, crop):
    path = tmp_path / f"strip{width}.png"
    centres = make_strip(path, panels, height, crop)
    m, photo = Material.from_deschaintre(path, return_photo=True)
    inner = height - 2 * crop
    assert (m.height, m.width) == (inner, inner)
    as_stored = lambda a: torch.from_numpy(np.asarray(a, np.float32) / 255).permute(2, 0, 1)  # noqa: E731
    torch.testing.assert_close(m.diffuse, as_stored(centres["diffuse"]), rtol=0, atol=1e-7)
    torch.testing.assert_close(m.specular, as_stored(centres["specular"]), rtol=0, atol=1e-7)
    assert m.diffuse[:, 0, 0].tolist() == pytest.approx([1 / 255, 2 / 255, 3 / 255])  # crop offset
    torch.testing.assert_close(m.roughness, torch.full((1, inner, inner), 70 / 255), rtol=0, atol=1e-7)
    decoded = 2 * centres["normal"][0, 0] / 255 - 1
    torch.testing.assert_close(m.normal[:, 5, 5], torch.tensor(decoded / np.linalg.norm(decoded), dtype=torch.float32))
    assert m.provenance == {"source": path.name, "format": f"deschaintre{panels}", "encoding": "stored-as-is"}
    assert m.convention == "deepbasis"
    if panels == 5:
        torch.testing.assert_close(photo, as_stored(centres["photo"]), rtol=0, atol=1e-7)
    else:
        assert photo is None
    assert isinstance(Material.from_deschaintre(path), Material)


def test_deschaintre_wrong_size(tmp_path):
    path = write_image(tmp_path / "odd.png", np.zeros((200, 1000, 3), np.float32))
    with pytest.raises(MaterialError, match="odd.png: 1000x200 is not a Deschaintre") as exc:
        Material.from_deschaintre(path)
    assert "1440x288" in str(exc.value)
    with pytest.raises(MaterialError, match="no such file"):
        Material.from_deschaintre(tmp_path / "missing.png")


def test_deschaintre_test_set():
    if not DESCHAINTRE_TEST.is_dir():
        pytest.skip(f"evaluation data not found at {DESCHAINTRE_TEST} (see shared/data/README.md)")
    files = sorted(DESCHAINTRE_TEST.glob("*.png"))
    assert len(files) == 84
    for path in files:
        m, photo = Material.from_deschaintre(path, return_photo=True)
        assert (m.height, m.width) == (256, 256) and photo.shape == (3, 256, 256)
        assert max_error(torch.linalg.vector_norm(m.normal, dim=0), torch.ones(256, 256)) < 1e-5
        assert m.normal[2].min() >= 0
        for t in (m.diffuse, m.roughness, m.specular, photo):
            assert 0.0 <= t.min() and t.max() <= 1.0
        assert m.provenance["format"] == "deschaintre5" and m.provenance["source"] == path.name


# --- metallic-roughness ----------------------------------------------------------------------------


@pytest.mark.parametrize("metal", ["dielectric", "metal", "mixed", "binary"])
def test_pbr_round_trip(metal):
    g = torch.Generator().manual_seed(1)
    h, w = 16, 16
    base = 0.1 + 0.9 * torch.rand(3, h, w, generator=g)  # luminance above f0: metals are identifiable
    metallic = {
        "dielectric": torch.zeros(1, h, w),
        "metal": torch.ones(1, h, w),
        "mixed": torch.rand(1, h, w, generator=g),
        "binary": (torch.rand(1, h, w, generator=g) > 0.5).float(),
    }[metal]
    roughness = torch.rand(1, h, w, generator=g)
    m = Material.from_pbr(base, metallic, roughness)
    torch.testing.assert_close(m.diffuse, base * (1 - metallic))
    torch.testing.assert_close(m.specular, 0.04 * (1 - metallic) + base * metallic)
    pbr = m.to_pbr()
    assert pbr["base_color"].shape == (3, h, w) and pbr["metallic"].shape == (1, h, w)
    assert max_error(pbr["metallic"], metallic) < 1e-3
    assert max_error(pbr["base_color"], base) < 1e-3
    again = Material.from_pbr(pbr["base_color"], pbr["metallic"], pbr["roughness"], normal=m.normal)
    for name in MAP_NAMES:
        assert max_error(getattr(again, name), getattr(m, name)) < 1e-3, name


def test_pbr_hand_computed_and_dielectrics():
    # base 0.8 grey, metallic 0.5: diffuse 0.4, specular 0.04 * 0.5 + 0.8 * 0.5 = 0.42;
    # f0 m^2 + (0.4 + 0.42 - 0.08) m + (0.04 - 0.42) = 0  ->  m = 0.5.
    m = Material.constant(2, 2, diffuse=0.4, specular=0.42)
    pbr = m.to_pbr()
    torch.testing.assert_close(pbr["metallic"], torch.full((1, 2, 2), 0.5))
    torch.testing.assert_close(pbr["base_color"], torch.full((3, 2, 2), 0.8))

    g = torch.Generator().manual_seed(2)
    dielectric = Material(random_material().normal, torch.rand(3, 16, 12, generator=g), torch.rand(1, 16, 12),
                          torch.full((3, 16, 12), 0.04))
    pbr = dielectric.to_pbr()
    assert (pbr["metallic"] == 0).all()
    torch.testing.assert_close(pbr["base_color"], dielectric.diffuse, rtol=0, atol=1e-6)
    assert (Material.constant(2, 2, specular=0.01).to_pbr()["metallic"] == 0).all()  # below f0

    with pytest.raises(MaterialError, match="metallic values lie in"):
        Material.from_pbr(torch.rand(3, 4, 4), torch.full((1, 4, 4), 1.5), torch.rand(1, 4, 4))
    with pytest.raises(MaterialError, match=r"base_color must have shape \(3, H, W\)"):
        Material.from_pbr(torch.rand(4, 4, 3), torch.zeros(1, 4, 4), torch.rand(1, 4, 4))


def test_metallic_share_of_a_batch_is_each_materials_split():
    from mideepbasis.material import metallic_share

    g = torch.Generator().manual_seed(5)
    base = 0.2 + 0.8 * torch.rand(2, 3, 8, 8, generator=g)
    metallic = torch.stack([torch.ones(1, 8, 8), torch.rand(1, 8, 8, generator=g)])
    split = [Material.from_pbr(b, m, torch.rand(1, 8, 8, generator=g), dielectric_f0=0.08) for b, m in zip(base, metallic)]
    diffuse = torch.stack([material.diffuse for material in split])
    specular = torch.stack([material.specular for material in split])
    shares = metallic_share(diffuse, specular, 0.08)
    assert shares.shape == (2, 1, 8, 8)
    torch.testing.assert_close(shares, metallic, rtol=0, atol=1e-3)


def test_grey_dielectric_specular_keeps_a_metals_colour_and_greys_a_dielectrics():
    from mideepbasis.material import grey_dielectric_specular

    weights = torch.tensor(constants.LUMINANCE_WEIGHTS).view(3, 1, 1)
    g = torch.Generator().manual_seed(4)
    base = 0.2 + 0.8 * torch.rand(3, 8, 8, generator=g)
    metal = Material.from_pbr(base, torch.ones(1, 8, 8), torch.rand(1, 8, 8), dielectric_f0=0.08)
    torch.testing.assert_close(grey_dielectric_specular(metal.diffuse, metal.specular, 0.08), metal.specular)
    # A bright diffuse under a dim green specular: a dielectric whose F0 has no colour.
    diffuse = torch.full((3, 8, 8), 0.5)
    green = torch.tensor([0.02, 0.07, 0.02]).view(3, 1, 1).expand(3, 8, 8)
    grey = grey_dielectric_specular(diffuse, green, 0.08)
    torch.testing.assert_close(grey, (weights * green).sum(0, keepdim=True).expand(3, 8, 8))
    # Half metal: half of its colour kept, the luminance unchanged.
    half = Material.from_pbr(base, torch.full((1, 8, 8), 0.5), torch.rand(1, 8, 8), dielectric_f0=0.08)
    kept = grey_dielectric_specular(half.diffuse, half.specular, 0.08)
    luminance = (weights * half.specular).sum(0, keepdim=True)
    torch.testing.assert_close(kept, luminance + 0.5 * (half.specular - luminance), rtol=0, atol=1e-4)
    torch.testing.assert_close((weights * kept).sum(0), luminance[0], rtol=0, atol=1e-5)
