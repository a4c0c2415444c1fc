"""Make the files the project ships: the studio HDR environment and the default flat textures.

    .venv/bin/python scripts/make_assets.py

Everything is computed here from closed-form formulas, so the shipped files are our own and
can be rebuilt bit for bit. Writes into scenes/envmaps/ and scenes/textures/.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mideepbasis.imageio import write_image

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


def main() -> None:
    envmaps = ROOT / "scenes" / "envmaps"
    textures = ROOT / "scenes" / "textures"
    write_image(envmaps / "studio.exr", studio_environment(), bit_depth=16)
    flat = {"flat_normal.exr": (0.0, 0.0, 1.0), "grey_diffuse.exr": (0.5, 0.5, 0.5),
            "mid_roughness.exr": (0.5,), "dielectric_specular.exr": (0.04, 0.04, 0.04)}
    for name, value in flat.items():
        write_image(textures / name, np.broadcast_to(np.asarray(value, np.float32), (2, 2, len(value))).copy())
    print(f"wrote {envmaps} and {textures}")


if __name__ == "__main__":
    main()
