"""A capture for other tools: MaterialX (``material.mtlx``) and USD (``material.usda``).

Both read the very textures of the glTF export (``export.gltf_material``), so that the three
files agree: ``base_color.png`` (sRGB), ``metallic_roughness.png`` (linear; roughness in G,
metallic in B, as glTF packs them), ``normal.png`` (linear, (n + 1) / 2, +y up) and
``specular_color.png`` (sRGB; the dielectric F0 is 0.04 x ``specular`` x this colour).

- MaterialX: an Autodesk Standard Surface, whose dielectric Fresnel at normal incidence is
  ``specular`` x ``specular_color`` x ((ior - 1) / (ior + 1))^2 = 0.04 x ``specular`` x colour at
  ior 1.5, as ``KHR_materials_specular`` has it: nothing of the glTF is lost. Roughness is the
  perceptual one (alpha = r^2) in both.
- USD: a ``UsdPreviewSurface`` in its metallic workflow on a 2 x 2 quad (+y up, as the glTF's),
  which has no input for a dielectric's specular colour: the specular colour is lost (the
  surface keeps F0 = 0.04), as in any metallic-roughness-only tool.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

#: The texture files the three exports share, by role.
TEXTURES = {"base_color": "base_color.png", "metallic_roughness": "metallic_roughness.png",
            "normal": "normal.png", "specular_color": "specular_color.png"}


@functools.lru_cache(maxsize=1)
def _standard_library():
    """MaterialX's standard data library, loaded once per process (30 - 160 ms a load)."""
    import MaterialX as mx

    library = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), library)
    return library


def materialx_document(specular_factor: float, name: str = "captured_material"):
    """The MaterialX document (``MaterialX.Document``, standard library imported) of a capture."""
    import MaterialX as mx

    document = mx.createDocument()
    document.importLibrary(_standard_library())
    graph = document.addNodeGraph(f"NG_{name}")

    def image(node_name, filename, kind, colour_space=None):
        node = graph.addNode("image", node_name, kind)
        file_input = node.addInput("file", "filename")
        file_input.setValueString(filename)
        if colour_space:
            file_input.setColorSpace(colour_space)
        return node

    base = image("base_color_image", TEXTURES["base_color"], "color3", "srgb_texture")
    packed = image("metallic_roughness_image", TEXTURES["metallic_roughness"], "vector3")
    specular = image("specular_color_image", TEXTURES["specular_color"], "color3", "srgb_texture")
    normal_image = image("normal_image", TEXTURES["normal"], "vector3")
    channels = {}
    for channel, index in (("roughness", 1), ("metalness", 2)):
        node = graph.addNode("extract", f"{channel}_channel", "float")
        node.addInput("in", "vector3").setConnectedNode(packed)
        node.setInputValue("index", index)
        channels[channel] = node
    normal = graph.addNode("normalmap", "normal_map", "vector3")
    normal.addInput("in", "vector3").setConnectedNode(normal_image)
    outputs = {}
    for output_name, node, kind in (("base_color", base, "color3"), ("specular_color", specular, "color3"),
                                    ("specular_roughness", channels["roughness"], "float"),
                                    ("metalness", channels["metalness"], "float"), ("normal", normal, "vector3")):
        output = graph.addOutput(f"{output_name}_output", kind)
        output.setConnectedNode(node)
        outputs[output_name] = output

    shader = document.addNode("standard_surface", f"SR_{name}", "surfaceshader")
    for input_name, kind in (("base_color", "color3"), ("specular_color", "color3"), ("specular_roughness", "float"),
                             ("metalness", "float"), ("normal", "vector3")):
        shader.addInput(input_name, kind).setConnectedOutput(outputs[input_name])
    shader.setInputValue("base", 1.0)
    shader.setInputValue("specular", float(specular_factor))
    shader.setInputValue("specular_IOR", 1.5)
    document.addMaterialNode(name, shader)
    return document


#: Whether this process has validated a capture's MaterialX document (``write_materialx``).
_VALIDATED: list[bool] = []


def write_materialx(folder: Path, specular_factor: float) -> Path:
    """``material.mtlx`` in ``folder`` (the textures must be there), checked by MaterialX's validator
    (the first of a process)."""
    import MaterialX as mx

    document = materialx_document(specular_factor)
    # The documents differ only in the specular factor, a float: validated once per process (60 ms).
    if not _VALIDATED:
        valid, message = document.validate()
        if not valid:  # a bug of ours, not of the user's input
            raise RuntimeError(f"MaterialX rejected the document: {message}")
        _VALIDATED.append(True)
    options = mx.XmlWriteOptions()
    options.elementPredicate = lambda element: not element.hasSourceUri()  # not the standard library
    path = Path(folder) / "material.mtlx"
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    mx.writeToXmlFile(document, str(temporary), options)
    os.replace(temporary, path)
    return path


def usd_available() -> bool:
    """Whether ``usd-core`` (``pxr``) is installed (``pip install 'mideepbasis[usd]'``)."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def write_usd(folder: Path, name: str = "captured_material") -> Path:
    """``material.usda`` in ``folder``: a 2 x 2 quad on the ground (+y up, like the glTF's) with a
    ``UsdPreviewSurface`` (metallic workflow) reading the glTF's textures."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

    path = Path(folder) / "material.usda"
    temporary = path.with_name(f".{path.stem}.tmp-{os.getpid()}.usda")
    stage = Usd.Stage.CreateNew(str(temporary))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/sample")
    stage.SetDefaultPrim(root.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/sample/quad")
    # Our +x is +X, our +y (the image's top) is -Z, as in the glTF; st runs up the image (t = 1 at the top).
    mesh.CreatePointsAttr([(-1, 0, 1), (1, 0, 1), (1, 0, -1), (-1, 0, -1)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateNormalsAttr([(0, 1, 0)] * 4)
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateExtentAttr([(-1, 0, -1), (1, 0, 1)])
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])

    material = UsdShade.Material.Define(stage, f"/sample/{name}")
    surface = UsdShade.Shader.Define(stage, f"/sample/{name}/surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, f"/sample/{name}/st_reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    reader_output = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    def texture(node_name, role, colour_space, scale=None, bias=None):
        shader = UsdShade.Shader.Define(stage, f"/sample/{name}/{node_name}")
        shader.CreateIdAttr("UsdUVTexture")
        shader.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(TEXTURES[role])
        shader.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
        shader.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader_output)
        for key in ("wrapS", "wrapT"):
            shader.CreateInput(key, Sdf.ValueTypeNames.Token).Set("clamp")
        if scale is not None:
            shader.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
            shader.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
        return shader

    base = texture("base_color_texture", "base_color", "sRGB")
    packed = texture("metallic_roughness_texture", "metallic_roughness", "raw")
    normal = texture("normal_texture", "normal", "raw", scale=(2, 2, 2, 1), bias=(-1, -1, -1, 0))
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        base.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(
        packed.CreateOutput("g", Sdf.ValueTypeNames.Float))
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).ConnectToSource(
        packed.CreateOutput("b", Sdf.ValueTypeNames.Float))
    surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
        normal.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    os.replace(temporary, path)
    return path
