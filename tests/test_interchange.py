"""MaterialX and USD exports: they validate, and read back they name the glTF's textures and values,
each texture in its right colour space, and displace the surface by height.png in scene units."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mideepbasis.export import gltf_material, write_height
from mideepbasis.imageio import read_image
from mideepbasis.interchange import materialx_document, usd_document, write_materialx, write_usd
from mideepbasis.material import Material


def usd_available() -> bool:
    """Whether ``usd-core`` (``pxr``), which reads the USD files back, is installed (the ``usd`` extra)."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def height_png(folder) -> np.ndarray:
    """``height.png`` read back, in [0, 1]."""
    import cv2

    return cv2.imread(str(folder / "height.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / 65535


def true_height(folder) -> np.ndarray:
    """``height.exr`` read back [patch half-widths = scene units: the quad spans 2]."""
    return read_image(folder / "height.exr")[..., 0].astype(np.float64)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A material folder with its glTF, height, MaterialX and USD exports."""
    folder = tmp_path_factory.mktemp("exported")
    generator = torch.Generator().manual_seed(0)
    size = 16
    normal = torch.nn.functional.normalize(torch.randn(3, size, size, generator=generator) * 0.2
                                           + torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1), dim=0)
    specular = torch.rand(3, size, size, generator=generator) * 0.08  # coloured, above the 0.04 of dielectrics
    material = Material(normal, torch.rand(3, size, size, generator=generator),
                        torch.rand(1, size, size, generator=generator), specular)
    material.save(folder)
    gltf = gltf_material(material, folder)
    (folder / "material.gltf").write_text(json.dumps(gltf))
    record = write_height(folder, material)
    height_range = (record["png_black"], record["png_white"])
    write_materialx(folder, gltf["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"][0],
                    height_range=height_range)
    write_usd(folder, height_range=height_range)
    return folder, gltf


def test_materialx_validates_and_carries_the_gltf(exported):
    import MaterialX as mx

    folder, gltf = exported
    document = mx.createDocument()
    mx.readFromXmlFile(document, str(folder / "material.mtlx"))
    library = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), library)
    document.importLibrary(library)
    valid, message = document.validate()
    assert valid, message
    files = {}
    for node in document.getNodeGraphs()[0].getNodes("image"):
        file_input = node.getInput("file")
        files[file_input.getValueString()] = file_input.getColorSpace()
    assert set(files) == {image["uri"] for image in gltf["images"]} | {"height.png"}
    assert files == {"base_color.png": "srgb_texture", "specular_color.png": "srgb_texture",
                     "metallic_roughness.png": "", "normal.png": "", "height.png": ""}  # colour data sRGB, the rest raw
    shader = document.getNodes("standard_surface")[0]
    factor = gltf["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"][0]
    # MaterialX writes six significant digits; a factor above 1 keeps the coloured F0 above 0.04.
    assert shader.getInputValue("specular") == pytest.approx(factor, rel=1e-5) and factor > 1
    assert shader.getInputValue("specular_IOR") == pytest.approx(1.5)  # 0.04 x specular x colour, as glTF
    extracts = {node.getName(): node.getInputValue("index") for node in document.getNodeGraphs()[0].getNodes("extract")}
    assert extracts == {"roughness_channel": 1, "metalness_channel": 2}  # glTF packs roughness in G, metallic in B


def test_materialx_displaces_by_the_height_png_in_scene_units(exported):
    """The material's displacement shader reads height.png (float, raw) less its value at zero
    height, times the height's range: read back, the PNG gives the EXR's heights again."""
    import MaterialX as mx

    folder, _ = exported
    document = mx.createDocument()
    mx.readFromXmlFile(document, str(folder / "material.mtlx"))
    material = document.getNodes("surfacematerial")[0]
    displacement = material.getConnectedNode("displacementshader")
    assert displacement.getCategory() == "displacement" and displacement.getType() == "displacementshader"
    graph = document.getNodeGraphs()[0]
    centred = graph.getNode(graph.getOutput(displacement.getInput("displacement").getOutputString()).getNodeName())
    image = centred.getConnectedNode("in1")
    assert centred.getCategory() == "subtract" and image.getCategory() == "image" and image.getType() == "float"
    assert image.getInputValue("file") == "height.png" and image.getInput("file").getColorSpace() == ""
    # The expected mapping, from the EXR alone: scale its range, the zero level its minimum's place.
    height = true_height(folder)
    low, high = height.min(), height.max()
    scale, zero = displacement.getInputValue("scale"), centred.getInputValue("in2")
    assert scale == pytest.approx(high - low, rel=1e-5) and high - low > 0.01
    assert zero == pytest.approx(-low / (high - low), rel=1e-5) and 0 < zero < 1
    displaced = (height_png(folder) - zero) * scale
    assert np.abs(displaced - height).max() < (high - low) * 1e-4  # 16-bit steps and six digits
    assert abs(displaced.mean()) < (high - low) * 1e-4  # the mean surface stays on the quad


def test_without_a_height_range_the_documents_have_no_displacement():
    """Callers that give no range (older ones) get the documents without height.png."""
    assert "displacement" not in materialx_document(1.0) and "height.png" not in materialx_document(1.0)
    assert "displacement" not in usd_document() and "height.png" not in usd_document()


@pytest.mark.parametrize("factor", [1.30061, 1.0, 0.25, 2.0 / 3.0, 12345.678, 1.5e-05])
def test_the_materialx_text_is_what_materialx_itself_writes(tmp_path, factor):
    """``write_materialx`` writes the text by hand: MaterialX, reading it, writes the same bytes."""
    import MaterialX as mx

    path = write_materialx(tmp_path, factor)
    document = mx.createDocument()
    mx.readFromXmlFile(document, str(path))
    assert mx.writeToXmlString(document) == path.read_text()
    specular = document.getNodes("standard_surface")[0].getInputValue("specular")
    assert specular == pytest.approx(factor, rel=1e-5)
    assert not list(tmp_path.glob(".*"))  # no temporary left


#: Height ranges (black, white) [patch half-widths] whose numbers the documents must write as the
#: libraries do: a capture's, tiny, large, flat, and ones with many digits.
HEIGHT_RANGES = [(-0.0098002357, 0.004810004), (-1.5e-07, 2.5e-07), (-2.5e-12, 1e-12), (0.0, 0.0),
                 (-123.456789, 98.7654321), (-1e-05, 3e-05), (-1.0 / 3.0, 2.0 / 3.0)]


@pytest.mark.parametrize("height_range", HEIGHT_RANGES)
def test_the_materialx_text_with_displacement_is_what_materialx_itself_writes(tmp_path, height_range):
    import MaterialX as mx

    path = write_materialx(tmp_path, 1.3, height_range=height_range)
    document = mx.createDocument()
    mx.readFromXmlFile(document, str(path))
    assert mx.writeToXmlString(document) == path.read_text()
    library = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), library)
    document.importLibrary(library)
    valid, message = document.validate()
    assert valid, message
    displacement = document.getNodes("displacement")[0]
    assert displacement.getInputValue("scale") == pytest.approx(height_range[1] - height_range[0], rel=1e-5, abs=1e-30)


@pytest.mark.skipif(not usd_available(), reason="usd-core is not installed (pip install 'mideepbasis[usd]')")
def test_usd_validates_and_carries_the_gltf(exported):
    from pxr import Usd, UsdShade, UsdValidation

    folder, gltf = exported
    stage = Usd.Stage.Open(str(folder / "material.usda"))
    # USD's own validators (usdchecker's): every one that is registered.
    registry = UsdValidation.ValidationRegistry()
    errors = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators()).Validate(stage)
    assert not errors, [error.GetMessage() for error in errors]
    textures = {}
    surface = None
    for prim in stage.Traverse():
        shader = UsdShade.Shader(prim)
        if not shader:
            continue
        identifier = shader.GetIdAttr().Get()
        if identifier == "UsdUVTexture":
            textures[shader.GetInput("file").Get().path] = shader.GetInput("sourceColorSpace").Get()
        elif identifier == "UsdPreviewSurface":
            surface = shader
    assert set(textures) <= {image["uri"] for image in gltf["images"]} | {"height.png"}
    assert textures == {"base_color.png": "sRGB", "metallic_roughness.png": "raw", "normal.png": "raw",
                        "height.png": "raw"}
    sources = {name: surface.GetInput(name).GetConnectedSource()[1] for name in ("roughness", "metallic", "diffuseColor")}
    assert sources == {"roughness": "g", "metallic": "b", "diffuseColor": "rgb"}
    mesh = stage.GetPrimAtPath("/sample/quad")
    assert UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()[0].GetPath().name == "captured_material"


@pytest.mark.skipif(not usd_available(), reason="usd-core is not installed (pip install 'mideepbasis[usd]')")
def test_the_usd_text_is_what_usd_itself_writes_and_takes_the_material_name(tmp_path):
    """``write_usd`` writes the text by hand: USD, given the stage it describes, writes the same bytes."""
    from pxr import Sdf, Usd, UsdShade

    path = write_usd(tmp_path, name="brick_wall")
    stage = Usd.Stage.Open(str(path))
    mesh = stage.GetPrimAtPath("/sample/quad")
    assert UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()[0].GetPath() == Sdf.Path("/sample/brick_wall")
    rewritten = tmp_path / "rewritten.usda"
    stage.GetRootLayer().Export(str(rewritten))
    assert rewritten.read_text() == path.read_text()
    assert not list(tmp_path.glob(".*"))  # no temporary left


@pytest.mark.skipif(not usd_available(), reason="usd-core is not installed (pip install 'mideepbasis[usd]')")
def test_usd_displaces_by_the_height_png_in_scene_units(exported):
    """The surface's displacement (the material's displacement terminal) reads height.png's red
    (raw) scaled by the height's range and biased by its minimum: the EXR's heights again."""
    from pxr import Usd, UsdShade

    folder, _ = exported
    stage = Usd.Stage.Open(str(folder / "material.usda"))
    material = UsdShade.Material(stage.GetPrimAtPath("/sample/captured_material"))
    surface, terminal, _ = material.ComputeDisplacementSource()
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface" and terminal == "displacement"
    texture, output, _ = surface.GetInput("displacement").GetConnectedSource()
    texture = UsdShade.Shader(texture)
    assert texture.GetIdAttr().Get() == "UsdUVTexture" and output == "r"
    assert texture.GetInput("file").Get().path == "height.png" and texture.GetInput("sourceColorSpace").Get() == "raw"
    height = true_height(folder)
    low, high = height.min(), height.max()
    scale, bias = texture.GetInput("scale").Get(), texture.GetInput("bias").Get()
    assert scale[0] == pytest.approx(high - low, rel=1e-5) and bias[0] == pytest.approx(low, rel=1e-5)
    assert tuple(scale) == (scale[0],) * 3 + (1,) and tuple(bias) == (bias[0],) * 3 + (0,)
    displaced = height_png(folder) * scale[0] + bias[0]
    assert np.abs(displaced - height).max() < (high - low) * 1e-4  # 16-bit steps and six digits
    assert abs(displaced.mean()) < (high - low) * 1e-4  # the mean surface stays on the quad


@pytest.mark.skipif(not usd_available(), reason="usd-core is not installed (pip install 'mideepbasis[usd]')")
@pytest.mark.parametrize("height_range", HEIGHT_RANGES)
def test_the_usd_text_with_displacement_is_what_usd_itself_writes(tmp_path, height_range):
    from pxr import Usd, UsdShade

    path = write_usd(tmp_path, height_range=height_range)
    stage = Usd.Stage.Open(str(path))
    rewritten = tmp_path / "rewritten.usda"
    stage.GetRootLayer().Export(str(rewritten))
    assert rewritten.read_text() == path.read_text()
    texture = UsdShade.Shader(stage.GetPrimAtPath("/sample/captured_material/height_texture"))
    assert texture.GetInput("scale").Get()[0] == pytest.approx(height_range[1] - height_range[0], rel=1e-5, abs=1e-30)
    assert texture.GetInput("bias").Get()[0] == pytest.approx(height_range[0], rel=1e-5, abs=1e-30)


def test_the_index_of_refraction_gives_back_the_dielectric_f0():
    from mideepbasis.interchange import ior_of_f0

    assert ior_of_f0(0.04) == pytest.approx(1.5)
    for f0 in (0.02, 0.032, 0.05, 0.1):
        n = ior_of_f0(f0)
        assert ((n - 1) / (n + 1)) ** 2 == pytest.approx(f0)
    assert ior_of_f0(0.0) == ior_of_f0(0.01) and ior_of_f0(0.9) == ior_of_f0(0.2)  # the dielectrics' range


@pytest.mark.skipif(not usd_available(), reason="usd-core is not installed (pip install 'mideepbasis[usd]')")
def test_the_usd_surface_carries_the_captured_f0_as_its_ior(tmp_path):
    from pxr import Usd, UsdShade

    from mideepbasis.export import dielectric_f0
    from mideepbasis.interchange import ior_of_f0

    material = Material.constant(8, 8, diffuse=0.4, roughness=0.3, specular=0.032)
    assert dielectric_f0(material) == pytest.approx(0.032, rel=1e-5)
    path = write_usd(tmp_path, ior=ior_of_f0(dielectric_f0(material)))
    stage = Usd.Stage.Open(str(path))
    surface = UsdShade.Shader(stage.GetPrimAtPath("/sample/captured_material/surface"))
    n = surface.GetInput("ior").Get()
    assert ((n - 1) / (n + 1)) ** 2 == pytest.approx(0.032, rel=1e-3)
