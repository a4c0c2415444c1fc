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
    """Whether ``usd-core`` (``pxr``) is installed (``pip install 'mideepbasis[usd]'``): only to read
    the USD files back (the tests); ``write_usd`` needs nothing."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def _usd_texture(material: str, node: str, role: str, colour_space: str, outputs: tuple[str, ...],
                 scale_bias: tuple[str, str] | None = None) -> str:
    """A ``UsdUVTexture`` shader of ``usd_document`` (its attributes in USD's own sorted order)."""
    lines = [f'        def Shader "{node}"', "        {", '            uniform token info:id = "UsdUVTexture"']
    if scale_bias:
        lines.append(f"            float4 inputs:bias = {scale_bias[1]}")
    lines.append(f"            asset inputs:file = @{TEXTURES[role]}@")
    if scale_bias:
        lines.append(f"            float4 inputs:scale = {scale_bias[0]}")
    lines += [f'            token inputs:sourceColorSpace = "{colour_space}"',
              f"            float2 inputs:st.connect = </sample/{material}/st_reader.outputs:result>",
              '            token inputs:wrapS = "clamp"', '            token inputs:wrapT = "clamp"',
              *(f"            float{3 if output == 'rgb' else ''} outputs:{output}" for output in outputs), "        }"]
    return "\n".join(lines)


def usd_document(name: str = "captured_material") -> str:
    """The text of ``material.usda`` (USD's ASCII format): a 2 x 2 quad on the ground (+y up, like
    the glTF's) with a ``UsdPreviewSurface`` (metallic workflow) reading the glTF's textures.

    Written as text rather than through ``pxr``: the document is the same for every capture but
    for its name, and importing ``pxr`` (0.1 s) while the preview renders in another thread could
    deadlock the process (its libraries' initialisers take the GIL while the loader's lock is held).
    The tests read it back with ``pxr`` and run USD's validators on it."""
    textures = "\n\n".join([
        _usd_texture(name, "base_color_texture", "base_color", "sRGB", ("rgb",)),
        _usd_texture(name, "metallic_roughness_texture", "metallic_roughness", "raw", ("b", "g")),
        _usd_texture(name, "normal_texture", "normal", "raw", ("rgb",), ("(2, 2, 2, 1)", "(-1, -1, -1, 0)"))])
    # Our +x is +X, our +y (the image's top) is -Z, as in the glTF; st runs up the image (t = 1 at the top).
    return f"""#usda 1.0
(
    defaultPrim = "sample"
    metersPerUnit = 1
    upAxis = "Y"
)

def Xform "sample"
{{
    def Mesh "quad" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {{
        float3[] extent = [(-1, 0, -1), (1, 0, 1)]
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        rel material:binding = </sample/{name}>
        normal3f[] normals = [(0, 1, 0), (0, 1, 0), (0, 1, 0), (0, 1, 0)] (
            interpolation = "vertex"
        )
        point3f[] points = [(-1, 0, 1), (1, 0, 1), (1, 0, -1), (-1, 0, -1)]
        texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1), (0, 1)] (
            interpolation = "vertex"
        )
    }}

    def Material "{name}"
    {{
        token outputs:surface.connect = </sample/{name}/surface.outputs:surface>

        def Shader "surface"
        {{
            uniform token info:id = "UsdPreviewSurface"
            color3f inputs:diffuseColor.connect = </sample/{name}/base_color_texture.outputs:rgb>
            float inputs:metallic.connect = </sample/{name}/metallic_roughness_texture.outputs:b>
            normal3f inputs:normal.connect = </sample/{name}/normal_texture.outputs:rgb>
            float inputs:roughness.connect = </sample/{name}/metallic_roughness_texture.outputs:g>
            int inputs:useSpecularWorkflow = 0
            token outputs:surface
        }}

        def Shader "st_reader"
        {{
            uniform token info:id = "UsdPrimvarReader_float2"
            string inputs:varname = "st"
            float2 outputs:result
        }}

{textures}
    }}
}}

"""


def write_usd(folder: Path, name: str = "captured_material") -> Path:
    """``material.usda`` in ``folder`` (``usd_document``), written whole or not at all."""
    path = Path(folder) / "material.usda"
    temporary = path.with_name(f".{path.stem}.tmp-{os.getpid()}.usda")
    temporary.write_text(usd_document(name))
    os.replace(temporary, path)
    return path
