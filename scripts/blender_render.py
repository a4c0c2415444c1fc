"""Render a capture's export in Blender (Cycles) under the capture's own flash: the exports' check.

    BLENDER_PYTHON scripts/blender_render.py MATERIAL_DIR gltf|usd OUT.exr [--offset TX,TY] [--fov 45]
        [--resolution 128] [--samples 64] [--nodes NODES.json]

Run with a Python that has ``bpy`` (Blender as a module, 4.5; ``pip install bpy==4.5.15`` in an
environment of its own). It imports ``material.gltf`` or ``material.usda`` of the folder into an
empty scene, puts a perspective camera and a point light at the capture's flash position
(``TX, TY, H`` [patch half-widths], H = 1 / tan(fov / 2), the lens shifted so the camera frames
the 2 x 2 sample exactly, as ``mideepbasis render --light flash`` does), renders it with Cycles on
the CPU into a linear EXR, and with ``--nodes`` writes what the imported material's shader
reads: each image's colour space, the Principled BSDF inputs that are linked, and the
displacement (the USD's, from ``height.png``), which Blender renders as it imports it: on the
sample's one quad, its four corners moved by the heights there.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import bpy


def imported(folder: Path, kind: str) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if kind == "gltf":
        bpy.ops.import_scene.gltf(filepath=str(folder / "material.gltf"))
    else:
        bpy.ops.wm.usd_import(filepath=str(folder / "material.usda"))


def shader_links() -> dict:
    """The imported material's image colour spaces, the Principled BSDF's linked inputs and the
    displacement: its method, the Displacement node's midlevel and scale, the image it reads (or None)."""
    materials = [m for m in bpy.data.materials if m.use_nodes and m.users]
    if not materials:
        raise SystemExit("no material was imported")
    nodes = materials[0].node_tree.nodes
    images = {node.image.name: node.image.colorspace_settings.name for node in nodes
              if node.type == "TEX_IMAGE" and node.image is not None}
    principled = next(node for node in nodes if node.type == "BSDF_PRINCIPLED")
    linked = sorted(socket.name for socket in principled.inputs if socket.is_linked)
    output = next(node for node in nodes if node.type == "OUTPUT_MATERIAL")
    displacement = None
    if output.inputs["Displacement"].is_linked:
        node = output.inputs["Displacement"].links[0].from_node
        upstream, sources = [node], []
        while upstream:  # the images the displacement reads, through any nodes between
            for socket in upstream.pop().inputs:
                for link in socket.links:
                    upstream.append(link.from_node)
                    if link.from_node.type == "TEX_IMAGE" and link.from_node.image is not None:
                        sources.append(link.from_node.image.name)
        displacement = {"method": materials[0].displacement_method, "node": node.type, "images": sorted(sources),
                        **{key: float(node.inputs[name].default_value) for key, name in
                           (("midlevel", "Midlevel"), ("scale", "Scale")) if name in node.inputs}}
    return {"images": images, "principled_linked": linked,
            "ior": float(principled.inputs["IOR"].default_value),
            "normal_map": any(node.type == "NORMAL_MAP" for node in nodes), "displacement": displacement}


def flash_scene(offset: tuple[float, float], fov: float, resolution: int, samples: int) -> None:
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.filter_width = 0.01  # a pixel is its centre's point, as the per-pixel render's
    scene.cycles.max_bounces = 0  # the flash's direct light only, as a flash photo of a plane
    scene.render.resolution_x = scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    world = bpy.data.worlds.new("dark")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world
    height = 1.0 / math.tan(math.radians(fov) / 2.0)
    camera = bpy.data.cameras.new("flash_camera")
    camera.sensor_fit = "HORIZONTAL"
    camera.angle = math.radians(fov)
    camera.shift_x, camera.shift_y = -offset[0] / 2.0, -offset[1] / 2.0  # frame the sample, not the view below
    camera_object = bpy.data.objects.new("flash_camera", camera)
    camera_object.location = (offset[0], offset[1], height)  # looking down -Z, +Y up: the sample's frame
    light = bpy.data.lights.new("flash", "POINT")
    light.energy = 1000.0
    light.shadow_soft_size = 0.0
    if hasattr(light, "use_soft_falloff"):
        light.use_soft_falloff = False  # an inverse-square point, not Blender's softened one
    light_object = bpy.data.objects.new("flash", light)
    light_object.location = camera_object.location
    for item in (camera_object, light_object):
        scene.collection.objects.link(item)
    scene.camera = camera_object


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("material", type=Path)
    parser.add_argument("kind", choices=("gltf", "usd"))
    parser.add_argument("output", type=Path)
    parser.add_argument("--offset", default="0,0")
    parser.add_argument("--fov", type=float, default=45.0)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--nodes", type=Path, default=None)
    args = parser.parse_args()
    offset = tuple(float(value) for value in args.offset.split(","))
    imported(args.material, args.kind)
    if args.nodes is not None:
        args.nodes.write_text(json.dumps(shader_links(), indent=1))
    flash_scene(offset, args.fov, args.resolution, args.samples)
    bpy.context.scene.render.filepath = str(args.output)
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main()
