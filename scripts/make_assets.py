"""Make the files the project ships: the studio HDR environment, the default flat textures, the
example material and the example capture (a flash photo with its ground truth).

    .venv/bin/python scripts/make_assets.py

Everything is computed here from closed-form formulas, so the shipped files are our own and
can be rebuilt bit for bit. Writes into scenes/envmaps/, scenes/textures/, mideepbasis/assets/example_material/ and
mideepbasis/assets/example_capture/.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mideepbasis.imageio import write_image
from mideepbasis.material import Material

ROOT = Path(__file__).resolve().parents[1]


def studio_environment(width: int = 1024, height: int = 512) -> np.ndarray:
    """A photo-studio light probe in Mitsuba's equirectangular layout (row 0 = zenith).

    A warm-grey dome brighter towards the top, a dark floor, a large key softbox, a
    smaller fill softbox opposite it and a thin strip light behind the sample, all with
    soft edges so that glossy materials show shaped highlights without fireflies.

    Returns:
        (height, width, 3) linear radiance [relative], float32.
    """
    rows = (np.arange(height) + 0.5) / height
    cols = (np.arange(width) + 0.5) / width
    theta = rows[:, None] * np.pi  # polar angle from the zenith [rad]
    phi = cols[None, :] * 2 * np.pi  # azimuth [rad]
    elevation = np.pi / 2 - theta

    dome = np.where(elevation > 0, 0.15 + 0.2 * np.sin(np.clip(elevation, 0, None)), 0.03)
    dome = np.broadcast_to(dome, (height, width))
    tint = np.array([1.0, 0.97, 0.92])
    image = dome[..., None] * tint

    def softbox(center_phi, center_elevation, half_width, half_height, radiance, color):
        d_phi = np.angle(np.exp(1j * (phi - center_phi)))
        d_elevation = elevation - center_elevation
        edge = 0.04  # width of the soft edge [rad]
        inside_phi = np.clip((half_width - np.abs(d_phi)) / edge + 0.5, 0, 1)
        inside_elevation = np.clip((half_height - np.abs(d_elevation)) / edge + 0.5, 0, 1)
        return (inside_phi * inside_elevation)[..., None] * radiance * np.asarray(color)

    # Azimuth 0 faces +y in the scenes (behind the sample as the preview camera sees it), 180
    # faces the camera: the key sits behind and to the side so glossy samples show it.
    image = image + softbox(np.radians(-28), np.radians(48), np.radians(20), np.radians(14), 5.0, (1.0, 0.98, 0.95))
    image = image + softbox(np.radians(235), np.radians(30), np.radians(14), np.radians(12), 2.0, (0.92, 0.96, 1.0))
    image = image + softbox(np.radians(0), np.radians(15), np.radians(40), np.radians(2.5), 3.0, (1.0, 1.0, 1.0))
    return image.astype(np.float32)


def normals_from_height(height: np.ndarray, strength: float) -> np.ndarray:
    """Unit normals (3, H, W) of a height field (H, W) [patch half-widths per unit height].

    Rows run towards -y (row 0 is the top edge), so d/dy = -d/drow.
    """
    rows, cols = height.shape
    d_dx = np.gradient(height, axis=1) * cols / 2.0
    d_dy = -np.gradient(height, axis=0) * rows / 2.0
    normal = np.stack([-strength * d_dx, -strength * d_dy, np.ones_like(height)])
    return normal / np.linalg.norm(normal, axis=0, keepdims=True)


def glazed_tiles(size: int = 256, tiles: int = 4, seed: int = 2023) -> Material:
    """A 4x4 panel of glazed ceramic tiles in grout: glossy coloured glaze with a slight
    ripple, per-tile hue variation, bevelled edges and rough recessed grout."""
    rng = np.random.default_rng(seed)
    coordinates = (np.arange(size) + 0.5) / size * tiles
    u, v = np.meshgrid(coordinates, coordinates)
    tile_u, tile_v = np.floor(u).astype(int), np.floor(v).astype(int)
    # Distance to the nearest tile edge [tile widths]; grout where it is below half the joint.
    edge = np.minimum(np.minimum(u % 1, 1 - u % 1), np.minimum(v % 1, 1 - v % 1))
    joint = 0.035
    bevel = np.clip((edge - joint) / 0.06, 0.0, 1.0)
    grout = edge < joint
    ripple = 0.0006 * np.sin(2 * np.pi * (1.3 * u + 0.7 * v)) * np.sin(2 * np.pi * (1.1 * v - 0.4 * u))
    height = 0.02 * np.sqrt(bevel) + np.where(grout, 0.0, ripple)
    normal = normals_from_height(height, strength=tiles / 2.0)

    hue_shift = rng.uniform(-0.06, 0.06, size=(tiles, tiles, 3))
    base_glaze = np.array([0.10, 0.32, 0.36])
    glaze = np.clip(base_glaze + hue_shift[tile_v, tile_u], 0.02, 0.9)
    grout_color = np.array([0.42, 0.40, 0.37])
    speckle = rng.normal(0.0, 0.02, size=(size, size, 1))
    diffuse = np.where(grout[..., None], grout_color + speckle, glaze + 0.3 * speckle)
    roughness = np.where(grout, 0.85, 0.16 + 0.05 * rng.uniform(size=(tiles, tiles))[tile_v, tile_u])
    specular = np.where(grout[..., None], 0.03, 0.05) * np.ones(3)
    return Material(normal=normal.astype(np.float32),
                    diffuse=np.clip(diffuse, 0, 1).transpose(2, 0, 1).astype(np.float32),
                    roughness=roughness[None].astype(np.float32),
                    specular=specular.transpose(2, 0, 1).astype(np.float32),
                    provenance={"source": "scripts/make_assets.py glazed_tiles", "seed": seed})


#: The example capture: a procedural material (a seed far from any training stream's), photographed
#: hand-held with a phone-like lens, as a 512 x 512 JPEG with its EXIF focal length.
EXAMPLE_CAPTURE = {"seed": 9_000_019, "family": "stone", "offset_deg": (6.0, -4.0), "focal_35mm": 37.0, "size": 512}


def example_capture(folder: Path) -> None:
    """Render the example flash photo and store it with its ground truth (material and light)."""
    import json
    import math

    import torch
    from PIL import Image

    from mideepbasis import geometry
    from mideepbasis.capturing import field_of_view_from_focal
    from mideepbasis.data.procedural import generate
    from mideepbasis.data.synth import SynthesisConfig, simulate_photo
    from mideepbasis.imageio import linear_to_srgb
    from mideepbasis.render import render_flash

    spec = EXAMPLE_CAPTURE
    size = spec["size"]
    material = generate(spec["seed"], size=size, family=spec["family"])
    fov = field_of_view_from_focal(spec["focal_35mm"], size, size)
    height = geometry.constants.camera_height(fov)
    offset = [height * math.tan(math.radians(a)) for a in spec["offset_deg"]]
    light = geometry.light_positions(torch.tensor([offset]), fov)
    with torch.no_grad():
        radiance = render_flash(material.to_tensor()[None], light.view(1, 1, 3), fov=fov)[:, 0]
    photo = simulate_photo(radiance, torch.Generator().manual_seed(spec["seed"]), SynthesisConfig(),
                           gains=torch.ones(1, 3))[0]
    pixels = np.round(linear_to_srgb(photo.permute(1, 2, 0).numpy()) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = int(spec["focal_35mm"])  # FocalLengthIn35mmFilm
    folder.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(folder / "photo.jpg", quality=92, exif=exif)
    material.save(folder / "truth", format="png")
    truth = {"offset": offset, "offset_deg": list(spec["offset_deg"]), "fov_deg": fov, "seed": spec["seed"],
             "family": spec["family"], "focal_35mm": spec["focal_35mm"],
             "note": "rendered by scripts/make_assets.py: physical convention, 8-bit sRGB JPEG with camera noise"}
    (folder / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")


def main() -> None:
    envmaps = ROOT / "scenes" / "envmaps"
    textures = ROOT / "scenes" / "textures"
    write_image(envmaps / "studio.exr", studio_environment(), bit_depth=16)
    flat = {"flat_normal.exr": (0.0, 0.0, 1.0), "grey_diffuse.exr": (0.5, 0.5, 0.5),
            "mid_roughness.exr": (0.5,), "dielectric_specular.exr": (0.04, 0.04, 0.04)}
    for name, value in flat.items():
        write_image(textures / name, np.broadcast_to(np.asarray(value, np.float32), (2, 2, len(value))).copy())
    example = ROOT / "mideepbasis" / "assets" / "example_material"
    glazed_tiles().save(example, format="png")
    example_capture(ROOT / "mideepbasis" / "assets" / "example_capture")
    print(f"wrote {envmaps}, {textures}, {example} and the example capture")


if __name__ == "__main__":
    import argparse

    # No options: parsing gives --help (which must not rebuild the files) and refuses any other.
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    main()
