"""Training inputs: photos rendered from materials under hand-held flashes, as a phone would take them.

For a batch of materials M this draws, per material, a hand-held offset and a variation xi,
renders M and M + xi under the same flash through the renderer interface (the ``svbrdf``
plugin), turns both renders into photos (exposure and white-balance jitter, shot and read
noise, clipping, 8-bit sRGB quantisation) and builds the 9-channel network inputs that
training and capture share (``encode_inputs``). ``PHONE_PHOTOS`` makes them as phones take
them: a field of view drawn per batch, tone curves, white-balance casts, vignetting, the
flash's own falloff, JPEG and slightly tilted samples.

Shapes: maps (B, 10, H, W) [normal 3, diffuse 3, roughness 1, specular 3]; images (B, 3, H, W)
linear; offsets (B, 2) [patch half-widths]; lights (B, 3) [patch half-widths].
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

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

    fov_range: tuple[float, float] | None = None
    """Draw each batch's field of view between these [deg], the camera's distance log-uniform,
    instead of ``fov`` (phones are held at many distances); the offsets keep their angles, so their
    lateral range scales with the distance. None: always ``fov``."""

    cast_in_diffuse: bool = False
    """A white-balance error tints the target's diffuse (the material as the camera sees it) and
    leaves its specular as it is, achromatic for a dielectric: the network learns to read a colour
    cast into the diffuse, never into the specular. False: the target is the material itself."""

    tone_contrast: tuple[float, float] = (0.0, 0.0)
    """Range (uniform, per photo) of the strength s of a phone's S-shaped tone curve after the sRGB
    encoding: y' = (1 - s) y + s (3 y^2 - 2 y^3). The capture decodes with plain sRGB, as it must
    for a photo of unknown processing. 0: plain sRGB."""

    highlight_compression: tuple[float, float] = (1.0, 1.0)
    """Range (log-uniform, per photo) of the white point W of a phone's highlight compression
    (``compress_highlights``). Phones keep a flash highlight from clipping (the real flash photos
    have 0 - 1.4 % of clipped pixels) by compressing it: here the extended Reinhard curve
    y = x (1 + x / W^2) / (1 + x) of x = g times the linear signal, before the clipping and the
    sRGB encoding, with the gain g that keeps a mid grey (0.18) where it was: the signal W / g
    reaches 1, and values below mid grey are lifted by up to g (1.14 at W = 2, 1.20 at W = 8). A
    highlight then has a flatter top than the GGX lobe that made it. 1: none."""

    vignetting: tuple[float, float] = (0.0, 0.0)
    """Range (uniform, per photo) of the lens's darkening v at the image corners: the photo times
    1 - v (r / r_corner)^2 [fraction]."""

    flash_cone: tuple[float, float] = (0.0, 0.0)
    """Range (uniform, per photo) of the exponent k of the flash's angular falloff, cos^k of the
    angle from its axis (a phone's LED is no perfect point light). 0: an isotropic point light."""

    specular_haze: tuple[float, float] = (0.0, 0.0)
    """Range (uniform, per material) of the share of the specular rendered in a second, broader lobe
    (roughness raised by ``haze_spread``) while the target keeps one lobe of the whole specular. A
    real highlight has heavier tails than one GGX lobe (a clear coat over a rougher base, dust,
    scratches): a network trained on one lobe alone puts what the lobe leaves unexplained into the
    diffuse map. 0: one lobe, as the maps say."""

    haze_spread: tuple[float, float] = (0.1, 0.4)
    """Range (uniform, per material) of how much rougher the haze's lobe is than the material's
    (``specular_haze``) [roughness, clipped at 1]."""

    jpeg_quality: tuple[int, int] | None = None
    """Range (uniform, per photo) of the JPEG quality the 8-bit photo is compressed at; None: none."""

    tilt_deg: float = 0.0
    """Largest tilt of the sample against the camera [deg] (a hand-held or imperfectly rectified
    plane): the photo is rendered with every normal tilted by one rotation, uniform up to this
    angle about a random axis in the plane; the target keeps the material's normals."""

    plain_probability: float = 0.0
    """Chance that a batch is photographed by the plain camera all the same (one ``fov``, plain sRGB,
    none of the phone levers): the network keeps what it does on rendered photos such as the
    shared test set's, while it learns the phones'. 0: the levers as set, for every batch."""

    supersample: int = 1
    """Photograph each material at this many times the size its maps come out at, then
    area-downsample the photo and the maps (the normals averaged and made unit), as ``capture``
    downsamples a 256 px photo to the network's 128 px: relief and highlights finer than a pixel
    then reach the network blurred as they do from a photo. The materials must be made at the
    larger size (``train`` makes them so). 1: photographed at the maps' own size."""

    def __post_init__(self):
        if not isinstance(self.supersample, int) or self.supersample < 1:
            raise ValueError(f"supersample must be a whole number of at least 1, got {self.supersample!r}")
        if self.fov_range is not None:
            low, high = self.fov_range
            if not 0.0 < low <= high < 180.0:
                raise ValueError(f"fov_range must be two angles with 0 < low <= high < 180 deg, got {self.fov_range}")
        for name in ("tone_contrast", "vignetting", "flash_cone", "specular_haze", "haze_spread"):
            low, high = getattr(self, name)
            if not 0.0 <= low <= high:
                raise ValueError(f"{name} must be a range 0 <= low <= high, got {getattr(self, name)}")
        if not 1.0 <= self.highlight_compression[0] <= self.highlight_compression[1]:
            raise ValueError(f"highlight_compression must be a range 1 <= low <= high, got {self.highlight_compression}")
        if self.tone_contrast[1] > 1.0 or self.vignetting[1] >= 1.0 or self.specular_haze[1] > 1.0:
            raise ValueError("tone_contrast and specular_haze must lie in [0, 1] and vignetting in [0, 1)")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError(f"jpeg_quality must be a range within [1, 100], got {self.jpeg_quality}")
        if not 0.0 <= self.tilt_deg < 90.0:
            raise ValueError(f"tilt_deg must lie in [0, 90), got {self.tilt_deg}")
        if not 0.0 <= self.plain_probability <= 1.0:
            raise ValueError(f"plain_probability must lie in [0, 1], got {self.plain_probability}")

    def plain(self) -> SynthesisConfig:
        """This config with every phone lever off (the plain camera)."""
        defaults = SynthesisConfig()
        return dataclasses.replace(self, plain_probability=0.0,
                                   **{name: getattr(defaults, name) for name in PHONE_LEVERS})


#: The fields of ``SynthesisConfig`` that make photos as phones take them, each a lever of its own
#: (off by default: one 45 deg camera, plain sRGB).
PHONE_LEVERS = ("fov_range", "cast_in_diffuse", "tone_contrast", "highlight_compression", "vignetting", "flash_cone",
                "jpeg_quality", "tilt_deg")

#: Photos as phones take them: the levers on (and a wider white-balance error), as the real-photo
#: training and validation use them.
PHONE_PHOTOS = {"fov_range": (20.0, 75.0), "cast_in_diffuse": True, "white_balance_sigma": 0.08,
                "tone_contrast": (0.0, 0.6), "vignetting": (0.0, 0.35), "flash_cone": (0.0, 3.0),
                "jpeg_quality": (70, 95), "tilt_deg": 4.0}


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


@dataclass
class PhoneCamera:
    """How the camera made each photo of a batch (``sample_camera``); one shot's settings serve
    both photos of a material (``repeated``).

    Attributes:
        gains: (B, 3) colour gains (exposure times white balance).
        tone: (B,) strength of the S-shaped tone curve (``SynthesisConfig.tone_contrast``), or None.
        vignetting: (B,) darkening at the corners (``SynthesisConfig.vignetting``), or None.
        jpeg_quality: B JPEG qualities, or None: no JPEG.
        white_point: (B,) white point of the highlight compression
            (``SynthesisConfig.highlight_compression``), or None.
    """

    gains: torch.Tensor
    tone: torch.Tensor | None = None
    vignetting: torch.Tensor | None = None
    jpeg_quality: list[int] | None = None
    white_point: torch.Tensor | None = None

    def repeated(self, times: int) -> PhoneCamera:
        """The settings of ``times`` copies of the batch, one after the other."""
        def repeat(values):
            return None if values is None else values * times if isinstance(values, list) else values.repeat(
                times, *([1] * (values.ndim - 1)))

        return PhoneCamera(repeat(self.gains), repeat(self.tone), repeat(self.vignetting), repeat(self.jpeg_quality),
                           repeat(self.white_point))


def sample_camera(batch: int, generator: torch.Generator, config: SynthesisConfig = SynthesisConfig()) -> PhoneCamera:
    """Draw the camera of each of ``batch`` photos; only the levers ``config`` turns on draw numbers."""
    gains = sample_gains(batch, generator, config)
    tone = vignetting = quality = None
    if config.tone_contrast[1] > 0:
        tone = _uniform(batch, config.tone_contrast, generator)
    if config.vignetting[1] > 0:
        vignetting = _uniform(batch, config.vignetting, generator)
    if config.jpeg_quality is not None:
        low, high = config.jpeg_quality
        quality = torch.randint(low, high + 1, (batch,), generator=generator).tolist()
    white_point = None
    if config.highlight_compression[1] > 1.0:
        white_point = _log_uniform(batch, config.highlight_compression, generator)
    return PhoneCamera(gains, tone, vignetting, quality, white_point)


def simulate_photo(radiance: torch.Tensor, generator: torch.Generator, config: SynthesisConfig = SynthesisConfig(),
                   gains: torch.Tensor | None = None, camera: PhoneCamera | None = None) -> torch.Tensor:
    """A phone photo of linear radiance: vignetting, gain jitter, noise, clipping, the tone curve,
    8-bit sRGB quantisation and JPEG, as ``camera`` says (drawn when None).

    Args:
        radiance: (B, 3, H, W) linear radiance.
        generator: the random generator.
        config: noise and jitter amounts.
        gains: (B, 3) colour gains to use (exposure times white balance), in place of ``camera``'s.
        camera: the camera's settings of each photo (``sample_camera``).

    Returns:
        (B, 3, H, W) linear photo in [0, 1], as decoded with plain sRGB (values of an 8-bit sRGB
        image when quantised).
    """
    batch = radiance.shape[0]
    if camera is None:
        camera = PhoneCamera(gains) if gains is not None else sample_camera(batch, generator, config)
    elif gains is not None:
        camera = dataclasses.replace(camera, gains=gains)
    signal = radiance * camera.gains.view(batch, 3, 1, 1).to(radiance)
    if camera.vignetting is not None:
        signal = signal * vignette(camera.vignetting, *radiance.shape[-2:]).to(radiance)
    shot = _log_uniform(batch, config.shot_noise, generator).view(batch, 1, 1, 1).to(radiance)
    read = _log_uniform(batch, config.read_noise, generator).view(batch, 1, 1, 1).to(radiance)
    noise = torch.randn(signal.shape, generator=generator).to(radiance)
    photo = signal + noise * torch.sqrt(shot * signal.clamp(min=0) + read * read)
    if camera.white_point is not None:
        photo = compress_highlights(photo, camera.white_point.view(batch, 1, 1, 1).to(radiance))
    photo = photo.clamp(0.0, 1.0)
    if not config.quantize and camera.tone is None:
        return photo
    encoded = linear_to_srgb(photo)
    if camera.tone is not None:
        encoded = tone_curve(encoded, camera.tone.view(batch, 1, 1, 1).to(radiance))
    if config.quantize:
        encoded = torch.round(encoded * 255.0) / 255.0
        if camera.jpeg_quality is not None:
            encoded = jpeg_round_trip(encoded, camera.jpeg_quality)
    return srgb_to_linear(encoded)


#: The linear grey level the highlight compression keeps (``compress_highlights``).
COMPRESSION_MID_GREY = 0.18


def compress_highlights(linear: torch.Tensor, white_point: torch.Tensor) -> torch.Tensor:
    """A phone's highlight compression of linear values (``SynthesisConfig.highlight_compression``):
    the extended Reinhard curve y = x (1 + x / W^2) / (1 + x) of x = g * linear, which maps x = W
    to 1, with the gain g that keeps ``COMPRESSION_MID_GREY`` (m) where it was, the root of
    (g m)^2 / W^2 + (1 - m) g m - m = 0; ``white_point`` W broadcasts against ``linear``. W = 1 is
    the identity; negative values (noise) are only scaled by g."""
    mid = COMPRESSION_MID_GREY
    white_squared = white_point * white_point
    scaled_mid = 0.5 * white_squared * (torch.sqrt((1.0 - mid) ** 2 + 4.0 * mid / white_squared) - (1.0 - mid))
    x = linear * (scaled_mid / mid)
    positive = x.clamp(min=0.0)
    return torch.where(x > 0, positive * (1.0 + positive / white_squared) / (1.0 + positive), x)


def tone_curve(encoded: torch.Tensor, strength: torch.Tensor) -> torch.Tensor:
    """A phone's S-shaped tone curve on sRGB-encoded values in [0, 1]: (1 - s) y + s (3 y^2 - 2 y^3),
    which keeps 0, 1/2 and 1, darkens the shadows and brightens the highlights (s in [0, 1])."""
    return (1.0 - strength) * encoded + strength * encoded * encoded * (3.0 - 2.0 * encoded)


def vignette(strength: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B, 1, H, W) the lens's falloff 1 - v (r / r_corner)^2 of each strength v (B,)."""
    points = geometry.pixel_points(height, width)
    radius = (points[0] ** 2 + points[1] ** 2) / 2.0  # (r / r_corner)^2: 1 at the corners
    return 1.0 - strength.view(-1, 1, 1, 1) * radius


def jpeg_round_trip(encoded: torch.Tensor, qualities: list[int]) -> torch.Tensor:
    """8-bit sRGB values (B, 3, H, W) in [0, 1] compressed as JPEG at each photo's quality and decoded."""
    import cv2

    codes = (encoded.detach().cpu() * 255.0).round().clamp(0, 255).to(torch.uint8)
    decoded = []
    for image, quality in zip(codes.permute(0, 2, 3, 1).numpy(), qualities, strict=True):
        ok, data = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        decoded.append(torch.from_numpy(cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1].copy()))
    return (torch.stack(decoded).permute(0, 3, 1, 2).to(encoded) / 255.0)


def sample_gains(batch: int, generator: torch.Generator, config: SynthesisConfig = SynthesisConfig()) -> torch.Tensor:
    """(B, 3) exposure times white-balance gains, log-normal around 1."""
    exposure = torch.randn(batch, 1, generator=generator) * config.exposure_sigma
    balance = torch.randn(batch, 3, generator=generator) * config.white_balance_sigma
    return torch.exp(exposure + balance)


def colour_cast(gains: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gains (B, 3) split into their brightness (B, 3), the geometric mean of the three repeated,
    and their colour cast (B, 3), whose geometric mean is 1: gains = brightness * cast."""
    brightness = torch.exp(torch.log(gains).mean(dim=1, keepdim=True)).expand_as(gains)
    return brightness, gains / brightness


def sample_fov(generator: torch.Generator, config: SynthesisConfig = SynthesisConfig()) -> float:
    """A batch's field of view [deg]: ``config.fov``, or drawn from ``fov_range`` with the camera's
    distance log-uniform (no random number drawn without a range)."""
    if config.fov_range is None:
        return float(config.fov)
    near, far = (math.log(constants.camera_height(angle)) for angle in sorted(config.fov_range, reverse=True))
    height = math.exp(near + (far - near) * torch.rand((), generator=generator).item())
    return math.degrees(2.0 * math.atan(1.0 / height))


def tilt_normals(maps: torch.Tensor, angles: torch.Tensor, azimuths: torch.Tensor) -> torch.Tensor:
    """Maps (B, 10, H, W) with every normal turned by the angle (B,) [rad] about the axis in the
    plane at azimuth (B,) [rad]: the material as seen on a tilted sample."""
    axis_x, axis_y = torch.cos(azimuths), torch.sin(azimuths)
    cos, sin = torch.cos(angles), torch.sin(angles)
    # Rodrigues' rotation about the unit axis (ax, ay, 0).
    rotation = torch.stack([
        torch.stack([cos + axis_x**2 * (1 - cos), axis_x * axis_y * (1 - cos), axis_y * sin], -1),
        torch.stack([axis_x * axis_y * (1 - cos), cos + axis_y**2 * (1 - cos), -axis_x * sin], -1),
        torch.stack([-axis_y * sin, axis_x * sin, cos], -1)], -2).to(maps)
    tilted = maps.clone()
    tilted[:, constants.NORMAL] = torch.einsum("bij,bjhw->bihw", rotation, maps[:, constants.NORMAL])
    return tilted


def with_haze(maps: torch.Tensor, shares: torch.Tensor, spreads: torch.Tensor) -> torch.Tensor:
    """(2B, 10, H, W): ``maps`` (B, 10, H, W) with their specular times 1 - share, then the haze
    alone (no diffuse): the specular times share at the roughness plus spread (clipped at 1). The
    two rendered under one flash and added are the material with a two-lobe specular
    (``SynthesisConfig.specular_haze``): under a flash beside the camera the Fresnel term is the
    specular itself, so the two lobes' F0 add up to the material's."""
    shares, spreads = shares.view(-1, 1, 1, 1), spreads.view(-1, 1, 1, 1)
    sharp, haze = maps.clone(), maps.clone()
    sharp[:, constants.SPECULAR] = maps[:, constants.SPECULAR] * (1.0 - shares)
    haze[:, constants.DIFFUSE] = 0.0
    haze[:, constants.SPECULAR] = maps[:, constants.SPECULAR] * shares
    haze[:, constants.ROUGHNESS] = (maps[:, constants.ROUGHNESS] + spreads).clamp(max=1.0)
    return torch.cat([sharp, haze])


def flash_cone_falloff(lights: torch.Tensor, exponents: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B, 1, H, W) the flash's angular falloff cos^k of the angle between its axis (straight down)
    and each pixel's point, for flashes at ``lights`` (B, 3) and exponents k (B,)."""
    points = geometry.pixel_points(height, width, dtype=lights.dtype, device=lights.device)[None]
    towards = points - lights.view(-1, 3, 1, 1)
    cosine = -towards[:, 2:3] / torch.linalg.vector_norm(towards, dim=1, keepdim=True)
    return cosine.clamp(min=1e-6) ** exponents.view(-1, 1, 1, 1).to(lights)


def _uniform(batch: int, bounds: tuple[float, float], generator: torch.Generator) -> torch.Tensor:
    return bounds[0] + (bounds[1] - bounds[0]) * torch.rand(batch, generator=generator)


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
        fov: the field of view the photos were taken with [deg] (``SynthesisConfig.fov_range``).
        plain: whether ``SynthesisConfig.plain_probability`` drew the plain camera for this batch.
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
    fov: float = constants.DEFAULT_FOV_DEG
    plain: bool = False
    extras: dict = field(default_factory=dict)


def synthesize(maps: torch.Tensor, generator: torch.Generator,
               config: SynthesisConfig = SynthesisConfig(), extra_inputs: tuple[str, ...] = ()) -> TrainingBatch:
    """Render and photograph a batch of materials and their variations (one renderer call).

    M and M + xi share the flash position and the camera's settings (one camera, one shot each)
    but not the noise. ``extra_inputs``: the network's optional input channels. With
    ``config.supersample`` F the maps are F times the batch's size: photos, maps and variations
    come out area-downsampled by F. With ``cast_in_diffuse`` the target maps (``maps``) carry the
    white balance's colour cast in their diffuse.
    """
    from ..render import render_flash

    batch, factor = maps.shape[0], config.supersample
    if maps.shape[-2] % factor or maps.shape[-1] % factor:
        raise ValueError(f"maps of {maps.shape[-2]}x{maps.shape[-1]} cannot be supersampled by {factor}")
    plain = config.plain_probability > 0 and torch.rand((), generator=generator).item() < config.plain_probability
    if plain:
        config = config.plain()
    fov = sample_fov(generator, config)
    variation = sample_variation(batch, generator, config.max_rotation, config.max_shift)
    offsets = sample_offsets(batch, generator, fov, config.max_offset_deg, config.offset_sigma_divisor)
    # Random numbers come from the (CPU) generator; the renders run where the maps are.
    lights = geometry.light_positions(offsets, fov).to(maps.device)
    both_lights = torch.cat([lights, lights])
    camera = cast = None
    if config.cast_in_diffuse:  # the target itself depends on the camera: drawn before the renders
        camera = sample_camera(batch, generator, config)
        brightness, cast = colour_cast(camera.gains)
        camera.gains = brightness
        maps = maps.clone()
        maps[:, constants.DIFFUSE] = (maps[:, constants.DIFFUSE] * cast.view(batch, 3, 1, 1).to(maps)).clamp(0.0, 1.0)
    varied = variation.apply(maps)
    seen = torch.cat([maps, varied])
    if cast is not None:  # under a co-located flash the Fresnel term is F0: the cast scales it exactly
        seen = seen.clone()
        seen[:, constants.SPECULAR] = seen[:, constants.SPECULAR] * torch.cat([cast, cast]).view(2 * batch, 3, 1, 1).to(maps)
    if config.tilt_deg > 0:
        angles = torch.deg2rad(_uniform(batch, (0.0, config.tilt_deg), generator))
        azimuths = _uniform(batch, (0.0, 2.0 * math.pi), generator)
        seen = tilt_normals(seen, torch.cat([angles, angles]), torch.cat([azimuths, azimuths]))
    hazy = config.specular_haze[1] > 0
    if hazy:
        shares, spreads = _uniform(batch, config.specular_haze, generator), _uniform(batch, config.haze_spread, generator)
        seen = with_haze(seen, torch.cat([shares, shares]).to(maps), torch.cat([spreads, spreads]).to(maps))
    lights_seen = torch.cat([both_lights, both_lights]) if hazy else both_lights
    with torch.no_grad():
        radiance = render_flash(seen, lights_seen.view(-1, 1, 3), fov=fov, convention=config.convention)[:, 0]
    if hazy:  # the haze's lobes, rendered after the materials
        radiance = radiance[:2 * batch] + radiance[2 * batch:]
    if config.flash_cone[1] > 0:
        exponents = _uniform(batch, config.flash_cone, generator)
        radiance = radiance * flash_cone_falloff(both_lights, torch.cat([exponents, exponents]).to(maps),
                                                 *radiance.shape[-2:])
    if camera is None:
        camera = sample_camera(batch, generator, config)
    photos = simulate_photo(radiance, generator, config, camera=camera.repeated(2))
    if factor > 1:  # as capture makes a photo smaller: area averages, the normals made unit again
        from ..resampling import downsample, downsample_maps

        size = (maps.shape[-2] // factor, maps.shape[-1] // factor)
        photos, maps, varied = downsample(photos, size), downsample_maps(maps, size), downsample_maps(varied, size)
    inputs = encode_inputs(photos, both_lights, fov, config.convention, extra_inputs=extra_inputs)
    return TrainingBatch(maps=maps, varied_maps=varied, variation=variation, offsets=offsets, lights=lights,
                         inputs=inputs[:batch], varied_inputs=inputs[batch:], photos=photos[:batch],
                         varied_photos=photos[batch:], fov=fov, plain=plain)
