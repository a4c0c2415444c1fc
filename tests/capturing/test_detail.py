"""The photo's detail above the network's resolution (``capturing.detail``): given to a map that
follows the photo, not to one that does not, the low band kept, bands of rows as the whole."""

from __future__ import annotations

import itertools
import re

import pytest
import torch
import torch.nn.functional as F

from mideepbasis import constants
from mideepbasis.capturing import detail
from mideepbasis.resampling import downsample, gaussian_blur, upsample_bilinear

from ..helpers import matte_egg_crate

#: What the tests ask: high-band energy of the detailed diffuse against the truth's, and how much of
#: the upsampled answer's error the detail removes.
TOLERANCES = {"energy_ratio": (0.6, 1.3), "error_left": 0.6, "low_band": 2e-3, "flat_normal": 1e-3,
              "made_up_band_left": 0.85, "fine_relief_correlation": 0.4, "fine_slope_kept": 2e-3,
              "noise_variance": 0.2, "noise_left": 0.1, "noise_energy_left": 0.15, "noise_free_change": 2e-3,
              "lobe_peak_mean": 5e-3, "lobe_peak_pixel": 0.05, "shading_change": 1e-6, "hue_energy_left": 0.05,
              "shading_correlation": 0.75, "hue_correlation": 0.25, "hue_relief_left": 0.1}

SIZE, LOW = 256, 32


def _falloff_photo(level: torch.Tensor) -> torch.Tensor:
    """(1, 3, SIZE, SIZE) ``level`` (1, 3, SIZE, SIZE) under a smooth flash falloff."""
    y, x = torch.meshgrid(torch.linspace(-1, 1, SIZE), torch.linspace(-1, 1, SIZE), indexing="ij")
    return level * (1.0 / (1.0 + 0.5 * (x**2 + y**2)) ** 1.5).view(1, 1, SIZE, SIZE)


def textured_scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A fine albedo texture (1, 3, SIZE, SIZE) and its photo under a smooth flash falloff."""
    generator = torch.Generator().manual_seed(seed)
    noise = torch.rand(1, 3, SIZE // 4, SIZE // 4, generator=generator)
    albedo = 0.15 + 0.6 * F.interpolate(noise, size=(SIZE, SIZE), mode="bicubic", align_corners=False).clamp(0, 1)
    return albedo, _falloff_photo(albedo)


def upsampled_answer(albedo: torch.Tensor, band_slope: float = 1.0 / detail.DIFFUSE_GAIN
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The network's answer as capture has it: the truth at LOW px (flat normals, roughness 0.4,
    specular 0.04), its diffuse's band above ``detail.LOW_SIGMA`` times ``band_slope`` (a network's
    answer is smoother than the truth: ``detail.DIFFUSE_GAIN``), and that upsampled to SIZE."""
    low = torch.zeros(1, 10, LOW, LOW)
    low[:, 2] = 1.0
    diffuse = downsample(albedo, LOW)
    smooth = gaussian_blur(diffuse, detail.LOW_SIGMA, padding="replicate")
    low[:, constants.DIFFUSE] = smooth + band_slope * (diffuse - smooth)
    low[:, constants.ROUGHNESS] = 0.4
    low[:, constants.SPECULAR] = 0.04
    return low, upsample_bilinear(low, SIZE, SIZE)


def high_band(image: torch.Tensor, size: int = SIZE) -> torch.Tensor:
    return image - upsample_bilinear(downsample(image, LOW), size, size)


def test_a_map_that_follows_the_photo_gets_its_detail_and_a_flat_one_none():
    albedo, photo = textured_scene()
    low, maps = upsampled_answer(albedo)
    before = maps.clone()
    detailed = detail.add_detail(maps, photo, low)
    diffuse = detailed[:, constants.DIFFUSE]
    ratio = float(high_band(diffuse).square().sum() / high_band(albedo).square().sum())
    low_ratio, high_ratio = TOLERANCES["energy_ratio"]
    assert low_ratio <= ratio <= high_ratio
    error = lambda m: float((m - albedo).square().mean().sqrt())  # noqa: E731
    assert error(diffuse) < TOLERANCES["error_left"] * error(before[:, constants.DIFFUSE])
    # The network's flat normals and constant roughness and specular do not follow the photo: no
    # relief is invented from the albedo's texture.
    assert float((detailed[:, 0:2]).abs().max()) < TOLERANCES["flat_normal"]
    assert torch.allclose(detailed[:, constants.ROUGHNESS], before[:, constants.ROUGHNESS], atol=1e-4)


def test_the_diffuse_gains_are_scaled_by_the_diffuse_gain(monkeypatch):
    albedo, photo = textured_scene(4)
    low, maps = upsampled_answer(albedo)

    def fine_energy():
        diffuse = detail.add_detail(maps.clone(), photo, low)[:, constants.DIFFUSE]
        return float(high_band(diffuse).square().sum())

    scaled = fine_energy()
    unscaled = tuple(1.0 if 3 <= channel < 6 else gain for channel, gain in enumerate(detail.GAIN_OF_CHANNEL))
    monkeypatch.setattr(detail, "GAIN_OF_CHANNEL", unscaled)
    # Energy goes with the square of the gain; the clip to [0, 1] takes a little off.
    assert scaled / fine_energy() == pytest.approx(detail.DIFFUSE_GAIN**2, rel=0.1)


def test_the_network_answer_below_its_resolution_is_kept():
    albedo, photo = textured_scene(1)
    low, maps = upsampled_answer(albedo)
    # The band below the network's: its pixels, blurred by one (what detail is fitted against).
    low_band = lambda m: gaussian_blur(downsample(m, LOW), 1.0, padding="replicate")  # noqa: E731
    before = low_band(maps.clone())
    after = low_band(detail.add_detail(maps, photo, low))
    change = float((after - before)[:, constants.DIFFUSE].abs().mean())
    assert change < TOLERANCES["low_band"]


def test_bands_of_rows_give_the_whole_image(monkeypatch):
    albedo, photo = textured_scene(2)
    low, maps = upsampled_answer(albedo)
    whole = detail.add_detail(maps.clone(), photo, low)
    monkeypatch.setattr(detail, "BAND_PIXELS", SIZE * 24)  # bands of 24 rows
    banded = detail.add_detail(maps.clone(), photo, low)
    assert torch.allclose(banded, whole, atol=1e-5)


@pytest.mark.parametrize("height, width", [(250, 250), (200, 200), (200, 256)])
def test_a_size_that_is_no_multiple_of_the_networks_gets_its_detail_and_keeps_its_answer(height, width):
    albedo, photo = textured_scene(1)
    low, _ = upsampled_answer(albedo)
    albedo, photo = downsample(albedo, (height, width)), downsample(photo, (height, width))
    maps = upsample_bilinear(low, height, width)
    before = maps.clone()
    detailed = detail.add_detail(maps, photo, low)
    assert detailed.shape == (1, 10, height, width)
    diffuse = detailed[:, constants.DIFFUSE]
    fine = lambda image: image - upsample_bilinear(downsample(image, LOW), height, width)  # noqa: E731
    ratio = float(fine(diffuse).square().sum() / fine(albedo).square().sum())
    low_ratio, high_ratio = TOLERANCES["energy_ratio"]
    assert low_ratio <= ratio <= high_ratio, ratio
    low_band = lambda m: gaussian_blur(downsample(m, LOW), 1.0, padding="replicate")  # noqa: E731
    change = float((low_band(detailed) - low_band(before))[:, constants.DIFFUSE].abs().mean())
    assert change < TOLERANCES["low_band"], change


def _noisy(photo: torch.Tensor, shot: float, read: float, seed: int = 0) -> torch.Tensor:
    """``photo`` with shot noise of variance ``shot`` per unit of signal and read noise of standard
    deviation ``read`` (a camera's, before its tone curve)."""
    generator = torch.Generator().manual_seed(seed)
    return photo + torch.randn(photo.shape, generator=generator) * torch.sqrt(shot * photo + read**2)


def _smooth_rows(photo: torch.Tensor):
    return detail._rows_at(detail._guides(downsample(photo, LOW)), SIZE, SIZE)


@pytest.mark.parametrize("shot, read", [(1e-3, 1e-3), (3e-3, 3e-2)])
def test_photo_noise_reads_the_noise_variance_by_level(shot, read):
    y = torch.linspace(0.15, 0.9, SIZE).view(1, 1, SIZE, 1)
    clean = (y * torch.linspace(0.6, 1.0, SIZE).view(1, 1, 1, SIZE)).expand(1, 3, SIZE, SIZE)
    photo = _noisy(clean, shot, read, seed=1)
    variances = detail.photo_noise(photo, _smooth_rows(photo), 64)
    levels = torch.tensor([0.2, 0.4, 0.6]).view(1, 1, 3, 1).expand(1, 4, 3, 1)
    measured = detail.noise_at(variances, levels)[0, :, :, 0]
    truth = shot * levels[0, :, :, 0] + read**2
    truth[3] /= 3  # the luminance, a mean of three channels
    assert torch.allclose(measured, truth, rtol=TOLERANCES["noise_variance"])
    assert float(detail.photo_noise(clean, _smooth_rows(clean), 64).max()) < 1e-10


def test_photo_noise_reads_patches_spaced_out_on_a_large_photo_whatever_the_bands(monkeypatch):
    photo = _noisy(torch.full((1, 3, SIZE, SIZE), 0.5), 1e-3, 1e-2)
    monkeypatch.setattr(detail, "NOISE_SAMPLES", SIZE * SIZE // 16)  # every fourth row and column
    whole = detail.photo_noise(photo, _smooth_rows(photo), SIZE)
    assert torch.equal(detail.photo_noise(photo, _smooth_rows(photo), 37), whole)
    monkeypatch.setattr(detail, "NOISE_SAMPLES", SIZE * SIZE)
    every_pixel = detail.photo_noise(photo, _smooth_rows(photo), SIZE)
    assert torch.allclose(whole, every_pixel, rtol=TOLERANCES["noise_variance"])
    assert float(every_pixel.min()) > 0.0


def test_photo_noise_is_not_read_from_a_texture_smooth_at_the_pixels_scale():
    albedo, photo = textured_scene(0)
    level = torch.full((1, 4, 1, 1), 0.3)
    texture = detail.noise_at(detail.photo_noise(photo, _smooth_rows(photo), SIZE), level)
    noisy = _noisy(photo, 1e-4, 1e-3)  # noise of about a tenth of the texture's fine contrast
    noise = detail.noise_at(detail.photo_noise(noisy, _smooth_rows(noisy), SIZE), level)
    assert float(texture.max()) < TOLERANCES["noise_left"] * float(noise.min())


def test_the_detail_takes_the_photos_noise_out_and_keeps_a_texture():
    # A flat albedo photographed with noise: the detail the diffuse gets is that noise, mostly.
    flat = torch.full((1, 3, SIZE, SIZE), 0.5)
    low, maps = upsampled_answer(flat)
    generator = torch.Generator().manual_seed(2)
    low[:, constants.DIFFUSE] += 0.05 * torch.randn(1, 3, LOW, LOW, generator=generator)  # some gain to give
    photo = _noisy(_falloff_photo(flat), 1e-3, 1e-3)
    energy = {denoise: float(high_band(detail.add_detail(maps.clone(), photo, low, denoise=denoise)
                                       [:, constants.DIFFUSE]).square().mean()) for denoise in (False, True)}
    assert energy[True] < TOLERANCES["noise_energy_left"] * energy[False]
    # A texture photographed without noise keeps its detail.
    albedo, clean = textured_scene(0)
    low, maps = upsampled_answer(albedo)
    kept = detail.add_detail(maps.clone(), clean, low, denoise=True)
    assert torch.allclose(kept, detail.add_detail(maps.clone(), clean, low, denoise=False),
                          atol=TOLERANCES["noise_free_change"])
    # With noise, the denoised diffuse is nearer the truth.
    noisy = _noisy(clean, 3e-3, 1e-2)
    error = {denoise: float((detail.add_detail(maps.clone(), noisy, low, denoise=denoise)[:, constants.DIFFUSE]
                             - albedo).square().mean()) for denoise in (False, True)}
    assert error[True] < error[False]


def test_bands_of_rows_give_the_whole_image_with_a_noisy_photo(monkeypatch):
    albedo, photo = textured_scene(2)
    photo = _noisy(photo, 3e-3, 1e-2)
    low, maps = upsampled_answer(albedo)
    whole = detail.add_detail(maps.clone(), photo, low, denoise=True)
    monkeypatch.setattr(detail, "BAND_PIXELS", SIZE * 24)  # bands of 24 rows
    assert torch.allclose(detail.add_detail(maps.clone(), photo, low, denoise=True), whole, atol=1e-5)


TEAL, GOLD = (0.05, 0.35, 0.40), (0.70, 0.50, 0.15)
WHITE, BLACK, SILVER = (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), (0.97, 0.96, 0.91)


def _fine_field(seed: int) -> torch.Tensor:
    """(1, 1, SIZE, SIZE) smooth noise in [0, 1] with cells of 4 pixels: finer than the network's."""
    generator = torch.Generator().manual_seed(seed)
    cells = torch.rand(1, 1, SIZE // 4, SIZE // 4, generator=generator)
    return F.interpolate(cells, size=(SIZE, SIZE), mode="bicubic", align_corners=False)


def _coloured_photo(hue_texture: bool, relief: bool, specular: tuple[float, float, float] = WHITE,
                    diffuse: tuple[float, float, float] | None = None) -> torch.Tensor:
    """(1, 3, SIZE, SIZE) a flash photo of teal and gold scales (or one colour) with, where
    ``relief``, a fine shading of the diffuse and of a ``specular``-coloured glint."""
    mask = (_fine_field(1) > 0.5).float() if hue_texture else torch.zeros(1, 1, SIZE, SIZE)
    albedo = (torch.tensor(TEAL).view(1, 3, 1, 1) * (1 - mask) + torch.tensor(GOLD).view(1, 3, 1, 1) * mask
              if diffuse is None else torch.tensor(diffuse).view(1, 3, 1, 1).expand(1, 3, SIZE, SIZE))
    shading = 1 + 0.3 * (_fine_field(2) - 0.5) if relief else torch.ones(1, 1, SIZE, SIZE)
    glint = 0.05 * (1 + (_fine_field(3) - 0.5)) if relief else torch.full((1, 1, SIZE, SIZE), 0.05)
    return _falloff_photo(albedo * shading + torch.tensor(specular).view(1, 3, 1, 1) * glint)


def _contrast(photo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The guides' contrast above the network's band and their smooth level, as ``add_detail`` takes them."""
    guides = torch.cat([photo, photo.mean(dim=1, keepdim=True)], dim=1)
    smooth = upsample_bilinear(downsample(guides, LOW), SIZE, SIZE)
    return (guides - smooth) / smooth, smooth


def _correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a * b).mean() / (a.square().mean() * b.square().mean()).sqrt())


@pytest.mark.parametrize("specular, diffuse", [(WHITE, (0.5, 0.5, 0.5)), (WHITE, TEAL), (SILVER, BLACK),
                                               (GOLD, BLACK)])
def test_shading_contrast_keeps_the_contrast_shading_makes(specular, diffuse):
    # A grey or a teal diffuse under a white glint, or a silver or gold metal: the chroma changes only
    # along the pixel's own colour's.
    contrast, smooth = _contrast(_coloured_photo(False, True, specular, diffuse))
    kept = detail.shading_contrast(contrast, smooth)
    change = (kept - contrast[:, 3:4]).square().mean() / contrast[:, 3:4].square().mean()
    assert float(change) < TOLERANCES["shading_change"]


def test_shading_contrast_takes_a_change_of_hue_out_and_keeps_the_shading_under_it():
    contrast, smooth = _contrast(_coloured_photo(True, False))
    kept = detail.shading_contrast(contrast, smooth)
    assert float(kept.square().mean()) < TOLERANCES["hue_energy_left"] * float(contrast[:, 3:4].square().mean())
    # Scales with shading: what is kept is the shading's, not the scales' edges.
    both, both_smooth = _contrast(_coloured_photo(True, True))
    kept = detail.shading_contrast(both, both_smooth)
    shading_only = _contrast(_coloured_photo(False, True))[0][:, 3:4]
    hue_only = contrast[:, 3:4]
    assert _correlation(both[:, 3:4], hue_only) > _correlation(both[:, 3:4], shading_only)  # the edges dominate
    assert _correlation(kept, shading_only) > TOLERANCES["shading_correlation"]
    assert _correlation(kept, hue_only) < TOLERANCES["hue_correlation"]


def _normals_following_the_photo(photo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The network's answer (at LOW px and upsampled) for ``photo``, its normals' x slope following
    the photo's luminance contrast at LOW px: relief read from it."""
    low = torch.zeros(1, 10, LOW, LOW)
    low[:, constants.DIFFUSE] = downsample(photo, LOW)
    low[:, 0:1] = 0.5 * detail.band_contrast(detail._guides(downsample(photo, LOW)))[:, 0:1]
    low[:, 2] = 1.0
    low[:, constants.ROUGHNESS], low[:, constants.SPECULAR] = 0.4, 0.04
    return low, upsample_bilinear(low, SIZE, SIZE)


def test_the_colour_test_gives_the_normals_no_relief_from_a_change_of_hue():
    photo = _coloured_photo(True, False)
    low, maps = _normals_following_the_photo(photo)
    added = {test: high_band(detail.add_detail(maps.clone(), photo, low, colour_test=test)[:, 0:2])
             for test in (False, True)}
    assert float(added[True].square().mean()) < TOLERANCES["hue_relief_left"] * float(added[False].square().mean())
    # The diffuse's detail is the same either way.
    assert torch.equal(detail.add_detail(maps.clone(), photo, low, colour_test=True)[:, constants.DIFFUSE],
                       detail.add_detail(maps.clone(), photo, low)[:, constants.DIFFUSE])


@pytest.mark.parametrize("denoise", [False, True])
def test_bands_of_rows_give_the_whole_image_with_the_colour_test(monkeypatch, denoise):
    photo = _noisy(_coloured_photo(True, True), 1e-4, 1e-3) if denoise else _coloured_photo(True, True)
    low, maps = _normals_following_the_photo(photo)
    whole = detail.add_detail(maps.clone(), photo, low, denoise=denoise, colour_test=True)
    monkeypatch.setattr(detail, "BAND_PIXELS", SIZE * 24)  # bands of 24 rows
    assert torch.allclose(detail.add_detail(maps.clone(), photo, low, denoise=denoise, colour_test=True), whole,
                          atol=1e-5)


@pytest.mark.parametrize("size", [LOW, LOW // 2])
def test_nothing_is_added_at_or_below_the_network_resolution(size):
    albedo, photo = textured_scene(3)
    low, _ = upsampled_answer(albedo)
    maps = downsample(low, size).clone()
    assert torch.equal(detail.add_detail(maps.clone(), downsample(photo, size), low), maps)


def test_the_specular_gets_no_detail_even_where_it_follows_the_photo():
    albedo, photo = textured_scene(4)
    low, maps = upsampled_answer(albedo)
    low[:, constants.SPECULAR] = low[:, constants.DIFFUSE] * 0.2  # a specular that follows the photo
    maps = upsample_bilinear(low, SIZE, SIZE)
    before = maps[:, constants.SPECULAR].clone()
    after = detail.add_detail(maps, photo, low)[:, constants.SPECULAR]
    assert torch.allclose(after, before.clamp(0, 1), atol=1e-6)


def _flash_photo(maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The photo (3, H, W) of ``maps`` under a hand-held flash, and the flash (3,)."""
    from mideepbasis.evaluation import flash_photos

    photos, lights = flash_photos(maps, torch.tensor([[0.25, -0.15]]), constants.DEFAULT_FOV_DEG, "physical", 1.0)
    return photos[0], lights[0]


def _matte(size: int) -> torch.Tensor:
    """(1, 10, size, size) flat, grey, matte."""
    maps = torch.zeros(1, 10, size, size)
    maps[:, 2] = 1.0
    maps[:, constants.DIFFUSE] = 0.5
    maps[:, constants.ROUGHNESS] = 1.0
    return maps


def test_relief_share_tells_relief_from_albedo_texture_isotropic_or_grained():
    import math

    size = 256
    coords = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    relief = matte_egg_crate(size, cycles=24, slope=0.15)  # an egg-crate relief of one albedo
    # Flat: a fine isotropic albedo texture, and a grain along one direction (30 deg).
    generator = torch.Generator().manual_seed(2)
    noise = F.interpolate(torch.rand(1, 1, size // 3, size // 3, generator=generator), size=(size, size),
                          mode="bicubic", align_corners=False)[0, 0]
    isotropic = _matte(size)
    isotropic[0, constants.DIFFUSE] = (0.2 + 0.5 * noise.clamp(0, 1)).expand(3, -1, -1)
    frequency = math.pi * 24
    grain = torch.cos(frequency * (x * math.cos(math.pi / 6) + y * math.sin(math.pi / 6))
                      + 0.5 * noise.double()).float()
    grained = _matte(size)
    grained[0, constants.DIFFUSE] = (0.45 + 0.25 * grain).expand(3, -1, -1)
    low, high = detail.RELIEF_SHARE
    shares = {}
    for name, maps in (("relief", relief), ("isotropic", isotropic), ("grained", grained)):
        photo, light = _flash_photo(maps)
        shares[name] = detail.relief_share(photo, light, (LOW, LOW))
    assert shares["relief"] > high
    assert shares["isotropic"] < low and shares["grained"] < low
    assert detail.relief_gain(shares["relief"]) == 1.0
    assert detail.relief_gain(shares["isotropic"]) == detail.relief_gain(shares["grained"]) == 0.0
    assert detail.relief_gain((low + high) / 2) == pytest.approx(0.5)


def test_normal_gain_zero_leaves_the_normals_upsampled_and_the_rest_as_with_gain_one():
    albedo, photo = textured_scene()
    low, maps = upsampled_answer(albedo)
    low[:, 0:2] = 0.2 * (low[:, constants.DIFFUSE][:, 0:2] - 0.4)  # normals that follow the photo's texture
    low[:, constants.NORMAL] = low[:, constants.NORMAL] / low[:, constants.NORMAL].norm(dim=1, keepdim=True)
    maps = upsample_bilinear(low, SIZE, SIZE)
    maps[:, constants.NORMAL] = maps[:, constants.NORMAL] / maps[:, constants.NORMAL].norm(dim=1, keepdim=True)
    whole = detail.add_detail(maps.clone(), photo, low)
    none = detail.add_detail(maps.clone(), photo, low, normal_gain=0.0)
    assert torch.allclose(none[:, constants.NORMAL], maps[:, constants.NORMAL], atol=1e-5)
    assert not torch.allclose(whole[:, constants.NORMAL], maps[:, constants.NORMAL], atol=1e-3)
    assert torch.equal(none[:, constants.REFLECTANCE], whole[:, constants.REFLECTANCE])


def test_contrast_read_as_albedo_gives_the_diffuse_the_albedos_fine_energy_whatever_the_networks_band():
    albedo, photo = textured_scene(2)
    # A network whose diffuse band is far weaker than the truth's: the fitted gains under-read it.
    low, maps = upsampled_answer(albedo, band_slope=0.4)

    def fine_diffuse(albedo_share: float) -> torch.Tensor:
        return detail.add_detail(maps.clone(), photo, low, albedo_share=albedo_share)[:, constants.DIFFUSE]

    truth_energy = float(high_band(albedo).square().sum())
    fitted, as_albedo = fine_diffuse(0.0), fine_diffuse(1.0)
    low_ratio, high_ratio = TOLERANCES["energy_ratio"]
    assert float(high_band(fitted).square().sum()) / truth_energy < low_ratio
    assert low_ratio <= float(high_band(as_albedo).square().sum()) / truth_energy <= high_ratio
    error = lambda m: float((m - albedo).square().mean().sqrt())  # noqa: E731
    assert error(as_albedo) < error(fitted)
    # Halfway is halfway between the two gains: the fine band is linear in them (no clip here).
    halfway = fine_diffuse(0.5)
    assert torch.allclose(high_band(halfway), (high_band(fitted) + high_band(as_albedo)) / 2, atol=1e-4)


def test_contrast_read_as_albedo_takes_the_relief_the_network_made_up_from_it_out_of_the_normals():
    albedo, photo = textured_scene()
    low, _ = upsampled_answer(albedo)
    low[:, 0:2] = 0.2 * (low[:, constants.DIFFUSE][:, 0:2] - 0.4)  # flat truth, normals that follow its albedo
    low[:, constants.NORMAL] = low[:, constants.NORMAL] / low[:, constants.NORMAL].norm(dim=1, keepdim=True)
    maps = upsample_bilinear(low, SIZE, SIZE)
    maps[:, constants.NORMAL] = maps[:, constants.NORMAL] / maps[:, constants.NORMAL].norm(dim=1, keepdim=True)

    def tilt(normals: torch.Tensor) -> float:  # RMS slope against the true flat normal
        return float(normals[:, 0:2].square().mean().sqrt())

    def band_tilt(normals: torch.Tensor) -> float:  # the same, of the band the detail step fits in
        slopes = normals[:, 0:2]
        smooth = gaussian_blur(downsample(slopes, LOW), detail.LOW_SIGMA, padding="replicate")
        return tilt(slopes - upsample_bilinear(smooth, SIZE, SIZE))

    as_albedo = detail.add_detail(maps.clone(), photo, low, normal_gain=0.0, albedo_share=1.0)[:, constants.NORMAL]
    assert tilt(as_albedo) < tilt(maps[:, constants.NORMAL])
    assert band_tilt(as_albedo) < TOLERANCES["made_up_band_left"] * band_tilt(maps[:, constants.NORMAL])


def _plain_grain(size: int) -> torch.Tensor:
    """(1, 10, size, size) flat and matte, its albedo a straight grain (24 cycles across)."""
    import math

    coords = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    grained = _matte(size)
    grained[0, constants.DIFFUSE] = (0.45 + 0.25 * torch.cos(math.pi * 24 * (0.8 * x + 0.6 * y))).float()
    return grained


def test_photo_relief_gain_reads_a_grained_albedo_from_four_times_the_network_size_on():
    size = 256
    grained = _plain_grain(size)
    photo, light = _flash_photo(grained)
    low_maps = downsample(grained, LOW)
    assert detail.photo_relief_gain(photo, light, low_maps, constants.DEFAULT_FOV_DEG, "physical") == 0.0
    # Twice the network's size: one octave, not read; the normals keep their detail.
    assert detail.photo_relief_gain(photo, light, downsample(grained, size // 2), constants.DEFAULT_FOV_DEG,
                                    "physical") == 1.0


def test_capture_records_the_normals_detail_it_kept_and_relief_test_false_keeps_it_all(tiny_checkpoint):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    size = 256
    grained = _plain_grain(size)
    photo, _ = _flash_photo(grained)
    kept = {}
    for test in (True, False):
        config = CaptureConfig(light=(0.25, -0.15), resolution=size, network_resolution=LOW, symmetries=1,
                               refine=RefineConfig(steps=0), relief_test=test)
        provenance = Capturer(tiny_checkpoint, config).capture(photo).material.provenance["capture"]
        kept[test] = provenance["normal_detail"], provenance["relief_test_read"], provenance["detail_added"]
        assert provenance["network_size"] == [LOW, LOW]
    assert kept == {True: (0.0, True, True), False: (1.0, False, True)}


def test_capture_denoises_the_detail_unless_told_not_to(tiny_checkpoint):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    size = 256
    photo, _ = _flash_photo(_plain_grain(size))
    photo = _noisy(photo[None], 3e-3, 1e-2)[0].clamp(0.0, 1.0)
    results = {}
    for denoise in (True, False):
        config = CaptureConfig(light=(0.25, -0.15), resolution=size, network_resolution=LOW, symmetries=1,
                               refine=RefineConfig(steps=0), denoise_detail=denoise)
        material = Capturer(tiny_checkpoint, config).capture(photo).material
        results[denoise] = material.provenance["capture"]["detail_denoised"], material.to_tensor()
    assert results[True][0] is True and results[False][0] is False
    fine_energy = {denoise: float(high_band(maps[constants.DIFFUSE][None], size).square().mean())
                   for denoise, (_, maps) in results.items()}
    assert fine_energy[True] < fine_energy[False]


def test_capture_leaves_a_change_of_hue_out_of_the_normals_only_where_the_relief_test_reads(tiny_checkpoint):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    photo = _coloured_photo(True, True)
    results = {}
    for size, test in itertools.product((SIZE, 2 * LOW), (True, False)):
        config = CaptureConfig(light=(0.25, -0.15), resolution=size, network_resolution=LOW, symmetries=1,
                               refine=RefineConfig(steps=0), relief_test=False, fine_relief=False, colour_test=test)
        material = Capturer(tiny_checkpoint, config).capture(downsample(photo, size)[0]).material
        results[size, test] = material.provenance["capture"]["colour_tested"], material.to_tensor()
    assert results[SIZE, True][0] is True and results[SIZE, False][0] is False
    assert not torch.equal(results[SIZE, True][1][0:2], results[SIZE, False][1][0:2])
    assert torch.equal(results[SIZE, True][1][3:], results[SIZE, False][1][3:])  # the normals' detail alone
    # Below 4 times the network's resolution the relief test does not read, nor does this one.
    assert results[2 * LOW, True][0] is False
    assert torch.equal(results[2 * LOW, True][1], results[2 * LOW, False][1])


def test_the_report_says_what_the_detail_step_did():
    from mideepbasis.reporting import detail_summary

    base = {"network_size": [128, 128], "detail_added": True, "relief_test_read": True}
    assert detail_summary({**base, "detail_added": False}) == "none: the maps hold the network's 128 px answer"
    untested = detail_summary({**base, "relief_test_read": False, "normal_detail": 1.0})
    assert "reads photos of 512 px and more" in untested
    assert "all of their detail" in detail_summary({**base, "normal_detail": 1.0})
    assert "carry some of the shading" in detail_summary({**base, "normal_detail": 0.34})
    assert "shading" not in detail_summary({**base, "normal_detail": 0.0}).split("albedo:")[1]
    assert "no relief in the normals" in detail_summary({**base, "normal_detail": 0.0})
    assert "kept 34% of the normals' detail" in detail_summary({**base, "normal_detail": 0.34})
    assert "noise" not in detail_summary({**base, "normal_detail": 0.34, "detail_denoised": False})
    assert detail_summary({**base, "normal_detail": 0.34, "detail_denoised": True}).endswith(
        "the photo's noise was taken out of it first (--denoise-detail)")
    assert "other 66%" in detail_summary({**base, "normal_detail": 0.34})
    assert detail_summary({"offset": [0.0, 0.0]}) is None  # a provenance that does not say
    assert "normal unit reads" in detail_summary({**base, "normal_detail": 0.34, "fine_relief": True})
    assert "normal unit" not in detail_summary({**base, "normal_detail": 0.34})
    assert "times 2.5 (--fine-relief-strength)" in detail_summary(
        {**base, "normal_detail": 0.34, "fine_relief": True, "fine_relief_strength": 2.5})
    assert "times 0.5 (--fine-relief-strength)" in detail_summary(
        {**base, "normal_detail": 0.34, "fine_relief": True, "fine_relief_strength": 0.5})
    # A provenance that does not record the strength: the unit's whole reading.
    assert "times 1 (--fine-relief-strength)" in detail_summary({**base, "normal_detail": 0.34, "fine_relief": True})
    # Nor the mirror images: one reading.
    assert "reads in the photo, times" in detail_summary({**base, "normal_detail": 0.34, "fine_relief": True})
    assert "reads in the photo and its 3 mirror images, where they agree, times" in detail_summary(
        {**base, "normal_detail": 0.34, "fine_relief": True, "fine_relief_symmetries": 4})
    assert "its 1 mirror image, where" in detail_summary(
        {**base, "normal_detail": 0.34, "fine_relief": True, "fine_relief_symmetries": 2})
    assert "a change of hue explains (--colour-test)" in detail_summary({**base, "normal_detail": 0.34,
                                                                          "colour_tested": True})
    assert "hue" not in detail_summary({**base, "normal_detail": 0.0, "colour_tested": True})
    assert "hue" not in detail_summary({**base, "normal_detail": 0.34, "colour_tested": False})


def _matte_relief(family: str, seed: int, size: int) -> torch.Tensor:
    """(1, 10, size, size) a procedural material's relief under one matte grey albedo: what a photo
    shows of it at a finer scale than the network's is shading alone."""
    from mideepbasis.data.procedural import generate

    maps = generate(seed, size=size, family=family).to_tensor()[None]
    maps[:, constants.DIFFUSE], maps[:, constants.ROUGHNESS], maps[:, constants.SPECULAR] = 0.5, 1.0, 0.0
    return maps


@pytest.mark.parametrize("symmetries", [1, 2])
@pytest.mark.parametrize("family,seed", [("concrete", 1), ("fabric", 4)])
def test_fine_relief_reads_a_reliefs_shading_finer_than_the_network(family, seed, symmetries):
    from mideepbasis.evaluation import above_band
    from mideepbasis.model.checkpoint import load_model

    model = load_model()
    size, network = 512, model.info.training_size
    maps = _matte_relief(family, seed, size)
    photo, light = _flash_photo(maps)
    slope = detail.fine_relief(model, photo[None], light, constants.DEFAULT_FOV_DEG, (network, network),
                               symmetries=symmetries)
    assert slope.shape == (1, 2, size, size)
    true_fine = above_band(maps[:, 0:2] / maps[:, 2:3], network)  # the true slopes above the network's band
    correlation = float((slope * true_fine).sum() / (slope.square().sum() * true_fine.square().sum()).sqrt())
    assert correlation > TOLERANCES["fine_relief_correlation"]


def _random_slopes(count: int, seed: int, size: int = 48) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return [torch.randn(1, 2, size, size, generator=generator) for _ in range(count)]


def test_mirror_agreement_is_one_where_readings_agree_a_quarter_for_four_unrelated_and_0_where_they_cancel():
    reading = _random_slopes(1, 0)[0]
    assert torch.allclose(detail.mirror_agreement([reading] * 4), torch.ones(1, 1, 48, 48), atol=1e-5)
    assert float(detail.mirror_agreement([reading, -reading]).abs().max()) < 1e-6
    unrelated = detail.mirror_agreement(_random_slopes(4, 1))
    # (17 x 17 windows of 2 channels: the ratio's spread is about 0.03.)
    assert abs(float(unrelated.mean()) - 0.25) < 0.02 and float(unrelated.max()) < 0.5


def _plane_gradient(image: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) the central-difference gradient of an image's mean along the plane's x (columns)
    and y (against the rows), the edges repeated: it mirrors with the image."""
    level = F.pad(image.mean(dim=1, keepdim=True), (1, 1, 1, 1), mode="replicate")
    along_x = (level[..., 1:-1, 2:] - level[..., 1:-1, :-2]) / 2
    along_y = (level[..., :-2, 1:-1] - level[..., 2:, 1:-1]) / 2
    return torch.cat([along_x, along_y], dim=1)


@pytest.mark.parametrize("count", [2, 4])
def test_the_mirror_images_readings_of_a_reading_that_mirrors_are_the_reading(count):
    photo = torch.rand(1, 3, 40, 56, generator=torch.Generator().manual_seed(2))
    lights = torch.tensor([[0.3, -0.2, 2.4]])

    def mirroring(image: torch.Tensor, flashes: torch.Tensor) -> torch.Tensor:
        # The image's gradient and the flash's direction across the plane: both mirror with the photo.
        return _plane_gradient(image) + 0.1 * flashes[:, :2, None, None]

    readings = detail.symmetric_readings(mirroring, photo, lights, count)
    assert len(readings) == count
    for reading in readings:
        torch.testing.assert_close(reading, mirroring(photo, lights), atol=1e-6, rtol=0)

    def fixed(image: torch.Tensor, flashes: torch.Tensor) -> torch.Tensor:
        # A slope along +x whatever the photo: what the photo's mirror images must cancel.
        return torch.tensor([1.0, 0.0]).view(1, 2, 1, 1).expand(1, 2, *image.shape[-2:])

    moved_back = detail.symmetric_readings(fixed, photo, lights, count)
    assert float((sum(moved_back) / count).abs().max()) == 0.0


def test_fine_relief_reads_mirror_images_only():
    with pytest.raises(ValueError, match="fine_relief reads 1, 2 or 4 mirror images, got 8"):
        detail.fine_relief(None, torch.zeros(1, 3, 64, 64), torch.tensor([0.0, 0.0, 2.4]), 45.0, (32, 32),
                           symmetries=8)


def test_fine_relief_runs_at_most_at_its_size_on_a_multiple_of_the_units_levels(monkeypatch):
    from mideepbasis.model.checkpoint import load_model

    model = load_model()
    seen = []
    relief_inputs = model.relief_inputs
    monkeypatch.setattr(model, "relief_inputs", lambda photo, *rest: seen.append(photo.shape[-2:]) or
                        relief_inputs(photo, *rest))
    photo = torch.full((1, 3, 300, 200), 0.3)
    slope = detail.fine_relief(model, photo, torch.tensor([0.1, 0.2, 2.4]), constants.DEFAULT_FOV_DEG, (64, 64),
                               max_size=256)
    # 300 x 200 scaled by 256 / 300 (256 x 170.7) and cut to multiples of 32 (the unit's 4 levels, 2 octaves).
    assert seen == [torch.Size([256, 160])] and slope.shape == (1, 2, 256, 160)


def test_a_fine_slope_takes_the_normals_gains_place_as_it_is():
    """``fine_relief`` weighs its slope by the relief test's gain itself: ``add_detail`` adds it as it
    is, whatever the gain it scales the normals' gains by."""
    albedo, photo = textured_scene(4)
    low, maps = upsampled_answer(albedo)
    generator = torch.Generator().manual_seed(5)
    slope = 0.05 * torch.randn(1, 2, SIZE // 2, SIZE // 2, generator=generator)  # at half the working size
    slope = slope - upsample_bilinear(downsample(slope, LOW), SIZE // 2, SIZE // 2)

    def tilts(normal_gain: float, fine_slope: torch.Tensor | None) -> torch.Tensor:
        detailed = detail.add_detail(maps.clone(), photo, low, normal_gain=normal_gain, fine_slope=fine_slope)
        return detailed[:, 0:2] / detailed[:, 2:3]

    flat = tilts(0.0, None)  # the normals as upsampled: the network's answer has flat normals here
    expected = upsample_bilinear(slope, SIZE, SIZE)
    expected = expected - upsample_bilinear(downsample(expected, LOW), SIZE, SIZE)  # what capture keeps below
    for gain in (1.0, 0.5, 0.0):
        added = tilts(gain, slope) - flat
        assert torch.allclose(added, expected, atol=TOLERANCES["fine_slope_kept"])
    # The reflectance is the same with the fine slope as without it.
    with_slope = detail.add_detail(maps.clone(), photo, low, fine_slope=slope)
    without = detail.add_detail(maps.clone(), photo, low)
    assert torch.equal(with_slope[:, constants.REFLECTANCE], without[:, constants.REFLECTANCE])


def _alternating_field(amplitude: torch.Tensor) -> torch.Tensor:
    """(1, 2, H, W) a slope of the given amplitude (1, 1, H, W) at each pixel whose sign alternates
    from pixel to pixel (x in a checkerboard, y from row to row): its RMS per axis in any window is
    the amplitude's there, and its mean over any block of even sides, where the amplitude is one, 0."""
    rows = torch.arange(amplitude.shape[-2]).view(-1, 1)
    columns = torch.arange(amplitude.shape[-1]).view(1, -1)
    signs = torch.stack([(-1.0) ** (rows + columns), (-1.0) ** rows.expand_as(rows + columns)])[None]
    return signs * amplitude


def test_steep_share_ramps_from_the_first_rms_slope_to_the_second():
    low, high = detail.STEEP_RELIEF
    for rms, share in ((0.5 * low, 0.0), (low, 0.0), ((low + high) / 2, 0.5), (high, 1.0), (2 * high, 1.0)):
        field = _alternating_field(torch.full((1, 1, 40, 40), rms))
        torch.testing.assert_close(detail.steep_share(field), torch.full((1, 1, 40, 40), share), atol=1e-5, rtol=0)


class _FixedUnit(torch.nn.Module):
    """A normal unit that reads one fixed slope whatever the photo (``fine_relief``'s interface)."""

    def __init__(self, slope: torch.Tensor):
        super().__init__()
        from types import SimpleNamespace

        self.config = SimpleNamespace(normal_unit_stride=32)
        self.slope = torch.nn.Parameter(slope, requires_grad=False)

    def relief_inputs(self, photo, lights, fov):
        return photo

    def octave_slope(self, inputs):
        return self.slope


def test_fine_relief_weighs_a_shallow_reading_by_the_gain_and_the_diffuse_share_and_a_steep_one_by_neither():
    size, low_size = 128, (8, 8)
    low, high = detail.STEEP_RELIEF
    # Shallow on the left half, steep on the right; alternating from pixel to pixel, so nothing of
    # it lies at or below the network's band (8 px) to be taken out.
    amplitude = torch.full((1, 1, size, size), 0.5 * low)
    amplitude[..., size // 2:] = 2 * high
    slope = _alternating_field(amplitude)
    unit = _FixedUnit(slope)
    photo, light = torch.full((1, 3, size, size), 0.3), torch.tensor([0.1, 0.2, 2.4])
    matte = torch.full((16, 16), 0.5)
    read = detail.fine_relief(unit, photo, light, 45.0, low_size, matte=matte, gain=0.4, strength=2.0)
    margin = detail.STEEP_RADIUS + 1  # the windows of the steepness reach across the border
    shallow, steep = (..., slice(0, size // 2 - margin)), (..., slice(size // 2 + margin, size))
    weight = 0.4 * 0.5 ** detail.FINE_RELIEF_MATTE_POWER
    torch.testing.assert_close(read[shallow], 2.0 * weight * slope[shallow], atol=1e-5, rtol=0)
    torch.testing.assert_close(read[steep], 2.0 * slope[steep], atol=1e-5, rtol=0)


def test_with_a_fine_slope_a_metal_keeps_the_normals_gains_detail_and_a_dielectric_none():
    """The fine slope reads the diffuse's shading and a metal has none: there the normals keep the
    photo's contrast times their gains, as without a fine slope; a dielectric gets the slope alone."""
    albedo, photo = textured_scene(4)
    low, _ = upsampled_answer(albedo)
    # The network's normals follow the photo's contrast at its resolution: the gains read relief.
    level = downsample(photo, LOW).mean(dim=1, keepdim=True)
    smooth = gaussian_blur(level, detail.LOW_SIGMA, padding="replicate")
    low[:, 0:1] = 0.5 * (level - smooth) / smooth
    low[:, constants.NORMAL] = low[:, constants.NORMAL] / low[:, constants.NORMAL].norm(dim=1, keepdim=True)
    # The left half a metal (no diffuse, a bright specular: metallic share 1), the right half a
    # dielectric (specular 0.04: metallic share 0).
    low[..., : LOW // 2][:, constants.DIFFUSE] = 0.0
    low[..., : LOW // 2][:, constants.SPECULAR] = 0.9
    maps = upsample_bilinear(low, SIZE, SIZE)
    shares = detail.metallic_shares(low)[0, 0]
    assert torch.allclose(shares[:, : LOW // 2], torch.ones(LOW, LOW // 2), atol=1e-6)
    assert torch.equal(shares[:, LOW // 2:], torch.zeros(LOW, LOW // 2))

    def added_tilts(fine_slope: torch.Tensor | None) -> torch.Tensor:
        detailed = detail.add_detail(maps.clone(), photo, low, fine_slope=fine_slope)
        return detailed[:, 0:2] / detailed[:, 2:3] - maps[:, 0:2] / maps[:, 2:3]

    gains_detail = added_tilts(None)
    with_slope = added_tilts(torch.zeros(1, 2, SIZE, SIZE))
    margin = 2 * SIZE // LOW  # the gains are upsampled across the border between the halves
    metal, dielectric = slice(margin, SIZE // 2 - margin), slice(SIZE // 2 + margin, SIZE - margin)
    assert float(gains_detail[..., metal].square().mean().sqrt()) > 0.01  # the gains read relief here
    assert float(gains_detail[..., dielectric].square().mean().sqrt()) > 0.01
    assert torch.allclose(with_slope[..., metal], gains_detail[..., metal], atol=TOLERANCES["fine_slope_kept"])
    assert float(with_slope[..., dielectric].abs().max()) < TOLERANCES["fine_slope_kept"]


def _model_with_a_small_normal_unit(tmp_path) -> torch.nn.Module:
    """A tiny network with a small normal unit, random weights of seed 0, as a checkpoint loads it."""
    from dataclasses import replace

    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    config = replace(preset("tiny"), normal_unit_width=4, normal_unit_blocks=(1, 1, 1), normal_unit_octaves=(1.0, 0.5))
    return save_checkpoint(tmp_path / "unit.safetensors", DeepBasisNet(config).eval())


def test_capture_reads_the_fine_relief_when_asked_from_four_times_the_network_size_where_the_test_reads_relief(
        tmp_path):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    model = _model_with_a_small_normal_unit(tmp_path)
    used = {}
    for surface, make in (("relief", lambda size: matte_egg_crate(size, cycles=24, slope=0.15)),
                          ("grain", _plain_grain)):
        for size in (128, 64):
            photo, _ = _flash_photo(make(size))
            for fine in (True, False):
                capture_config = CaptureConfig(light=(0.25, -0.15), resolution=size, network_resolution=LOW,
                                               symmetries=1, refine=RefineConfig(steps=0), fine_relief=fine)
                provenance = Capturer(model, capture_config).capture(photo).material.provenance["capture"]
                used[surface, size, fine] = provenance["fine_relief"], provenance["normal_detail"] > 0
    # Read only when asked, from 4 times the network's size on, and where the relief test keeps relief.
    assert {key: value[0] for key, value in used.items() if value[0]} == {("relief", 128, True): True}
    assert used["relief", 128, True][1] and not used["grain", 128, True][1]


def _fine_relief_calls(monkeypatch) -> list[dict]:
    """The keyword arguments of each call capture makes to ``fine_relief`` from here on (it still runs)."""
    from mideepbasis.capturing import pipeline

    calls = []
    fine_relief = pipeline.fine_relief
    monkeypatch.setattr(pipeline, "fine_relief", lambda *args, **kwargs: calls.append(kwargs)
                        or fine_relief(*args, **kwargs))
    return calls


def test_capture_reads_as_many_mirror_images_for_the_fine_relief_as_its_symmetries_up_to_two(tmp_path,
                                                                                           monkeypatch):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    model = _model_with_a_small_normal_unit(tmp_path)
    photo, _ = _flash_photo(matte_egg_crate(128, cycles=24, slope=0.15))
    calls = _fine_relief_calls(monkeypatch)
    for symmetries in (1, 2, 8):
        capture_config = CaptureConfig(light=(0.25, -0.15), resolution=128, network_resolution=LOW,
                                       symmetries=symmetries, refine=RefineConfig(steps=0))
        Capturer(model, capture_config).capture(photo)
    asked = [call["symmetries"] for call in calls]
    assert asked == [1, 2, detail.FINE_RELIEF_SYMMETRIES] and detail.FINE_RELIEF_SYMMETRIES == 2


def test_capture_gives_the_fine_relief_the_relief_tests_gain_to_weigh_its_reading_by(tmp_path, monkeypatch):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig, pipeline

    model = _model_with_a_small_normal_unit(tmp_path)
    photo, _ = _flash_photo(matte_egg_crate(128, cycles=24, slope=0.15))
    calls = _fine_relief_calls(monkeypatch)
    # A gain of its own, so that what reaches the fine relief is told from a 1 it might be given.
    monkeypatch.setattr(pipeline, "photo_relief_gain", lambda *args, **kwargs: 0.37)
    capture_config = CaptureConfig(light=(0.25, -0.15), resolution=128, network_resolution=LOW, symmetries=1,
                                   refine=RefineConfig(steps=0))
    provenance = Capturer(model, capture_config).capture(photo).material.provenance["capture"]
    assert [call["gain"] for call in calls] == [0.37] and provenance["normal_detail"] == 0.37


def test_the_fine_relief_strength_scales_the_relief_capture_adds_above_the_network(tmp_path):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    model = _model_with_a_small_normal_unit(tmp_path)
    photo, _ = _flash_photo(matte_egg_crate(128, cycles=24, slope=0.15))

    def fine_tilts(strength: float) -> torch.Tensor:
        """(2, 128, 128) the captured normals' tilt above the network's band."""
        capture_config = CaptureConfig(light=(0.25, -0.15), resolution=128, network_resolution=LOW, symmetries=1,
                                       refine=RefineConfig(steps=0), fine_relief=True, fine_relief_strength=strength)
        result = Capturer(model, capture_config).capture(photo)
        assert result.material.provenance["capture"]["fine_relief_strength"] == strength
        normals = result.material.to_tensor()[constants.NORMAL]
        tilts = normals[0:2] / normals[2:3]
        return tilts - upsample_bilinear(downsample(tilts[None], (LOW, LOW)), 128, 128)[0]

    without, read = fine_tilts(0.0), fine_tilts(1.0)
    added = read - without
    assert float(added.square().mean().sqrt()) > 1e-3  # the unit reads relief here
    # The relief added is linear in the strength (to first order in the slope, as normals add it).
    for strength in (0.5, 2.5):
        scaled = fine_tilts(strength) - without
        assert float((scaled - strength * added).square().mean().sqrt()) < 0.01 * strength * float(
            added.square().mean().sqrt())


def test_a_negative_fine_relief_strength_is_refused(capsys):
    from mideepbasis.capturing import CaptureConfig
    from mideepbasis.cli import main

    with pytest.raises(ValueError, match="fine_relief_strength must be 0 or more, got -1"):
        CaptureConfig(fine_relief_strength=-1.0)
    with pytest.raises(SystemExit):
        main(["capture", "photo.jpg", "-o", "out", "--fine-relief-strength", "-1"])
    assert "--fine-relief-strength: must be 0 or more, got -1" in capsys.readouterr().err


def test_a_fine_relief_strength_without_the_fine_relief_is_refused_in_one_line(tmp_path, capsys):
    from mideepbasis.capturing import CaptureConfig
    from mideepbasis.cli import main
    from mideepbasis.evaluation import EvaluationConfig

    message = "fine_relief_strength 3 applies only with fine_relief (not with --no-fine-relief)"
    with pytest.raises(ValueError, match=re.escape(message)):
        CaptureConfig(fine_relief=False, fine_relief_strength=3.0)
    with pytest.raises(ValueError, match=re.escape(message)):
        EvaluationConfig(data="d", fine_relief=False, fine_relief_strength=3.0)
    assert CaptureConfig(fine_relief_strength=3.0).fine_relief_strength == 3.0  # the fine relief is on by default
    assert EvaluationConfig(data="d", fine_relief_strength=3.0).fine_relief_strength == 3.0
    assert CaptureConfig(fine_relief=False).fine_relief_strength == detail.FINE_RELIEF_STRENGTH
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"")  # never read: the options are refused first
    assert main(["capture", str(photo), "-o", str(tmp_path / "out"), "--no-fine-relief",
                 "--fine-relief-strength", "3"]) != 0
    assert main(["evaluate", "--data", str(tmp_path), "-o", str(tmp_path / "evaluated"), "--no-fine-relief",
                 "--fine-relief-strength", "3"]) != 0
    errors = capsys.readouterr().err.strip().splitlines()
    assert errors == [f"mideepbasis: error: capture: {message}", f"mideepbasis: error: evaluate: {message}"]
    assert not (tmp_path / "out").exists() and not (tmp_path / "evaluated").exists()


def test_the_colour_test_under_the_fine_relief_is_refused_in_one_line(tmp_path, capsys):
    from mideepbasis.capturing import CaptureConfig
    from mideepbasis.cli import main

    message = "colour_test applies only without fine_relief (with --no-fine-relief)"
    with pytest.raises(ValueError, match=re.escape(message)):
        CaptureConfig(colour_test=True)
    assert CaptureConfig(fine_relief=False, colour_test=True).colour_test
    assert main(["capture", str(tmp_path / "photo.jpg"), "-o", str(tmp_path / "out"), "--colour-test"]) != 0
    assert capsys.readouterr().err.strip() == f"mideepbasis: error: capture: {message}"
    assert not (tmp_path / "out").exists()


def test_a_relief_reader_reads_the_fine_relief_in_the_units_place(tmp_path, capsys):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig
    from mideepbasis.capturing.pipeline import flash_position
    from mideepbasis.cli import main
    from mideepbasis.model.relief_reader import ReliefReader, ReliefReaderConfig, read_relief, save_reader

    model = _model_with_a_small_normal_unit(tmp_path)
    reader = ReliefReader(ReliefReaderConfig(width=4, encoder_blocks=(1, 1), middle_blocks=1))
    with torch.no_grad():  # a reader that reads a strong relief from anything
        reader.net.ending.bias.fill_(0.2)
    weights = save_reader(tmp_path / "reader.safetensors", reader)
    photo, _ = _flash_photo(matte_egg_crate(128, cycles=24, slope=0.15))
    captured = {}
    for name, options in (("unit", {}), ("reader", {"relief_reader": str(weights)})):
        capture_config = CaptureConfig(light=(0.25, -0.15), resolution=128, network_resolution=LOW, symmetries=1,
                                       refine=RefineConfig(steps=0), fine_relief=True, **options)
        capturer = Capturer(model, capture_config)
        loaded = capturer.photo_from_tensor(photo)
        captured[name] = capturer.predict(loaded, (0.25, -0.15))
    fov, light = constants.DEFAULT_FOV_DEG, flash_position((0.25, -0.15), constants.DEFAULT_FOV_DEG)
    low_maps = captured["reader"].output.maps[:1].detach()
    matte = detail.matte_share(low_maps, light, fov, capturer.convention, capturer.model.config.plane_extent)
    # The reader's slope, weighted by the diffuse's share as the unit's is.
    expected = read_relief(reader, photo[None], light, fov, (LOW, LOW)) * upsample_bilinear(
        matte[None, None] ** detail.FINE_RELIEF_MATTE_POWER, 128, 128) * capture_config.fine_relief_strength
    read = captured["reader"].fine_slope
    assert float(expected.abs().max()) > 0.01
    assert torch.allclose(read, expected, atol=1e-6)
    assert not torch.allclose(read, captured["unit"].fine_slope, atol=1e-3)
    assert capturer.capture(photo).material.provenance["capture"]["relief_reader"] == "reader.safetensors"
    message = "relief_reader r.safetensors applies only with fine_relief (not with --no-fine-relief)"
    with pytest.raises(ValueError, match=re.escape(message)):
        CaptureConfig(fine_relief=False, relief_reader="r.safetensors")
    assert main(["capture", str(tmp_path / "photo.png"), "-o", str(tmp_path / "out"), "--no-fine-relief",
                 "--relief-reader", "r.safetensors"]) != 0
    assert capsys.readouterr().err.strip() == f"mideepbasis: error: capture: {message}"


def test_fine_relief_is_weighted_by_the_diffuse_share_to_its_power(monkeypatch):
    from mideepbasis.model.checkpoint import load_model

    # No reading counts as steep here: steep relief, which no weight holds back, is tested on its own.
    monkeypatch.setattr(detail, "STEEP_RELIEF", (1e6, 2e6))
    model = load_model()
    photo, light = _flash_photo(_matte_relief("concrete", 1, 128))

    def read(matte: torch.Tensor | None) -> torch.Tensor:
        return detail.fine_relief(model, photo[None], light, constants.DEFAULT_FOV_DEG, (32, 32), matte=matte)

    whole = read(None)
    assert float(whole.abs().max()) > 0.0
    assert torch.allclose(read(torch.ones(32, 32)), whole)
    half = read(torch.full((32, 32), 0.5))
    assert torch.allclose(half, whole * 0.5**detail.FINE_RELIEF_MATTE_POWER, atol=1e-7)
    # A highlight over the left half (no diffuse share there) leaves its relief out.
    left_dark = torch.ones(32, 32)
    left_dark[:, :12] = 0.0
    sided = read(left_dark)
    assert float(sided[..., :40].abs().max()) == 0.0 and torch.equal(sided[..., 56:], whole[..., 56:])


# --- the lobe's peak under the normals' detail -------------------------------------------------------

def _ggx_peak(alpha: torch.Tensor, tilt2: torch.Tensor) -> torch.Tensor:
    """pi D(m) of GGX, alpha^2 / ((n.m)^2 (alpha^2 - 1) + 1)^2, for m along the untilted normal and
    the microfacet normal n tilted from it by an angle of squared tangent ``tilt2`` (float64)."""
    cos2 = 1.0 / (1.0 + tilt2.double())
    alpha2 = alpha.double() ** 2
    return alpha2 / (cos2 * (alpha2 - 1.0) + 1.0) ** 2


def test_lobe_peak_is_the_ggx_distribution_at_the_untilted_normals_half_vector():
    alpha = torch.tensor([0.01, 0.1, 0.5, 1.0]).view(-1, 1)
    tilt2 = torch.tensor([0.0, 1e-4, 0.01, 0.3, 4.0]).view(1, -1)
    expected = _ggx_peak(alpha, tilt2)
    assert torch.allclose(detail.lobe_peak(alpha**2, tilt2).double(), expected, rtol=1e-5)


def _block_mean(image: torch.Tensor, block: int) -> torch.Tensor:
    return F.avg_pool2d(image, block)


def test_lobe_peak_factors_keep_each_pixels_mean_peak_with_the_widest_lobe():
    block, blocks = 8, 3
    size = block * blocks
    generator = torch.Generator().manual_seed(6)
    roughness = 0.3 + 0.05 * torch.rand(1, 1, size, size, generator=generator)
    tilt2 = torch.zeros(1, 1, size, size)
    # Row 0: no tilt; row 1: Gaussian tilts of growing spread; row 2: one steep pixel in 64.
    for column, spread in enumerate((0.01, 0.02, 0.04)):
        slopes = spread * torch.randn(2, block, block, generator=generator)
        tilt2[0, 0, block:2 * block, column * block:(column + 1) * block] = slopes.square().sum(dim=0)
    tilt2[0, 0, 2 * block::block, ::block] = 1.0
    factors = detail.lobe_peak_factors(roughness, tilt2, (blocks, blocks))
    assert torch.equal(factors[0, 0, 0], torch.ones(blocks))
    alpha = roughness.double() ** 2
    target = _block_mean(1.0 / alpha**2, block)
    spread = F.interpolate(factors.double(), scale_factor=block, mode="nearest")
    kept = _block_mean(_ggx_peak(spread * alpha, tilt2), block)
    wider = _block_mean(_ggx_peak(spread * 1.01 * alpha, tilt2), block)
    tilted = torch.ones(blocks, blocks, dtype=torch.bool)
    tilted[0] = False
    # The narrowed lobe keeps the mean peak (to the factors' linear reading) and a 1 % wider one does not.
    assert torch.all(kept[0, 0][tilted] >= target[0, 0][tilted] * (1 - 2e-3))
    assert torch.all(wider[0, 0][tilted] < target[0, 0][tilted])
    # The more the tilts spread, the narrower the lobe.
    assert factors[0, 0, 1, 0] > factors[0, 0, 1, 1] > factors[0, 0, 1, 2]
    assert float(factors[0, 0, 1, 2]) > detail.NARROWEST_LOBE
    # One steep pixel in 64 leaves the peak (its lobe points away) rather than widening it: about
    # 1/64 of the peak to make up, alpha^2 -> 63/64 alpha^2, where a slope variance of 1/64 taken from
    # alpha^2 (at most 0.35^4 here) would leave nothing.
    assert factors[0, 0, 2] == pytest.approx(torch.full((blocks,), (63 / 64) ** 0.5), abs=5e-3)


def test_lobe_peak_factors_leave_a_lobe_whose_every_pixel_is_tilted_far_beyond_it():
    # Every pixel tilted by 63 deg under a rough lobe: narrowing only dims the tilted peaks more, so the
    # width whose mean peak comes nearest the untilted one is the lobe's own.
    roughness = torch.full((1, 1, 8, 8), 0.9)
    tilt2 = torch.full((1, 1, 8, 8), 4.0)
    assert torch.equal(detail.lobe_peak_factors(roughness, tilt2, (1, 1)), torch.ones(1, 1, 1, 1))


def test_the_roughness_keeps_each_network_pixels_mean_lobe_peak_under_the_normals_detail():
    albedo, photo = textured_scene(4)
    low, maps = upsampled_answer(albedo)  # flat normals, roughness 0.4
    generator = torch.Generator().manual_seed(7)
    slope = 0.05 * torch.randn(1, 2, SIZE, SIZE, generator=generator)
    slope = slope - upsample_bilinear(downsample(slope, LOW), SIZE, SIZE)
    strength = 0.75  # the normals' slopes as capture renders them

    def detailed(keep: bool) -> torch.Tensor:
        return detail.add_detail(maps.clone(), photo, low, fine_slope=slope, keep_lobe_peak=keep, slope_scale=strength)

    plain, kept = detailed(False), detailed(True)
    rough = constants.ROUGHNESS
    assert torch.equal(kept[:, :rough.start], plain[:, :rough.start])
    assert torch.equal(kept[:, rough.stop:], plain[:, rough.stop:])
    assert torch.all(kept[:, rough] <= plain[:, rough] + 1e-6) and float(kept[:, rough].mean()) < 0.39
    # Each network pixel's mean GGX peak under the rendered tilts (the normals were flat before).
    tilt2 = (strength * kept[:, 0:2] / kept[:, 2:3]).square().sum(dim=1, keepdim=True)
    block = SIZE // LOW
    target = _block_mean(1.0 / (plain[:, rough].double() ** 2) ** 2, block)
    ratio = lambda m: _block_mean(_ggx_peak(m[:, rough] ** 2, tilt2), block) / target  # noqa: E731
    assert float(ratio(plain).mean()) < 0.9  # the detail dims the peak
    # Kept on average; pixel by pixel to the factors' bilinear upsampling, which mixes neighbours'.
    assert float(ratio(kept).mean()) == pytest.approx(1.0, abs=TOLERANCES["lobe_peak_mean"])
    assert torch.allclose(ratio(kept), torch.ones_like(target), atol=TOLERANCES["lobe_peak_pixel"])


def test_bands_of_rows_give_the_whole_image_keeping_the_lobe_peak(monkeypatch):
    albedo, photo = textured_scene(2)
    low, maps = upsampled_answer(albedo)
    slope = 0.05 * torch.randn(1, 2, SIZE, SIZE, generator=torch.Generator().manual_seed(8))
    whole = detail.add_detail(maps.clone(), photo, low, fine_slope=slope, keep_lobe_peak=True)
    monkeypatch.setattr(detail, "BAND_PIXELS", SIZE * 24)  # bands of 24 rows
    banded = detail.add_detail(maps.clone(), photo, low, fine_slope=slope, keep_lobe_peak=True)
    assert torch.allclose(banded, whole, atol=1e-5)
    assert not torch.allclose(whole[:, constants.ROUGHNESS], maps[:, constants.ROUGHNESS], atol=1e-3)


def test_the_lobe_peak_is_kept_at_a_size_that_is_no_multiple_of_the_networks():
    albedo, photo = textured_scene(1)
    low, _ = upsampled_answer(albedo)
    height, width = 200, 256
    photo, maps = downsample(photo, (height, width)), upsample_bilinear(low, height, width)
    slope = 0.05 * torch.randn(1, 2, height, width, generator=torch.Generator().manual_seed(9))
    kept = detail.add_detail(maps.clone(), photo, low, fine_slope=slope, keep_lobe_peak=True)
    plain = detail.add_detail(maps.clone(), photo, low, fine_slope=slope)
    assert kept.shape == (1, 10, height, width)
    assert float(kept[:, constants.ROUGHNESS].mean()) < float(plain[:, constants.ROUGHNESS].mean()) - 0.005


def test_capture_keeps_the_refined_lobes_peak_unless_told_not_to(tiny_checkpoint):
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig

    size = 256
    photo, _ = _flash_photo(matte_egg_crate(size, cycles=24, slope=0.15))
    results = {}
    for keep in (True, False):
        config = CaptureConfig(light=(0.25, -0.15), resolution=size, network_resolution=LOW, symmetries=1,
                               refine=RefineConfig(steps=2), keep_lobe_peak=keep)
        capturer = Capturer(tiny_checkpoint, config)
        material = capturer.capture(photo).material
        results[keep] = material.provenance["capture"]["lobe_peak_kept"], material.to_tensor()
        # The network's own roughness, unrefined, is left as it is: only the refined lobe is narrowed.
        loaded = capturer.photo_from_tensor(photo)
        assert not capturer.predict(loaded, config.light).keep_lobe_peak
    assert results[True][0] is True and results[False][0] is False
    # At twice the network's size (one octave of detail) the lobe is left as refined.
    config = CaptureConfig(light=(0.25, -0.15), resolution=2 * LOW, network_resolution=LOW, symmetries=1,
                           refine=RefineConfig(steps=2))
    small = downsample(photo[None], 2 * LOW)[0]  # a tensor photo is taken at its own size
    assert Capturer(tiny_checkpoint, config).capture(small).material.provenance["capture"]["lobe_peak_kept"] is False
    kept, unkept = results[True][1], results[False][1]
    rough = constants.ROUGHNESS
    others = [channel for channel in range(kept.shape[0]) if channel != rough.start]
    assert torch.allclose(kept[others], unkept[others], atol=1e-6)  # two refinements: to float rounding
    assert torch.all(kept[rough] <= unkept[rough] + 1e-6) and float((unkept[rough] - kept[rough]).mean()) > 1e-4
