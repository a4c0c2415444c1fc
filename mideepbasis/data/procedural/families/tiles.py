"""Tiles and bricks with grout: glazed square tiles, running-bond bricks, small mosaics."""

from __future__ import annotations

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, grid, hsv_color, smoothstep
from ..registry import family


@family("tiles_bricks")
def tiles_bricks(canvas: Canvas) -> Surface:
    variant = canvas.choice(["glazed_tiles", "bricks", "mosaic", "terracotta"])
    if variant == "bricks":
        columns = canvas.frequency(canvas.uniform(1.5, 4.0))
        rows = canvas.frequency(columns * canvas.uniform(2.0, 3.2))
        rows += rows % 2 if canvas.tileable else 0
        offset = 0.5
    elif variant == "mosaic":
        columns = rows = canvas.frequency(canvas.uniform(8, 20))
        offset = 0.0
    else:
        columns = canvas.frequency(canvas.uniform(2, 7))
        rows = canvas.frequency(columns * canvas.uniform(0.8, 1.25)) if canvas.chance(0.3) else columns
        offset = 0.0
    cells = grid(canvas, columns, rows, offset)
    rng = canvas.rng

    # Grout joint: half-width [sample widths]; tiles rise from it with a rounded bevel.
    joint = canvas.uniform(0.002, 0.008) if variant != "bricks" else canvas.uniform(0.004, 0.012)
    bevel = canvas.uniform(0.002, 0.012)
    inside = smoothstep(joint, joint + bevel, cells.edge)
    grout_mask = 1.0 - smoothstep(joint * 0.6, joint, cells.edge)
    tile_relief = canvas.uniform(0.5, 3.0) * MILLIMETRE
    per_tile = rng.random((cells.count, 6)).astype(np.float32)[cells.index]
    tilt = (per_tile[..., 0] - 0.5) * (cells.local_u - 0.5) + (per_tile[..., 1] - 0.5) * (cells.local_v - 0.5)
    height = tile_relief * np.sqrt(inside) + 0.3 * MILLIMETRE * tilt * inside

    if variant in ("bricks", "terracotta"):
        hue = canvas.uniform(0.0, 0.09)
        base = hsv_color(hue, canvas.uniform(0.35, 0.75), canvas.uniform(0.35, 0.75))
        texture = canvas.noise(beta=1.2, low=4)
        height = height + (0.15 + 0.15 * texture) * MILLIMETRE * inside
        color_jitter = 0.75 + 0.5 * per_tile[..., 2:5]
        tile_diffuse = base * color_jitter * (1.0 + 0.12 * texture[..., None])
        tile_roughness = canvas.uniform(0.65, 0.95) + 0.05 * texture
        tile_f0 = dielectric_f0(canvas, 0.03, 0.045)
    else:
        hue = canvas.uniform(0, 1)
        saturation = canvas.uniform(0.0, 0.7)
        value = canvas.uniform(0.3, 0.95)
        spread = canvas.uniform(0.0, 0.12 if variant == "glazed_tiles" else 0.35)
        tile_colors = np.stack([hsv_color(hue + spread * (h - 0.5), saturation * (0.7 + 0.6 * s), value * (0.8 + 0.4 * v))
                                for h, s, v in rng.random((cells.count, 3))])
        tile_diffuse = tile_colors[cells.index]
        ripple = canvas.noise(beta=3.0, low=2, high=24)
        height = height + canvas.uniform(0.02, 0.12) * MILLIMETRE * ripple * inside
        tile_roughness = canvas.uniform(0.05, 0.3) + 0.04 * per_tile[..., 5]
        tile_f0 = dielectric_f0(canvas, 0.04, 0.06)

    grout_color = hsv_color(canvas.uniform(0.05, 0.15), canvas.uniform(0.0, 0.25), canvas.uniform(0.3, 0.85))
    grout_noise = canvas.noise(beta=0.5, low=16)
    grout_diffuse = grout_color * (1.0 + 0.1 * grout_noise[..., None])
    height = height - 0.2 * MILLIMETRE * grout_mask * (grout_noise > 1.2)

    mask = grout_mask[..., None]
    diffuse = tile_diffuse * (1 - mask) + grout_diffuse * mask
    roughness = tile_roughness * (1 - grout_mask) + canvas.uniform(0.75, 1.0) * grout_mask
    specular = tile_f0 * (1 - mask) + dielectric_f0(canvas, 0.025, 0.04) * mask
    return Surface(height=height, diffuse=diffuse, roughness=roughness, specular=np.broadcast_to(specular, diffuse.shape),
                   variant=variant)
