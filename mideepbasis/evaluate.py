"""Evaluation: map errors and re-rendering errors of predicted materials against ground truth.

Protocol (the paper's): the input photo is re-rendered from the ground-truth maps under a flash
(centred, or a seeded hand-held offset per material), photographed as an 8-bit sRGB image, and
the method predicts the maps from it. Map RMSE is computed on the maps in their stored encoding
(the Deschaintre test maps are used as stored, so that is their in-memory value; normals as
(n + 1) / 2). The re-rendering error compares renders of the prediction and of the truth under
the same 30 random lights and viewpoints per material (seeded, identical for every method), on
clipped sRGB-encoded images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from . import constants, geometry
from .imageio import linear_to_srgb

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


def light_error_deg(estimate, truth, fov: float = constants.DEFAULT_FOV_DEG) -> float:
    """Angle between an estimated and a true flash position seen from the sample centre [deg].

    Args:
        estimate, truth: lateral offsets (tx, ty) [patch half-widths], or (..., 2) tensors.
    """
    a = geometry.light_positions(torch.as_tensor(estimate, dtype=torch.float64), fov)
    b = geometry.light_positions(torch.as_tensor(truth, dtype=torch.float64), fov)
    cosine = (a * b).sum(-1) / (torch.linalg.vector_norm(a, dim=-1) * torch.linalg.vector_norm(b, dim=-1))
    angle = torch.rad2deg(torch.arccos(cosine.clamp(-1.0, 1.0)))
    return float(angle) if angle.ndim == 0 else angle


def map_rmse(predicted: torch.Tensor, truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-material RMSE of each map in the stored encoding, (B,) each.

    Normals are compared as stored, (n + 1) / 2; the other maps as they are (linear, or the stored
    values of a dataset read as-is); roughness has one channel.
    """
    def rmse(a, b):
        return ((a - b) ** 2).mean(dim=(1, 2, 3)).sqrt()

    return {"normal": rmse((predicted[:, 0:3] + 1) / 2, (truth[:, 0:3] + 1) / 2),
            "diffuse": rmse(predicted[:, 3:6], truth[:, 3:6]),
            "roughness": rmse(predicted[:, 6:7], truth[:, 6:7]),
            "specular": rmse(predicted[:, 7:10], truth[:, 7:10])}


def rerender(maps: torch.Tensor, lights: torch.Tensor, views: torch.Tensor, convention: str,
             backend: str = "mitsuba") -> torch.Tensor:
    """Clipped, sRGB-encoded renders of (B, 10, H, W) maps under (K, 3) lights and views -> (B, K, 3, H, W).

    ``physical``: the light's intensity is pi d^2 for its mean distance d to the sample centre, so
    a white Lambertian facing it renders to about 1. ``deepbasis``: their unit lamp without falloff.
    """
    from .render import render_flash

    batch = maps.shape[0]
    intensity = math.pi * float((lights**2).sum(-1).mean()) if convention == "physical" else constants.DEEPBASIS_LAMP_INTENSITY
    with torch.no_grad():
        linear = render_flash(maps, lights.expand(batch, -1, -1), convention=convention, intensity=intensity,
                              backend=backend, views=views.expand(batch, -1, -1))
    return linear_to_srgb(linear.clamp(0.0, 1.0))


def rerender_rmse(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, views: torch.Tensor,
                  convention: str, backend: str = "mitsuba") -> torch.Tensor:
    """Per-material RMSE between re-renderings of prediction and truth, (B,)."""
    difference = rerender(predicted, lights, views, convention, backend) - rerender(truth, lights, views, convention, backend)
    return (difference**2).mean(dim=(1, 2, 3, 4)).sqrt()


def trivial_baseline(materials: torch.Tensor) -> torch.Tensor:
    """The trivial prediction for a set (N, 10, H, W): a flat normal and the set's mean maps, (10, H, W)."""
    mean = materials.mean(dim=(0, 2, 3))
    baseline = mean.view(10, 1, 1).expand(10, *materials.shape[-2:]).clone()
    baseline[0:3] = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    return baseline


def flash_photos(maps: torch.Tensor, offsets: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG,
                 convention: str = constants.DEFAULT_CONVENTION) -> tuple[torch.Tensor, torch.Tensor]:
    """The evaluation inputs: 8-bit sRGB photos of ``maps`` (B, 10, H, W) under flashes at lateral
    ``offsets`` (B, 2) [patch half-widths], no noise. Returns (photos (B, 3, H, W) linear, lights (B, 3))."""
    from .data.synth import SynthesisConfig, simulate_photo
    from .render import render_flash

    lights = geometry.light_positions(offsets, fov)
    with torch.no_grad():
        radiance = render_flash(maps, lights.view(-1, 1, 3), fov=fov, convention=convention)[:, 0]
    quiet = SynthesisConfig(shot_noise=(1e-30, 1e-30), read_noise=(1e-30, 1e-30), quantize=True)
    photos = simulate_photo(radiance, torch.Generator().manual_seed(0), quiet, gains=torch.ones(maps.shape[0], 3))
    return photos, lights


@dataclass
class Scores:
    """Per-material scores of one method on a set."""

    names: list[str]
    maps: dict[str, torch.Tensor] = field(default_factory=dict)
    render: torch.Tensor | None = None

    def summary(self) -> dict:
        result = {name: float(values.mean()) for name, values in self.maps.items()}
        if self.render is not None:
            result["render_rmse"] = float(self.render.mean())
        return result
