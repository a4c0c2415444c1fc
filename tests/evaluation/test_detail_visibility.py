"""``benchmarks/detail.py``'s shading_visibility: a matte surface's fine relief shows in its flash
photo as the first-order shading ``(l_xy / l_z) . dn_xy``, with slope 1."""

import numpy as np
import pytest
import torch

from mideepbasis import constants
from mideepbasis.data.procedural import generate
from mideepbasis.evaluation import flash_photos, high_band_energy

from ..helpers import benchmark_module, matte_egg_crate


def test_matte_relief_shows_with_slope_one():
    detail = benchmark_module("detail")
    maps = matte_egg_crate(256, cycles=24, slope=0.15)
    photos, lights = flash_photos(maps, torch.tensor([[0.3, -0.2]]), constants.DEFAULT_FOV_DEG, "physical", 1.0)
    seen = detail.shading_visibility(maps, photos, lights[0], band=64)
    assert seen["correlation"] > 0.9
    assert 0.85 < seen["slope"] < 1.15
    assert 0.3 < seen["along_light"] < 0.7
    assert abs(seen["explained"] - seen["correlation"] ** 2 * seen["along_light"]) < 1e-9
    # The shading shows the slope along the light; the window's filter integrates it into the height,
    # whose gradient gives back the slope across the light too: more than the pixel-wise estimate.
    assert seen["window_explained"] > 0.6
    assert seen["window_explained"] > seen["explained"] + 0.1


def test_the_window_oracle_explains_nothing_of_unrelated_contrast():
    detail = benchmark_module("detail")
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(256, 256, generator=generator)
    tilt = torch.randn(2, 256, 256, generator=generator)
    fine = torch.randn(2, 256, 256, generator=generator)
    assert abs(detail.window_explained(noise, tilt, fine)) < 0.05  # 676 taps fitted on 40,000 pixels


def test_a_swapped_reflectance_keeps_the_relief_and_takes_the_other_albedo():
    detail = benchmark_module("detail")
    relief = matte_egg_crate(32, cycles=4, slope=0.15)
    other = torch.rand(1, constants.BASIS_CHANNELS, 32, 32, generator=torch.Generator().manual_seed(5))
    swapped = detail.with_reflectance_of(relief, other)
    assert torch.equal(swapped[:, constants.NORMAL], relief[:, constants.NORMAL])
    assert torch.equal(swapped[:, constants.REFLECTANCE], other[:, constants.REFLECTANCE])
    # Under a plain albedo the egg-crate shows as before; under the other's noise its shading is swamped.
    lights = torch.tensor([[0.3, -0.2]])
    seen = {}
    for name, maps in (("plain", relief), ("swapped", swapped)):
        photos, flashes = flash_photos(maps, lights)
        seen[name] = detail.shading_visibility(maps, photos, flashes[0], band=8)["correlation"]
    assert seen["swapped"] < seen["plain"] - 0.3


def test_photo_jitter_is_a_seeded_relative_noise_of_the_asked_spread():
    detail = benchmark_module("detail")
    photos = torch.full((1, 3, 128, 128), 0.25)
    first = detail.jittered(photos, 1e-3, seed=7)
    relative = first / photos - 1.0
    assert abs(float(relative.std()) - 1e-3) < 5e-5  # 49,152 draws: the spread's error about 3e-6
    assert abs(float(relative.mean())) < 2e-5
    assert torch.equal(first, detail.jittered(photos, 1e-3, seed=7))
    assert not torch.equal(first, detail.jittered(photos, 1e-3, seed=8))
    assert torch.equal(detail.jittered(photos, 0.0, seed=7), photos)


def test_network_band_moments_give_slope_one_for_the_truth_and_a_half_for_half_its_band():
    from types import SimpleNamespace

    from mideepbasis.resampling import downsample

    detail = benchmark_module("detail")
    truth = matte_egg_crate(128, cycles=12, slope=0.15)
    truth[:, constants.DIFFUSE] = torch.rand(1, 3, 128, 128, generator=torch.Generator().manual_seed(2))
    low = downsample(truth, (32, 32))
    halved = low.clone()
    for channels in (slice(0, 2), constants.DIFFUSE):  # the normals' x and y, the diffuse: half their variation
        mean = low[:, channels].mean(dim=(-2, -1), keepdim=True)
        halved[:, channels] = mean + 0.5 * (low[:, channels] - mean)
    for maps, slope in ((low, 1.0), (halved, 0.5)):
        moments = detail.network_band_moments(SimpleNamespace(output=SimpleNamespace(maps=maps)), truth)
        for name in ("diffuse", "normal"):
            ratio = moments[name]["predicted_truth"] / moments[name]["truth_truth"]
            assert abs(ratio - slope) < 1e-4, (name, ratio)


def test_materials_from_another_first_seed_are_a_set_apart_of_the_same_kinds():
    detail = benchmark_module("detail")
    default = detail.materials(3, 1)
    other = detail.materials(3, 1, first_seed=detail.HELD_OUT_SEED + 1000)
    assert [m["seed"] for m in default[:3]] == [detail.HELD_OUT_SEED + i for i in range(3)]
    assert [m["seed"] for m in other[:3]] == [detail.HELD_OUT_SEED + 1000 + i for i in range(3)]
    assert [(m["kind"], m["family"]) for m in other] == [(m["kind"], m["family"]) for m in default]
    assert not {m["seed"] for m in default} & {m["seed"] for m in other}


def test_the_relief_test_bound_weighs_each_material_by_its_gain_squared_and_fine_energy():
    detail = benchmark_module("detail")
    records = [{"truth_energy": {"normal": 3.0}, "normal_detail": 1.0},
               {"truth_energy": {"normal": 1.0}, "normal_detail": 0.5}]
    assert abs(detail.relief_test_bound(records) - (3.0 + 0.25) / 4.0) < 1e-12
    for record in records:
        record["normal_detail"] = 1.0
    assert detail.relief_test_bound(records) == 1.0


def test_the_details_correlation_tells_the_truths_detail_from_made_up_detail_of_the_same_energy():
    detail = benchmark_module("detail")
    band = 16  # both reliefs' cycles (24 and 31 across) lie far above it
    truth = matte_egg_crate(256, cycles=24, slope=0.15)
    made_up = matte_egg_crate(256, cycles=31, slope=0.15)  # a relief of the same slopes elsewhere

    def energy(maps: torch.Tensor) -> float:
        return float(high_band_energy(maps, band)["normal"][0])

    def correlation(maps: torch.Tensor) -> float:
        return detail.fine_cross(maps, truth, band)["normal"] / (energy(maps) * energy(truth)) ** 0.5

    assert abs(correlation(truth) - 1.0) < 1e-6
    assert abs(correlation(-truth) + 1.0) < 1e-6  # the relief turned inside out: every slope wrong
    # About the same fine energy, none of it where the truth's is.
    assert abs(energy(made_up) / energy(truth) - 1.0) < 0.1
    assert abs(correlation(made_up)) < 0.1


def test_the_true_detail_bound_keeps_the_answer_below_the_band_and_takes_the_truths_above_it():
    detail = benchmark_module("detail")
    band = 16  # blocks of 8 px: whole cycles of the relief's 8 px period, so its band below is flat
    truth = matte_egg_crate(128, cycles=16, slope=0.15)
    truth[:, constants.DIFFUSE] = 0.5 + 0.2 * truth[:, 0:1]  # an albedo that follows the relief
    # A blurred answer with a wrong level: 0.05 darker, the relief made flat.
    answer = truth.clone()
    answer[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    answer[:, constants.DIFFUSE] = 0.45
    bounded = detail.with_true_detail(answer, truth, band)
    # The diffuse: the answer's level with the truth's texture above the band, so an error of 0.05 alone.
    assert torch.allclose(bounded[:, constants.DIFFUSE] - truth[:, constants.DIFFUSE],
                          torch.full_like(truth[:, constants.DIFFUSE], -0.05), atol=1e-5)
    # The normals: unit, and the truth's own where the answer below the band is the truth's (flat).
    assert torch.allclose(bounded[:, constants.NORMAL].norm(dim=1), torch.ones(1, 128, 128), atol=1e-5)
    assert float((bounded[:, constants.NORMAL] - truth[:, constants.NORMAL]).abs().max()) < 0.02
    # The truth gives itself back.
    assert torch.allclose(detail.with_true_detail(truth, truth, band), truth, atol=1e-5)


def test_mean_tilt_of_a_plane_is_its_slope_angle():
    detail = benchmark_module("detail")
    x = np.linspace(-1.0, 1.0, 64, dtype=np.float32)  # the sample spans 2 patch half-widths
    for slope in (0.05, 0.3, 1.0):
        plane = np.broadcast_to(slope * x[None, :], (64, 64)).copy()
        # Central differences of a linear ramp are exact; only the replicated edge columns halve the slope.
        expected = (62 * np.degrees(np.arctan(slope * 64 / 63)) + 2 * np.degrees(np.arctan(slope * 32 / 63))) / 64
        assert detail.mean_tilt(plane) == pytest.approx(expected, rel=1e-4)


def test_relief_scales_read_each_size_as_its_material_leans():
    detail = benchmark_module("detail")
    chosen = detail.materials(2, 0)
    report = detail.relief_scales(chosen, size=64, low=32)
    assert [row["seed"] for row in report["per_material"]] == [m["seed"] for m in chosen]
    for row in report["per_material"]:
        for size, key in ((64, "tilt_full"), (32, "tilt_low")):
            normal = generate(row["seed"], size=size, family=row["family"]).normal
            tilt = float(torch.rad2deg(torch.acos(normal[2].clamp(-1, 1))).mean())
            assert row[key] == pytest.approx(tilt, abs=0.01), (row["family"], size)
