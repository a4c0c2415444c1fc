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
   gain, is added to the map. With ``add_detail``'s ``denoise`` (``CaptureConfig.denoise_detail``)
   that contrast is denoised first (``denoise_contrast``: the photo's noise, measured from the
   photo itself by level with ``photo_noise``, is taken out of its finest octave): a noisy photo's
   noise otherwise goes into the diffuse as speckle.

The diffuse channels follow the photo's channel of their colour, the normal and roughness its
luminance; the specular is left as it is (``GAIN_OF_CHANNEL``).
Where the network's map does not follow the photo (a flat normal map on veined marble, a constant
roughness) the gain is about zero and nothing is added: relief comes only where the network read
the photo's shading as relief. The network's answer below its resolution is kept: what is added
is the photo's band above it. Normals are renormalised, the other maps clipped to [0, 1].

With ``add_detail``'s ``colour_test`` (``CaptureConfig.colour_test``) the normals follow the photo's
luminance contrast less the part that a change of hue explains (``shading_contrast``): shading
changes a pixel's chroma only along its own colour's, and the edges of a printed or inlaid colour
texture would otherwise tilt the normals.

The network can read an albedo's fine texture as relief all the same. So the normals' gains are
scaled by how much of the photo's fine contrast is shading at all (``relief_share``, a test that
needs no network: shading's gradients turn with the direction to the flash, an albedo's do not;
``relief_gain``): a veined marble or a grained wood gets no relief from its texture.
Where that test reads the fine contrast as albedo, the diffuse takes it as albedo: on a flat
surface the photo's relative contrast is the albedo's, so the diffuse's gains move, by the share
read as albedo (``albedo_share``), from the fitted ones toward the network's diffuse itself. And
the network's own normals, where they follow that contrast just below its resolution, hold relief
made up from the albedo: that share of their band, as the fitted gains explain it, is taken out.

With ``CaptureConfig.fine_relief`` (on by default) the normals' detail is read another way
(``fine_relief``): the network's normal unit, which reads relief from a flash photo's shading, run
once more on the photo itself (at up to ``FINE_RELIEF_SIZE``) and on its mirror images, its slope
above the network's band averaged over them and weighted by where they agree (``mirror_agreement``:
a relief's reading mirrors with the photo, the unit's misreadings of glints and grain do not) and by
each pixel's diffuse share (glints are the specular's, not relief) and by the relief test's gain,
times ``FINE_RELIEF_STRENGTH``, put in place of the photo's contrast times the normals' gains.
Where the unit reads steep relief (``steep_share``) neither weight applies: the test reads steep
relief as albedo (a relief's shading follows its own slope where that is steeper than the
light's tilt), and grain and glints read as shallow relief. A metal has no diffuse shading for
the unit to read: by each network pixel's metallic share (as the exports split the maps) the
normals keep the gains' detail, the reading of the specular's shading.

Fine normals, read either way, spread the specular lobe, and the refinement fitted the lobe to the
photo without them: with ``add_detail``'s ``keep_lobe_peak`` (``CaptureConfig.keep_lobe_peak``)
the roughness is narrowed under the normals' detail so that each network pixel's mean specular
peak stays as it was (``lobe_peak_factors``), and the highlights under other lights keep their
brightness.
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import TYPE_CHECKING, Callable

import torch
import torch.nn.functional as F

from .. import constants
from ..geometry import pixel_points, unit_vectors
from ..material import metallic_share
from ..resampling import downsample, exact_in_bands, gaussian_blur, upsample_bilinear, upsampled_rows

if TYPE_CHECKING:
    from ..model.network import DeepBasisNet

#: Radius of the windows the gains are fitted in, and averaged over [network pixels].
WINDOW = 2

#: Regularisation of the gains [contrast^2]: photo contrast of a few percent or less (noise, JPEG)
#: carries little gain.
EPS = 1e-3

#: Blur that separates the band just below the network's resolution, where the gains are fitted
#: [network pixels]. On held-out procedural materials (``benchmarks/detail.py``) 2 gave the diffuse
#: more of the truth's fine energy than 1 (relief 0.550 against 0.520, flat textured 0.407 against
#: 0.294) and lower re-rendering errors; 3 and 4 little more, the relief's diffuse error rising.
LOW_SIGMA = 2.0

#: Darkest photo level a contrast is taken against [linear].
DARKEST = 1e-3

#: For each of the ten map channels, the guide it follows: 0 - 2 the photo's red, green and blue,
#: 3 its luminance (the mean of the three).
GUIDE_OF_CHANNEL = (3, 3, 3, 0, 1, 2, 3, 3, 3, 3)

#: Scale of the diffuse's gains. The gains are fitted against the network's band, and that is
#: weaker than the truth's: on held-out procedural materials the shipped network's diffuse band at
#: its resolution has a slope of about 0.6 on the truth's (``benchmarks/detail.py`` prints it per
#: group), so the least-squares gain under-reads the photo's albedo contrast. There, at 1024 px, at
#: scales 1 / 1.15 / 1.25 / 1.5: flat textured diffuse RMSE 0.0415 / 0.0410 / 0.0408 / 0.0407, fine
#: energy 0.41 / 0.53 / 0.62 / 0.87 of the truth's; relief diffuse RMSE 0.0650 / 0.0657 / 0.0663 /
#: 0.0683 (upsampled: 0.0690), fine energy 0.55 / 0.70 / 0.81 / 1.10, re-rendering 0.0809 / 0.0797 /
#: 0.0791 / 0.0782 (every figure with the relief test off). 1.25 gives both groups the truth's fine
#: energy within 0.6 - 1.3, each diffuse below the upsampled one. With the test on, the share of the
#: contrast it reads as albedo takes the network's diffuse as its gain instead (``albedo_share``).
DIFFUSE_GAIN = 1.25

#: Scale of each map channel's gain: the specular gets none. There the photo's fine contrast is
#: the highlight's noise and glints: on held-out procedural materials (``benchmarks/detail.py``) it
#: gave the specular 22 times the truth's fine energy and a larger error.
GAIN_OF_CHANNEL = (1.0, 1.0, 1.0, DIFFUSE_GAIN, DIFFUSE_GAIN, DIFFUSE_GAIN, 1.0, 0.0, 0.0, 0.0)

#: Output pixels per band of rows at the working resolution (the memory of one band's buffers).
BAND_PIXELS = 1 << 20

#: Blur that separates the photo's finest octave, where ``denoise_contrast`` takes the noise out
#: [working pixels]: it holds three quarters of white noise's variance. Denoising the next two
#: octaves as well (blurs of 2 and 4 pixels) took out no more on a noisy fine texture.
DENOISE_SIGMA = 1.0

#: Radius of the windows the finest octave is denoised in [working pixels].
DENOISE_RADIUS = 2

#: The rows a band of ``add_detail`` reads beyond its own for ``denoise_contrast``: the blur's taps
#: and the window.
DENOISE_HALO = 3 * int(DENOISE_SIGMA) + DENOISE_RADIUS

#: Bins of the photo's level (log-spaced from ``DARKEST`` to 1) its noise is measured in
#: (``photo_noise``), and the fewest patches a bin needs to be measured.
NOISE_BINS = 16
NOISE_MIN_PATCHES = 1000

#: Side of the patches ``photo_noise`` measures the noise on, and their least spacing [working pixels].
NOISE_PATCH = 7
NOISE_STRIDE = 2

#: About the most patches ``photo_noise`` measures: a larger photo's are spaced further apart.
NOISE_SAMPLES = 1 << 16


#: Radius of the windows ``shading_contrast`` fits the luminance's slope on the hue's change in
#: [working pixels].
HUE_RADIUS = 3

#: Regularisation of that slope [contrast^2]: a hue change of about a percent or less (noise, JPEG)
#: takes little out.
HUE_EPS = 1e-4

#: Saturation of a pixel's colour [chroma over luminance] below which ``shading_contrast`` counts it
#: as grey: there shading changes no hue, and both of the chroma's directions are the albedo's. It is
#: kept far below a metal's tint (silver's is about 0.04): shading changes a tinted pixel's chroma
#: along its tint, and a larger one would leave part of that in the albedo's directions.
GREY_CHROMA = 2e-3

#: ``relief_share`` at and below which the photo's fine contrast reads as albedo alone, and at
#: and above which as relief enough for the normals' whole detail (``relief_gain``). On procedural
#: materials of training seeds at 1024 px (not the benchmark's), flat textured stone and wood read
#: -0.10 to +0.07 (oriented grain and veins), most relief 0.14 - 0.80.
RELIEF_SHARE = (0.10, 0.25)

#: Largest side the relief's share is measured at [pixels]: a larger photo is area-averaged to it
#: first (the shading's direction shows at every scale above the network's band).
RELIEF_SIZE = 1024


def relief_share(photo: torch.Tensor, light: torch.Tensor, low_size: tuple[int, int], extent: float = 1.0,
                 matte: torch.Tensor | None = None, max_size: int = RELIEF_SIZE) -> float:
    """How much of the photo's fine contrast is shading: the part of its gradients' direction
    that turns with the direction to the flash.

    To first order a matte surface's shading above the network's band is ``t . dn``, ``dn`` the
    relief's normals there and ``t = l_xy / l_z`` the light's tilt at the pixel. For an isotropic
    relief the contrast's gradient tensor ``g g^T`` is then, in expectation,
    ``s |t|^2 (I / 2 + (u u^T - I / 2) / 2)``, ``u`` the unit tilt: its anisotropic part points
    along the light, which turns around the flash's foot point across the photo. An albedo's
    texture, veined or grained, has a direction of its own that does not turn with the light. So
    the gradient tensors are fitted, by least squares over the pixels, as a constant
    tensor (the albedo) plus ``k |t|^2 (u u^T - I / 2)`` (the shading), and the share is
    ``2 k mean(|t|^2) / mean(trace)``: about 0 for albedo alone, 1 for relief alone. ``matte``
    weighs the pixels by the diffuse's share of the photo: a specular highlight falls off along
    the light too.

    Args:
        photo: (3, H, W) or (1, 3, H, W) linear; light: (3,) the flash [patch half-widths];
        low_size: the network's (h, w), whose band is taken out; matte: (h', w') in [0, 1], at
            any size (upsampled); None: 1.

    Returns:
        the share (not clipped: noise reads a little below 0 or above 1).
    """
    photo = photo.reshape(-1, *photo.shape[-3:])[:1].float()
    height, width = photo.shape[-2:]
    scale = max(1, -(-max(height, width) // max_size))
    if scale > 1:
        photo = downsample(photo, (height // scale, width // scale))
        height, width = photo.shape[-2:]
    luminance = photo.mean(dim=1, keepdim=True)
    smooth = upsample_bilinear(downsample(luminance, low_size), height, width)
    contrast = ((luminance - smooth) / smooth.clamp(min=DARKEST))[0, 0]
    along_x = (contrast[1:-1, 2:] - contrast[1:-1, :-2]) / 2
    along_y = (contrast[:-2, 1:-1] - contrast[2:, 1:-1]) / 2  # rows run down, y up
    tensor = torch.stack([along_x**2, along_x * along_y, along_y**2])
    points = pixel_points(height, width)[:, 1:-1, 1:-1] * extent
    towards = light.float().view(3, 1, 1) - points
    tilt = towards[:2] / towards[2:3].clamp(min=1e-6)
    strength = (tilt**2).sum(dim=0)
    unit = tilt / strength.sqrt().clamp(min=1e-9)
    shading = torch.stack([strength * (unit[0]**2 - 0.5), strength * unit[0] * unit[1], strength * (unit[1]**2 - 0.5)])
    weights = (torch.ones_like(strength) if matte is None
               else upsample_bilinear(matte.float()[None, None], height, width)[0, 0, 1:-1, 1:-1].clamp(min=0.0))
    weights = (weights / weights.sum().clamp(min=1e-12)).double()
    # Weighted least squares of the tensors on a constant plus k times the shading's: the constant
    # is each component's weighted mean less k times the shading's, and k the ratio of the centred
    # products' sums; the off-diagonal component counts twice (a tensor's norm).
    component_weight = torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64).view(3, 1, 1)
    centred_tensor = tensor.double() - (tensor.double() * weights).sum(dim=(1, 2), keepdim=True)
    centred_shading = shading.double() - (shading.double() * weights).sum(dim=(1, 2), keepdim=True)
    k = float((component_weight * weights * centred_tensor * centred_shading).sum()
              / (component_weight * weights * centred_shading**2).sum().clamp(min=1e-30))
    mean_trace = float(((tensor[0] + tensor[2]).double() * weights).sum())
    mean_strength = float((strength.double() * weights).sum())
    return 2.0 * k * mean_strength / max(mean_trace, 1e-30)


def relief_gain(share: float) -> float:
    """The share of the normals' detail to keep, from ``relief_share``: 0 at and below
    ``RELIEF_SHARE[0]``, 1 at and above ``RELIEF_SHARE[1]``, linear between."""
    low, high = RELIEF_SHARE
    return min(1.0, max(0.0, (share - low) / (high - low)))


def matte_share(maps: torch.Tensor, light: torch.Tensor, fov: float, convention: str,
                extent: float = 1.0) -> torch.Tensor:
    """(h, w) the diffuse's share of the luminance of ``maps`` (1, 10, h, w) rendered under the
    flash at ``light`` (3,), in [0, 1]."""
    from ..render import render_flash

    lights = light.float().view(1, 1, 3)
    whole = render_flash(maps.float(), lights, fov=fov, convention=convention, extent=extent)[0, 0].mean(dim=0)
    matte_maps = maps.float().clone()
    matte_maps[:, constants.SPECULAR] = 0.0
    diffuse = render_flash(matte_maps, lights, fov=fov, convention=convention, extent=extent)[0, 0].mean(dim=0)
    return (diffuse / whole.clamp(min=1e-6)).clamp(0.0, 1.0)


#: Least ratio of the photo's side to the network's at which ``photo_relief_gain`` reads the relief's
#: share (two octaves above the network's band); below it the normals keep their whole detail. One
#: octave reads too noisily: on procedural materials of training seeds at 256 px (a 128 px network)
#: a flat oiled plank read 0.114 (0.032 at 1024 px) and a relief plastic 0.64 (-0.09).
RELIEF_MIN_FACTOR = 4

#: Power of the diffuse's share that weighs the pixels of ``relief_share`` in ``photo_relief_gain``:
#: a pixel counts fully only where the highlight hardly reaches.
MATTE_POWER = 4


def relief_test_reads(photo_size: tuple[int, int], low_size: tuple[int, int]) -> bool:
    """Whether ``photo_relief_gain`` reads a photo of ``photo_size`` (H, W) against maps of
    ``low_size`` (h, w): from ``RELIEF_MIN_FACTOR`` times their size on."""
    return min(photo_size[0] / low_size[0], photo_size[1] / low_size[1]) >= RELIEF_MIN_FACTOR


def photo_relief_gain(photo: torch.Tensor, light: torch.Tensor, low_maps: torch.Tensor, fov: float, convention: str,
                      extent: float = 1.0, matte: torch.Tensor | None = None) -> float:
    """``relief_gain`` of a photo (3, H, W) taken with the flash at ``light`` (3,), the diffuse's
    share of it from the network's maps ``low_maps`` (1, 10, h, w) (``matte_share``, or ``matte``
    (h, w) where given); 1 for a photo the test does not read (``relief_test_reads``)."""
    if not relief_test_reads(tuple(photo.shape[-2:]), tuple(low_maps.shape[-2:])):
        return 1.0
    if matte is None:
        matte = matte_share(low_maps[:1].detach().cpu(), light.cpu(), fov, convention, extent)
    share = relief_share(photo.cpu(), light.cpu(), tuple(low_maps.shape[-2:]), extent, matte=matte**MATTE_POWER)
    return relief_gain(share)


#: Largest side the normal unit reads the fine relief at (``fine_relief``) [pixels]: a larger photo
#: is area-averaged to it first. The unit, trained at 128 px, reads a 1024 px photo's relief as it
#: reads a 128 px one's: on held-out procedural relief at 1024 px (``benchmarks/detail.py``) its
#: slope above the 128 px band correlates 0.57 with the truth's, 0.48 with each relief under
#: another material's albedo (so it reads the shading, not an albedo that follows the relief;
#: unweighted, a script outside the repository). On the photo area-averaged to 512 px the relief
#: gained nothing over the normals' gains. Its memory and time grow with the side's square (about
#: 2 s and 0.9 GB at 1024 px on two cores).
FINE_RELIEF_SIZE = 1024


#: Power of the diffuse's share (``matte_share``) that weighs the fine relief, pixel by pixel
#: (``fine_relief``'s ``matte``): where the flash's highlight dominates, the photo's fine contrast
#: is mostly glints and the specular's own texture, which the unit reads as bumps. At 1024 px,
#: powers 0 / 1 / 2: card-blue (foil glitter) 0.1671 / 0.1606 / 0.1603 (without the fine relief
#: 0.1609); the calibration set's relief normal RMSE 0.0683 / 0.0690 / 0.0699 (``benchmarks/
#: detail.py --first-seed 500001000 --seed 1``); the benchmark's crumpled foil 0.0139 / 0.0136 /
#: 0.0136 (0.0135), its brushed silver, a metal with no diffuse share, 0.0421 / 0.0458 / 0.0492
#: (0.0452) with the unit's reading alone in its normals; keeping the gains' detail by the
#: metallic share (``add_detail``), 0.0426 at power 1.
FINE_RELIEF_MATTE_POWER = 1.0


#: The factor of the relief the unit reads that capture gives the normals by default
#: (``CaptureConfig.fine_relief_strength``): the reading itself, as its mirror images agree on it
#: (``fine_relief``'s ``symmetries``). Chosen on the calibration set (``benchmarks/detail.py
#: --first-seed 500001000 --seed 1``, every reading weighted, before ``STEEP_RELIEF``): the most
#: that keeps the flat textured materials' made-up relief below the upsampled answer's (their
#: normal RMSE with 2 readings 0.0146 at 1; with 4, 0.0146 at 1 and 0.0155 at 1.5; upsampled
#: 0.0150), where the relief's normal RMSE still falls (0.0692 at 1; with 4 readings 0.0693 at 1,
#: 0.0680 at 1.5).
#: A single reading at 1 gives card-blue's foil relief it does not have (benchmarks/README.md,
#: detail: the fine relief's strength); agreeing mirror images do not.
FINE_RELIEF_STRENGTH = 1.0


def release_freed_heap() -> None:
    """Give the pages of freed heap blocks back to the system (glibc's ``malloc_trim``). The normal
    unit's activations at 1024 px are blocks under glibc's mmap threshold: freed, they stay in its
    heap, and a 4096 px capture's later stages then peak about 100 MiB higher. Elsewhere than
    glibc, nothing."""
    import ctypes

    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (AttributeError, OSError):
        pass


#: How many of the photo's mirror images ``fine_relief`` reads at most (``mirror_images``); capture
#: reads no more than its ``symmetries``. Each is one more run of the unit (about 3 s at 1024 px on
#: two cores). On the calibration set (``benchmarks/detail.py --first-seed 500001000 --seed 1``) the
#: four mirrorings read no better than the photo and its half turn.
FINE_RELIEF_SYMMETRIES = 2


def mirror_images(count: int):
    """The ``count`` symmetries (1, 2 or 4; ``model.symmetry.Symmetry``) ``fine_relief`` reads the
    photo under: the photo itself, then its half turn, then its two mirrorings. Turns by a
    quarter are left out: they would turn the network's size too."""
    from ..model.symmetry import SYMMETRY_SETS, Symmetry

    if count not in (1, 2, 4):
        raise ValueError(f"fine_relief reads 1, 2 or 4 mirror images, got {count!r}")
    half_turn = Symmetry(mirror_columns=True, mirror_rows=True)
    return {1: SYMMETRY_SETS[1], 2: (Symmetry(), half_turn), 4: SYMMETRY_SETS[4]}[count]


#: Radius of the windows ``mirror_agreement`` compares the readings in [reading pixels].
AGREEMENT_RADIUS = 8

#: Power of ``mirror_agreement`` that weighs the mean reading in ``fine_relief``.
AGREEMENT_POWER = 2.0


#: The unit's local RMS slope [slope units, per axis] over which its reading stops being weighted
#: by the relief test's gain and the diffuse's share (``steep_share``): from the first value on it
#: is kept more and more, from the second on whole. The relief test reads a relief's shading by its
#: first-order term, the slope times the light's tilt (``relief_share``); where the slope is
#: steeper than the tilt (an RMS of 0.34 - 0.40 over the detail benchmark's photos), the shading's
#: gradients follow the relief's own slopes and the test reads them as albedo: a steep slate of the
#: detail benchmark, rendered without specular and with one albedo, reads 0.29 relief, its slopes
#: scaled by 0.1 read 0.88 (a script outside the repository). An albedo's grain and the specular's
#: glints read as shallow relief (card-blue's photos: an RMS of 0.035 - 0.051 over each). Chosen on
#: the calibration set (``benchmarks/detail.py --first-seed 500001000 --seed 1``, and with
#: ``--materials 24 --flat 4``) as the fine relief's strength was: the lowest of (0.25, 0.5),
#: (0.2, 0.4) and (0.15, 0.3) that keeps the flat textured materials' normal RMSE below the upsampled
#: answer's in both (12 relief materials: 0.01472, 0.01483, 0.01502 against 0.01498; 24: 0.01457,
#: 0.01485 against 0.0148; the relief's normal RMSE 0.0687 and 0.0727 at (0.25, 0.5), every reading
#: weighted 0.0692 and 0.0756; benchmarks/README.md, detail: steep relief).
STEEP_RELIEF = (0.25, 0.5)

#: Radius of the windows ``steep_share`` measures the reading's RMS slope in [reading pixels].
STEEP_RADIUS = 8


def steep_share(slope: torch.Tensor, steep: tuple[float, float] | None = None,
                radius: int = STEEP_RADIUS) -> torch.Tensor:
    """(B, 1, H, W) in [0, 1], how steep a slope field (B, 2, H, W) is around each pixel: its RMS
    slope per axis in windows of ``2 radius + 1`` pixels, 0 at and below ``steep[0]``
    (``STEEP_RELIEF`` by default), 1 at and above ``steep[1]``, linear between."""
    low, high = STEEP_RELIEF if steep is None else steep
    rms = _box(slope.square().mean(dim=1, keepdim=True), radius).sqrt()
    return ((rms - low) / (high - low)).clamp(0.0, 1.0)


def mirror_agreement(readings: list[torch.Tensor], radius: int = AGREEMENT_RADIUS) -> torch.Tensor:
    """(B, 1, H, W) how far readings (B, 2, H, W) of one slope agree, in windows of ``2 radius + 1``
    pixels: the energy of their mean over their mean energy, 1 where they are the same, ``1 / n``
    for ``n`` unrelated ones of equal energy, 0 where they cancel."""
    mean = sum(readings) / len(readings)
    common = _box(mean.square().sum(dim=1, keepdim=True), radius)
    each = _box(sum(reading.square().sum(dim=1, keepdim=True) for reading in readings) / len(readings), radius)
    return common / each.clamp(min=1e-12)


def symmetric_readings(read: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], photo: torch.Tensor,
                       lights: torch.Tensor, count: int) -> list[torch.Tensor]:
    """``read(photo, lights)``, a slope field (B, 2, H, W), for the photo (B, 3, H, W) and its flash
    (B, 3) moved by each of the ``count`` ``mirror_images``, each reading moved back: a relief's
    slope read from a mirrored photo under the mirrored flash is the mirrored slope. One reading at
    a time (the unit's memory)."""
    return [symmetry.field(read(symmetry.image(photo).contiguous(), symmetry.vectors(lights, dim=1)), inverse=True)
            for symmetry in mirror_images(count)]


def fine_relief(model: DeepBasisNet, photo: torch.Tensor, light: torch.Tensor, fov: float,
                low_size: tuple[int, int], max_size: int = FINE_RELIEF_SIZE,
                matte: torch.Tensor | None = None, strength: float = 1.0, reader=None,
                convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0,
                symmetries: int = 1, gain: float = 1.0) -> torch.Tensor:
    """The relief finer than the network's resolution as its normal unit reads it from the photo.

    The unit (``DeepBasisNet.normal_unit``, its octaves summed as in the network's pass) runs on
    the photo area-averaged to at most ``max_size`` px, a multiple of the sizes its levels halve
    to; what its slope holds at and below ``low_size`` (area average, bilinear back) is taken out:
    there the network's answer stays. With ``symmetries`` above 1 it reads the photo's mirror
    images too (``symmetric_readings``); their mean is weighted by their agreement
    (``mirror_agreement``) to the power ``AGREEMENT_POWER``. The slope is weighted by ``matte`` to
    the power ``FINE_RELIEF_MATTE_POWER`` (the relief is read where the photo shows the diffuse's
    shading) and by ``gain``, the relief test's, but where the mean reading is steep
    (``steep_share``): there by 1. ``strength`` scales it (``CaptureConfig.fine_relief_strength``).

    Args:
        model: a network with a normal unit; photo: (B, 3, H, W) linear; light: (B, 3) or (3,)
            the flash [patch half-widths]; fov: the photo's [deg]; low_size: the network's (h, w);
        matte: (h', w') the diffuse's share of the photo (``matte_share``), at any size; None: 1;
        strength: the slope's factor, 1 the unit's own reading;
        reader: a relief reader (``model.relief_reader``) that reads the slope in the unit's place
            (``read_relief``, at up to ``max_size`` too), under ``convention`` and ``extent``;
        symmetries: 1, 2 or 4 mirror images read (``mirror_images``);
        gain: the relief test's (``photo_relief_gain``), in [0, 1].

    Returns:
        (B, 2, H', W') the x and y slope to add to the normals at the photo's size (bilinear up
        to it), H' and W' at most ``max_size``.
    """
    from ..model.relief_reader import read_relief, read_size

    mirror_images(symmetries)  # checked before any work
    lights = light.float().reshape(-1, 3).expand(photo.shape[0], 3)
    if reader is not None:
        def read(image: torch.Tensor, flashes: torch.Tensor) -> torch.Tensor:
            return read_relief(reader, image, flashes, fov, low_size, max_size, convention, extent)

        seen = photo
    else:
        size = read_size(tuple(photo.shape[-2:]), max_size, model.config.normal_unit_stride)
        seen = photo.float() if size == tuple(photo.shape[-2:]) else downsample(photo.float(), size)
        device = next(model.parameters()).device

        def read(image: torch.Tensor, flashes: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                slope = model.octave_slope(model.relief_inputs(image.to(device), flashes.to(device), fov))
            slope = slope.float().to(photo.device)
            return slope - upsample_bilinear(downsample(slope, low_size), *slope.shape[-2:])

    readings = symmetric_readings(read, seen, lights, symmetries)
    mean = sum(readings) / len(readings)
    slope = mean * mirror_agreement(readings) ** AGREEMENT_POWER if len(readings) > 1 else mean
    del readings
    release_freed_heap()
    weight = float(gain)
    if matte is not None:
        share = matte.float().to(slope.device)[None, None] ** FINE_RELIEF_MATTE_POWER
        weight = weight * upsample_bilinear(share, *slope.shape[-2:])
    steep = steep_share(mean)
    return slope * (weight + (1.0 - weight) * steep) * strength


def _noise_bin(level: torch.Tensor) -> torch.Tensor:
    """The noise bin (``NOISE_BINS``) of each linear level, as a fractional index."""
    position = torch.log(level.clamp(min=DARKEST)) / torch.log(torch.tensor(DARKEST))
    return ((1.0 - position) * (NOISE_BINS - 1)).clamp(0.0, NOISE_BINS - 1)


def photo_noise(photo: torch.Tensor, smooth_rows: Callable[[int, int], torch.Tensor], rows: int) -> torch.Tensor:
    """(B, 4, NOISE_BINS) the noise variance [linear^2] of each guide (``_guides``) of ``photo``
    (B, 3, H, W), by its smooth level (``smooth_rows(start, stop)``: (B, 4, rows, W)).

    In each bin of the level, the least eigenvalue of the covariance of the guide's patches of
    ``NOISE_PATCH`` x ``NOISE_PATCH`` pixels (Liu, Tanaka and Okutomi's estimate): noise adds its
    variance to every direction of the patches' space, where a texture or relief that is smooth at
    the pixel's scale leaves the finest directions nearly empty. The eigenvalue is corrected for the
    sample's own spread (``(1 - sqrt(d / n))^2`` for d dimensions and n patches). Each guide is
    measured apart: a phone's JPEG keeps the luminance's noise and takes out most of the colour's.
    A texture or a relief's shading as fine as the pixels reads as noise too (on noise-free
    procedural photos a speckled granite's about 6 % of its level, a fine leather's 39 %). A bin of
    fewer than ``NOISE_MIN_PATCHES`` patches takes its nearest measured one's, and none measured:
    0. Read band by band of ``rows`` rows, on patches ``NOISE_STRIDE`` pixels apart or more, at
    most about ``NOISE_SAMPLES`` of them.
    """
    batch, _, height, width = photo.shape
    size, centre, dimensions = NOISE_PATCH, NOISE_PATCH // 2, NOISE_PATCH**2
    step = max(NOISE_STRIDE, math.ceil((height * width / NOISE_SAMPLES) ** 0.5))
    patches, bins = [], []
    for start in range(0, height - size + 1, rows):
        stop = min(height - size + 1, start + rows)
        first = start + (-start) % step  # patches start on every step-th row of the photo, whatever the bands
        if first >= stop:
            continue
        guides = _guides(photo[..., first:stop + size - 1, :].float())
        band = F.unfold(guides.reshape(-1, 1, *guides.shape[-2:]), size, stride=step)  # (B 4, d, n)
        patches.append(band.view(batch, 4, dimensions, -1))
        level = smooth_rows(first + centre, stop + centre)[..., ::step, centre:width - size + 1 + centre:step]
        bins.append(_noise_bin(level).round().to(torch.uint8).flatten(2))
    variances = torch.zeros(batch, 4, NOISE_BINS)
    if not patches:
        return variances  # a photo too small to measure: no noise taken out
    patches, bins = torch.cat(patches, dim=3), torch.cat(bins, dim=2)
    for item in range(batch):
        for guide in range(4):
            measured = {}
            order = torch.sort(bins[item, guide], stable=True).indices
            grouped = patches[item, guide][:, order]
            counts = torch.bincount(bins[item, guide].long(), minlength=NOISE_BINS).tolist()
            ends = list(itertools.accumulate(counts))
            for number, (count, end) in enumerate(zip(counts, ends)):
                if count < NOISE_MIN_PATCHES:
                    continue
                chosen = grouped[:, end - count:end]
                centred = chosen - chosen.mean(dim=1, keepdim=True)
                least = float(torch.linalg.eigvalsh((centred @ centred.T).double() / count)[0])
                measured[number] = max(0.0, least) / (1.0 - (dimensions / count) ** 0.5) ** 2
            if not measured:
                continue
            for number in range(NOISE_BINS):
                variances[item, guide, number] = measured[min(measured, key=lambda other: abs(other - number))]
    return variances


def noise_at(variances: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """(B, 4, h, w) the noise variance [linear^2] at each level (B, 4, h, w), linear between the
    bins of ``variances`` (B, 4, NOISE_BINS) (``photo_noise``)."""
    position = _noise_bin(level)
    lower = position.floor().long().clamp(max=NOISE_BINS - 2)
    fraction = position - lower
    table = variances.to(level)[:, :, None, None, :]
    below = torch.take_along_dim(table, lower[..., None], dim=-1)[..., 0]
    above = torch.take_along_dim(table, (lower + 1)[..., None], dim=-1)[..., 0]
    return below + fraction * (above - below)


@functools.cache
def _finest_octave_noise_share() -> float:
    """The share of white noise's variance in the finest octave of ``denoise_contrast``: the sum of
    the squares of its kernel (an impulse less its blur)."""
    size = 2 * 3 * int(DENOISE_SIGMA) + 1
    impulse = torch.zeros(1, 1, size, size, dtype=torch.float64)
    impulse[..., size // 2, size // 2] = 1.0
    return float((impulse - gaussian_blur(impulse, DENOISE_SIGMA, padding="constant")).square().sum())


def denoise_contrast(contrast: torch.Tensor, noise: torch.Tensor, radius: int = DENOISE_RADIUS) -> torch.Tensor:
    """The photo's fine contrast (B, C, h, w) with its noise of variance ``noise`` (B, C, h, w)
    [contrast^2] shrunk.

    The contrast, divided by the noise's standard deviation (white noise of variance 1 then), is
    split by a Gaussian blur of ``DENOISE_SIGMA`` into its finest octave, which holds three quarters
    of white noise's variance and little of a texture smooth at the pixel's scale, and the rest; in
    windows of ``radius``, the finest octave is scaled by the share of its local variance above the
    noise's there (an adaptive Wiener filter). A texture or relief well above the noise keeps its
    contrast, noise alone is mostly taken out.
    """
    deviation = noise.clamp(min=1e-12).sqrt()
    whitened = contrast / deviation
    coarser = gaussian_blur(whitened, DENOISE_SIGMA, padding="replicate")
    finest = whitened - coarser
    share = _finest_octave_noise_share()
    variance = _box(finest * finest, radius)
    return (coarser + (variance - share).clamp(min=0.0) / variance.clamp(min=share) * finest) * deviation


#: Two orthonormal directions across grey in RGB: the chroma's axes.
CHROMA_AXES = ((2.0**-0.5, -(2.0**-0.5), 0.0), (6.0**-0.5, 6.0**-0.5, -2.0 * 6.0**-0.5))


def shading_contrast(contrast: torch.Tensor, smooth: torch.Tensor, radius: int = HUE_RADIUS,
                     eps: float = HUE_EPS) -> torch.Tensor:
    """The photo's fine luminance contrast less the part a change of hue explains: what shading
    can have made.

    Shading changes a pixel's light by the diffuse's colour (its diffuse shading) and by the
    specular's (a dielectric's is grey; a metal has next to no diffuse), so it moves the pixel's
    chroma only along the chroma of its smooth colour, which is a mix of the two. A change of the
    chroma across that, a change of hue, is the albedo's: on a printed or inlaid colour texture its
    edges are the strongest of the photo's fine contrast, and a relief read from them tilts the
    normals where nothing is tilted. In windows of ``radius``, the luminance contrast's
    least-squares slopes on the two chroma components of each pixel's change, less their part along
    its smooth colour's chroma, are fitted (a guided filter's gains, regularised by ``eps``, then
    averaged over the window), and that part is taken out. A change of brightness or saturation
    within one hue is the albedo's as well; that one the relief test weighs (``relief_share``).

    Args:
        contrast: (B, 4, h, w) the guides' contrast ``(I - L(I)) / L(I)`` (red, green, blue,
            luminance; ``_guides``); smooth: (B, 4, h, w) their smooth level ``L(I)`` [linear].

    Returns:
        (B, 1, h, w) the luminance's contrast, the part a change of hue explains taken out.
    """
    luminance = contrast[:, 3:4]
    level = smooth[:, 3:4].clamp(min=DARKEST)
    axes = torch.tensor(CHROMA_AXES, dtype=contrast.dtype, device=contrast.device)
    # The change and the smooth colour, each over the smooth level: their chroma in luminance units.
    change = torch.einsum("kc,bchw->bkhw", axes, contrast[:, :3] * smooth[:, :3]) / level
    tint = torch.einsum("kc,bchw->bkhw", axes, smooth[:, :3]) / level
    along = (change * tint).sum(dim=1, keepdim=True) / ((tint * tint).sum(dim=1, keepdim=True) + GREY_CHROMA**2)
    hue = change - along * tint
    first, second = hue[:, 0:1], hue[:, 1:2]
    # The windows' means of the regressors, the luminance and their products, in one pass.
    means = _box(torch.cat([first, second, luminance, first * first, second * second, first * second,
                            first * luminance, second * luminance], dim=1), radius)
    mean_first, mean_second, mean_luminance = means[:, 0:1], means[:, 1:2], means[:, 2:3]
    var_first = means[:, 3:4] - mean_first**2 + eps
    var_second = means[:, 4:5] - mean_second**2 + eps
    covariance = means[:, 5:6] - mean_first * mean_second
    with_first = means[:, 6:7] - mean_first * mean_luminance
    with_second = means[:, 7:8] - mean_second * mean_luminance
    determinant = (var_first * var_second - covariance**2).clamp(min=1e-20)
    slopes = _box(torch.cat([var_second * with_first - covariance * with_second,
                             var_first * with_second - covariance * with_first], dim=1) / determinant, radius)
    return luminance - slopes[:, 0:1] * first - slopes[:, 1:2] * second


def _guides(photo: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B, 4, H, W): red, green, blue and luminance."""
    return torch.cat([photo, photo.mean(dim=1, keepdim=True)], dim=1)


def _box(image: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over (2 radius + 1)^2 windows, the edges replicated."""
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    return F.avg_pool2d(padded, 2 * radius + 1, stride=1)


def band_contrast(guides: torch.Tensor, sigma: float = LOW_SIGMA) -> torch.Tensor:
    """(B, 4, h, w) the photo's guides (``_guides``) -> (B, 10, h, w): for each map channel, its
    guide's contrast ``(I - blur(I)) / blur(I)`` above a Gaussian blur of ``sigma`` pixels
    (``GUIDE_OF_CHANNEL``)."""
    base = gaussian_blur(guides, sigma, padding="replicate")
    return ((guides - base) / base.clamp(min=DARKEST))[:, list(GUIDE_OF_CHANNEL)]


def detail_gains(low_maps: torch.Tensor, contrast: torch.Tensor, window: int = WINDOW, eps: float = EPS,
                 sigma: float = LOW_SIGMA, albedo_share: float = 0.0) -> torch.Tensor:
    """The gains of each map channel on the photo's contrast at the network's resolution.

    Args:
        low_maps: (B, 10, h, w) the network's maps; contrast: (B, 10, h, w) the photo's at their
            size (``band_contrast`` of the same ``sigma``);
        albedo_share: the share of the photo's fine contrast read as albedo, in [0, 1]: the
            diffuse's gains are ``(1 - albedo_share)`` times the fitted ones plus ``albedo_share``
            times the network's diffuse (an albedo's relative contrast is the photo's).

    Returns:
        (B, 10, h, w) gains [map units per unit of contrast], ``GAIN_OF_CHANNEL`` applied.
    """
    band = low_maps.float() - gaussian_blur(low_maps.float(), sigma, padding="replicate")
    mean_guide, mean_band = _box(contrast, window), _box(band, window)
    covariance = _box(contrast * band, window) - mean_guide * mean_band
    variance = (_box(contrast * contrast, window) - mean_guide**2).clamp(min=0.0)
    strength = torch.tensor(GAIN_OF_CHANNEL, dtype=torch.float32).view(1, -1, 1, 1)
    gains = _box(covariance / (variance + eps), window) * strength
    if albedo_share > 0.0:
        gains[:, constants.DIFFUSE] = ((1.0 - albedo_share) * gains[:, constants.DIFFUSE]
                                       + albedo_share * low_maps.float()[:, constants.DIFFUSE])
    return gains


def metallic_shares(maps: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) the metallic share of maps (B, 10, H, W), as the exports split them
    (``material.metallic_share`` at ``constants.EXPORT_METAL_F0``)."""
    return metallic_share(maps[:, constants.DIFFUSE].float(), maps[:, constants.SPECULAR].float(),
                          constants.EXPORT_METAL_F0)


def add_detail(maps: torch.Tensor, photo: torch.Tensor, low_maps: torch.Tensor,
               normal_gain: float = 1.0, albedo_share: float = 0.0,
               fine_slope: torch.Tensor | None = None, denoise: bool = False, keep_lobe_peak: bool = False,
               slope_scale: float = 1.0, colour_test: bool = False) -> torch.Tensor:
    """``maps`` with the photo's detail above the resolution of ``low_maps`` (module docstring).

    Args:
        maps: (B, 10, H, W) the maps at the working resolution (changed in place and returned).
        photo: (B, 3, H, W) linear, the photo they were captured from.
        low_maps: (B, 10, h, w) the network's maps at its own resolution (h < H).
        normal_gain: the share of the gains' normal detail kept (``relief_gain``): 0 where the
            photo's fine contrast reads as albedo alone. A ``fine_slope`` is added as it is.
        albedo_share: the share of the photo's fine contrast read as albedo: the diffuse takes it
            as albedo (``detail_gains``), and the network's normals lose that share of their band
            that follows the photo's contrast (relief made up from the albedo); capture passes
            ``1 - normal_gain``.
        fine_slope: (B, 2, H', W') ``fine_relief``: the normals' detail (weighted by the relief
            test's gain there but where it reads steep relief), in place of the photo's contrast
            times their gains but for the metallic share of each network pixel
            (``metallic_shares``): a metal has no diffuse to read relief from, and keeps that share
            of the gains' detail; None: the gains' detail everywhere.
        denoise: the photo's fine contrast denoised first (``denoise_contrast``, the noise measured
            from the photo by ``photo_noise``); False: as it is.
        keep_lobe_peak: narrow the roughness where the normals get detail, so that each network
            pixel's mean specular peak stays as it was (``lobe_peak_factors``).
        slope_scale: the factor the normals' slopes are rendered at (``CaptureConfig.normal_strength``,
            applied after): the added tilts are measured at it.
        colour_test: the normals follow the photo's contrast less the part a change of hue explains
            (``shading_contrast``); False: its whole luminance contrast.

    Returns:
        (B, 10, H, W).
    """
    height, width = maps.shape[-2:]
    low_size = tuple(low_maps.shape[-2:])
    if low_size[0] >= height:
        return maps
    with torch.no_grad():
        low_guides = _guides(downsample(photo.float(), low_size))
        low_contrast = band_contrast(low_guides)
        gains = detail_gains(low_maps, low_contrast, albedo_share=albedo_share)
        # Where the contrast reads as albedo, what of the network's normals follows it is relief made
        # up from the albedo: it goes with what the detail holds below the network's resolution.
        made_up = albedo_share * gains[:, constants.NORMAL] * low_contrast[:, constants.NORMAL]
        # The fine slope reads the diffuse's shading, weighted by its share; a metal has none. There
        # the photo's contrast times the normals' gains, which reads the specular's shading, stays.
        gains[:, constants.NORMAL] *= normal_gain if fine_slope is None else normal_gain * metallic_shares(low_maps)
        factor = height // low_size[0]
        banded = (exact_in_bands(low_size[0], height) and low_size[1] * factor == width)
        rows = max(factor, BAND_PIXELS // width // factor * factor) if banded else height

        guide_rows, gain_rows = _rows_at(low_guides, height, width), _rows_at(gains, height, width)
        slope_rows = None if fine_slope is None else _rows_at(fine_slope.float(), height, width)

        # The detail, and what it holds below the network's resolution, which is taken out again:
        # the network's answer there stays as it is.
        below = maps.new_empty(maps.shape[0], maps.shape[1], *low_size)
        # The normals' added x and y, for the tilts the lobe's peak is kept under.
        added_xy = maps.new_empty(maps.shape[0], 2, height, width, dtype=torch.float16) if keep_lobe_peak else None
        noise_rows = None
        if denoise:
            # The noise's variance in contrast units at the network's size, upsampled as the smooth
            # guides are: it follows their level.
            relative = noise_at(photo_noise(photo, guide_rows, rows), low_guides) / low_guides.clamp(min=DARKEST) ** 2
            noise_rows = _rows_at(relative, height, width)
        # The windows of the denoising and of the hue's fit, one after the other, reach that far.
        halo = (DENOISE_HALO if denoise else 0) + (2 * HUE_RADIUS if colour_test else 0)
        for start in range(0, height, rows):
            stop = min(height, start + rows)
            # Rows around the band too: the denoising's windows reach into them.
            first, last = max(0, start - halo), min(height, stop + halo)
            smooth = guide_rows(first, last)
            contrast = (_guides(photo[..., first:last, :].float()) - smooth) / smooth.clamp(min=DARKEST)
            if noise_rows is not None:
                contrast = denoise_contrast(contrast, noise_rows(first, last))
            guided = contrast[:, list(GUIDE_OF_CHANNEL)]
            if colour_test:
                guided[:, constants.NORMAL] = shading_contrast(contrast, smooth)
            added = gain_rows(start, stop) * guided[..., start - first:stop - first, :]
            if slope_rows is not None:
                added[:, 0:2] += slope_rows(start, stop)
            maps[..., start:stop, :] += added
            if added_xy is not None:
                added_xy[..., start:stop, :] = added[:, 0:2]
            if banded:
                below[..., start // factor:-(-stop // factor), :] = downsample(
                    added, (-(-stop // factor) - start // factor, low_size[1]))
            else:  # one band of every row, at a size that is no multiple of the network's
                below[...] = downsample(added, low_size)
        # The detail's own tilts: what it adds above the network's resolution, not the made-up relief
        # taken out below it.
        below_xy_rows = _rows_at(below[:, 0:2].clone(), height, width) if keep_lobe_peak else None
        below[:, constants.NORMAL] += made_up
        below_rows = _rows_at(below, height, width)
        lobe_factors = maps.new_ones(maps.shape[0], 1, *low_size) if keep_lobe_peak else None
        for start in range(0, height, rows):
            stop = min(height, start + rows)
            band = maps[..., start:stop, :]
            band -= below_rows(start, stop)
            band[:, constants.NORMAL] = unit_vectors(torch.cat([band[:, 0:2], band[:, 2:3].clamp(min=1e-3)], dim=1),
                                                     dim=1)
            band[:, constants.REFLECTANCE] = band[:, constants.REFLECTANCE].clamp(0.0, 1.0)
            if lobe_factors is not None:
                tilt = (added_xy[..., start:stop, :].float() - below_xy_rows(start, stop)) * slope_scale
                tilt2 = tilt.square().sum(dim=1, keepdim=True) / band[:, 2:3].clamp(min=0.1) ** 2
                low_rows = slice(start // factor, -(-stop // factor)) if banded else slice(None)
                band_low = (low_rows.stop - low_rows.start, low_size[1]) if banded else low_size
                lobe_factors[..., low_rows, :] = lobe_peak_factors(band[:, constants.ROUGHNESS], tilt2, band_low)
        if lobe_factors is not None:
            # roughness = alpha^(1/2): the width's factor f scales it by f^(1/2)
            factor_rows = _rows_at(lobe_factors.sqrt(), height, width)
            for start in range(0, height, rows):
                stop = min(height, start + rows)
                maps[:, constants.ROUGHNESS, start:stop] *= factor_rows(start, stop)
    return maps


#: Least factor ``lobe_peak_factors`` narrows a GGX width by.
NARROWEST_LOBE = 0.3

#: Factors of the GGX width ``lobe_peak_factors`` tries, evenly from 1 down to ``NARROWEST_LOBE``.
LOBE_FACTORS = 24


def lobe_peak(alpha2: torch.Tensor, tilt2: torch.Tensor) -> torch.Tensor:
    """pi times the GGX distribution of width alpha (``alpha2`` = alpha^2) at the half vector along a
    normal, for a microfacet normal tilted from it by an angle of squared tangent ``tilt2``:
    ``alpha^2 (1 + t^2)^2 / (alpha^2 + t^2)^2`` (``1 / alpha^2`` untilted)."""
    return alpha2 * (1.0 + tilt2) ** 2 / (alpha2 + tilt2) ** 2


def lobe_peak_factors(roughness: torch.Tensor, tilt2: torch.Tensor, low_size: tuple[int, int],
                      floor: float = constants.PHYSICAL_MIN_ROUGHNESS) -> torch.Tensor:
    """The factor of each network pixel's GGX width (alpha = roughness^2) that keeps its specular
    peak, averaged over the pixel, as it was before the normals got tilts of squared tangent
    ``tilt2``.

    Fine normals spread a lobe: a pixel tilted by t is seen at the peak's half vector as far as
    t off its own normal, so the mean over a network pixel of the GGX peak ``lobe_peak`` falls,
    most where the lobe is narrow. The refinement fitted the lobe, highlight's peak included, to
    the photo without those tilts. Of ``LOBE_FACTORS`` factors f from 1 down, the first whose
    narrowed lobe, f alpha, has a mean peak at least the untilted one's is found, and the factor is
    read linearly between it and the one before; where none has, the factor whose mean peak comes
    nearest (tilts far wider than the lobe: narrowing it dims the tilted pixels more). Unlike a
    slope variance taken from alpha^2 (Toksvig's filtering of a normal map, undone) this holds for
    heavy-tailed tilts too: a few steep ones leave the peak, they do not widen it.

    Args:
        roughness: (B, 1, H, W); tilt2: (B, 1, H, W) the squared tangent of each pixel's added tilt;
        low_size: the network's (h, w), whose pixels the peak is averaged over.

    Returns:
        (B, 1, h, w) factors in [``NARROWEST_LOBE``, 1].
    """
    alpha2 = roughness.float().clamp(min=floor) ** 4
    target = downsample(1.0 / alpha2, low_size)
    factors = torch.ones_like(target)
    found = torch.zeros_like(target, dtype=torch.bool)
    # Where no factor reaches the target (tilts far wider than the lobe: narrowing it only dims the
    # tilted pixels more), the one whose mean peak comes nearest.
    nearest, nearest_peak = torch.ones_like(target), torch.full_like(target, -1.0)
    previous_factor, previous_peak = None, None
    for factor in torch.linspace(1.0, NARROWEST_LOBE, LOBE_FACTORS).tolist():
        peak = downsample(lobe_peak(factor**2 * alpha2, tilt2), low_size)
        higher = peak > nearest_peak
        nearest[higher], nearest_peak[higher] = factor, peak[higher]
        kept = (peak >= target) & ~found  # at the first factor, 1: ``factors`` holds it already
        if previous_peak is not None:  # linear between the last factor short of the target and this one
            share = ((target - previous_peak) / (peak - previous_peak).clamp(min=1e-30)).clamp(0.0, 1.0)
            factors[kept] = (previous_factor + share * (factor - previous_factor))[kept]
        found |= kept
        if bool(found.all()):
            break
        previous_factor, previous_peak = factor, peak
    return torch.where(found, factors, nearest)


def _rows_at(value: torch.Tensor, height: int, width: int):
    """A function of (start, stop) giving those rows of ``value`` (B, C, h, w) upsampled bilinearly
    to (height, width): band by band where ``upsampled_rows`` can (``add_detail`` then works in
    bands of rows), else from one upsampling (and in one band)."""
    if tuple(value.shape[-2:]) == (height, width):
        return lambda start, stop: value[..., start:stop, :]
    factor = height // value.shape[-2]
    if exact_in_bands(value.shape[-2], height) and value.shape[-1] * factor == width:
        return lambda start, stop: upsampled_rows(value, height, width, start, stop)
    whole = upsample_bilinear(value, height, width)
    return lambda start, stop: whole[..., start:stop, :]
