"""Evaluation: metrics against hand-computed cases, seeded reproducibility, shared lights, skipped files."""

from __future__ import annotations

import json
import math

import pytest
import torch

from mideepbasis.capturing import RefineConfig
from mideepbasis.evaluation import (EvaluationConfig, light_error_deg, map_rmse, random_lights_and_views, rerender_rmse,
                                    run_evaluation, ssim, trivial_baseline)


def flat(size=16, diffuse=0.5, roughness=0.4, specular=0.04):
    maps = torch.zeros(1, 10, size, size)
    maps[:, 2] = 1.0
    maps[:, 3:6], maps[:, 6], maps[:, 7:10] = diffuse, roughness, specular
    return maps


def test_identical_inputs_give_zero_error():
    maps = flat()
    lights, views = random_lights_and_views(5)
    assert all(float(v[0]) == 0.0 for v in map_rmse(maps, maps).values())
    assert float(rerender_rmse(maps, maps, lights, views, "physical")[0]) == 0.0
    image = torch.rand(2, 3, 32, 32)
    assert torch.allclose(ssim(image, image), torch.ones(2))


def test_known_differences_give_the_known_rmse():
    a, b = flat(diffuse=0.5), flat(diffuse=0.6)
    assert float(map_rmse(a, b)["diffuse"][0]) == pytest.approx(0.1, abs=1e-6)
    tilted = flat()
    tilted[:, 0], tilted[:, 2] = math.sin(0.2), math.cos(0.2)
    # Normals are compared as stored, (n + 1) / 2: half the difference of the vectors.
    expected = math.sqrt(((math.sin(0.2) / 2) ** 2 + ((1 - math.cos(0.2)) / 2) ** 2) / 3)
    assert float(map_rmse(tilted, flat())["normal"][0]) == pytest.approx(expected, rel=1e-5)
    # SSIM of two constant images by hand: (2 x y + c1) / (x^2 + y^2 + c1).
    x, y, c1 = 0.3, 0.5, 0.01**2
    value = ssim(torch.full((1, 1, 16, 16), x, dtype=torch.float64), torch.full((1, 1, 16, 16), y, dtype=torch.float64))
    assert float(value[0]) == pytest.approx((2 * x * y + c1) / (x * x + y * y + c1), rel=1e-5)


def test_light_error_by_hand():
    height = 1 / math.tan(math.radians(22.5))
    offset = (height * math.tan(math.radians(10.0)), 0.0)
    assert light_error_deg(offset, (0.0, 0.0)) == pytest.approx(10.0, abs=1e-6)


def test_trivial_baseline_is_flat_and_the_set_mean():
    maps = torch.cat([flat(diffuse=0.2), flat(diffuse=0.6)])
    baseline = trivial_baseline(maps)
    assert torch.allclose(baseline[3:6], torch.full((3, 16, 16), 0.4))
    assert torch.equal(baseline[0:3, 0, 0], torch.tensor([0.0, 0.0, 1.0]))


def test_random_lights_are_seeded_and_shared():
    a, b = random_lights_and_views(30, seed=3), random_lights_and_views(30, seed=3)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], random_lights_and_views(30, seed=4)[0])
    assert (a[0][:, 2] > 0).all() and (a[1][:, 2] > 0).all()


def test_evaluation_is_seeded_and_skips_a_corrupt_material(evaluation_dataset, tmp_path):
    folder, model = evaluation_dataset
    summaries = []
    for run in ("a", "b"):
        config = EvaluationConfig(data=str(folder), format="folder", out=str(tmp_path / run), model=str(model),
                                  baselines=True, refine=RefineConfig(steps=3))
        with pytest.warns(UserWarning, match="skipping"):
            summaries.append(run_evaluation(config, progress=False))
    a, b = summaries
    assert a["n_materials"] == 3 and a["skipped"] == 1
    # Equal but for float rounding: the refinement's gradients are summed by drjit's threads, in an
    # order that the machine's load decides.
    for key in ("maps_rmse", "render_rmse", "render_flip", "render_ssim"):
        assert a[key] == pytest.approx(b[key], rel=1e-5, abs=1e-7), key
    assert set(a["rows"]) == {"model (no refinement)", "model + refinement (3 steps, normals kept)", "trivial"}
    assert a["render_rmse_torch_reference"] == pytest.approx(a["render_rmse"], rel=1e-3)
    for name in ("summary.json", "per_material.csv", "table.md", "bars.png", "gallery.png"):
        assert (tmp_path / "a" / name).is_file(), name
    written = json.loads((tmp_path / "a" / "summary.json").read_text())
    # LPIPS is computed only where its weights are on this machine (nothing is downloaded); the note says which.
    from mideepbasis.evaluation import LPIPS

    if LPIPS.weight_files()[2] is None:
        assert isinstance(written["render_lpips"], float) and written["render_lpips"] >= 0
    else:
        assert written["render_lpips"] is None and any("LPIPS skipped" in note for note in written["notes"])
    assert (tmp_path / "a" / "per_material.csv").read_text().count("\n") == 1 + 3 * 3


def test_lpips_plumbing_with_a_seeded_backbone_of_alexnets_shapes(tmp_path):
    # The real weights are never downloaded; random ones of the same shapes test the loading and the formula.
    from mideepbasis.evaluation import LPIPS

    torch.manual_seed(0)
    shapes = {"features.0": (64, 3, 11, 11), "features.3": (192, 64, 5, 5), "features.6": (384, 192, 3, 3),
              "features.8": (256, 384, 3, 3), "features.10": (256, 256, 3, 3)}
    state = {}
    for name, shape in shapes.items():
        state[f"{name}.weight"] = torch.randn(shape) * 0.05
        state[f"{name}.bias"] = torch.zeros(shape[0])
    state["classifier.1.weight"] = torch.zeros(2, 2)  # ignored: only the features are used
    alexnet, linear = tmp_path / "alexnet.pth", tmp_path / "alex.pth"
    torch.save(state, alexnet)
    lins = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate(LPIPS.CHANNELS)}
    torch.save(lins, linear)
    metric = LPIPS(alexnet, linear)
    a, b = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
    assert torch.allclose(metric(a, a), torch.zeros(2), atol=1e-7)
    forward, backward = metric(a, b), metric(b, a)
    assert (forward > 0).all() and torch.allclose(forward, backward, rtol=1e-5)
    # The distance is linear in the per-layer weights: doubling them doubles it.
    torch.save({k: 2 * v for k, v in lins.items()}, linear)
    assert torch.allclose(LPIPS(alexnet, linear)(a, b), 2 * forward, rtol=1e-5)


def test_strips_with_inward_normals_are_repaired_for_rendering_and_compared_as_stored(tmp_path):
    from mideepbasis.evaluation import load_evaluation_materials
    from mideepbasis.imageio import write_image
    from mideepbasis.material import REPAIRED_NORMAL_Z, Material, MaterialError

    generator = torch.Generator().manual_seed(0)
    size = 512
    panels = []
    normal = torch.zeros(3, size, size)
    normal[2] = 1.0
    normal[:, :4, :5] = torch.tensor([0.6, 0.0, -0.8]).view(3, 1, 1)  # 20 pixels point into the surface
    panels.append((normal + 1) / 2)
    panels += [torch.rand(3, size, size, generator=generator), torch.full((3, size, size), 0.5),
               torch.full((3, size, size), 0.04)]
    strip = torch.cat(panels, dim=2).permute(1, 2, 0).numpy()
    folder = tmp_path / "strips"
    folder.mkdir()
    write_image(folder / "inward.png", strip)
    write_image(folder / "clean.png", torch.cat([(torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, size, size) + 1) / 2,
                                                 *panels[1:]], dim=2).permute(1, 2, 0).numpy())
    with pytest.raises(MaterialError, match="normals point into the surface"):
        Material.from_deschaintre(folder / "inward.png", repair_normals=False)
    materials = load_evaluation_materials(folder, "deschaintre4")
    assert materials.skipped == 0 and materials.names == ["clean", "inward"]
    assert materials.repaired_pixels == [0, 20]
    repaired, stored = materials.maps[1, :3, :4, :5], materials.stored[1, :3, :4, :5]
    assert (stored[2] < -0.7).all()  # compared as stored (8-bit quantised, unit length)
    assert torch.allclose(repaired[2], torch.full((4, 5), REPAIRED_NORMAL_Z / (REPAIRED_NORMAL_Z**2 + 0.6**2) ** 0.5),
                          atol=2e-3)  # rendered above the surface
    assert torch.equal(materials.maps[0], materials.stored[0])  # nothing to repair: one and the same
    assert torch.equal(materials.maps[1, 3:], materials.stored[1, 3:])


def test_evaluation_counts_the_repaired_normals(tmp_path, evaluation_dataset):
    from mideepbasis.imageio import write_image

    _, model = evaluation_dataset
    size = 512
    normal = torch.zeros(3, size, size)
    normal[2] = 1.0
    normal[:, :8, :8] = torch.tensor([0.0, 0.6, -0.8]).view(3, 1, 1)
    rest = [torch.full((3, size, size), 0.3), torch.full((3, size, size), 0.5), torch.full((3, size, size), 0.04)]
    folder = tmp_path / "strips"
    folder.mkdir()
    write_image(folder / "inward.png", torch.cat([(normal + 1) / 2, *rest], dim=2).permute(1, 2, 0).numpy())
    summary = run_evaluation(EvaluationConfig(data=str(folder), format="deschaintre4", out=str(tmp_path / "out"),
                                              model=str(model), resolution=64), progress=False)
    assert summary["n_materials"] == 1 and summary["skipped"] == 0
    assert summary["repaired_normal_pixels"] == 64 and summary["materials_with_repaired_normals"] == 1
    assert any("pointing into the surface" in note for note in summary["notes"])
    assert math.isfinite(summary["render_rmse"])


def test_evaluation_averages_over_the_symmetries_capture_does_unless_told(evaluation_dataset, tmp_path):
    from mideepbasis.capturing import CaptureConfig

    folder, model = evaluation_dataset
    summaries = {}
    for symmetries in (None, 1):
        config = EvaluationConfig(data=str(folder), format="folder", out=str(tmp_path / str(symmetries)),
                                  model=str(model), symmetries=symmetries)
        with pytest.warns(UserWarning, match="skipping"):
            summaries[symmetries] = run_evaluation(config, progress=False)
    assert summaries[None]["symmetries"] == CaptureConfig().symmetries == 8
    assert summaries[1]["symmetries"] == 1
    # The averaged prediction is another prediction: its errors differ from the single pass's.
    assert summaries[None]["maps_rmse"] != summaries[1]["maps_rmse"]


def test_the_direct_baseline_row_runs_a_network_without_bases(evaluation_dataset, tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    folder, model = evaluation_dataset
    torch.manual_seed(0)
    direct = save_checkpoint(tmp_path / "direct.safetensors", DeepBasisNet(preset("tiny", use_bases=False)).eval())
    config = EvaluationConfig(data=str(folder), format="folder", out=str(tmp_path / "out"), model=str(model),
                              baselines=True, direct_model=str(direct), limit=2)
    with pytest.warns(UserWarning, match="skipping"):
        summary = run_evaluation(config, progress=False)
    assert "direct (no bases)" in summary["rows"] and summary["rows"]["direct (no bases)"]["render_rmse"] > 0


def test_an_evaluation_passes_the_capture_options_it_sets_and_leaves_the_rest_to_capture():
    from mideepbasis.capturing import CaptureConfig
    from mideepbasis.evaluation.run import SHARED_CAPTURE_FIELDS, evaluation_capture_config

    default = evaluation_capture_config(EvaluationConfig(data="d"), fov=30.0)
    assert default == CaptureConfig(fov=30.0)
    given = {"symmetries": 2, "relief_test": False, "fine_relief_strength": 3.0,
             "relief_reader": "reader.safetensors", "denoise_detail": True, "keep_lobe_peak": False,
             "grey_specular": True, "specular_floor": 0.0, "normal_strength": 0.5, "lobe_variation": 0.25}
    # The fine relief's strength and reader apply only with the fine relief on, capture's default, and
    # the colour test only with it off.
    assert set(given) | {"fine_relief", "colour_test"} == set(SHARED_CAPTURE_FIELDS)
    config = evaluation_capture_config(EvaluationConfig(data="d", **given), fov=30.0, detail=False)
    assert {name: getattr(config, name) for name in given} == given
    assert config.fov == 30.0 and config.detail is False
    for name, value in given.items():  # each differs from capture's default, so each was passed on
        assert getattr(CaptureConfig(), name) != value
    assert CaptureConfig().fine_relief
    without = evaluation_capture_config(EvaluationConfig(data="d", fine_relief=False, colour_test=True))
    assert not without.fine_relief and without.colour_test and not CaptureConfig().colour_test


def test_evaluate_refuses_a_lobe_variation_outside_zero_to_one(capsys):
    from mideepbasis.cli import main

    with pytest.raises(SystemExit):
        main(["evaluate", "--data", "nowhere", "--lobe-variation", "1.5"])
    assert "--lobe-variation: must lie in [0, 1], got 1.5" in capsys.readouterr().err
