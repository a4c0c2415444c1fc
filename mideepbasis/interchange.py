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

Given the range of ``height.png`` (``export.write_height``: the PNG's black and white in patch
half-widths, which are the quad's scene units: it spans 2), both also displace the surface by
the height along its normal: MaterialX through a ``displacement`` node (``scale`` the range, the
PNG's value of zero height subtracted in the node graph), USD through ``inputs:displacement``
(the texture's ``scale`` the range, its ``bias`` the PNG's black). The height has zero mean, so
the mean surface stays where the quad is.
"""

from __future__ import annotations

import math

from pathlib import Path

import numpy as np

from .imageio import write_bytes

#: The texture files the three exports share, by role.
TEXTURES = {"base_color": "base_color.png", "metallic_roughness": "metallic_roughness.png",
            "normal": "normal.png", "specular_color": "specular_color.png"}

#: The height map the MaterialX and USD exports displace the surface by (16-bit, its range mapped
#: to [0, 1]; ``export.write_height``).
HEIGHT_TEXTURE = "height.png"


def height_mapping(height_range: tuple[float, float]) -> tuple[float, float]:
    """(scale, bias) that take ``height.png``'s values v in [0, 1] to heights in scene units
    (patch half-widths): h = scale v + bias, ``height_range`` the PNG's (black, white); six
    significant digits, as the documents write them."""
    low, high = (float(value) for value in height_range)
    scale = float(f"{high - low:.6g}")
    return scale, float(f"{low:.6g}") + 0.0  # no negative zero


def _zero_level(height_range: tuple[float, float]) -> float:
    """The value of ``height.png`` at zero height (six significant digits)."""
    low, high = (float(value) for value in height_range)
    return float(f"{-low / max(high - low, 1e-12):.6g}") + 0.0


def materialx_document(specular_factor: float, name: str = "captured_material",
                       height_range: tuple[float, float] | None = None) -> str:
    """The text of ``material.mtlx``: an Autodesk Standard Surface reading the glTF's textures
    through a node graph, ``specular`` the glTF's specular factor (six significant digits, as
    MaterialX writes floats). With ``height_range`` (``height.png``'s black and white [patch
    half-widths]) the material also has a ``displacement`` shader: ``height.png`` less its value at
    zero height, times ``scale`` = white - black.

    Written as text rather than through the MaterialX API: the document is the same for every
    capture but for one float, and building and validating it took 0.2 s of each capture's
    Python time, beside the preview thread that needs the interpreter too. The tests read it
    back with MaterialX, validate it against the standard library and check that MaterialX writes
    it back the same."""
    graph = f"NG_{name}"

    def image(node: str, role: str, kind: str, colour: bool) -> str:
        colour_space = ' colorspace="srgb_texture"' if colour else ""
        return (f'    <image name="{node}" type="{kind}">\n'
                f'      <input name="file" type="filename" value="{TEXTURES[role]}"{colour_space} />\n'
                "    </image>\n")

    def extract(channel: str, index: int) -> str:
        return (f'    <extract name="{channel}_channel" type="float">\n'
                '      <input name="in" type="vector3" nodename="metallic_roughness_image" />\n'
                f'      <input name="index" type="integer" value="{index}" />\n'
                "    </extract>\n")

    height_nodes = height_output = displacement = displacement_input = ""
    if height_range is not None:
        scale, _ = height_mapping(height_range)
        height_nodes = ('    <image name="height_image" type="float">\n'
                        f'      <input name="file" type="filename" value="{HEIGHT_TEXTURE}" />\n'
                        "    </image>\n"
                        '    <subtract name="height_centred" type="float">\n'
                        '      <input name="in1" type="float" nodename="height_image" />\n'
                        f'      <input name="in2" type="float" value="{_zero_level(height_range):.6g}" />\n'
                        "    </subtract>\n")
        height_output = '    <output name="height_output" type="float" nodename="height_centred" />\n'
        displacement = (f'  <displacement name="DS_{name}" type="displacementshader">\n'
                        f'    <input name="displacement" type="float" output="height_output" nodegraph="{graph}" />\n'
                        f'    <input name="scale" type="float" value="{scale:.6g}" />\n'
                        "  </displacement>\n")
        displacement_input = (f'    <input name="displacementshader" type="displacementshader" '
                              f'nodename="DS_{name}" />\n')
    outputs = (("base_color", "color3", "base_color_image"), ("specular_color", "color3", "specular_color_image"),
               ("specular_roughness", "float", "roughness_channel"), ("metalness", "float", "metalness_channel"),
               ("normal", "vector3", "normal_map"))
    return ('<?xml version="1.0"?>\n<materialx version="1.39">\n'
            f'  <nodegraph name="{graph}">\n'
            + image("base_color_image", "base_color", "color3", True)
            + image("metallic_roughness_image", "metallic_roughness", "vector3", False)
            + image("specular_color_image", "specular_color", "color3", True)
            + image("normal_image", "normal", "vector3", False)
            + extract("roughness", 1) + extract("metalness", 2)
            + '    <normalmap name="normal_map" type="vector3">\n'
              '      <input name="in" type="vector3" nodename="normal_image" />\n'
              "    </normalmap>\n"
            + height_nodes
            + "".join(f'    <output name="{output}_output" type="{kind}" nodename="{node}" />\n'
                      for output, kind, node in outputs)
            + height_output
            + "  </nodegraph>\n"
            f'  <standard_surface name="SR_{name}" type="surfaceshader">\n'
            + "".join(f'    <input name="{output}" type="{kind}" output="{output}_output" nodegraph="{graph}" />\n'
                      for output, kind, _ in outputs)
            + '    <input name="base" type="float" value="1" />\n'
            f'    <input name="specular" type="float" value="{float(specular_factor):.6g}" />\n'
            '    <input name="specular_IOR" type="float" value="1.5" />\n'
            "  </standard_surface>\n"
            + displacement
            + f'  <surfacematerial name="{name}" type="material">\n'
            f'    <input name="surfaceshader" type="surfaceshader" nodename="SR_{name}" />\n'
            + displacement_input
            + "  </surfacematerial>\n</materialx>\n")


def write_materialx(folder: Path, specular_factor: float, height_range: tuple[float, float] | None = None) -> Path:
    """``material.mtlx`` in ``folder`` (``materialx_document``; the textures, and ``height.png``
    with ``height_range``, must be there), written whole or not at all."""
    return write_bytes(Path(folder) / "material.mtlx",
                       materialx_document(specular_factor, height_range=height_range).encode())


def _usd_texture(material: str, node: str, role: str, colour_space: str, outputs: tuple[str, ...],
                 scale_bias: tuple[str, str] | None = None) -> str:
    """A ``UsdUVTexture`` shader of ``usd_document`` (its attributes in USD's own sorted order)."""
    lines = [f'        def Shader "{node}"', "        {", '            uniform token info:id = "UsdUVTexture"']
    if scale_bias:
        lines.append(f"            float4 inputs:bias = {scale_bias[1]}")
    lines.append(f"            asset inputs:file = @{HEIGHT_TEXTURE if role == 'height' else TEXTURES[role]}@")
    if scale_bias:
        lines.append(f"            float4 inputs:scale = {scale_bias[0]}")
    lines += [f'            token inputs:sourceColorSpace = "{colour_space}"',
              f"            float2 inputs:st.connect = </sample/{material}/st_reader.outputs:result>",
              '            token inputs:wrapS = "clamp"', '            token inputs:wrapT = "clamp"',
              *(f"            float{3 if output == 'rgb' else ''} outputs:{output}" for output in outputs), "        }"]
    return "\n".join(lines)


def _usd_float(value: float) -> str:
    """A float as USD's text format writes a ``float``: the shortest digits that give back the
    float32, positional from 1e-6 to 1e21, else as ``1.5e-7``."""
    single = np.float32(value) + np.float32(0.0)  # no negative zero
    if single == 0 or 1e-6 <= abs(single) < 1e21:
        return np.format_float_positional(single, trim="-")
    return np.format_float_scientific(single, trim="-", exp_digits=1).replace("e+", "e")


def ior_of_f0(f0: float) -> float:
    """The index of refraction whose Fresnel reflectance at normal incidence is ``f0``:
    f0 = ((n - 1) / (n + 1))^2, so n = (1 + sqrt(f0)) / (1 - sqrt(f0)); f0 clamped to [0.01, 0.2]
    (n 1.22 - 2.62, the dielectrics' range)."""
    root = math.sqrt(min(max(f0, 0.01), 0.2))
    return (1.0 + root) / (1.0 - root)


def usd_document(name: str = "captured_material", ior: float = 1.5,
                 height_range: tuple[float, float] | None = None) -> str:
    """The text of ``material.usda`` (USD's ASCII format): a 2 x 2 quad on the ground (+y up, like
    the glTF's) with a ``UsdPreviewSurface`` (metallic workflow) reading the glTF's textures, its
    ``ior`` the one of the captured dielectric F0 (``ior_of_f0``): the surface's only input for a
    grey dielectric specular (Blender and other readers take F0 = 0.04, ior 1.5, without it).
    With ``height_range`` (``height.png``'s black and white [patch half-widths]), the surface's
    ``displacement`` reads ``height.png`` scaled and biased into scene units (``height_mapping``).

    Written as text rather than through ``pxr``: the document is the same for every capture but
    for its name, and importing ``pxr`` (0.1 s) while the preview renders in another thread could
    deadlock the process (its libraries' initialisers take the GIL while the loader's lock is held).
    The tests read it back with ``pxr`` and run USD's validators on it."""
    textures = "\n\n".join([
        _usd_texture(name, "base_color_texture", "base_color", "sRGB", ("rgb",)),
        _usd_texture(name, "metallic_roughness_texture", "metallic_roughness", "raw", ("b", "g")),
        _usd_texture(name, "normal_texture", "normal", "raw", ("rgb",), ("(2, 2, 2, 1)", "(-1, -1, -1, 0)"))]
        + ([] if height_range is None else [_usd_texture(name, "height_texture", "height", "raw", ("r",), tuple(
            f"({value}, {value}, {value}, {last})" for value, last in
            zip(map(_usd_float, height_mapping(height_range)), (1, 0))))]))
    displacement_output = displacement_input = displacement_terminal = ""
    if height_range is not None:
        displacement_output = f"""
        token outputs:displacement.connect = </sample/{name}/surface.outputs:displacement>"""
        displacement_input = f"""
            float inputs:displacement.connect = </sample/{name}/height_texture.outputs:r>"""
        displacement_terminal = """
            token outputs:displacement"""
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
    {{{displacement_output}
        token outputs:surface.connect = </sample/{name}/surface.outputs:surface>

        def Shader "surface"
        {{
            uniform token info:id = "UsdPreviewSurface"
            color3f inputs:diffuseColor.connect = </sample/{name}/base_color_texture.outputs:rgb>{displacement_input}
            float inputs:ior = {round(ior, 4):g}
            float inputs:metallic.connect = </sample/{name}/metallic_roughness_texture.outputs:b>
            normal3f inputs:normal.connect = </sample/{name}/normal_texture.outputs:rgb>
            float inputs:roughness.connect = </sample/{name}/metallic_roughness_texture.outputs:g>
            int inputs:useSpecularWorkflow = 0{displacement_terminal}
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


def write_usd(folder: Path, name: str = "captured_material", ior: float = 1.5,
              height_range: tuple[float, float] | None = None) -> Path:
    """``material.usda`` in ``folder`` (``usd_document``), written whole or not at all."""
    return write_bytes(Path(folder) / "material.usda", usd_document(name, ior, height_range).encode())
