"""Detail above the network's resolution, from the photo (``CaptureConfig.detail``).

The network sees the photo at its own resolution (128 px for the shipped model) and its blending
weights and deviations are upsampled to the working resolution: a 2048 px map holds the detail
of a 128 px one. Here each map gets the photo's finer detail in proportion to how its own
variation follows the photo's just below the network's resolution:

1. At the network's resolution, the photo's contrast band ``(I - blur(I)) / blur(I)`` and each
   map's band ``m - blur(m)`` (Gaussian blur of ``LOW_SIGMA`` network pixels) give, in windows of
   ``WINDOW`` network pixels around each pixel, the least-squares slope ``a`` of the map's band on
   the photo's (a guided filter's gain, regularised by ``EPS``, then averaged over the window).
2. At the working resolution, the photo's contrast above the network's band, ``(I - L(I)) / L(I)``
   with ``L`` the photo area-averaged to the network's size and upsampled, times the upsampled
   gain, is added to the map.

The diffuse channels follow the photo's channel of their colour, the normal and roughness its
luminance; the specular is left as it is (``GAIN_OF_CHANNEL``).
Where the network's map does not follow the photo (a flat normal map on veined marble, a constant
roughness) the gain is about zero and nothing is added: relief comes only where the network read
the photo's shading as relief. The network's answer below its resolution is kept: what is added
is the photo's band above it. Normals are renormalised, the other maps clipped to [0, 1].
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .. import constants
from ..geometry import unit_vectors
from ..resampling import downsample, exact_in_bands, gaussian_blur, upsample_bilinear, upsampled_rows

#: Radius of the windows the gains are fitted in, and averaged over [network pixels].
WINDOW = 2

#: Regularisation of the gains [contrast^2]: photo contrast of a few percent or less (noise, JPEG)
#: carries little gain.
EPS = 1e-3

#: Blur that separates the band just below the network's resolution, where the gains are fitted
#: [network pixels].
LOW_SIGMA = 1.0

#: Darkest photo level a contrast is taken against [linear].
DARKEST = 1e-3

#: For each of the ten map channels, the guide it follows: 0 - 2 the photo's red, green and blue,
#: 3 its luminance (the mean of the three).
GUIDE_OF_CHANNEL = (3, 3, 3, 0, 1, 2, 3, 3, 3, 3)

#: Scale of each map channel's gain: the specular gets none. There the photo's fine contrast is
#: the highlight's noise and glints: on held-out procedural materials (``benchmarks/detail.py``) it
#: gave the specular 22 times the truth's fine energy and a larger error.
GAIN_OF_CHANNEL = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0)

#: How the diffuse channels' gains are set: ``"fitted"``, the slope of their band on the photo's, as
#: every map's; ``"albedo"``, the diffuse's own local value times the correlation of the two bands
#: (in [0, 1]): what a pure albedo texture under smooth shading needs, whatever the network's own blur
#: at its finest band. On held-out procedural materials (``benchmarks/detail.py --diffuse-gain``)
#: "albedo" gives flat textured materials the right fine energy but puts relief's shading into the
#: diffuse, so "fitted" is the default.
DIFFUSE_GAIN = "fitted"

#: Output pixels per band of rows at the working resolution (the memory of one band's buffers).
BAND_PIXELS = 1 << 20

#: Side of the windows the normal unit runs in at the working resolution (``fine_slope``) [pixels]:
#: about the size it was trained at, as its channel attention pools over its whole input.
FINE_TILE = 1024

#: Context on each side of a window, cut away from its slope [pixels].
FINE_MARGIN = 32

#: Largest side the flash falloff is rendered at for ``fine_slope``, then interpolated (it holds no
#: fine detail) [pixels].
FALLOFF_SIZE = 256


def _guides(photo: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B, 4, H, W): red, green, blue and luminance."""
    return torch.cat([photo, photo.mean(dim=1, keepdim=True)], dim=1)


def _box(image: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over (2 radius + 1)^2 windows, the edges replicated."""
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    return F.avg_pool2d(padded, 2 * radius + 1, stride=1)


def detail_gains(low_maps: torch.Tensor, low_photo: torch.Tensor, window: int = WINDOW, eps: float = EPS,
                 sigma: float = LOW_SIGMA, diffuse_gain: str | None = None) -> torch.Tensor:
    """The gains of each map channel on the photo's contrast at the network's resolution.

    Args:
        low_maps: (B, 10, h, w) the network's maps; low_photo: (B, 3, h, w) linear.
        diffuse_gain: ``DIFFUSE_GAIN``'s choices; None: ``DIFFUSE_GAIN``.

    Returns:
        (B, 10, h, w) gains [map units per unit of contrast], ``GAIN_OF_CHANNEL`` applied.
    """
    guides = _guides(low_photo.float())
    base = gaussian_blur(guides, sigma, padding="replicate")
    contrast = ((guides - base) / base.clamp(min=DARKEST))[:, list(GUIDE_OF_CHANNEL)]
    band = low_maps.float() - gaussian_blur(low_maps.float(), sigma, padding="replicate")
    mean_guide, mean_band = _box(contrast, window), _box(band, window)
    covariance = _box(contrast * band, window) - mean_guide * mean_band
    variance = (_box(contrast * contrast, window) - mean_guide**2).clamp(min=0.0)
    strength = torch.tensor(GAIN_OF_CHANNEL, dtype=torch.float32).view(1, -1, 1, 1)
    gains = _box(covariance / (variance + eps), window)
    diffuse_gain = DIFFUSE_GAIN if diffuse_gain is None else diffuse_gain
    if diffuse_gain == "albedo":
        band_variance = (_box(band * band, window) - mean_band**2).clamp(min=0.0)
        correlation = (covariance / (variance * band_variance).sqrt().clamp(min=1e-8)).clamp(0.0, 1.0)
        smooth = low_maps.float() - band
        gains[:, constants.DIFFUSE] = _box(correlation * smooth, window)[:, constants.DIFFUSE]
    elif diffuse_gain != "fitted":
        raise ValueError(f"diffuse_gain: {diffuse_gain!r} is neither 'fitted' nor 'albedo'")
    return gains * strength


def add_detail(maps: torch.Tensor, photo: torch.Tensor, low_maps: torch.Tensor, normals: bool = True) -> torch.Tensor:
    """``maps`` with the photo's detail above the resolution of ``low_maps`` (module docstring);
    ``normals`` False leaves the normals to ``fine_slope``: both on, the photo's fine contrast
    would be read as relief twice.

    Args:
        maps: (B, 10, H, W) the maps at the working resolution (changed in place and returned).
        photo: (B, 3, H, W) linear, the photo they were captured from.
        low_maps: (B, 10, h, w) the network's maps at its own resolution (h < H).

    Returns:
        (B, 10, H, W).
    """
    height, width = maps.shape[-2:]
    low_size = tuple(low_maps.shape[-2:])
    if low_size[0] >= height:
        return maps
    with torch.no_grad():
        low_photo = downsample(photo.float(), low_size)
        gains = detail_gains(low_maps, low_photo)
        if not normals:
            gains[:, constants.NORMAL] = 0.0
        low_guides = _guides(low_photo)
        factor = height // low_size[0]
        banded = (exact_in_bands(low_size[0], height) and low_size[1] * factor == width)
        rows = max(factor, BAND_PIXELS // width // factor * factor) if banded else height

        def up(value: torch.Tensor, start: int, stop: int) -> torch.Tensor:
            return (upsampled_rows(value, height, width, start, stop) if banded
                    else upsample_bilinear(value, height, width)[..., start:stop, :])

        # The detail, and what it holds below the network's resolution, which is taken out again:
        # the network's answer there stays as it is.
        below = maps.new_empty(maps.shape[0], maps.shape[1], *low_size)
        for start in range(0, height, rows):
            stop = min(height, start + rows)
            smooth = up(low_guides, start, stop)
            contrast = (_guides(photo[..., start:stop, :].float()) - smooth) / smooth.clamp(min=DARKEST)
            added = up(gains, start, stop) * contrast[:, list(GUIDE_OF_CHANNEL)]
            maps[..., start:stop, :] += added
            below[..., start // factor:-(-stop // factor), :] = downsample(
                added, (-(-stop // factor) - start // factor, low_size[1]))
        for start in range(0, height, rows):
            stop = min(height, start + rows)
            band = maps[..., start:stop, :]
            band -= up(below, start, stop)
            band[:, constants.NORMAL] = unit_vectors(torch.cat([band[:, 0:2], band[:, 2:3].clamp(min=1e-3)], dim=1),
                                                     dim=1)
            band[:, constants.REFLECTANCE] = band[:, constants.REFLECTANCE].clamp(0.0, 1.0)
    return maps


def fine_slope(model, photo: torch.Tensor, lights: torch.Tensor, fov: float, low_size: tuple[int, int],
               tile: int = FINE_TILE, margin: int = FINE_MARGIN) -> torch.Tensor:
    """The normal unit's slope at the photo's own resolution, above the network's: relief finer than
    the network sees, read from the photo's shading by the unit that reads it at the network's
    resolution (``DeepBasisNet.normal_unit``; ``CaptureConfig.fine_normals``).

    The unit runs on windows of ``tile`` pixels with ``margin`` pixels of context, so its memory
    does not grow with the photo and each window is about the size the unit was trained on. Its
    inputs (``model.inputs.relief_inputs``) are made for each window from the whole photo's
    geometry: the flash falloff (rendered at ``FALLOFF_SIZE`` and interpolated), the plane points,
    and the high-pass blur of the unit's own pixels. What the slope holds below ``low_size`` is
    taken out: there the network's answer stays.

    Args:
        model: a ``DeepBasisNet`` with a normal unit.
        photo: (B, 3, H, W) linear; lights: (B, 3) flash positions [patch half-widths]; fov [deg].
        low_size: the network's (h, w), h < H.

    Returns:
        (B, 2, H, W) the x and y slope to add to unit normals (then renormalised).
    """
    from ..geometry import pixel_points
    from ..model.inputs import flash_falloff, relief_inputs

    batch, _, height, width = photo.shape
    convention, extent = model.config.convention, model.config.plane_extent
    lights = lights.view(batch, 3).float()
    coarse = flash_falloff(lights, min(height, FALLOFF_SIZE), min(width, FALLOFF_SIZE), fov, convention, extent)
    sigma = max(0.5, (model.info.training_size or low_size[1]) / 64.0)
    slope = torch.empty(batch, 2, height, width)
    with torch.no_grad():
        for top in range(0, height, tile):
            for left in range(0, width, tile):
                rows = range(max(0, top - margin), min(height, top + tile + margin))
                cols = range(max(0, left - margin), min(width, left + tile + margin))
                points = pixel_points(height, width, rows=rows, cols=cols)[None]
                # grid_sample's y runs down the image, the plane's up.
                grid = torch.stack([points[0, 0], -points[0, 1]], dim=-1)[None].expand(batch, -1, -1, -1)
                falloff = F.grid_sample(coarse, grid, mode="bilinear", padding_mode="border", align_corners=False)
                window = photo[..., rows.start:rows.stop, cols.start:cols.stop].float()
                relief = relief_inputs(window, lights, fov, convention, extent, falloff=falloff,
                                       points=points * extent, highpass_sigma=sigma)
                answer = torch.tanh(model.normal_unit(relief))
                inner_top, inner_left = top - rows.start, left - cols.start
                bottom, right = min(height, top + tile), min(width, left + tile)
                slope[..., top:bottom, left:right] = answer[..., inner_top:inner_top + bottom - top,
                                                            inner_left:inner_left + right - left]
    slope -= upsample_bilinear(downsample(slope, low_size), height, width)
    return slope


def add_fine_slope(maps: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """``maps`` (B, 10, H, W) with ``slope`` (B, 2, H, W) added to their normals' x and y, which are
    then renormalised (changed in place and returned)."""
    normals = maps[:, constants.NORMAL]
    normals[:, 0:2] += slope
    maps[:, constants.NORMAL] = unit_vectors(normals, dim=1)
    return maps

