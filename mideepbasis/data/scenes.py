"""Calibrated scenes of procedural materials, photographed as a phone would: the held-out
validation set of the real-photo protocol (``evaluation.real``).

Each scene is one procedural material (seeds far from any training material's) photographed nine
times by one phone: a field of view drawn as ``SynthesisConfig.fov_range`` draws it, the first
photo a hand-held shot near the centre, the eight others from around it (flash angles up to the
hand-held limit, heights within -8 / +12 % of the first). Every photo goes through the same camera
(``data.synth``: white-balance cast, tone curve, vignetting, flash cone, noise, 8-bit, JPEG),
rendered at twice the photos' size and area-averaged. The positions are those of the sample's own
frame, as a calibration measures them: no tilt. A scene is written in the layout of the real
calibrated scenes, with its true material in ``truth/`` as the camera sees it (diffuse and
specular with the white balance's cast: what re-renders the photos).

Shapes: maps (10, H, W); positions (9, 3) [patch half-widths], written in cm.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import torch

from .. import constants, geometry
from .synth import (PHONE_PHOTOS, SynthesisConfig, colour_cast, flash_cone_falloff, sample_camera, sample_fov,
                    sample_offsets, simulate_photo)

#: Seeds of the scenes' materials start here: far from training (material i of a run) and from
#: the training validation (10^9 + i).
SCENE_SEED = 3 * 10**9

#: Photos per scene, as the real calibrated scenes have.
PHOTOS_PER_SCENE = 9

#: Side of the photographed square [cm] written into the scenes (any value: positions scale with it).
SIDE_CM = 6.848


def scene_geometry(generator: torch.Generator, config: SynthesisConfig) -> torch.Tensor:
    """(9, 3) co-located camera and flash positions [patch half-widths]: a hand-held first photo,
    then eight from around it."""
    fov = sample_fov(generator, config)
    first = geometry.light_positions(sample_offsets(1, generator, fov, config.max_offset_deg,
                                                    config.offset_sigma_divisor), fov)
    return torch.cat([first, flashes_around(PHOTOS_PER_SCENE - 1, fov, generator, config.max_offset_deg)])


def flashes_around(count: int, fov: float, generator: torch.Generator,
                   max_offset_deg: float = constants.MAX_OFFSET_DEG) -> torch.Tensor:
    """(count, 3) co-located camera and flash positions around the sample [patch half-widths], as a
    calibrated scene's other photos are taken: directions uniform over the disc of the hand-held
    limit ``max_offset_deg``, heights within -8 / +12 % of the camera's at ``fov``."""
    height = constants.camera_height(fov)
    radius = torch.sqrt(torch.rand(count, generator=generator)) * math.tan(math.radians(max_offset_deg))
    azimuth = torch.rand(count, generator=generator) * 2 * math.pi
    heights = height * (0.92 + 0.2 * torch.rand(count, generator=generator))
    return torch.stack([heights * radius * torch.cos(azimuth), heights * radius * torch.sin(azimuth), heights], -1)


def photograph_scene(maps: torch.Tensor, positions: torch.Tensor, generator: torch.Generator,
                     config: SynthesisConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The photos (9, 3, H / 2, W / 2), linear, of maps (10, H, W) at ``positions`` by one phone
    camera, and the true maps (10, H / 2, W / 2) as that camera sees them (diffuse with its cast)."""
    from ..render import render_flash
    from ..resampling import downsample, downsample_maps

    count = len(positions)
    camera = sample_camera(1, generator, config)
    seen, truth = maps[None].clone(), maps[None].clone()
    if config.cast_in_diffuse:  # the camera's colours: what re-renders its photos
        brightness, cast = colour_cast(camera.gains)
        camera.gains = brightness
        for channels in (constants.DIFFUSE, constants.SPECULAR):
            truth[:, channels] = (truth[:, channels] * cast.view(1, 3, 1, 1)).clamp(0.0, 1.0)
        seen = truth.clone()
    intensity = math.pi * float(positions[0, 2]) ** 2
    with torch.no_grad():
        radiance = render_flash(seen, positions[None], intensity=intensity, convention=config.convention)[0]
    if config.flash_cone[1] > 0:
        exponent = config.flash_cone[0] + (config.flash_cone[1] - config.flash_cone[0]) * torch.rand(1, generator=generator)
        radiance = radiance * flash_cone_falloff(positions, exponent.expand(count), *radiance.shape[-2:])
    size = (maps.shape[-2] // 2, maps.shape[-1] // 2)
    photos = simulate_photo(downsample(radiance, size), generator, config, camera=camera.repeated(count))
    return photos, downsample_maps(truth, size)[0]


def make_scenes(out: Path, count: int, seed: int = 0, size: int = 256, progress: bool = True) -> list[Path]:
    """Write ``count`` calibrated scenes of ``size`` px photos into the folder ``out`` (made), the
    materials of seeds ``SCENE_SEED + seed + k``; returns the scene folders."""
    from tqdm import tqdm

    from ..imageio import write_bytes, write_image
    from ..material import Material
    from .procedural import GeneratorConfig, generate

    config = replace(SynthesisConfig(**PHONE_PHOTOS), convention=constants.DEFAULT_CONVENTION)
    folders = []
    for index in tqdm(range(count), desc="scenes", unit="scene", disable=not progress):
        number = SCENE_SEED + seed + index
        generator = torch.Generator().manual_seed(number)
        maps = generate(number, config=GeneratorConfig(size=2 * size)).to_tensor()
        positions = scene_geometry(generator, config)
        photos, truth = photograph_scene(maps, positions, generator, config)
        folder = out / f"scene{seed + index:04d}"
        for number_of_photo, photo in enumerate(photos):
            write_image(folder / f"{number_of_photo:02d}.png", photo.permute(1, 2, 0).numpy(), encode_srgb=True)
        centimetres = positions * SIDE_CM / 2
        lines = "".join(",".join(f"{v:.4f}" for v in row.tolist()) + "\n" for row in centimetres)
        write_bytes(folder / "camera_pos.txt", lines.encode())
        write_bytes(folder / "light_pos.txt", lines.encode())
        write_bytes(folder / "image_size.txt", f"{SIDE_CM:.4f}\n".encode())
        Material.from_tensor(truth, provenance={"scene": "procedural", "seed": number}).save(folder / "truth")
        folders.append(folder)
    return folders
