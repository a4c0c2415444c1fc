"""Training inputs: photos rendered from materials under hand-held flashes, as a phone would take them.

For a batch of materials M this draws, per material, a hand-held offset and a variation xi,
renders M and M + xi under the same flash through the renderer interface (the ``svbrdf``
plugin), turns both renders into photos (exposure and white-balance jitter, shot and read
noise, clipping, 8-bit sRGB quantisation) and builds the 9-channel network inputs that
training and capture share (``encode_inputs``).

Shapes: maps (B, 10, H, W) [normal 3, diffuse 3, roughness 1, specular 3]; images (B, 3, H, W)
linear; offsets (B, 2) [patch half-widths]; lights (B, 3) [patch half-widths].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .. import constants, geometry
from ..imageio import linear_to_srgb, srgb_to_linear
from ..model.inputs import encode_inputs


@dataclass(frozen=True)
class SynthesisConfig:
    """How training photos are made."""

    fov: float = constants.DEFAULT_FOV_DEG
    """Field of view of the simulated phone camera [deg]."""

    max_offset_deg: float = constants.MAX_OFFSET_DEG
    """Largest hand-held offset, as seen from the sample centre [deg] (delta)."""

    offset_sigma_divisor: float = constants.OFFSET_SIGMA_DIVISOR
    """Per-axis standard deviation of the offset angle is delta divided by this."""

    convention: str = constants.DEFAULT_CONVENTION
    """Shading convention of the renders."""

    exposure_sigma: float = 0.15
    """Standard deviation of the log exposure gain (auto-exposure error) [natural log units]."""

    white_balance_sigma: float = 0.03
    """Standard deviation of the log gain of each colour channel (white-balance error)."""

    shot_noise: tuple[float, float] = (1e-4, 3e-3)
    """Range (log-uniform) of the shot-noise variance per unit of signal [linear units]."""

    read_noise: tuple[float, float] = (1e-4, 3e-3)
    """Range (log-uniform) of the standard deviation of the read noise [linear units]."""

    quantize: bool = True
    """Clip and quantise the photo to 8-bit sRGB, as a JPEG from a phone is."""

    max_rotation: float = math.pi / 6
    """Largest rotation of the normals by the variation xi [rad]."""

    max_shift: float = 0.3
    """Largest shift of the other maps by the variation xi [unitless]."""

    supersample: int = 1
    """Photograph each material at this many times the size its maps come out at, then
    area-downsample the photo and the maps (the normals averaged and made unit), as ``capture``
    downsamples a 256 px photo to the network's 128 px: relief and highlights finer than a pixel
    then reach the network blurred as they do from a photo. The materials must be made at the
    larger size (``train`` makes them so). 1: photographed at the maps' own size."""

    def __post_init__(self):
        if not isinstance(self.supersample, int) or self.supersample < 1:
            raise ValueError(f"supersample must be a whole number of at least 1, got {self.supersample!r}")


# --- hand-held offsets -----------------------------------------------------------------------------


def sample_offsets(batch: int, generator: torch.Generator, fov: float = constants.DEFAULT_FOV_DEG,
                   max_offset_deg: float = constants.MAX_OFFSET_DEG,
                   sigma_divisor: float = constants.OFFSET_SIGMA_DIVISOR) -> torch.Tensor:
    """Hand-held lateral offsets of camera and flash.

    Each axis's offset angle is drawn from N(0, (delta / sigma_divisor)^2) [deg]; the offset
    is t = H tan(angle) per axis and is clipped radially so that atan(|t| / H) <= delta.

    Returns:
        (B, 2) offsets (tx, ty) [patch half-widths].
    """
    height = constants.camera_height(fov)
    angles = torch.randn(batch, 2, generator=generator) * (max_offset_deg / sigma_divisor)
    offsets = height * torch.tan(torch.deg2rad(angles))
    limit = height * math.tan(math.radians(max_offset_deg))
    length = torch.linalg.vector_norm(offsets, dim=-1, keepdim=True)
    return offsets * torch.clamp(limit / length.clamp(min=1e-12), max=1.0)


# --- the variation xi of the variation-consistency loss ------------------------------------------


@dataclass
class Variation:
    """A per-material change of the maps: the xi of the variation-consistency loss.

    The normals turn about +z by ``rotation``; each of the 7 other channels (diffuse 3,
    roughness 1, specular 3) moves as ``m' = (m + shift) / (1 + shift)``, which keeps [0, 1] in
    [0, 1]. The same xi applies to every pixel and, through ``apply``, to maps and to bases alike.

    Attributes:
        rotation: (B,) angle [rad], uniform in [0, max_rotation].
        shift: (B, 7) shift [unitless], uniform in [0, max_shift], one per channel.
    """

    rotation: torch.Tensor
    shift: torch.Tensor

    def apply(self, maps: torch.Tensor) -> torch.Tensor:
        """Vary (B, 10, ...) maps or bases (any trailing dimensions)."""
        extra = (1,) * (maps.ndim - 2)
        cos = torch.cos(self.rotation).view(-1, *extra).to(maps)
        sin = torch.sin(self.rotation).view(-1, *extra).to(maps)
        # split, not indexing: its backward concatenates instead of zero-filling full tensors.
        nx, ny, nz, rest = maps.split([1, 1, 1, 7], dim=1)
        cos, sin = cos.unsqueeze(1), sin.unsqueeze(1)
        shift = self.shift.view(self.shift.shape[0], 7, *extra).to(maps)
        return torch.cat([cos * nx - sin * ny, sin * nx + cos * ny, nz, (rest + shift) / (1.0 + shift)], dim=1)


def sample_variation(batch: int, generator: torch.Generator, max_rotation: float = math.pi / 6,
                     max_shift: float = 0.3) -> Variation:
    """Draw xi for a batch: rotations uniform in [0, max_rotation], shifts uniform in [0, max_shift]."""
    rotation = torch.rand(batch, generator=generator) * max_rotation
    shift = torch.rand(batch, 7, generator=generator) * max_shift
    return Variation(rotation=rotation, shift=shift)


# --- the camera ---------------------------------------------------------------------------------


def simulate_photo(radiance: torch.Tensor, generator: torch.Generator, config: SynthesisConfig = SynthesisConfig(),
                   gains: torch.Tensor | None = None) -> torch.Tensor:
    """A phone photo of linear radiance: gain jitter, noise, clipping and 8-bit sRGB quantisation.

    Args:
        radiance: (B, 3, H, W) linear radiance.
        generator: the random generator.
        config: noise and jitter amounts.
        gains: (B, 3) colour gains to use (exposure times white balance); drawn when None.

    Returns:
        (B, 3, H, W) linear photo in [0, 1] (values of an 8-bit sRGB image when quantised).
    """
    batch = radiance.shape[0]
    if gains is None:
        gains = sample_gains(batch, generator, config)
    signal = radiance * gains.view(batch, 3, 1, 1).to(radiance)
    shot = _log_uniform(batch, config.shot_noise, generator).view(batch, 1, 1, 1).to(radiance)
    read = _log_uniform(batch, config.read_noise, generator).view(batch, 1, 1, 1).to(radiance)
    noise = torch.randn(signal.shape, generator=generator).to(radiance)
    photo = signal + noise * torch.sqrt(shot * signal.clamp(min=0) + read * read)
    photo = photo.clamp(0.0, 1.0)
    if config.quantize:
        photo = srgb_to_linear(torch.round(linear_to_srgb(photo) * 255.0) / 255.0)
    return photo


def sample_gains(batch: int, generator: torch.Generator, config: SynthesisConfig = SynthesisConfig()) -> torch.Tensor:
    """(B, 3) exposure times white-balance gains, log-normal around 1."""
    exposure = torch.randn(batch, 1, generator=generator) * config.exposure_sigma
    balance = torch.randn(batch, 3, generator=generator) * config.white_balance_sigma
    return torch.exp(exposure + balance)


def _log_uniform(batch: int, bounds: tuple[float, float], generator: torch.Generator) -> torch.Tensor:
    low, high = math.log(bounds[0]), math.log(bounds[1])
    return torch.exp(low + (high - low) * torch.rand(batch, generator=generator))


# --- a training batch -------------------------------------------------------------------------------


@dataclass
class TrainingBatch:
    """Everything one training step needs for the supervised and the variation-consistency losses.

    Attributes:
        maps, varied_maps: (B, 10, H, W) the materials M and M + xi.
        variation: the xi that maps one to the other.
        offsets: (B, 2) hand-held offsets [patch half-widths]; lights: (B, 3) flash positions.
        inputs, varied_inputs: (B, 9, H, W) network inputs of the photos of M and of M + xi.
        photos, varied_photos: (B, 3, H, W) the linear photos themselves.
    """

    maps: torch.Tensor
    varied_maps: torch.Tensor
    variation: Variation
    offsets: torch.Tensor
    lights: torch.Tensor
    inputs: torch.Tensor
    varied_inputs: torch.Tensor
    photos: torch.Tensor
    varied_photos: torch.Tensor
    extras: dict = field(default_factory=dict)


def synthesize(maps: torch.Tensor, generator: torch.Generator,
               config: SynthesisConfig = SynthesisConfig(), extra_inputs: tuple[str, ...] = ()) -> TrainingBatch:
    """Render and photograph a batch of materials and their variations (one renderer call).

    M and M + xi share the flash position and the camera's gains (one camera, one shot each)
    but not the noise. ``extra_inputs``: the network's optional input channels. With
    ``config.supersample`` F the maps are F times the batch's size: photos, maps and variations
    come out area-downsampled by F.
    """
    from ..render import render_flash

    batch, factor = maps.shape[0], config.supersample
    if maps.shape[-2] % factor or maps.shape[-1] % factor:
        raise ValueError(f"maps of {maps.shape[-2]}x{maps.shape[-1]} cannot be supersampled by {factor}")
    variation = sample_variation(batch, generator, config.max_rotation, config.max_shift)
    varied = variation.apply(maps)
    offsets = sample_offsets(batch, generator, config.fov, config.max_offset_deg, config.offset_sigma_divisor)
    # Random numbers come from the (CPU) generator; the renders run where the maps are.
    lights = geometry.light_positions(offsets, config.fov).to(maps.device)
    both_lights = torch.cat([lights, lights])
    with torch.no_grad():
        radiance = render_flash(torch.cat([maps, varied]), both_lights.view(2 * batch, 1, 3),
                                fov=config.fov, convention=config.convention)[:, 0]
    gains = sample_gains(batch, generator, config)
    photos = simulate_photo(radiance, generator, config, gains=torch.cat([gains, gains]))
    if factor > 1:  # as capture makes a photo smaller: area averages, the normals made unit again
        from ..resampling import downsample, downsample_maps

        size = (maps.shape[-2] // factor, maps.shape[-1] // factor)
        photos, maps, varied = downsample(photos, size), downsample_maps(maps, size), downsample_maps(varied, size)
    inputs = encode_inputs(photos, both_lights, config.fov, config.convention, extra_inputs=extra_inputs)
    return TrainingBatch(maps=maps, varied_maps=varied, variation=variation, offsets=offsets, lights=lights,
                         inputs=inputs[:batch], varied_inputs=inputs[batch:], photos=photos[:batch],
                         varied_photos=photos[batch:])
