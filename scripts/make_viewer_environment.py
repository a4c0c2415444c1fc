"""Prefilter the studio environment for the report's relightable viewer (split-sum lighting).

    .venv/bin/python scripts/make_viewer_environment.py [--width 64] [--levels 6]

Reads scenes/envmaps/studio.exr (equirectangular, Mitsuba's envmap frame: +y up in the map,
u = atan2(x, -z) / 2 pi, v = acos(y) / pi; the preview scene turns the map's +y to the world's +z)
and writes mideepbasis/assets/viewer/studio_prefiltered.json:

- ``levels`` bands of ``width`` x ``width / 2`` pixels stacked vertically, float16 RGB as base64:
  band k is the radiance around each direction weighted by a GGX lobe of roughness
  k / (levels - 1) (alpha = r^2), in the same parameterisation as the map;
- ``irradiance``: the nine order-2 spherical-harmonic coefficients of the radiance, in the map's
  frame (basis of Ramamoorthi and Hanrahan 2001, ordered 1, y, z, x, xy, yz, 3z^2 - 1, xz, x^2 - y^2).
"""

from __future__ import annotations

import argparse
import base64
import json
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def directions(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (H, W, 3) at the pixel centres of an equirectangular map, and solid angles (H, W)."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi, theta = 2 * math.pi * u[None, :], math.pi * v[:, None]
    x = np.sin(phi) * np.sin(theta)
    y = np.cos(theta) * np.ones_like(phi)
    z = -np.cos(phi) * np.sin(theta)
    solid = (2 * math.pi / width) * (math.pi / height) * np.sin(theta) * np.ones_like(phi)
    return np.stack([x, y, z], axis=-1), solid


def downsample(image: np.ndarray, width: int) -> np.ndarray:
    factor = image.shape[1] // width
    height = image.shape[0] // factor
    return image[:height * factor, :width * factor].reshape(height, factor, width, factor, 3).mean(axis=(1, 3))


def ggx_prefilter(radiance: np.ndarray, roughness: float) -> np.ndarray:
    """The radiance around each direction R weighted by D(h) (n . w) with n = v = R (split sum)."""
    height, width = radiance.shape[:2]
    dirs, solid = directions(width, height)
    flat_dirs, flat_radiance, flat_solid = dirs.reshape(-1, 3), radiance.reshape(-1, 3), solid.reshape(-1)
    if roughness <= 0:
        return radiance
    alpha2 = roughness**4
    result = np.empty_like(flat_radiance)
    for start in range(0, len(flat_dirs), 256):
        reflect = flat_dirs[start:start + 256]
        cos = reflect @ flat_dirs.T  # (R, W)
        half_cos = np.sqrt(np.clip((1 + cos) / 2, 0, 1))  # cos of the half vector to R
        ndf = alpha2 / (math.pi * (half_cos**2 * (alpha2 - 1) + 1) ** 2)
        weight = ndf * np.clip(cos, 0, None) * flat_solid[None, :]
        result[start:start + 256] = weight @ flat_radiance / weight.sum(axis=1, keepdims=True)
    return result.reshape(height, width, 3)


def spherical_harmonics(radiance: np.ndarray) -> np.ndarray:
    """(9, 3) coefficients of the radiance in the real SH basis of order 2."""
    height, width = radiance.shape[:2]
    dirs, solid = directions(width, height)
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    basis = np.stack([np.full_like(x, 0.282095), 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y,
                      1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z, 0.546274 * (x * x - y * y)])
    return np.einsum("khw,hwc,hw->kc", basis, radiance, solid)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--levels", type=int, default=6)
    parser.add_argument("-o", "--output", type=Path, default=ROOT / "mideepbasis/assets/viewer/studio_prefiltered.json")
    args = parser.parse_args()

    from mideepbasis.imageio import read_image

    source = read_image(ROOT / "scenes/envmaps/studio.exr").astype(np.float64)
    radiance = downsample(source, args.width)
    bands = [ggx_prefilter(radiance, level / (args.levels - 1)) for level in range(args.levels)]
    atlas = np.concatenate(bands, axis=0)
    rgba = np.concatenate([atlas, np.ones_like(atlas[..., :1])], axis=-1).astype(np.float16)
    document = {"source": "scenes/envmaps/studio.exr", "width": args.width, "height": args.width // 2,
                "levels": args.levels, "format": "float16 RGBA, rows top to bottom, band k: roughness k/(levels-1)",
                "data": base64.b64encode(rgba.tobytes()).decode(),
                "irradiance": spherical_harmonics(source[::4, ::4] if source.shape[1] > 256 else source).round(6).tolist()}
    args.output.write_text(json.dumps(document) + "\n")
    print(f"wrote {args.output} ({args.output.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
