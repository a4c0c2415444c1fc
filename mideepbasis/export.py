"""What a capture leaves behind: the material folder, a Mitsuba scene, a glTF material, renders, a report.

``save_capture`` writes everything into a temporary folder beside the target and renames it into
place at the end, so the target is either complete or untouched.

Files of a capture folder:

- ``normal.png``, ``diffuse.png``, ``roughness.png``, ``specular.png``, ``material.json``: the
  material (docs/ARCHITECTURE.md section 6); with ``exr=True`` also the ``.exr`` maps (linear, signed normals);
- ``light.json``: the flash offset [patch half-widths] and its angle [deg], the field of view and
  where it came from, the lighting search's passes;
- ``photo.png`` (the working photo), ``rerender.png`` (the material under the estimated flash),
  ``error.png`` (|rerender - photo|, x4), ``environment.png`` (path traced in the studio, with
  ``preview_sphere.png`` and ``preview_cloth.png`` beside it; with a
  true material also ``environment_truth.png`` and ``environment_difference.png``);
- ``scene.xml``: a Mitsuba scene of the capture that uses the maps above and the ``svbrdf`` plugin
  (``import mideepbasis.render`` registers it before ``mi.load_file``);
- ``material.gltf`` with ``base_color.png``, ``metallic_roughness.png`` and ``specular_color.png``:
  a glTF 2.0 quad with the metallic-roughness approximation and KHR_materials_specular;
- ``height.exr``, ``height.png``, ``height.json``: the height integrated from the normals, which
  ``material.mtlx`` and ``material.usda`` (``interchange.py``) displace their surface by;
- ``report.png`` and ``report.html``.
"""

from __future__ import annotations

import base64
import json
import math
import os
import queue
import struct
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from . import constants
from .imageio import background_writes, linear_to_srgb, write_bytes, write_image
from .outputs import OutputFolder


def _json_bytes(document: dict) -> bytes:
    return (json.dumps(document, indent=2) + "\n").encode()


def _hwc(image: torch.Tensor) -> np.ndarray:
    return image.detach().cpu().permute(1, 2, 0).numpy()


# --- the Mitsuba scene ------------------------------------------------------------------------------

_SCENE = """<!-- A mideepbasis capture as a Mitsuba 3 scene: the flash shot that was estimated, with the
     captured maps on the sample square [-1, 1]^2 (z = 0, +z up). The svbrdf plugin is Python:
         import mideepbasis.render, mitsuba as mi
         image = mi.render(mi.load_file("scene.xml"), spp=64)
     Maps: diffuse and specular are sRGB PNGs (decoded by Mitsuba), normal (n + 1) / 2, roughness linear.
     Image row 0 lies at +y: the bitmaps flip v. -->
<scene version="3.0.0">
    <default name="spp" value="64"/>
    <default name="resolution" value="{resolution}"/>

    <integrator type="direct">
        <integer name="emitter_samples" value="1"/>
        <integer name="bsdf_samples" value="0"/>
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <string name="fov_axis" value="x"/>
        <float name="principal_point_offset_x" value="{ppx}"/>
        <float name="principal_point_offset_y" value="{ppy}"/>
        <transform name="to_world">
            <lookat origin="{tx}, {ty}, {height}" target="{tx}, {ty}, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$resolution"/>
            <integer name="height" value="$resolution"/>
            <string name="pixel_format" value="rgb"/>
            <rfilter type="box"/>
        </film>
    </sensor>

    <emitter type="point">
        <point name="position" x="{tx}" y="{ty}" z="{height}"/>
        <float name="intensity" value="{intensity}"/>
    </emitter>

    <shape type="rectangle">
        <bsdf type="svbrdf">
            <string name="convention" value="{convention}"/>
            <string name="normal_encoding" value="unsigned"/>
{textures}
        </bsdf>
    </shape>
</scene>
"""

_TEXTURE = """            <texture type="bitmap" name="{name}">
                <string name="filename" value="{name}.png"/>
                <boolean name="raw" value="{raw}"/>
                <transform name="to_uv"><scale x="1" y="-1"/><translate x="0" y="1"/></transform>
            </texture>"""


def scene_xml(offset: tuple[float, float], fov: float, resolution: int, convention: str) -> str:
    """The capture as Mitsuba XML, reading the PNG maps beside it."""
    height = constants.camera_height(fov)
    tx, ty = offset
    textures = "\n".join(_TEXTURE.format(name=name, raw="false" if name in ("diffuse", "specular") else "true")
                         for name in ("normal", "diffuse", "roughness", "specular"))
    return _SCENE.format(resolution=resolution, fov=fov, ppx=-tx / 2, ppy=ty / 2, tx=tx, ty=ty, height=height,
                         intensity=math.pi * height**2, convention=convention, textures=textures)


# --- glTF ----------------------------------------------------------------------------------------------

def export_pbr(material) -> dict:
    """The metallic-roughness maps every export writes: ``Material.to_pbr`` at ``constants.EXPORT_METAL_F0``."""
    return material.to_pbr(constants.EXPORT_METAL_F0)


def gltf_material(material, folder: Path, name: str = "captured material", pbr: dict | None = None) -> dict:
    """Write the glTF textures into ``folder`` and return the glTF 2.0 document of a 2 x 2 quad
    lying on the ground (+Y up) with the material: metallic-roughness plus KHR_materials_specular.

    Our +x is glTF +X, our +y (the top of the image) is glTF -Z; the normal texture is the
    material's ``normal.png`` (glTF normal maps are +Y up, as ours). ``pbr``: the material's
    ``export_pbr``, when the caller has it already.
    """
    pbr = pbr if pbr is not None else export_pbr(material)
    base = pbr["base_color"]
    metallic, roughness = pbr["metallic"], pbr["roughness"]
    zeros = torch.zeros_like(metallic)
    write_image(folder / "base_color.png", _hwc(base), encode_srgb=True)
    write_image(folder / "metallic_roughness.png", _hwc(torch.cat([zeros, roughness, metallic])))
    texture, factor = specular_color(material, pbr)
    write_image(folder / "specular_color.png", _hwc(texture), encode_srgb=True)

    positions = [(-1.0, 0.0, 1.0), (1.0, 0.0, 1.0), (1.0, 0.0, -1.0), (-1.0, 0.0, -1.0)]
    normals = [(0.0, 1.0, 0.0)] * 4
    tangents = [(1.0, 0.0, 0.0, 1.0)] * 4
    uvs = [(0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0)]
    indices = [0, 1, 2, 0, 2, 3]
    blobs = [struct.pack("<12f", *sum(positions, ())), struct.pack("<12f", *sum(normals, ())),
             struct.pack("<16f", *sum(tangents, ())), struct.pack("<8f", *sum(uvs, ())), struct.pack("<6H", *indices)]
    offsets, data = [], b""
    for blob in blobs:
        offsets.append(len(data))
        data += blob + b"\0" * ((-len(blob)) % 4)
    views = [{"buffer": 0, "byteOffset": o, "byteLength": len(b)} for o, b in zip(offsets, blobs)]
    views[-1]["target"] = 34963
    for view in views[:-1]:
        view["target"] = 34962
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-1, 0, -1], "max": [1, 0, 1]},
        {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC4"},
        {"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": 4, "componentType": 5123, "count": 6, "type": "SCALAR"},
    ]
    return {
        "asset": {"version": "2.0", "generator": "mideepbasis"},
        "extensionsUsed": ["KHR_materials_specular"],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "sample"}],
        "meshes": [{"name": "sample", "primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2,
                                                                     "TEXCOORD_0": 3}, "indices": 4, "material": 0}]}],
        "materials": [{
            "name": name,
            "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
                                     "metallicFactor": 1.0, "roughnessFactor": 1.0},
            "normalTexture": {"index": 2},
            "extensions": {"KHR_materials_specular": {"specularColorTexture": {"index": 3},
                                                      "specularColorFactor": [factor] * 3}},
        }],
        "textures": [{"source": i, "sampler": 0} for i in range(4)],
        "images": [{"uri": uri} for uri in ("base_color.png", "metallic_roughness.png", "normal.png", "specular_color.png")],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": views, "accessors": accessors,
    }


# --- the capture folder ------------------------------------------------------------------------------


def write_height(folder: Path, material) -> dict:
    """``height.exr`` (float32, [patch half-widths], zero mean) and ``height.png`` (16-bit, its range
    mapped to [0, 1]) of the material's normals (``height.height_from_normals``, periodic for a
    tileable capture); returns the range, which ``height.json`` records for the PNG."""
    from .height import height_from_normals

    tileable = bool((material.provenance.get("capture") or {}).get("tileable", False))
    height = height_from_normals(material.normal, tileable)[0]
    low, high = float(height.min()), float(height.max())
    write_image(folder / "height.exr", height.numpy())
    write_image(folder / "height.png", ((height - low) / max(high - low, 1e-12)).numpy(), bit_depth=16)
    record = {"unit": "patch half-widths (the sample spans 2)", "png_black": low, "png_white": high,
              "tileable": tileable}
    write_bytes(folder / "height.json", _json_bytes(record))
    return record


def dielectric_f0(material, pbr: dict | None = None) -> float:
    """The mean F0 of a material's dielectric part: its specular's grey level weighted by 1 -
    metallic (``to_pbr``), what a reader with one index of refraction (USD) can show."""
    metallic = (pbr or export_pbr(material))["metallic"]
    dielectric = (1.0 - metallic).clamp(min=0.0)
    weight = float(dielectric.sum())
    if weight <= 0:
        return constants.DIELECTRIC_F0
    return float((material.specular.mean(dim=0, keepdim=True) * dielectric).sum()) / weight


def specular_color(material, pbr: dict | None = None) -> tuple[torch.Tensor, float]:
    """The specular colour of the metallic-roughness exports (glTF KHR_materials_specular, MaterialX):
    (the texture (3, H, W) in [0, 1], its factor >= 1), with dielectric F0 = 0.04 x factor x texture.
    Where a pixel is partly metal, its dielectric part has the F0 that ``export_pbr`` split it at
    (``constants.EXPORT_METAL_F0``), so that a reader's (1 - metallic) F0 + metallic x base colour gives back
    the specular; elsewhere the F0 is the specular itself."""
    metallic = (pbr or export_pbr(material))["metallic"]
    # In place: each (3, H, W) temporary is 0.2 GB at 4096 px.
    specular = material.specular.clone().masked_fill_(metallic > 0, constants.EXPORT_METAL_F0)
    factor = max(1.0, float(specular.max()) / constants.DIELECTRIC_F0)
    return specular.div_(constants.DIELECTRIC_F0 * factor).clamp_(0, 1), factor


#: Largest map side the path-traced previews are given [pixels]. A preview is 256 px wide and
#: shows the sample smaller than that, so larger maps are area-averaged down first: the same
#: picture with less aliasing, and at 2048 px 3 x 4 texture uploads of 16 MB fewer.
PREVIEW_MAP_SIZE = 2 * constants.PREVIEW_RESOLUTION


def preview_maps(maps: torch.Tensor, most: int = PREVIEW_MAP_SIZE) -> torch.Tensor:
    """(10, H, W) maps as a preview is given them: unchanged (the same tensor) when neither side
    exceeds ``most``, else area-averaged so that the longer side is ``most``, normals renormalised."""
    from .resampling import downsample_maps

    height, width = maps.shape[-2:]
    if max(height, width) <= most:
        return maps
    scale = most / max(height, width)
    size = (max(1, round(height * scale)), max(1, round(width * scale)))
    return downsample_maps(maps[None].float(), size)[0]


def save_capture(result, out: str | os.PathLike | OutputFolder, exr: bool = False, overwrite: bool = False,
                 environment: str = "studio", environment_spp: int = constants.CAPTURE_PREVIEW_SPP,
                 environment_sampler: str = constants.CAPTURE_PREVIEW_SAMPLER,
                 progress: bool = False, truth=None, preview_tiles: float = 2.0,
                 shape_spp: int = constants.SHAPE_PREVIEW_SPP, shape_sampler: str = constants.SHAPE_PREVIEW_SAMPLER,
                 shape_previews: bool = True) -> Path:
    """Write everything a capture gives (see the module docstring) into ``out``, atomically: an
    ``OutputFolder`` (checked and locked since before the capture), or a path made one here with
    ``overwrite``. A kill at any instant leaves the old folder or the new one, whole.

    With ``truth`` (a Material the user has maps of), also ``environment_truth.png``: the true
    material path traced in the same scene with the same seed and samples, and
    ``environment_difference.png``: |truth - capture| of the two sRGB images, times 4.
    ``preview_sphere.png`` and ``preview_cloth.png`` show the material on a ball and on a draped
    cloth in the same environment, the maps repeated ``preview_tiles`` times across them (unless
    ``shape_previews`` is False: two path-traced images fewer).
    """
    folder = out if isinstance(out, OutputFolder) else OutputFolder(out, overwrite=overwrite)
    with folder:
        _write_capture(result, folder.staging, exr, environment, environment_spp, environment_sampler, progress,
                       truth, preview_tiles, shape_spp, shape_sampler, shape_previews)
    return folder.target


def _write_capture(result, staging: Path, exr: bool, environment: str, environment_spp: int,
                   environment_sampler: str, progress: bool, truth, preview_tiles: float, shape_spp: int,
                   shape_sampler: str, shape_previews: bool) -> None:
    """The files of ``save_capture``, written into ``staging``."""
    from .render import release_memory, render_flash_tiled
    from .render.scenes import preview_scene, render_preview, shape_scene
    from .reporting import report_panel, report_sheet, write_report_page, write_report_sheet

    # The MaterialX and USD files are written as text: loading pxr while the preview thread ran
    # deadlocked about one capture in ten (a library loaded beside running threads can).
    from .interchange import ior_of_f0, write_materialx, write_usd
    material = result.material
    maps = material.to_tensor()[None]
    # The re-rendering first, before the preview thread starts: drjit is then used by that
    # thread alone.
    rerender = render_flash_tiled(maps, result.light_position, fov=result.fov, convention=material.convention)
    release_memory()
    shown = preview_maps(maps[0])
    del maps  # 0.7 GB at 4096 px, beside the material's own maps

    finished: queue.SimpleQueue = queue.SimpleQueue()  # (file name, linear (H, W, 3)) of each preview, then None

    rfilter = constants.PREVIEW_FILM_FILTER

    def path_trace() -> None:
        """The previews, each handed to ``finished`` as soon as it is traced."""
        try:
            scene = preview_scene(shown, environment=environment, spp=environment_spp,
                                  convention=material.convention, sampler=environment_sampler, rfilter=rfilter)
            finished.put(("environment", render_preview(scene, progress=progress)))
            for shape in ("sphere", "cloth") if shape_previews else ():
                shape_view = shape_scene(shown, shape, environment, tiles=preview_tiles, spp=shape_spp,
                                         convention=material.convention, sampler=shape_sampler, rfilter=rfilter)
                finished.put((f"preview_{shape}", render_preview(shape_view)))
            if truth is not None:
                truth_scene = preview_scene(preview_maps(truth.to_tensor()), environment=environment,
                                            spp=environment_spp, convention=material.convention,
                                            sampler=environment_sampler, rfilter=rfilter)
                # The same seed as the capture's.
                finished.put(("environment_truth", render_preview(truth_scene, progress=progress)))
        finally:
            finished.put(None)  # also after a failure, which ``result()`` then raises

    # The path tracing, the longest part, starts before every export: drjit lets go of the GIL
    # while it traces, and the maps' encoding and writing (PNG and EXR on their own threads)
    # and the other files run beside it. At 1024 px, exports run first would delay it by 0.9 s.
    with ThreadPoolExecutor(max_workers=1) as tracer, background_writes():
        traced = tracer.submit(path_trace)
        # The photo, the re-rendering and its error first, and the sheet's panels of them: then the
        # full-size images are let go before the maps' exports (0.4 GB at 4096 px).
        error = (rerender.clamp(0, 1) - result.photo).abs()
        rerender_rmse = float(error.square().mean().sqrt())
        # Clipped by torch on every core: NumPy's clip of the permuted views took 0.4 s at 2048 px.
        write_image(staging / "photo.png", _hwc(result.photo.clamp(0, 1)), encode_srgb=True)
        write_image(staging / "rerender.png", _hwc(rerender.clamp(0, 1)), encode_srgb=True)
        sheet = report_sheet(result, rerender, report_panel(error), rerender_rmse)  # all but the environment panel
        write_image(staging / "error.png", _hwc(error.mul_(4).clamp_(0, 1)), encode_srgb=True)
        del error, rerender
        if exr:
            material.save(staging, format="exr")
        material.save(staging, format="png")
        height = write_height(staging, material)  # before the MaterialX and USD files, which use its range
        height_range = (height["png_black"], height["png_white"])
        light = {"offset": list(result.offset), "offset_unit": "patch half-widths",
                 "offset_angle_deg": result.offset_angle_deg,
                 "offset_angles_deg": [math.degrees(math.atan(t / constants.camera_height(result.fov)))
                                       for t in result.offset],
                 "position": result.light_position.tolist(), "fov_deg": result.fov, "fov_source": result.fov_source,
                 "searched": result.searched, "search": result.search_history}
        write_bytes(staging / "light.json", _json_bytes(light))
        (staging / "scene.xml").write_text(scene_xml(result.offset, result.fov, material.width,
                                                     material.convention))
        pbr = export_pbr(material)  # once, for the glTF and the MaterialX export
        gltf = gltf_material(material, staging, pbr=pbr)
        write_bytes(staging / "material.gltf", _json_bytes(gltf))
        # The glTF's specular factor, not a second conversion (0.1 s at 1024 px).
        write_materialx(staging, gltf["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"][0],
                        height_range=height_range)
        write_usd(staging, ior=ior_of_f0(dielectric_f0(material, pbr)), height_range=height_range)
        # Each preview, and the report with its environment panel, is encoded while the next traces.
        images = {}
        while (item := finished.get()) is not None:
            name, images[name] = item
            write_image(staging / f"{name}.png", images[name].clip(0, 1), encode_srgb=True)
            if name == "environment":
                write_report_sheet(staging, sheet, images[name])
        traced.result()
        environment_image = images["environment"]
        if truth is not None:
            difference = np.abs(linear_to_srgb(images["environment_truth"].clip(0, 1))
                                - linear_to_srgb(environment_image.clip(0, 1)))
            write_image(staging / "environment_difference.png", (difference * 4).clip(0, 1))
    # The page reads the written maps (its relighting viewer embeds them): after the writes.
    write_report_page(result, staging, rerender_rmse)
