"""Independent references shared by several tests."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import torch

#: The benchmark scripts' folder (not a package: they import ``common`` beside them).
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def benchmark_module(name: str):
    """The benchmark script ``benchmarks/NAME.py`` loaded as a module (its ``main`` not run)."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module


def directional_albedo(view_angle_deg: float, diffuse: float = 1.0, roughness: float = 1.0, specular: float = 0.0,
                       steps: int = 512) -> float:
    """The integral of f cos over the hemisphere for a flat, uniform material seen from ``view_angle_deg``
    off its normal: the radiance it reflects under a uniform sky of unit radiance. Midpoint quadrature
    of the torch reference BSDF (``render/reference.py``), in float64."""
    from mideepbasis.render import reference

    view = torch.tensor([0.0, -math.sin(math.radians(view_angle_deg)), math.cos(math.radians(view_angle_deg))],
                        dtype=torch.float64)
    theta = (torch.arange(steps, dtype=torch.float64) + 0.5) / steps * (math.pi / 2)
    phi = (torch.arange(2 * steps, dtype=torch.float64) + 0.5) / (2 * steps) * (2 * math.pi)
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    light = torch.stack([torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p), torch.cos(t)])[None]
    ones = torch.ones(1, 3, *t.shape, dtype=torch.float64)
    normal = ones * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
    value = reference.eval_cosine("physical", normal, view.view(1, 3, 1, 1).expand_as(light), light, ones * diffuse,
                                  ones[:, :1] * roughness, ones * specular)
    return float((value[0, 0] * torch.sin(t)).sum() * (math.pi / 2 / steps) * (2 * math.pi / (2 * steps)))


def matte_egg_crate(size: int, cycles: int, slope: float) -> torch.Tensor:
    """(1, 10, size, size): grey Lambertian albedo, no specular, normals of the height
    h = a sin(pi k x) sin(pi k y) on [-1, 1]^2 (k = ``cycles``), a = slope / (pi k): peak slope ``slope``."""
    from mideepbasis import constants, geometry

    coords = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    frequency = math.pi * cycles
    dh_dx = slope * torch.cos(frequency * x) * torch.sin(frequency * y)
    dh_dy = slope * torch.sin(frequency * x) * torch.cos(frequency * y)
    normal = geometry.unit_vectors(torch.stack([-dh_dx, -dh_dy, torch.ones_like(x)]), dim=0).float()
    maps = torch.zeros(1, 10, size, size)
    maps[0, constants.NORMAL] = normal
    maps[0, constants.DIFFUSE] = 0.5
    maps[0, constants.ROUGHNESS] = 1.0
    return maps
