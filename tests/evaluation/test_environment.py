"""Evaluation under environment light: zero against itself, a noise floor that falls as 1/sqrt(spp),
a white Lambertian under a uniform sky at its known value, the rows in summary, table and plots."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mideepbasis.evaluation.environment import (EnvironmentProtocol, EnvironmentRenderer, binned, masked_metrics,
                                                parse_environments, spearman, to_display)
from mideepbasis.errors import InputError

from ..helpers import directional_albedo
from mideepbasis.evaluation import EvaluationConfig, run_evaluation

#: Tolerances of the Monte Carlo checks.
TOLERANCES = {
    "noise_ratio": 0.25,  # relative: floor(16 spp) / floor(256 spp) against sqrt(16)
    "lambertian": 0.01,  # absolute, linear radiance, against the quadrature of the torch reference
    "same_seed": 1e-6,  # RMSE of a render against itself: drjit's parallel sums are not bit-exact
}


def material(size=32, seed=0):
    from mideepbasis.data.procedural import GeneratorConfig, generate

    return generate(seed, config=GeneratorConfig(size=size)).to_tensor()


def test_a_material_against_itself_gives_zero_and_the_noise_floor_falls_as_one_over_sqrt_spp():
    maps = material()
    floors = {}
    for spp in (16, 256):
        renderer = EnvironmentRenderer(EnvironmentProtocol(environments=("studio",), views_deg=(40.0,), resolution=32,
                                                           spp=spp, sampler="independent"))
        first, mask = renderer.render(maps, "studio", 40.0, seed=0)
        again, _ = renderer.render(maps, "studio", 40.0, seed=0)
        other, _ = renderer.render(maps, "studio", 40.0, seed=1)
        same = masked_metrics(to_display(first), to_display(again), mask)
        # Zero up to float rounding (drjit's parallel accumulation is not bit-exact between runs).
        assert same["rmse"] < TOLERANCES["same_seed"] and same["flip"] < 1e-4 and same["ssim"] == pytest.approx(1.0, abs=1e-6)
        assert 0.2 < mask.mean() < 0.9  # the sample and the sky are both in view
        floors[spp] = masked_metrics(to_display(first), to_display(other), mask)["rmse"]
    assert floors[16] / floors[256] == pytest.approx(4.0, rel=TOLERANCES["noise_ratio"]), floors


def test_a_white_lambertian_under_a_uniform_sky_renders_to_its_known_value():
    maps = torch.zeros(10, 8, 8)
    maps[2], maps[3:6], maps[6] = 1.0, 1.0, 1.0  # flat, white, rough; specular 0 (Schlick still reflects a little)
    protocol = EnvironmentProtocol(environments=("uniform",), views_deg=(40.0,), resolution=9, spp=4096)
    image, mask = EnvironmentRenderer(protocol).render(maps, "uniform", 40.0, seed=0)
    assert mask[4, 4]
    # The camera looks at the sample centre from 40 deg: f cos integrated over the hemisphere there.
    expected = directional_albedo(40.0)
    assert 1.0 < expected < 1.1  # the white diffuse lobe gives 1, Schlick's grazing reflection a little more
    assert image[4, 4].mean() == pytest.approx(expected, abs=TOLERANCES["lambertian"])


def test_binning_averages_blocks_inside_the_mask():
    image = np.arange(16, dtype=np.float32).reshape(4, 4, 1).repeat(3, axis=2)
    mask = np.ones((4, 4), bool)
    mask[0, 0] = False
    blocks, inside = binned(image, mask, 2)
    assert blocks[..., 0].tolist() == [[2.5, 4.5], [10.5, 12.5]]
    assert inside.tolist() == [[False, True], [True, True]]


def test_spearman_by_hand():
    assert spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # x = 1..5, y ranks 2,1,4,3,5: rho = 1 - 6 sum d^2 / (n (n^2 - 1)) = 1 - 6 * 4 / 120
    assert spearman([1, 2, 3, 4, 5], [0.2, 0.1, 0.4, 0.3, 0.5]) == pytest.approx(0.8)


def test_unknown_environments_are_refused_in_one_line(tmp_path):
    assert parse_environments("studio, sunsky") == ("studio", "sunsky")
    with pytest.raises(InputError, match="'nowhere.exr' is neither"):
        parse_environments("studio,nowhere.exr")


def test_evaluation_under_environments_writes_its_rows_and_counts_a_corrupt_material(evaluation_dataset, tmp_path):
    folder, model = evaluation_dataset
    config = EvaluationConfig(data=str(folder), format="folder", out=str(tmp_path / "out"), model=str(model),
                              baselines=True, environment=("uniform", "studio"), environment_spp=16,
                              environment_resolution=24)
    with pytest.warns(UserWarning, match="skipping"):
        summary = run_evaluation(config, progress=False)
    assert summary["n_materials"] == 3 and summary["skipped"] == 1
    written = json.loads((tmp_path / "out" / "summary.json").read_text())
    for name in ("uniform", "studio"):
        entry = written["env"][name]
        assert set(entry["noise_floor"]) == {"rmse", "flip", "ssim"}
        assert set(entry["rows"]) == {"model (no refinement)", "model + refinement (250 steps, normals kept)",
                                      "trivial"}
        for metric in ("rmse", "flip", "ssim"):
            assert entry[metric] == entry["rows"]["model (no refinement)"][metric]
        assert entry["rmse"] > entry["noise_floor"]["rmse"] > 0  # an untrained network is far from the truth
        assert -1.0 <= entry["spearman_flash_vs_env"] <= 1.0
    table = (tmp_path / "out" / "table.md").read_text()
    assert "| noise floor | studio |" in table and "| trivial | uniform |" in table
    for image in ("env_bars.png", "env_gallery.png"):
        assert (tmp_path / "out" / image).is_file(), image
    header = (tmp_path / "out" / "per_material.csv").read_text().splitlines()[0]
    assert "env_studio_rmse" in header and "env_uniform_ssim" in header


def test_the_capture_previews_stratified_samples_are_no_noisier_than_64_independent_ones():
    from mideepbasis import constants
    from mideepbasis.render.scenes import preview_scene, render

    maps = material(size=64, seed=11)

    def display(spp, sampler, seed=0):
        scene = preview_scene(maps, spp=spp, resolution=64, sampler=sampler)
        return to_display(render(scene, seed=seed))

    reference = display(2048, "independent", seed=7)
    noise = {sampler: float(np.sqrt(((display(spp, sampler) - reference) ** 2).mean()))
             for sampler, spp in (("independent", 64), (constants.CAPTURE_PREVIEW_SAMPLER, constants.CAPTURE_PREVIEW_SPP))}
    assert noise[constants.CAPTURE_PREVIEW_SAMPLER] <= 1.05 * noise["independent"], noise


def test_the_capture_shape_previews_samples_are_no_noisier_than_32_independent_ones():
    from mideepbasis import constants
    from mideepbasis.render.scenes import render, shape_scene

    maps = material(size=64, seed=11)
    for shape in ("sphere", "cloth"):
        def display(spp, sampler, seed=0):
            scene = shape_scene(maps, shape, spp=spp, resolution=64, sampler=sampler)
            return to_display(render(scene, seed=seed))

        reference = display(1024, "independent", seed=7)
        noise = {sampler: float(np.sqrt(((display(spp, sampler) - reference) ** 2).mean()))
                 for sampler, spp in (("independent", 32), (constants.SHAPE_PREVIEW_SAMPLER, constants.SHAPE_PREVIEW_SPP))}
        assert noise[constants.SHAPE_PREVIEW_SAMPLER] <= 1.05 * noise["independent"], (shape, noise)
