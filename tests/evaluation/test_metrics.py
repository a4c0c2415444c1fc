"""evaluation/metrics.py, each metric against an independent reference (issue 12 section 3).

The references are computed here with plain math, NumPy or torch: closed forms (constant and
checkerboard images for SSIM, constant images for FLIP's colour pipeline, offsets at known angles
for the light error), a direct per-window SSIM, the shading formulas of
``mideepbasis/render/shading.py``'s docstring evaluated by hand per pixel, and a functional LPIPS.
None of them calls the function it checks. ``tests/evaluation/test_run.py`` holds the older hand-computed
cases (identical inputs, a diffuse and a tilted-normal map RMSE, SSIM of two constants, a 10 degree
light error, the trivial baseline's diffuse mean, LPIPS plumbing).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mideepbasis import constants
from mideepbasis.evaluation import (LPIPS, Scores, detail_ratio, flip, high_band_energy, light_error_deg, map_rmse,
                                    rerender, rerender_rmse, score, ssim, ssim_map, summary_scores, trivial_baseline)
from mideepbasis.resampling import downsample, upsample_bilinear

#: (rtol, atol) per comparison, Kornia style: float64 closed forms are tight; renders are float32 on
#: the Mitsuba side and sRGB-encoded (slope up to 12.92); FLIP's library works in float32.
TOLERANCE = {
    "float64": (1e-9, 1e-12),
    "ssim": (1e-9, 1e-10),
    "render": (0.0, 1e-5),
    "rmse": (1e-4, 1e-6),
    "flip": (1e-3, 1e-4),
    "lpips": (1e-4, 1e-6),
}


def assert_close(actual, expected, kind):
    rtol, atol = TOLERANCE[kind]
    torch.testing.assert_close(torch.as_tensor(actual, dtype=torch.float64),
                               torch.as_tensor(expected, dtype=torch.float64), rtol=rtol, atol=atol)


def material(size=16, normal=(0.0, 0.0, 1.0), diffuse=(0.5, 0.5, 0.5), roughness=0.5, specular=(0.0, 0.0, 0.0)):
    maps = torch.zeros(1, 10, size, size)
    maps[0, 0:3] = torch.tensor(normal).view(3, 1, 1)
    maps[0, 3:6] = torch.tensor(diffuse).view(3, 1, 1)
    maps[0, 6] = roughness
    maps[0, 7:10] = torch.tensor(specular).view(3, 1, 1)
    return maps


# --- light_error_deg -----------------------------------------------------------------------------------

def _height(fov_deg):
    # The sample [-1, 1] fills the frame: half-width 1 seen under half the field of view.
    return 1.0 / math.tan(math.radians(fov_deg) / 2)


LIGHT_CASES = [
    # (estimate, truth, fov, expected angle [deg] by hand)
    ((0.0, 0.0), (0.0, 0.0), 45.0, 0.0),
    ((0.3, -0.2), (0.3, -0.2), 45.0, 0.0),
    # Symmetric about the centre: twice the offset's angle atan(t / H).
    ((0.5, 0.0), (-0.5, 0.0), 45.0, 2 * math.degrees(math.atan(0.5 / _height(45.0)))),
    ((0.0, 0.4), (0.0, -0.4), 45.0, 2 * math.degrees(math.atan(0.4 / _height(45.0)))),
    # Orthogonal offsets of equal length t: cos = H^2 / (t^2 + H^2).
    ((0.6, 0.0), (0.0, 0.6), 45.0, math.degrees(math.acos(_height(45.0) ** 2 / (0.36 + _height(45.0) ** 2)))),
    # Another field of view: H = 1 / tan(30 deg) = sqrt(3), an offset seen at 12 degrees.
    ((math.sqrt(3) * math.tan(math.radians(12.0)), 0.0), (0.0, 0.0), 60.0, 12.0),
    # Collinear offsets on one side: the difference of their angles.
    ((0.0, 0.8), (0.0, 0.3), 30.0,
     math.degrees(math.atan(0.8 / _height(30.0)) - math.atan(0.3 / _height(30.0)))),
]


@pytest.mark.parametrize("estimate, truth, fov, expected", LIGHT_CASES)
def test_light_error_against_plain_trigonometry(estimate, truth, fov, expected):
    assert light_error_deg(estimate, truth, fov) == pytest.approx(expected, abs=1e-6)
    assert light_error_deg(truth, estimate, fov) == pytest.approx(expected, abs=1e-6)


def test_light_error_of_batches_is_per_row():
    estimates = torch.tensor([[0.5, 0.0], [0.6, 0.0], [0.1, 0.1]])
    truths = torch.tensor([[-0.5, 0.0], [0.0, 0.6], [0.1, 0.1]])
    expected = [case[3] for case in (LIGHT_CASES[2], LIGHT_CASES[4])] + [0.0]
    angles = light_error_deg(estimates, truths)
    assert isinstance(angles, torch.Tensor) and angles.shape == (3,)
    assert_close(angles, expected, "rmse")


# --- map_rmse -------------------------------------------------------------------------------------------

MAP_CASES = [
    # (map, channels changed, delta, pixels changed as a fraction, expected RMSE by hand)
    # Normals are stored as (n + 1) / 2: a normal difference d is d / 2 in the stored encoding.
    ("normal", (0, 1, 2), 0.3, 1.0, 0.15),
    ("normal", (1,), 0.4, 1.0, 0.2 / math.sqrt(3)),
    ("diffuse", (3, 4, 5), 0.25, 1.0, 0.25),
    ("diffuse", (4,), 0.3, 1.0, 0.3 / math.sqrt(3)),
    ("roughness", (6,), 0.2, 1.0, 0.2),
    ("roughness", (6,), 0.2, 0.25, 0.1),  # a quarter of the pixels: sqrt(0.04 / 4)
    ("specular", (7, 8, 9), 0.06, 1.0, 0.06),
    ("specular", (9,), 0.6, 0.25, math.sqrt(0.36 / 4 / 3)),
]


@pytest.mark.parametrize("name, channels, delta, fraction, expected", MAP_CASES)
def test_map_rmse_of_known_differences(name, channels, delta, fraction, expected):
    generator = torch.Generator().manual_seed(1)
    truth = torch.rand(2, 10, 8, 8, generator=generator, dtype=torch.float64) * 0.5
    predicted = truth.clone()
    side = {1.0: 8, 0.25: 4}[fraction]  # the top-left side x side pixels of 8 x 8
    predicted[0, list(channels), :side, :side] += delta  # material 0 only; material 1 stays exact
    errors = map_rmse(predicted, truth)
    assert set(errors) == {"normal", "diffuse", "roughness", "specular"}
    for other, values in errors.items():
        assert values.shape == (2,)
        assert_close(values, [expected if other == name else 0.0, 0.0], "float64")


# --- high_band_energy and detail_ratio ------------------------------------------------------------------

def _one_pixel_checkerboard(size, amplitudes, means):
    """(1, 10, size, size): per channel a constant plus a +-amplitude checkerboard of 1-pixel squares.
    Area-averaging 2 x 2 blocks leaves the constant, which bilinear upsampling keeps (edges too):
    the residual above size / 2 is the checkerboard exactly, its energy amplitude^2 a channel."""
    rows, columns = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    sign = 1.0 - 2.0 * ((rows + columns) % 2).double()
    return (torch.tensor(means, dtype=torch.float64).view(1, 10, 1, 1)
            + torch.tensor(amplitudes, dtype=torch.float64).view(1, 10, 1, 1) * sign)


AMPLITUDES = (0.1, 0.2, 0.0, 0.05, 0.05, 0.1, 0.3, 0.02, 0.0, 0.01)
MEANS = (0.0, 0.0, 1.0, 0.4, 0.5, 0.3, 0.5, 0.04, 0.04, 0.04)


def test_high_band_energy_of_a_checkerboard_by_hand():
    maps = _one_pixel_checkerboard(16, AMPLITUDES, MEANS)
    energy = high_band_energy(maps, band=8)
    expected = {name: sum(AMPLITUDES[c] ** 2 for c in range(10)[channels])
                for name, channels in constants.MAP_SLICES.items()}
    for name, value in energy.items():
        assert value.shape == (1,)
        assert_close(value, [expected[name]], "float64")
    # At or below the band there is nothing above it.
    assert all(float(v[0]) == 0.0 for v in high_band_energy(maps, band=16).values())


def test_detail_ratio_is_one_zero_and_four_in_energy_on_a_checkerboard():
    truth = _one_pixel_checkerboard(16, AMPLITUDES, MEANS)
    blurred = _one_pixel_checkerboard(16, (0.0,) * 10, MEANS)  # the band-limited part alone
    doubled = _one_pixel_checkerboard(16, tuple(2 * a for a in AMPLITUDES), MEANS)
    for predicted, expected in ((truth, 1.0), (blurred, 0.0), (doubled, 4.0)):
        for value in detail_ratio(predicted, truth, band=8).values():
            assert_close(value, [expected], "float64")


def test_detail_ratio_of_a_textured_material_and_its_blur():
    # Smooth random fields (4 x 4 knots) plus strong pixel noise, 64 px, against a 16-px band: the
    # band-limited copy keeps 1/8 of its own Laplacian above the band (``high_band_energy``).
    generator = torch.Generator().manual_seed(3)
    smooth = torch.nn.functional.interpolate(torch.rand(2, 10, 4, 4, generator=generator, dtype=torch.float64),
                                             size=(64, 64), mode="bicubic", align_corners=False)
    truth = smooth + 0.2 * torch.rand(2, 10, 64, 64, generator=generator, dtype=torch.float64)
    blurred = upsample_bilinear(downsample(truth, 16), 64, 64)
    doubled = 2 * truth - blurred  # the energy above the band doubled in amplitude
    for value in detail_ratio(truth, truth, band=16).values():
        assert_close(value, [1.0, 1.0], "float64")
    for value in detail_ratio(blurred, truth, band=16).values():
        assert (value >= 0).all() and (value < 0.05).all()
    for value in detail_ratio(doubled, truth, band=16).values():
        assert ((value > 3.8) & (value < 4.0)).all()


def test_detail_ratio_is_nan_without_true_detail_and_refuses_other_sizes():
    truth = _one_pixel_checkerboard(16, (0.1,) * 6 + (0.0,) + (0.1,) * 3, MEANS)  # a constant roughness
    ratio = detail_ratio(truth, truth, band=8)
    assert math.isnan(float(ratio["roughness"][0])) and float(ratio["diffuse"][0]) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        detail_ratio(truth[..., :8, :8], truth, band=4)


# --- trivial_baseline -----------------------------------------------------------------------------------

def test_trivial_baseline_by_hand_on_a_small_set():
    # Two materials of 2 x 2 pixels, every channel a different ramp; normals tilted, to be replaced.
    materials = torch.zeros(2, 10, 2, 2, dtype=torch.float64)
    for n in range(2):
        for c in range(10):
            for i in range(2):
                for j in range(2):
                    materials[n, c, i, j] = 0.01 * (c + 1) + 0.1 * n + 0.02 * i + 0.04 * j
    materials[:, 0:3] = torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64).view(3, 1, 1)
    before = materials.clone()
    baseline = trivial_baseline(materials)
    assert baseline.shape == (10, 2, 2)
    assert torch.equal(materials, before)  # the set is left alone
    for c in range(3, 10):
        values = [0.01 * (c + 1) + 0.1 * n + 0.02 * i + 0.04 * j for n in range(2) for i in range(2) for j in range(2)]
        mean = sum(values) / len(values)  # = 0.01 (c + 1) + 0.05 + 0.01 + 0.02
        assert mean == pytest.approx(0.01 * (c + 1) + 0.08)
        assert_close(baseline[c], torch.full((2, 2), mean, dtype=torch.float64), "float64")
    for i in range(2):
        for j in range(2):
            assert baseline[0:3, i, j].tolist() == [0.0, 0.0, 1.0]


# --- rerender and rerender_rmse: the shading formulas by hand ----------------------------------------

def _srgb(linear):
    linear = linear.clamp(0.0, 1.0)
    return torch.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear.clamp(min=1e-12) ** (1 / 2.4) - 0.055)


def _pixel_points(size):
    # Pixel (row i, col j) sees (-1 + (2j + 1) / w, 1 - (2i + 1) / h, 0).
    coordinate = (2 * torch.arange(size, dtype=torch.float64) + 1) / size
    x = (coordinate - 1).view(1, size).expand(size, size)
    y = (1 - coordinate).view(size, 1).expand(size, size)
    return torch.stack([x, y, torch.zeros_like(x)], dim=-1)  # (h, w, 3)


def _unit(v):
    return v / v.norm(dim=-1, keepdim=True)


def hand_render(maps, light, view, intensity, convention):
    """Linear radiance of one material (10, h, w) under one light and one view, (3, h, w), float64:
    the formulas of render/shading.py's docstring written out per pixel."""
    maps = maps.double()
    points = _pixel_points(maps.shape[-1])
    to_light = torch.tensor(light, dtype=torch.float64) - points
    l, v = _unit(to_light), _unit(torch.tensor(view, dtype=torch.float64) - points)
    h = _unit(l + v)
    n = maps[0:3].permute(1, 2, 0)
    d, s = maps[3:6].permute(1, 2, 0), maps[7:10].permute(1, 2, 0)
    alpha = (maps[6].clamp(min=1e-3) ** 2)[..., None]
    nl, nv, nh, vh = ((n * l).sum(-1, keepdim=True), (n * v).sum(-1, keepdim=True), (n * h).sum(-1, keepdim=True),
                      (v * h).sum(-1, keepdim=True))
    above = (l[..., 2:] > 0) & (v[..., 2:] > 0)
    if convention == "physical":
        ndf = alpha**2 / (math.pi * (nh**2 * (alpha**2 - 1) + 1) ** 2)

        def g1(x):
            return 2 * x / (x + torch.sqrt(alpha**2 + (1 - alpha**2) * x**2))

        fresnel = s + (1 - s) * (1 - vh) ** 5
        f = d / math.pi + ndf * g1(nl) * g1(nv) * fresnel / (4 * nl * nv)
        falloff = intensity / (to_light**2).sum(-1, keepdim=True)
        radiance = torch.where(above & (nl > 0) & (nv > 0), f * nl * falloff, 0.0)
    else:  # deepbasis: cosines clamped to 1e-12, Schlick-GGX k = alpha / 2, spherical-Gaussian Fresnel, no falloff
        nl, nv, nh, vh = (x.clamp(min=1e-12) for x in (nl, nv, nh, vh))
        ndf = alpha**2 / (math.pi * (nh**2 * (alpha**2 - 1) + 1) ** 2)
        k = alpha / 2
        visibility = 1 / ((nl * (1 - k) + k) * (nv * (1 - k) + k))
        fresnel = s + (1 - s) * 2 ** ((-5.55473 * vh - 6.98316) * vh)
        f = d * (1 - s) / math.pi + 0.25 * ndf * visibility * fresnel
        radiance = torch.where(above, f * nl * math.pi * intensity, 0.0)
    return radiance.permute(2, 0, 1)


def test_rerender_of_a_flat_lambertian_under_one_light_is_albedo_over_pi_cos_i_over_d2():
    # physical: the light's intensity is pi |l|^2, so the radiance is albedo cos |l|^2 / r^2 (specular
    # F0 = 0 and the view at the light: the Fresnel term (1 - v.h)^5 vanishes).
    size, light = 16, (0.3, -0.2, 2.5)
    albedo = torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64)
    points = _pixel_points(size)
    to_light = torch.tensor(light, dtype=torch.float64) - points
    r2 = (to_light**2).sum(-1)
    cosine = to_light[..., 2] / r2.sqrt()
    intensity = math.pi * sum(c * c for c in light)
    expected = albedo.view(3, 1, 1) / math.pi * cosine * intensity / r2
    assert expected.max() < 1  # nothing clipped
    lights = torch.tensor([light])
    for backend in ("mitsuba", "torch"):
        image = rerender(material(size, diffuse=tuple(albedo.tolist())), lights, lights, "physical", backend=backend)
        assert image.shape == (1, 1, 3, size, size)
        assert_close(image[0, 0], _srgb(expected), "render")


RENDER_CASES = [
    # (id, convention, material keywords, lights, views)
    ("tilted-lambertian", "physical", dict(normal=(math.sin(0.3), 0.0, math.cos(0.3)), diffuse=(0.6, 0.4, 0.2)),
     [(1.0, 0.5, 2.0)], [(1.0, 0.5, 2.0)]),
    ("ggx-view-apart", "physical", dict(diffuse=(0.3, 0.2, 0.1), roughness=0.5, specular=(0.04, 0.2, 0.5)),
     [(0.8, -0.4, 2.2)], [(-0.6, 0.5, 2.8)]),
    ("ggx-tilted-shiny", "physical", dict(normal=(0.0, math.sin(-0.2), math.cos(0.2)), diffuse=(0.1, 0.1, 0.1),
                                           roughness=0.35, specular=(0.3, 0.3, 0.3)),
     [(0.2, 0.3, 2.5)], [(-0.1, -0.4, 3.0)]),
    ("two-lights", "physical", dict(diffuse=(0.4, 0.4, 0.4), roughness=0.6, specular=(0.04, 0.04, 0.04)),
     [(0.5, 0.0, 2.0), (-1.0, 1.5, 3.0)], [(0.0, 0.5, 2.5), (1.0, -1.0, 2.0)]),
    ("deepbasis", "deepbasis", dict(diffuse=(0.3, 0.5, 0.2), roughness=0.4, specular=(0.1, 0.2, 0.3)),
     [(0.4, 0.2, 2.4)], [(-0.3, 0.1, 2.6)]),
    ("clipped", "physical", dict(diffuse=(1.0, 1.0, 1.0), roughness=0.2, specular=(0.5, 0.5, 0.5)),
     [(0.7, 0.7, 0.6), (0.0, 0.0, 2.0)], [(0.7, 0.7, 0.6), (0.0, 0.0, 2.0)]),
]


@pytest.mark.parametrize("backend", ["mitsuba", "torch"])
@pytest.mark.parametrize("case, convention, keywords, lights, views", RENDER_CASES,
                         ids=[case[0] for case in RENDER_CASES])
def test_rerender_matches_the_shading_formulas_by_hand(case, convention, keywords, lights, views, backend):
    size = 16
    maps = material(size, **keywords)
    # physical: one intensity for all K lights, pi times their mean squared distance to the centre;
    # deepbasis: the unit lamp.
    intensity = (math.pi * sum(sum(c * c for c in light) for light in lights) / len(lights)
                 if convention == "physical" else 1.0)
    linear = torch.stack([hand_render(maps[0], light, view, intensity, convention)
                          for light, view in zip(lights, views)])
    expected = _srgb(linear)
    image = rerender(maps, torch.tensor(lights), torch.tensor(views), convention, backend=backend)
    assert image.shape == (1, len(lights), 3, size, size)
    assert_close(image[0], expected, "render")
    if keywords.get("specular", (0.0, 0.0, 0.0)) != (0.0, 0.0, 0.0) and convention == "physical":
        # The specular lobe matters here: the diffuse part alone is far from the render.
        diffuse_only = torch.stack([_srgb(hand_render(material(size, **{**keywords, "specular": (0.0,) * 3})[0], light,
                                                      view, intensity, convention))
                                    for light, view in zip(lights, views)])
        assert (diffuse_only - expected).abs().max() > 1e-2
    if case == "clipped":
        assert (linear > 1.05).any() and (linear < 0.5).any()  # part of the render is clipped, part is not
        assert (image[0][linear > 1] > 1 - 1e-6).all()


def test_rerender_rmse_against_hand_renders():
    size = 16
    lights = [(0.5, 0.2, 2.3), (-0.7, 0.9, 3.1)]
    views = [(-0.2, 0.4, 2.8), (0.6, -0.5, 2.0)]
    intensity = math.pi * sum(sum(c * c for c in light) for light in lights) / len(lights)
    truth = torch.cat([material(size, diffuse=(0.5, 0.4, 0.3), roughness=0.5, specular=(0.04,) * 3),
                       material(size, diffuse=(0.2, 0.2, 0.2), roughness=0.3, specular=(0.1,) * 3)])
    predicted = torch.cat([material(size, diffuse=(0.4, 0.4, 0.35), roughness=0.6, specular=(0.04,) * 3),
                           truth[1:]])

    def hand(maps):
        return torch.stack([_srgb(hand_render(maps, light, view, intensity, "physical"))
                            for light, view in zip(lights, views)])

    expected = [float(((hand(predicted[0]) - hand(truth[0])) ** 2).mean().sqrt()), 0.0]
    assert expected[0] > 0.01
    for backend in ("mitsuba", "torch"):
        values = rerender_rmse(predicted, truth, torch.tensor(lights), torch.tensor(views), "physical", backend=backend)
        assert values.shape == (2,)
        assert_close(values, expected, "rmse")


# --- SSIM -----------------------------------------------------------------------------------------------

def _gaussian_window(window, sigma):
    offsets = [k - (window - 1) / 2 for k in range(window)]
    weights = [math.exp(-(k * k) / (2 * sigma * sigma)) for k in offsets]
    total = sum(weights)
    return [w / total for w in weights]


def ssim_by_windows(a, b, window=11, sigma=1.5):
    """Wang et al. (2004) SSIM, window by window: Gaussian-weighted means, variances and covariance of
    each valid window, (N, C, H - window + 1, W - window + 1). NumPy, float64."""
    g = np.array(_gaussian_window(window, sigma))
    weights = np.outer(g, g)
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    n, c, h, w = a.shape
    out = np.zeros((n, c, h - window + 1, w - window + 1))
    c1, c2 = (0.01 * 1) ** 2, (0.03 * 1) ** 2  # K1 = 0.01, K2 = 0.03, dynamic range L = 1
    for index in np.ndindex(n, c, h - window + 1, w - window + 1):
        m, k, i, j = index
        pa, pb = a[m, k, i:i + window, j:j + window], b[m, k, i:i + window, j:j + window]
        mu_a, mu_b = (weights * pa).sum(), (weights * pb).sum()
        var_a, var_b = (weights * (pa - mu_a) ** 2).sum(), (weights * (pb - mu_b) ** 2).sum()
        cov = (weights * (pa - mu_a) * (pb - mu_b)).sum()
        out[index] = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return out


@pytest.mark.parametrize("window, sigma", [(11, 1.5), (7, 1.0)])
def test_ssim_map_against_a_window_by_window_reference(window, sigma):
    generator = torch.Generator().manual_seed(2)
    a = torch.rand(2, 3, 18, 17, generator=generator, dtype=torch.float64)
    b = (0.7 * a + 0.3 * torch.rand(2, 3, 18, 17, generator=generator, dtype=torch.float64)).clamp(0, 1)
    b[1] = 1 - a[1]  # anti-correlated: negative structure term
    expected = ssim_by_windows(a, b, window, sigma)
    assert (expected[1] < 0).all()
    value = ssim_map(a, b, window, sigma)
    assert value.shape == (2, 3, 18 - window + 1, 17 - window + 1)
    assert_close(value, expected, "ssim")
    assert_close(ssim(a, b, window, sigma), expected.mean(axis=(1, 2, 3)), "ssim")


def _checkerboard(size, mean, amplitude):
    i = torch.arange(size, dtype=torch.float64)
    sign = (-1.0) ** (i.view(-1, 1) + i.view(1, -1))
    return (mean + amplitude * sign).view(1, 1, size, size)


SSIM_CLOSED_FORMS = [
    # (mean a, amplitude a, mean b, amplitude b): checkerboards m + s (-1)^(i + j)
    (0.5, 0.2, 0.5, 0.2),   # identical: 1
    (0.4, 0.2, 0.6, 0.2),   # a constant shift: the luminance term only
    (0.5, 0.3, 0.5, 0.1),   # a contrast change: the structure term only
    (0.5, 0.2, 0.5, -0.2),  # inverted: negative
    (0.3, 0.0, 0.7, 0.0),   # constants
]


@pytest.mark.parametrize("m_a, s_a, m_b, s_b", SSIM_CLOSED_FORMS)
def test_ssim_of_checkerboards_in_closed_form(m_a, s_a, m_b, s_b):
    # Under a separable window g, a checkerboard's local mean is m + s c A^2 with c = +-1 the sign at
    # the window's centre and A = sum_k g_k (-1)^k; its variance is s^2 (1 - A^4), and the covariance
    # of two checkerboards s_a s_b (1 - A^4).
    g = _gaussian_window(11, 1.5)
    big_a = sum(w * (-1) ** k for k, w in enumerate(g))
    c1, c2 = 0.01**2, 0.03**2
    values = []
    for sign in (1, -1):
        mu_a, mu_b = m_a + s_a * sign * big_a**2, m_b + s_b * sign * big_a**2
        var_a, var_b, cov = s_a**2 * (1 - big_a**4), s_b**2 * (1 - big_a**4), s_a * s_b * (1 - big_a**4)
        values.append(((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)))
    # An even image size: the 10 x 10 map holds as many windows centred on each sign.
    value = ssim(_checkerboard(20, m_a, s_a), _checkerboard(20, m_b, s_b))
    assert_close(value, [sum(values) / 2], "ssim")
    if (m_a, s_a) == (m_b, s_b):
        assert float(value[0]) == pytest.approx(1.0, abs=1e-12)


# --- FLIP -----------------------------------------------------------------------------------------------

def flip_of_constant_images(reference, test):
    """LDR-FLIP of two constant sRGB images (Andersson et al. 2020), by hand. A constant image has no
    edges or points, so the feature error is 0 and FLIP is the colour error: sRGB -> linear -> XYZ ->
    CIELAB (D65 white), Hunt-adjusted (a, b) * 0.01 L, HyAB distance, ^0.7, then the piecewise map
    with p_c = 0.4, p_t = 0.95 against the green-blue distance. (The spatial filters have unit sum,
    so they leave a constant image alone.)"""
    to_xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])

    def hunt_lab(srgb):
        c = np.asarray(srgb, np.float64)
        linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
        t = (to_xyz @ linear) / (to_xyz @ np.ones(3))
        delta = 6 / 29
        f = np.where(t > delta**3, np.cbrt(t), t / (3 * delta**2) + 4 / 29)
        lightness = 116 * f[1] - 16
        return np.array([lightness, 0.01 * lightness * 500 * (f[0] - f[1]), 0.01 * lightness * 200 * (f[1] - f[2])])

    def hyab(p, q):
        return abs(p[0] - q[0]) + math.hypot(p[1] - q[1], p[2] - q[2])

    error = hyab(hunt_lab(reference), hunt_lab(test)) ** 0.7
    c_max = hyab(hunt_lab([0, 1, 0]), hunt_lab([0, 0, 1])) ** 0.7
    p_c, p_t = 0.4, 0.95
    if error < p_c * c_max:
        return p_t / (p_c * c_max) * error
    return p_t + (error - p_c * c_max) / (c_max - p_c * c_max) * (1 - p_t)


FLIP_CONSTANTS = [
    ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)),
    ((0.3, 0.3, 0.3), (0.3, 0.3, 0.31)),
    ((0.5, 0.5, 0.5), (0.6, 0.6, 0.6)),
    ((0.2, 0.4, 0.6), (0.25, 0.35, 0.7)),
    ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
]


def test_flip_of_constant_images_is_the_colour_error_by_hand():
    size = 24
    a = torch.stack([torch.tensor(x).view(3, 1, 1).expand(3, size, size) for x, _ in FLIP_CONSTANTS])
    b = torch.stack([torch.tensor(y).view(3, 1, 1).expand(3, size, size) for _, y in FLIP_CONSTANTS])
    values = flip(a, b)  # one value per pair, in order
    assert values.shape == (len(FLIP_CONSTANTS),)
    assert_close(values, [flip_of_constant_images(x, y) for x, y in FLIP_CONSTANTS], "flip")
    assert float(values[0]) == 0.0


def test_flip_is_zero_for_identical_images_and_grows_with_the_difference():
    generator = torch.Generator().manual_seed(3)
    image = torch.rand(1, 3, 32, 32, generator=generator) * 0.8
    noise = torch.rand(1, 3, 32, 32, generator=generator)
    assert float(flip(image, image)[0]) == 0.0
    values = [float(flip(image, (image + step * noise).clamp(0, 1))[0]) for step in (0.02, 0.05, 0.1, 0.2)]
    assert 0 < values[0] < values[1] < values[2] < values[3] < 1


# --- LPIPS ----------------------------------------------------------------------------------------------

def lpips_by_hand(state, lins, a, b):
    """LPIPS (Zhang et al. 2018, AlexNet) written out functionally: inputs mapped to [-1, 1], the
    scaling layer, AlexNet's five conv + ReLU stages (max pooling before stages 2 and 3), channel-wise
    unit normalisation of each stage's output, the per-stage linear weights on squared differences,
    spatial means, summed over stages."""
    import torch.nn.functional as nnf

    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
    stages = [("features.0", dict(stride=4, padding=2), False), ("features.3", dict(padding=2), True),
              ("features.6", dict(padding=1), True), ("features.8", dict(padding=1), False),
              ("features.10", dict(padding=1), False)]

    def features(x):
        x = ((2 * x - 1) - shift) / scale
        out = []
        for name, options, pool in stages:
            if pool:
                x = nnf.max_pool2d(x, 3, 2)
            x = torch.relu(nnf.conv2d(x, state[f"{name}.weight"], state[f"{name}.bias"], **options))
            norm = torch.sqrt((x**2).sum(dim=1, keepdim=True))
            out.append(x / (norm + 1e-10))
        return out

    total = torch.zeros(a.shape[0])
    for index, (fa, fb) in enumerate(zip(features(a), features(b))):
        weight = lins[f"lin{index}.model.1.weight"].view(1, -1, 1, 1)
        total = total + (weight * (fa - fb) ** 2).sum(dim=1).mean(dim=(1, 2))
    return total


def test_lpips_against_a_functional_reference(tmp_path):
    # Seeded weights of AlexNet's shapes (the real ones are never downloaded); biases non-zero so that
    # the ReLUs cut.
    generator = torch.Generator().manual_seed(4)
    shapes = {"features.0": (64, 3, 11, 11), "features.3": (192, 64, 5, 5), "features.6": (384, 192, 3, 3),
              "features.8": (256, 384, 3, 3), "features.10": (256, 256, 3, 3)}
    state = {}
    for name, shape in shapes.items():
        fan_in = shape[1] * shape[2] * shape[3]
        state[f"{name}.weight"] = torch.randn(shape, generator=generator) / math.sqrt(fan_in)
        state[f"{name}.bias"] = 0.1 * torch.randn(shape[0], generator=generator)
    lins = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=generator) for i, c in enumerate(LPIPS.CHANNELS)}
    torch.save(state, tmp_path / "alexnet.pth")
    torch.save(lins, tmp_path / "alex.pth")
    metric = LPIPS(tmp_path / "alexnet.pth", tmp_path / "alex.pth")
    a = torch.rand(3, 3, 64, 64, generator=generator)
    b = (a + 0.3 * torch.rand(3, 3, 64, 64, generator=generator)).clamp(0, 1)
    b[2] = a[2]
    expected = lpips_by_hand(state, lins, a, b)
    assert (expected[:2] > 1e-3).all() and float(expected[2]) == 0.0
    assert_close(metric(a, b), expected, "lpips")


# --- score, summary_scores, Scores ----------------------------------------------------------------------

def test_score_against_hand_renders_and_hand_map_errors():
    size = 16
    light = (0.2, 0.1, 2.5)
    lights = torch.tensor([light])  # the view at the light: a Lambertian with F0 = 0 renders in closed form
    truth = torch.cat([material(size, diffuse=(0.5, 0.5, 0.5)), material(size, diffuse=(0.3, 0.2, 0.6))])
    predicted = torch.cat([material(size, diffuse=(0.4, 0.4, 0.4)), truth[1:]])
    stored = truth.clone()
    stored[:, 0] += 0.2  # the maps as stored differ from the rendered ones in the normal's x only

    points = _pixel_points(size)
    to_light = torch.tensor(light, dtype=torch.float64) - points
    r2 = (to_light**2).sum(-1)
    shade = to_light[..., 2] / r2.sqrt() * sum(c * c for c in light) / r2  # cos |l|^2 / r^2
    render_a = _srgb(0.4 * shade).expand(1, 3, size, size)
    render_b = _srgb(0.5 * shade).expand(1, 3, size, size)
    expected_rmse = float(((render_a - render_b) ** 2).mean().sqrt())

    class ConstantLPIPS:
        def __call__(self, a, b):
            return torch.full((a.shape[0],), 0.25)

    result = score(predicted, truth, lights, lights, "physical", lpips=ConstantLPIPS(), cross_check=True, stored=stored)
    assert set(result) == {"maps_normal", "maps_diffuse", "maps_roughness", "maps_specular", "render_rmse",
                           "render_flip", "render_ssim", "render_lpips", "render_rmse_torch"}
    assert all(v.shape == (2,) for v in result.values())
    # Maps against the stored maps: the normal's x off by 0.2 -> 0.1 stored, over 3 channels.
    assert_close(result["maps_normal"], [0.1 / math.sqrt(3)] * 2, "rmse")
    assert_close(result["maps_diffuse"], [0.1, 0.0], "rmse")
    assert_close(result["maps_roughness"], [0.0, 0.0], "rmse")
    assert_close(result["maps_specular"], [0.0, 0.0], "rmse")
    # Renders against the truth (not the stored maps): material 1 is predicted exactly.
    assert_close(result["render_rmse"], [expected_rmse, 0.0], "rmse")
    assert_close(result["render_rmse_torch"], [expected_rmse, 0.0], "rmse")
    assert_close(result["render_ssim"], [float(ssim(render_a, render_b)[0]), 1.0], "rmse")
    assert_close(result["render_flip"], [float(flip(render_a.float(), render_b.float())[0]), 0.0], "flip")
    assert float(result["render_ssim"][0]) < 1 and float(result["render_flip"][0]) > 0
    assert result["render_lpips"].tolist() == [0.25, 0.25]
    without = score(predicted, truth, lights, lights, "physical")
    assert "render_lpips" not in without and "render_rmse_torch" not in without
    assert_close(without["maps_normal"], [0.0, 0.0], "rmse")  # stored defaults to the truth


def test_summary_scores_nests_the_means_by_hand():
    means = {"maps_normal": 0.1, "maps_diffuse": 0.2, "maps_roughness": 0.3, "maps_specular": 0.4, "render_rmse": 0.5,
             "render_flip": 0.6, "render_ssim": 0.7, "render_lpips": 0.8, "render_rmse_torch": 0.9}
    assert summary_scores(means) == {"maps_rmse": {"normal": 0.1, "diffuse": 0.2, "roughness": 0.3, "specular": 0.4},
                                     "render_rmse": 0.5, "render_flip": 0.6, "render_ssim": 0.7}


def test_scores_summary_is_the_mean_per_metric():
    scores = Scores(names=["a", "b"], maps={"diffuse": torch.tensor([0.1, 0.3])}, render=torch.tensor([0.2, 0.6]))
    assert scores.summary() == pytest.approx({"diffuse": 0.2, "render_rmse": 0.4})
    assert Scores(names=["a"], maps={"normal": torch.tensor([0.5])}).summary() == {"normal": 0.5}
