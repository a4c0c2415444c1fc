"""The evaluation protocol (the paper's): the materials, the input photos, the flash offsets, and
the lights and views of the re-rendering error, in one place.

The input photo is re-rendered from the ground-truth maps under a flash (centred, or a seeded
hand-held offset per material), photographed as an 8-bit sRGB image, and the method predicts the
maps from it. The re-rendering error compares renders of the prediction and of the truth under the
same 30 random lights and viewpoints per material (seeded, identical for every method).

Shapes: maps (N, 10, H, W); offsets (N, 2) [patch half-widths]; lights and views (K, 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from .. import constants, geometry


#: Number of random light and view pairs per material for the re-rendering error.
RERENDER_COUNT = 30


def random_lights_and_views(count: int = RERENDER_COUNT, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` light positions and viewpoints [patch half-widths], (count, 3) each, seeded.

    Directions are cosine-distributed over the upper hemisphere at distances of 2 to 4 patch
    half-widths from a random point of the central half of the sample, as hand-held shots and
    room lights are: grazing ones are rare.
    """
    generator = torch.Generator().manual_seed(seed)

    def positions():
        u = torch.rand(count, 2, generator=generator)
        radius, angle = torch.sqrt(u[:, 0] * 0.9), 2 * math.pi * u[:, 1]  # cos(theta) >= 0.3
        direction = torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), torch.sqrt(1 - radius**2)], -1)
        distance = 2.0 + 2.0 * torch.rand(count, 1, generator=generator)
        centre = torch.cat([torch.rand(count, 2, generator=generator) - 0.5, torch.zeros(count, 1)], -1)
        return centre + distance * direction

    return positions(), positions()


def flash_photos(maps: torch.Tensor, offsets: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG,
                 convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The evaluation inputs: 8-bit sRGB photos of ``maps`` (B, 10, H, W) under flashes at lateral
    ``offsets`` (B, 2) [patch half-widths], no noise. Returns (photos (B, 3, H, W) linear, lights (B, 3))."""
    from ..data.synth import SynthesisConfig, simulate_photo
    from ..render import render_flash

    lights = geometry.light_positions(offsets, fov)
    with torch.no_grad():
        radiance = render_flash(maps, lights.view(-1, 1, 3), fov=fov, convention=convention, extent=extent)[:, 0]
    quiet = SynthesisConfig(shot_noise=(1e-30, 1e-30), read_noise=(1e-30, 1e-30), quantize=True)
    photos = simulate_photo(radiance, torch.Generator().manual_seed(0), quiet, gains=torch.ones(maps.shape[0], 3))
    return photos, lights


def evaluation_offsets(count: int, seed: int, fov: float) -> torch.Tensor:
    """The seeded hand-held offsets of the evaluation inputs, one per material, (count, 2)."""
    from ..data.synth import sample_offsets

    return sample_offsets(count, torch.Generator().manual_seed(seed), fov)


@dataclass
class EvaluationSet:
    """The materials of an evaluation, every one at one size.

    Attributes:
        names: one per material.
        maps: (N, 10, H, W) the maps to render (normals a dataset stored pointing into the
            surface repaired: z raised to ``material.REPAIRED_NORMAL_Z``, renormalised).
        stored: (N, 10, H, W) the maps as stored, for map metrics (equal to ``maps`` but for the
            repaired normals).
        repaired_pixels: per material, how many normals were repaired.
        skipped: unreadable materials.
    """

    names: list[str]
    maps: torch.Tensor
    stored: torch.Tensor
    repaired_pixels: list[int]
    skipped: int


def load_evaluation_materials(data: str | Path, format: str) -> EvaluationSet:
    """The readable materials of a dataset (``EvaluationSet``); only unreadable files are skipped."""
    from ..data.datasets import DeschaintreDataset, MaterialFolderDataset, PBRFolderDataset

    data = Path(data)
    if format in ("deschaintre5", "deschaintre4"):
        reader = DeschaintreDataset(data)
    elif format == "folder":
        reader = MaterialFolderDataset(data)
        if not len(reader):
            reader = PBRFolderDataset(data)
    else:
        from ..errors import InputError

        raise InputError(f"unknown dataset format {format!r}: expected deschaintre5, deschaintre4 or folder")
    names, maps, stored, repaired = [], [], [], []
    for source in reader.sources:
        material = reader.try_load(source)
        if material is None:
            continue
        names.append(Path(str(source)).stem)
        tensor = material.to_tensor()
        maps.append(tensor)
        if material.stored_normal is None:
            stored.append(tensor)
        else:
            stored.append(torch.cat([material.stored_normal.detach().float(), tensor[constants.REFLECTANCE]]))
        repaired.append(int(material.provenance.get("repaired_normal_pixels", 0)))
    if not maps:
        from ..errors import InputError

        raise InputError(f"{data}: no readable materials ({reader.skipped} skipped)")
    size = min(m.shape[-1] for m in maps)
    maps = [m if m.shape[-1] == size else resize_maps(m, size) for m in maps]
    stored = [m if m.shape[-1] == size else resize_maps(m, size) for m in stored]
    return EvaluationSet(names, torch.stack(maps), torch.stack(stored), repaired, reader.skipped)


def load_evaluation_set(data: str | Path, format: str) -> tuple[list[str], torch.Tensor, int]:
    """(names, maps to render (N, 10, H, W), number skipped): ``load_evaluation_materials`` in short."""
    materials = load_evaluation_materials(data, format)
    return materials.names, materials.maps, materials.skipped


def resize_maps(maps: torch.Tensor, size: int) -> torch.Tensor:
    """Maps (10, H, W) resampled to (10, size, size) by area averaging, the normals renormalised."""
    from ..resampling import downsample_maps

    return downsample_maps(maps[None], size)[0]


#: The paper's DeepBasis map RMSE (its 122 test scenes), for tables.
PAPER_DEEPBASIS = {"normal": 0.053, "diffuse": 0.031, "roughness": 0.162, "specular": 0.043}


#: Roughness groups of the lighting-accuracy table: upper bounds of the mean roughness.
ROUGHNESS_GROUPS = {"low": 0.33, "medium": 0.66, "high": 1.01}
