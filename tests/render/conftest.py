"""Helpers shared by the rendering tests: random materials and constant textures."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import mideepbasis.render  # noqa: F401  (variant, LLVM and plugin set-up)
import mitsuba as mi


def random_maps(batch: int, height: int, width: int, seed: int = 0, min_roughness: float = 0.1,
                max_tilt_deg: float = 50.0) -> torch.Tensor:
    """(B, 10, H, W) random materials: tilted unit normals, albedos in [0, 1], roughness >= min."""
    generator = torch.Generator().manual_seed(seed)
    tilt = torch.rand(batch, 1, height, width, generator=generator) * math.radians(max_tilt_deg)
    azimuth = torch.rand(batch, 1, height, width, generator=generator) * 2 * math.pi
    normal = torch.cat([torch.sin(tilt) * torch.cos(azimuth), torch.sin(tilt) * torch.sin(azimuth), torch.cos(tilt)], 1)
    diffuse = torch.rand(batch, 3, height, width, generator=generator)
    roughness = min_roughness + (1 - min_roughness) * torch.rand(batch, 1, height, width, generator=generator)
    specular = torch.rand(batch, 3, height, width, generator=generator)
    return torch.cat([normal, diffuse, roughness, specular], 1)


def constant_bitmap(values) -> dict:
    """A ``mi.load_dict`` entry for a 2x2 raw bitmap filled with ``values``."""
    data = np.broadcast_to(np.asarray(values, np.float32), (2, 2, len(values))).copy()
    return {"type": "bitmap", "data": mi.TensorXf(data), "raw": True, "filter_type": "nearest"}


def tilted_normal(tilt_deg: float, azimuth_deg: float = 30.0) -> list[float]:
    tilt, azimuth = math.radians(tilt_deg), math.radians(azimuth_deg)
    return [math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)]


def constant_svbrdf(convention="physical", normal=(0.0, 0.0, 1.0), diffuse=(0.3, 0.5, 0.2), roughness=0.5,
                    specular=(0.3, 0.3, 0.5)) -> mi.BSDF:
    """An ``svbrdf`` plugin instance with spatially constant maps."""
    return mi.load_dict({"type": "svbrdf", "convention": convention, "normal": constant_bitmap(normal),
                         "diffuse": constant_bitmap(diffuse), "roughness": constant_bitmap([roughness]),
                         "specular": constant_bitmap(specular)})


@pytest.fixture
def fov_height():
    """(fov [deg], camera height H) of the default capture."""
    return 45.0, 1.0 / math.tan(math.radians(22.5))
