"""Contact sheets of materials: per material a flash render and the four maps, labelled."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from .. import constants
from ..imageio import linear_to_srgb, write_image

#: Columns of one material on a sheet.
PANELS = ("flash", "normal", "diffuse", "roughness", "specular")


def material_panels(maps: torch.Tensor, flash: torch.Tensor) -> np.ndarray:
    """One sheet row for a material, (H, 5 W, 3) sRGB-encoded in [0, 1].

    Args:
        maps: (10, H, W) stacked maps.
        flash: (3, H, W) linear flash render.
    """
    def hwc(t):
        return t.permute(1, 2, 0).numpy()

    normal = (hwc(maps[constants.NORMAL]) + 1.0) / 2.0
    diffuse = linear_to_srgb(hwc(maps[constants.DIFFUSE]))
    roughness = np.repeat(hwc(maps[constants.ROUGHNESS]), 3, axis=2)
    specular = linear_to_srgb(hwc(maps[constants.SPECULAR]))
    render = linear_to_srgb(np.clip(hwc(flash), 0.0, 1.0))
    return np.concatenate([render, normal, diffuse, roughness, specular], axis=1)


def contact_sheet(maps: torch.Tensor, flashes: torch.Tensor, labels: list[str], columns: int = 4,
                  tile: int = 128) -> np.ndarray:
    """A grid of materials, ``columns`` materials across, each as five ``tile``-pixel panels with a label.

    Args:
        maps: (N, 10, H, W); flashes: (N, 3, H, W) linear renders; labels: N captions.

    Returns:
        (rows * tile, columns * 5 * tile, 3) sRGB-encoded image in [0, 1].
    """
    count = maps.shape[0]
    rows = (count + columns - 1) // columns
    sheet = np.ones((rows * tile, columns * len(PANELS) * tile, 3), np.float32)
    for index in range(count):
        strip = material_panels(maps[index], flashes[index])
        strip = cv2.resize(strip, (len(PANELS) * tile, tile), interpolation=cv2.INTER_AREA)
        cv2.putText(strip, labels[index][:40], (4, tile - 6), cv2.FONT_HERSHEY_SIMPLEX, tile / 400, (1, 1, 1), 1,
                    cv2.LINE_AA)
        row, column = divmod(index, columns)
        sheet[row * tile:(row + 1) * tile, column * len(PANELS) * tile:(column + 1) * len(PANELS) * tile] = strip
        sheet[row * tile:(row + 1) * tile, column * len(PANELS) * tile] = 0.0  # a dark rule between materials
    return sheet


def procedural_sheet(count: int, seed: int, output: Path, size: int = 256, columns: int = 4,
                     tileable: bool = False, family: str | None = None, progress: bool = True) -> Path:
    """Generate ``count`` procedural materials from ``seed`` on, render each under the centred
    flash and write the contact sheet to ``output`` (PNG, atomically)."""
    from tqdm import tqdm

    from .. import geometry
    from ..render import render_flash
    from .procedural import GeneratorConfig, generate

    GeneratorConfig(size=size, tileable=tileable)  # its check of the settings, before the progress bar
    maps, labels = [], []
    for index in tqdm(range(count), desc="materials", disable=not progress):
        material = generate(seed + index, size=size, family=family, tileable=tileable)
        maps.append(material.to_tensor())
        provenance = material.provenance
        mixed = f"+{provenance['mixed_with']['family']}" if "mixed_with" in provenance else ""
        labels.append(f"{seed + index} {provenance['family']}/{provenance['variant']}{mixed}")
    maps = torch.stack(maps)
    lights = geometry.light_positions(torch.zeros(count, 1, 2))
    with torch.no_grad():
        flashes = render_flash(maps, lights)[:, 0]
    return write_image(output, contact_sheet(maps, flashes, labels, columns=columns))
