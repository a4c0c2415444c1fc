"""The procedural generator: determinism, coverage of the families, ranges, plausibility, seamless tiling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mideepbasis.data.procedural import FAMILIES, GeneratorConfig, generate, generate_surface
from mideepbasis.data.procedural.core import height_to_normal

#: Families the generator must offer (the issue's list of what people photograph).
REQUIRED_FAMILIES = {"tiles_bricks", "wood", "stone", "metal", "fabric", "leather", "plastic", "paper", "concrete",
                     "ceramic", "organic", "sparkle"}

#: The mean step across the wrap-around edge may be at most this many times the largest mean step
#: between two neighbouring interior columns (or rows): a seam is a jump no interior column shows.
#: (Structure such as grout makes some interior steps large, and a groove may sit on the edge
#: itself, so the seam is compared with the largest step, not the typical one.)
SEAM_RATIO = 1.5


def test_all_required_families_are_registered():
    assert REQUIRED_FAMILIES <= set(FAMILIES), sorted(REQUIRED_FAMILIES - set(FAMILIES))
    assert len(FAMILIES) >= 12


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_same_seed_gives_the_same_material(family):
    a, b = generate(11, size=64, family=family), generate(11, size=64, family=family)
    assert torch.equal(a.to_tensor(), b.to_tensor())
    c = generate(12, size=64, family=family)
    assert not torch.equal(a.to_tensor(), c.to_tensor())


def test_random_families_cover_every_family():
    drawn = {generate(seed, size=32, config=GeneratorConfig(mix_probability=0.0, weathering=False)).provenance["family"]
             for seed in range(40 * len(FAMILIES))}
    assert drawn == set(FAMILIES)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_values_stay_in_range_and_plausible(family):
    for seed in range(12):
        material = generate(seed, size=96, family=family)
        maps = material.to_tensor()
        normal, diffuse, roughness, specular = maps[:3], maps[3:6], maps[6:7], maps[7:]
        assert torch.allclose((normal * normal).sum(0), torch.ones(96, 96), atol=1e-4)
        assert (normal[2] > 0).all()
        for name, m in (("diffuse", diffuse), ("roughness", roughness), ("specular", specular)):
            assert m.min() >= 0 and m.max() <= 1, (seed, name)
        # Dielectric pixels (low F0) are grey; metal pixels (high F0) have a dark diffuse albedo.
        f0 = specular.mean(0)
        dielectric = f0 < 0.1
        if dielectric.any():
            spread = (specular.max(0).values - specular.min(0).values)[dielectric]
            assert (spread < 0.02).float().mean() > 0.99, (seed, "coloured dielectric F0")
            assert (f0[dielectric] > 0.015).float().mean() > 0.95, (seed, "dielectric F0 below 0.02")
        metal = f0 > 0.5
        if metal.any():
            assert (diffuse.mean(0)[metal] < 0.1).float().mean() > 0.98, (seed, "bright diffuse on metal")


def seam_ratio(image: np.ndarray, axis: int) -> float:
    """Mean step across the wrap-around edge over the largest interior mean step."""
    other = 1 - axis
    steps = np.abs(np.diff(image, axis=axis)).mean(axis=other)
    first = np.take(image, 0, axis=axis)
    last = np.take(image, -1, axis=axis)
    return float(np.abs(first - last).mean() / max(float(steps.max()), 1e-6))


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_tileable_materials_wrap_without_a_seam(family):
    """Relief, diffuse, roughness and specular wrap; the normals follow from the wrapped relief
    (``test_normals_of_a_periodic_relief_wrap``). Normals are not compared directly: a groove that
    sits exactly on the edge (a board joint) makes a large but real step there."""
    ratios = []
    for seed in range(6):
        surface, _, _ = generate_surface(seed, GeneratorConfig(size=128, tileable=True), family=family)
        channels = [surface.height, surface.roughness] + [surface.diffuse[..., c] for c in range(3)] + \
                   [surface.specular[..., c] for c in range(3)]
        for channel in channels:
            if channel.std() < 1e-6:
                continue
            ratios += [seam_ratio(channel, axis=1), seam_ratio(channel, axis=0)]
    assert ratios and max(ratios) < SEAM_RATIO, f"{family}: seam ratios up to {max(ratios):.2f}"


def test_normals_of_a_periodic_relief_wrap():
    size = 64
    u = (np.arange(size) + 0.5) / size
    height = 0.05 * np.sin(2 * np.pi * 3 * u)[None, :] * np.cos(2 * np.pi * 2 * u)[:, None]
    normal = height_to_normal(height.astype(np.float32), tileable=True)
    rolled = height_to_normal(np.roll(height, (7, 11), axis=(0, 1)).astype(np.float32), tileable=True)
    assert np.allclose(np.roll(normal, (7, 11), axis=(0, 1)), rolled, atol=1e-6)
    # And they are the analytic normals of the relief (central differences, second order).
    d_dx = 0.05 * 2 * np.pi * 3 * np.cos(2 * np.pi * 3 * u)[None, :] * np.cos(2 * np.pi * 2 * u)[:, None] / 2
    assert np.allclose(-normal[..., 0] / normal[..., 2], d_dx, atol=0.02 * np.abs(d_dx).max())


def test_non_tileable_material_has_edges_that_differ():
    maps = generate(3, size=128, family="concrete", tileable=False,
                    config=GeneratorConfig(weathering=False, mix_probability=0.0)).to_tensor().numpy()
    # Only that "tileable" is what makes the edges match: unrelated edges make a visible seam.
    assert max(seam_ratio(maps[c], axis=axis) for c in range(10) for axis in (0, 1)) > SEAM_RATIO


@pytest.mark.parametrize("size", [48, 200, 512])
def test_any_resolution(size):
    material = generate(5, size=size)
    assert (material.height, material.width) == (size, size)


def test_relief_factor_reaches_the_mean_tilt_asked_for():
    from mideepbasis.data.procedural import relief_factor
    from mideepbasis.data.procedural.core import height_to_normal

    x = np.linspace(-1.0, 1.0, 64, dtype=np.float32)
    height = (0.01 * np.sin(3 * x))[None, :].repeat(64, axis=0)  # ridges along y
    for tilt in (1.0, 10.0, 30.0):
        normal = height_to_normal(height * relief_factor(height, tilt, False, max_factor=1e4), False)
        assert np.degrees(np.arccos(normal[..., 2])).mean() == pytest.approx(tilt, abs=0.01)
    assert relief_factor(np.zeros((8, 8), np.float32), 10.0, False) == 1.0  # nothing to scale
    assert relief_factor(height, 60.0, False, max_factor=5.0) == 5.0  # out of reach: capped


def test_relief_of_every_family_is_scaled_to_the_drawn_tilt():
    for family in ("stone", "leather", "wood"):
        tilts = []
        for seed in range(3):
            maps = generate(seed, family=family, config=GeneratorConfig(size=64, relief_tilt_deg=(12.0, 12.0),
                                                                        max_relief_factor=1e4)).to_tensor()
            tilts.append(float(torch.rad2deg(torch.acos(maps[2].clamp(-1, 1))).mean()))
        assert tilts == pytest.approx([12.0] * 3, abs=1.5), (family, tilts)


def coarse_share(normal: torch.Tensor, size: int = 8) -> float:
    """The share of the normal's x and y (2, H, W) in features larger than 1/size of the sample."""
    xy = normal[None, :2]
    coarse = torch.nn.functional.interpolate(torch.nn.functional.interpolate(xy, size=(size, size), mode="area"),
                                             size=xy.shape[-2:], mode="bilinear", align_corners=False)
    return float(coarse.square().mean() / xy.square().mean())


def test_coarse_relief_adds_broad_bumps_and_keeps_the_rest_of_the_material():
    plain_config = GeneratorConfig(size=64)
    coarse_config = GeneratorConfig(size=64, coarse_relief_tilt_deg=(20.0, 20.0), coarse_relief_probability=1.0)
    for seed in range(4):
        plain, coarse = generate(seed, config=plain_config), generate(seed, config=coarse_config)
        assert torch.equal(plain.diffuse, coarse.diffuse) and torch.equal(plain.roughness, coarse.roughness)
        assert torch.equal(plain.specular, coarse.specular)
        assert coarse.provenance["coarse_relief_tilt_deg"] == pytest.approx(20.0)
        assert "coarse_relief_tilt_deg" not in plain.provenance
        # The broad undulation carries much of the normal's lean, and the material leans more.
        share, plain_share = coarse_share(coarse.normal), coarse_share(plain.normal)
        assert share > max(2 * plain_share, plain_share + 0.1), (seed, share, plain_share)
        tilt = [float(torch.rad2deg(torch.acos(m.normal[2].clamp(-1, 1))).mean()) for m in (plain, coarse)]
        assert tilt[1] > tilt[0], seed
    never = GeneratorConfig(size=64, coarse_relief_tilt_deg=(20.0, 20.0), coarse_relief_probability=0.0)
    assert torch.equal(generate(1, config=never).normal, generate(1, config=plain_config).normal)


#: Sums of the normal and of the other maps of seeds 0 - 2 at 64 px under the training runs' settings
#: (undulation (1.5, 30) deg at chance 0.85), made by the generator of commit a876e17: the materials of
#: earlier runs stay as they were.
EARLIER_MATERIAL_SUMS = [(3625.0993710723415, 3967.2309139166027), (3920.9702582043465, 6424.493373312056),
                         (4024.237602466779, 6325.84723530896)]


def test_materials_stay_those_of_earlier_runs_with_the_new_options_off():
    config = GeneratorConfig(size=64, coarse_relief_tilt_deg=(1.5, 30.0), coarse_relief_probability=0.85)
    # The maps are float32 made by vectorised kernels, which round differently on other processors
    # (2.5e-9 of the sum seen between two machines of this project); any change of what is drawn
    # moves a sum by far more than 1e-6 of it.
    for seed, (normal_sum, rest_sum) in enumerate(EARLIER_MATERIAL_SUMS):
        maps = generate(seed, config=config).to_tensor().double()
        assert float(maps[:3].sum()) == pytest.approx(normal_sum, rel=1e-6), seed
        assert float(maps[3:].sum()) == pytest.approx(rest_sum, rel=1e-6), seed


#: Provenance of seeds 0 - 3 under the shipped model's training settings (gloss at chance 0.45,
#: darkening at 0.75), drawn before the low-relief and relief-inversion chances were removed: their
#: two draws, always off, are still made, so the factors drawn after them are those of earlier runs.
EARLIER_FACTORS = [{"coarse_relief_tilt_deg": 29.24209723934958, "diffuse_factor": 0.2839490512975886},
                   {"coarse_relief_tilt_deg": 15.757660389717584, "diffuse_factor": 0.5652577608836423},
                   {"roughness_factor": 0.8143429327521011},
                   {"coarse_relief_tilt_deg": 18.337767719601004, "roughness_factor": 0.9471519013945359,
                    "diffuse_factor": 0.7263520734887519}]


def test_the_draws_of_the_shipped_models_training_settings_stay_those_of_earlier_runs():
    config = GeneratorConfig(size=64, relief_tilt_deg=(1.5, 30.0), coarse_relief_tilt_deg=(2.5, 35.0),
                             coarse_relief_probability=0.85, gloss_probability=0.45, darkening_probability=0.75)
    for seed, expected in enumerate(EARLIER_FACTORS):
        provenance = generate(seed, config=config).provenance
        drawn = {key: provenance[key] for key in ("coarse_relief_tilt_deg", "roughness_factor", "diffuse_factor")
                 if key in provenance}
        assert drawn == pytest.approx(expected, rel=1e-12), seed


def test_gloss_and_darkening_scale_the_roughness_and_albedo_and_keep_the_relief():
    plain_config = GeneratorConfig(size=64)
    shifted_config = GeneratorConfig(size=64, gloss_probability=1.0, gloss_scale=(0.5, 0.5),
                                     darkening_probability=1.0, darkening_scale=(0.25, 0.25))
    for seed in (0, 1, 8, 17):  # 8 and 17 have albedos clipped at 1: scaled as clipped
        plain, shifted = generate(seed, config=plain_config), generate(seed, config=shifted_config)
        assert shifted.provenance["roughness_factor"] == pytest.approx(0.5)
        assert shifted.provenance["diffuse_factor"] == pytest.approx(0.25)
        assert "roughness_factor" not in plain.provenance and "diffuse_factor" not in plain.provenance
        assert torch.equal(plain.normal, shifted.normal) and torch.equal(plain.specular, shifted.specular)
        torch.testing.assert_close(shifted.roughness, 0.5 * plain.roughness, atol=1e-6, rtol=1e-6)
        # Where the surface is a dielectric, the final clipping leaves the diffuse alone: the factor is all.
        dielectric = (plain.specular.mean(dim=0) < 0.3).expand_as(plain.diffuse)
        torch.testing.assert_close(shifted.diffuse[dielectric], 0.25 * plain.diffuse[dielectric], atol=1e-6, rtol=1e-6)
    # Drawn at their ranges' ends only: log-uniform within them.
    drawn = GeneratorConfig(size=64, gloss_probability=1.0, darkening_probability=1.0)
    factors = [generate(seed, config=drawn).provenance for seed in range(8)]
    assert all(0.35 <= f["roughness_factor"] <= 1.0 and 0.15 <= f["diffuse_factor"] <= 1.0 for f in factors)
    assert len({round(f["roughness_factor"], 6) for f in factors}) == 8
