"""The SVBRDF model and the flash render in plain torch: the independent cross-check.

Nothing here calls drjit or Mitsuba. The formulas are those of docs/ARCHITECTURE.md section 4, written
a second time from the text, so that agreement with the plugin (``flash.py`` through
``bridge.py``) checks both. Tensors are (..., 3, H, W) or broadcast against it.
"""

from __future__ import annotations

import math

import torch

from .. import constants
from ..geometry import pixel_points


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(dim=-3, keepdim=True)


def _normalize(v: torch.Tensor) -> torch.Tensor:
    # Not torch.linalg.vector_norm: over a non-last dimension it is ~90x slower on the CPU.
    return v * torch.rsqrt((v * v).sum(dim=-3, keepdim=True))


def eval_cosine(convention: str, normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor,
                diffuse: torch.Tensor, roughness: torch.Tensor, specular: torch.Tensor) -> torch.Tensor:
    """f(wi, wo) max(n.wo, 0): the BSDF value times the cosine at the light direction.

    Args:
        convention: ``physical`` or ``deepbasis``.
        normal: normal-mapped normal, (..., 3, H, W); normalised here.
        wi, wo: unit directions to the viewer and the light, (..., 3, H, W), local frame (+z up).
        diffuse, specular: albedos [0, 1], (..., 3, H, W).
        roughness: roughness [0, 1], (..., 1, H, W); alpha = r^2.

    Returns:
        (..., 3, H, W); zero where wi or wo is below the geometric surface.
    """
    n = _normalize(normal)
    h = _normalize(wi + wo)
    cos_v, cos_l = _dot(n, wi), _dot(n, wo)
    cos_h, cos_vh = _dot(n, h), _dot(wi, h)
    # |n x h|^2 rather than 1 - (n.h)^2: the GGX peak of smooth materials needs the precision.
    sin2_h = (torch.linalg.cross(n, h, dim=-3) ** 2).sum(dim=-3, keepdim=True)
    above = (wi[..., 2:3, :, :] > 0) & (wo[..., 2:3, :, :] > 0)

    if convention == "physical":
        alpha2 = roughness.clamp_min(constants.PHYSICAL_MIN_ROUGHNESS) ** 4
        ndf = alpha2 / (math.pi * (alpha2 * cos_h**2 + sin2_h) ** 2)

        def g1(x):
            return 2 * x / (x + torch.sqrt(alpha2 + (1 - alpha2) * x**2))

        fresnel = specular + (1 - specular) * (1 - cos_vh).clamp(0, 1) ** 5
        valid = above & (cos_v > 0) & (cos_l > 0)
        cos_v_safe = torch.where(valid, cos_v, torch.ones_like(cos_v))
        cos_l_safe = torch.where(valid, cos_l, torch.ones_like(cos_l))
        value = diffuse / math.pi + ndf * g1(cos_l_safe) * g1(cos_v_safe) * fresnel / (4 * cos_l_safe * cos_v_safe)
        return torch.where(valid, value * cos_l_safe, torch.zeros_like(value))

    if convention == "deepbasis":
        eps = constants.DEEPBASIS_COSINE_EPS
        cos_v, cos_l = cos_v.clamp_min(eps), cos_l.clamp_min(eps)
        cos_h, cos_vh = cos_h.clamp_min(eps), cos_vh.clamp_min(eps)
        alpha = roughness.clamp_min(constants.DEEPBASIS_MIN_ROUGHNESS) ** 2
        alpha2 = alpha**2
        ndf = alpha2 / (math.pi * (alpha2 * cos_h**2 + sin2_h) ** 2)
        k = (alpha / 2).clamp_min(eps)
        visibility = 1 / ((cos_l * (1 - k) + k) * (cos_v * (1 - k) + k))
        fresnel = specular + (1 - specular) * torch.exp2(cos_vh * (-5.55473 * cos_vh - 6.98316))
        value = diffuse * (1 - specular) / math.pi + 0.25 * ndf * visibility * fresnel
        return torch.where(above, value * cos_l, torch.zeros_like(value))

    raise ValueError(f"unknown shading convention {convention!r}; expected one of {constants.CONVENTIONS}")


def render_flash(maps: torch.Tensor, lights: torch.Tensor, intensity: float,
                 convention: str = constants.DEFAULT_CONVENTION, views: torch.Tensor | None = None,
                 extent: float = 1.0) -> torch.Tensor:
    """Per-pixel flash render of a batch of materials under co-located camera and flash.

    Args:
        maps: (B, 10, H, W) stacked [normal 3, diffuse 3, roughness 1, specular 3].
        lights: (B, K, 3) camera and flash positions [patch half-widths].
        views: (B, K, 3) viewpoints apart from the lights, or None (co-located).
        intensity: radiant intensity [W/sr] (``physical``) or lamp intensity (``deepbasis``).
        convention: ``physical`` or ``deepbasis``.

    Returns:
        linear radiance, (B, K, 3, H, W).
    """
    height, width = maps.shape[-2:]
    normal, diffuse, roughness, specular = (m.unsqueeze(1) for m in torch.split(maps, [3, 3, 1, 3], dim=1))
    points = pixel_points(height, width, maps.device, maps.dtype) * extent
    to_light = lights[..., :, None, None] - points  # (B, K, 3, H, W)
    distance2 = (to_light**2).sum(dim=-3, keepdim=True)
    direction = to_light / torch.sqrt(distance2)
    to_view = direction if views is None else _normalize(views[..., :, None, None] - points)
    value = eval_cosine(convention, normal, to_view, direction, diffuse, roughness, specular)
    if convention == "deepbasis":
        return value * (math.pi * intensity)
    return value * intensity / distance2
