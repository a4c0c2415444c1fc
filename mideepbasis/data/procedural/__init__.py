"""The procedural SVBRDF generator: the project's only source of training materials.

    from mideepbasis.data.procedural import generate, FAMILIES
    material = generate(seed=7, size=256)                    # a random family
    material = generate(seed=7, family="wood", tileable=True)

A material is made in four steps, all drawn from one generator seeded by ``seed`` (the same
seed gives the same material): a family builds a ``Surface`` (relief, albedos, roughness); with
some chance a second family is mixed in through a mask; weathering layers (scratches, dirt,
wear, stains, fingerprints) are applied with their chances; the normals are computed from the
relief. Values stay physically plausible: dielectrics have a grey F0 of about 0.02 to 0.08 and a
coloured diffuse albedo, metals a coloured F0 and a dark diffuse albedo.

(A package rather than one module, for its twelve families (docs/ARCHITECTURE.md section 15):
``core`` has the primitives, ``families/`` one module per family, ``layers`` the weathering and
mixing.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ... import constants
from ...material import Material
from . import families as _families  # noqa: F401  (registers every family)
from .core import MIN_SIZE, Canvas, Surface, height_to_normal
from .layers import mixing_mask, unevenness, weather
from .registry import FAMILIES


@dataclass(frozen=True)
class GeneratorConfig:
    """How materials are drawn."""

    size: int = constants.DEFAULT_RESOLUTION
    """Width and height of the maps [pixels]."""

    tileable: bool = False
    """Make every map wrap around its edges without a seam."""

    families: tuple[str, ...] | None = None
    """Families to draw from (all registered families when None)."""

    mix_probability: float = 0.2
    """Chance that a second family is mixed in through a mask."""

    weathering: bool = True
    """Apply the weathering layers (each with its own chance)."""

    bump_scale: tuple[float, float] = (0.6, 4.0)
    """Range of a random factor on the relief, log-uniform: the same structure deeper or flatter
    (used where ``relief_tilt_deg`` is None)."""

    relief_tilt_deg: tuple[float, float] | None = (2.4, 45.0)
    """Range (log-uniform) of the mean tilt of the normals that each material's relief is scaled
    to [deg], whatever its family: relief of every strength for every kind of surface. With it
    the median mean tilt of 300 materials is 9.4 deg (the shared test set's: 8.9 deg); a random
    factor on the family's own relief (``bump_scale``) gave 4.1 deg and a quarter of the materials
    under 1.1 deg, some families being nearly flat. Sparse relief cannot always reach its target
    under ``max_relief_factor``, so the measured tilts run a little below the drawn ones."""

    max_relief_factor: float = 50.0
    """Largest factor on a family's relief when scaling it to ``relief_tilt_deg``: a surface flat
    but for a few scratches keeps them as scratches rather than turning them into walls."""

    coarse_relief_tilt_deg: tuple[float, float] | None = None
    """Range (log-uniform) of the mean tilt [deg] of a broad undulation added under the relief, with
    chance ``coarse_relief_probability`` (None: none, the families' relief alone): bumps of 1/2 to
    1/16 of the sample (power-law noise of 1 - 8 cycles), independent of the colours. The
    families' relief, scaled to a mean tilt, is mostly fine: features under 1/16 of the sample
    carry the normal's x and y at 0.036 RMS in the coarse band of 48 materials, against 0.089 in
    the shared test set; (1.5, 30) with chance 0.7 gives 0.067."""

    coarse_relief_probability: float = 0.7
    """Chance of the broad undulation of ``coarse_relief_tilt_deg``."""

    gloss_probability: float = 0.0
    """Chance that the roughness is scaled by a factor drawn from ``gloss_scale``: the families'
    roughness runs high (median of the material means 0.53, against 0.39 in the shared test
    set), so glossy surfaces with sharp highlights are rarer than in what people photograph."""

    gloss_scale: tuple[float, float] = (0.35, 1.0)
    """Range (log-uniform) of the factor on the roughness of a glossier material."""

    darkening_probability: float = 0.0
    """Chance that the diffuse albedo is scaled by a factor drawn from ``darkening_scale``, its
    colour kept: the families' albedos run bright (median of the material means 0.15 in linear
    light, against 0.05 in the shared test set), so the specular term rarely dominates."""

    darkening_scale: tuple[float, float] = (0.15, 1.0)
    """Range (log-uniform) of the factor on the diffuse albedo of a darker material."""

    def __post_init__(self):
        if self.size < MIN_SIZE:
            raise ValueError(f"procedural materials need at least {MIN_SIZE} pixels, got {self.size}")


def _family_names(config: GeneratorConfig) -> list[str]:
    names = list(config.families) if config.families else list(FAMILIES)
    unknown = [name for name in names if name not in FAMILIES]
    if unknown:
        raise ValueError(f"unknown procedural families {unknown}; known: {sorted(FAMILIES)}")
    return names


def generate_surface(seed: int, config: GeneratorConfig = GeneratorConfig(),
                     family: str | None = None) -> tuple[Surface, np.ndarray, dict]:
    """The surface, its normals ((H, W, 3)) and its provenance, before it becomes a Material."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x6D69646565]))
    canvas = Canvas(config.size, rng, config.tileable)
    names = _family_names(config)
    name = family or names[int(rng.integers(len(names)))]
    if name not in FAMILIES:
        raise ValueError(f"unknown procedural family {name!r}; known: {sorted(FAMILIES)}")
    surface = FAMILIES[name](canvas)
    provenance = {"generator": "mideepbasis.procedural", "seed": int(seed), "family": name,
                  "variant": surface.variant, "size": config.size, "tileable": config.tileable}
    if canvas.chance(config.mix_probability):
        other_name = names[int(rng.integers(len(names)))]
        other = FAMILIES[other_name](canvas)
        mask, kind = mixing_mask(canvas)
        surface = surface.blend(other, mask)
        provenance["mixed_with"] = {"family": other_name, "variant": other.variant, "mask": kind}
    surface = unevenness(canvas, surface)
    if config.weathering:
        surface, applied = weather(canvas, surface)
        provenance["layers"] = applied
    if config.relief_tilt_deg is None:
        height = surface.height * canvas.loguniform(*config.bump_scale)
    else:
        target = canvas.loguniform(*config.relief_tilt_deg)
        height = surface.height * relief_factor(surface.height, target, config.tileable, config.max_relief_factor)
    if config.coarse_relief_tilt_deg is not None and canvas.chance(config.coarse_relief_probability):
        # Drawn after everything else, so the colours and the fine relief stay those of the seed.
        undulation = canvas.noise(beta=3.0, low=1.0, high=8.0)
        tilt = canvas.loguniform(*config.coarse_relief_tilt_deg)
        height = height + undulation * relief_factor(undulation, tilt, config.tileable, max_factor=1e4)
        provenance["coarse_relief_tilt_deg"] = tilt
    # Two draws that nothing uses, in the places of a low-relief chance and a relief-inversion chance
    # (both off): they keep what is drawn after them, and so every seed's material, fixed across versions.
    canvas.rng.random()
    canvas.rng.random()
    # The marginals' shifts come last, for the same reason, and leave the relief as it is.
    diffuse, roughness = surface.diffuse, surface.roughness
    if canvas.chance(config.gloss_probability):
        factor = canvas.loguniform(*config.gloss_scale)
        roughness = np.clip(roughness, 0, 1) * factor  # of the values the material would have had
        provenance["roughness_factor"] = factor
    if canvas.chance(config.darkening_probability):
        factor = canvas.loguniform(*config.darkening_scale)
        diffuse = np.clip(diffuse, 0, 1) * factor
        provenance["diffuse_factor"] = factor
    surface = Surface(height, diffuse, roughness, surface.specular, surface.variant).clipped()
    return surface, height_to_normal(surface.height, config.tileable), provenance


def relief_factor(height: np.ndarray, tilt_deg: float, tileable: bool, max_factor: float = 50.0) -> float:
    """The factor s such that the normals of ``s * height`` lean ``tilt_deg`` [deg] on average
    (the mean over pixels of atan(s |grad h|)), at most ``max_factor``; 1 for a flat height field."""
    normal = height_to_normal(height, tileable)
    slope = np.sqrt(normal[..., 0] ** 2 + normal[..., 1] ** 2) / normal[..., 2]
    target = np.radians(tilt_deg)
    if not slope.any():
        return 1.0
    low, high = -12.0, float(np.log(max_factor))  # bisection on log s: the mean tilt grows with s
    if np.arctan(np.exp(high) * slope).mean() <= target:
        return max_factor
    for _ in range(20):  # 1e-5 in log s
        middle = 0.5 * (low + high)
        if np.arctan(np.exp(middle) * slope).mean() < target:
            low = middle
        else:
            high = middle
    return float(np.exp(0.5 * (low + high)))


def generate(seed: int, size: int | None = None, family: str | None = None, tileable: bool | None = None,
             config: GeneratorConfig = GeneratorConfig()) -> Material:
    """A procedural material.

    Args:
        seed: the material's seed; the same seed (and configuration) gives the same material.
        size: width and height [pixels] (overrides ``config.size``).
        family: force a family (see ``FAMILIES``); default drawn from the seed.
        tileable: make the maps wrap without a seam (overrides ``config.tileable``).
        config: the generator configuration.

    Returns:
        a ``Material`` in the conventions of docs/ARCHITECTURE.md section 5 (``physical``), with the
        recipe in its provenance.
    """
    overrides = {key: value for key, value in (("size", size), ("tileable", tileable)) if value is not None}
    if overrides:
        config = GeneratorConfig(**{**config.__dict__, **overrides})
    surface, normal, provenance = generate_surface(seed, config, family)

    def channels_first(image):
        return torch.from_numpy(np.ascontiguousarray(np.moveaxis(image, -1, 0)))

    return Material(normal=channels_first(normal), diffuse=channels_first(surface.diffuse),
                    roughness=torch.from_numpy(np.ascontiguousarray(surface.roughness[None])),
                    specular=channels_first(surface.specular), provenance=provenance,
                    source=f"procedural material {seed}")


__all__ = ["FAMILIES", "GeneratorConfig", "generate", "generate_surface"]
