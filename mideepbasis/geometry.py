"""Capture geometry (docs/ARCHITECTURE.md section 3): pixel points, light positions and hand-held offsets.

The sample is the square [-1, 1]^2 in the plane z = 0; camera and flash sit together at
(tx, ty, H) with H = 1 / tan(fov / 2). Distances are in patch half-widths.
"""

from __future__ import annotations

import math

import torch

from . import constants


def pixel_points(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Plane points seen by the pixel centres, (3, H, W): x = -1 + (2j + 1) / w, y = 1 - (2i + 1) / h."""
    rows = torch.arange(height, device=device, dtype=dtype)
    cols = torch.arange(width, device=device, dtype=dtype)
    y = (1 - (2 * rows + 1) / height)[:, None].expand(height, width)
    x = ((2 * cols + 1) / width - 1)[None, :].expand(height, width)
    return torch.stack([x, y, torch.zeros_like(x)])


def light_positions(offsets: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG) -> torch.Tensor:
    """Camera-and-flash positions for lateral hand-held offsets.

    Args:
        offsets: (..., 2) lateral offsets (tx, ty) [patch half-widths].
        fov: field of view along the image width [deg].

    Returns:
        (..., 3) positions (tx, ty, H) [patch half-widths].
    """
    height = torch.full_like(offsets[..., :1], constants.camera_height(fov))
    return torch.cat([offsets, height], dim=-1)


def vector_length(vectors: torch.Tensor, dim: int = -1, keepdim: bool = False) -> torch.Tensor:
    """Euclidean length of the vectors along ``dim``.

    Written out: torch.linalg.vector_norm (and F.normalize, which calls it) over any dimension but
    the last is 30 - 100 times slower on the CPU (torch 2.13; (1, 10, 3, 128, 128) over dim 2: 13 ms
    against 0.2 ms), which would be 70 ms of a capture's prediction.
    """
    return (vectors * vectors).sum(dim=dim, keepdim=keepdim).sqrt()


def unit_vectors(vectors: torch.Tensor, dim: int = -1, eps: float = 1e-12) -> torch.Tensor:
    """The vectors along ``dim`` made unit length (F.normalize: the length floored at ``eps``)."""
    return vectors / vector_length(vectors, dim, keepdim=True).clamp(min=eps)


def scaled_slopes(normals: torch.Tensor, strength: float, dim: int = -1) -> torch.Tensor:
    """Unit normals whose slopes are ``strength`` times the given ones: x and y scaled, then the
    vectors made unit again (a normal map's strength; 0 is flat, 1 leaves them).

    Args:
        normals: (..., 3, ...) with the three components along ``dim``.
    """
    x, y, z = normals.unbind(dim)
    return unit_vectors(torch.stack([x * strength, y * strength, z], dim=dim), dim=dim)


def offset_angle_deg(offsets: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG) -> torch.Tensor:
    """Angle atan(|t| / H) of an offset as seen from the sample centre [deg], shape (...)."""
    return torch.rad2deg(torch.atan(torch.linalg.vector_norm(offsets, dim=-1) / constants.camera_height(fov)))


def max_offset(fov: float = constants.DEFAULT_FOV_DEG, max_angle_deg: float = constants.MAX_OFFSET_DEG) -> float:
    """Largest lateral offset |t| = H tan(delta) [patch half-widths]."""
    return constants.camera_height(fov) * math.tan(math.radians(max_angle_deg))


def flash_intensity(fov: float = constants.DEFAULT_FOV_DEG, convention: str = constants.DEFAULT_CONVENTION) -> float:
    """Radiant intensity of the flash [W/sr]: pi H^2 (``physical``: a white Lambertian at the
    centre renders to 1.0), or the DeepBasis lamp intensity (``deepbasis``, no falloff)."""
    if convention == "deepbasis":
        return constants.DEEPBASIS_LAMP_INTENSITY
    return math.pi * constants.camera_height(fov) ** 2


def lighting_mark_material(height: int, width: int) -> torch.Tensor:
    """The lighting-mark reference material, (1, 10, H, W): flat, diffuse 0.1, specular 0.5, roughness 0.15.

    Rendered under a hypothesised flash, it tells the network where that flash is (docs/ARCHITECTURE.md section 7).
    """
    maps = torch.empty(1, constants.BASIS_CHANNELS, height, width)
    maps[:, 0:2] = 0.0
    maps[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    maps[:, constants.DIFFUSE] = constants.LIGHTING_MARK_DIFFUSE
    maps[:, constants.ROUGHNESS] = constants.LIGHTING_MARK_ROUGHNESS
    maps[:, constants.SPECULAR] = constants.LIGHTING_MARK_SPECULAR
    return maps
