"""The real-photo protocol (``evaluation.real``): calibrated scenes read with one-line errors, a
scene rendered from a known material scored about 0 with that material, and the command."""

from __future__ import annotations

import json
import math

import pytest
import torch

from mideepbasis import cli, constants
from mideepbasis.errors import InputError
from mideepbasis.evaluation import real
from mideepbasis.imageio import write_image
from mideepbasis.material import Material
from mideepbasis.render import reference

SIDE_CM = 8.0


def positions_cm():
    """Nine co-located camera-and-flash positions [cm] around a centre, about 20 cm up."""
    angles = torch.linspace(0, 2 * math.pi, 9)[:8]
    others = torch.stack([2.5 * torch.cos(angles), 2.5 * torch.sin(angles), 19.0 + torch.sin(3 * angles)], -1)
    return torch.cat([torch.tensor([[0.4, -0.3, 20.0]]), others])


def known_material(size=64):
    generator = torch.Generator().manual_seed(0)
    normal = torch.nn.functional.normalize(torch.randn(3, size, size, generator=generator) * 0.1
                                           + torch.tensor([0, 0, 1.0]).view(3, 1, 1), dim=0)
    diffuse = 0.1 + 0.5 * torch.rand(3, size, size, generator=generator)
    return Material(normal, diffuse, torch.full((1, size, size), 0.4), torch.full((3, size, size), 0.04))


def write_scene(folder, material, positions, exposure=0.8):
    """Photos of ``material`` at ``positions`` [cm] by the torch reference renderer, as 8-bit sRGB
    PNGs, and the position files."""
    half = SIDE_CM / 2
    lights = positions / half
    intensity = math.pi * float(lights[0, 2]) ** 2
    photos = reference.render_flash(material.to_tensor()[None], lights[None], intensity, views=lights[None])[0]
    folder.mkdir(parents=True)
    for index, photo in enumerate(photos):
        write_image(folder / f"{index:02d}.png", (exposure * photo).clamp(0, 1).permute(1, 2, 0).numpy(),
                    encode_srgb=True)
    lines = "".join(",".join(f"{v:.5f}" for v in row.tolist()) + "\n" for row in positions)
    (folder / "camera_pos.txt").write_text(lines)
    (folder / "light_pos.txt").write_text(lines)
    (folder / "image_size.txt").write_text(f"{SIDE_CM}\n")
    material.save(folder / "truth", format="png16")
    return folder


def test_a_scene_of_a_known_material_scores_about_zero_with_that_material(tmp_path):
    material = known_material()
    scene = real.load_scene(write_scene(tmp_path / "scene", material, positions_cm()))
    assert scene.fov(0) == pytest.approx(math.degrees(2 * math.atan(4.0 / 20.0)))
    photos = real.scene_photos(scene, 64)
    scores = real.score_rerenders(material.to_tensor(), photos, scene, 0, constants.DEFAULT_CONVENTION)
    assert scores.exposure == pytest.approx(0.8, rel=0.01)  # the photos' exposure, fitted on photo 00
    assert scores.rmse < 0.004 and scores.ssim > 0.99  # 8-bit quantisation
    # The other photos as input: the same.
    assert real.score_rerenders(material.to_tensor(), photos, scene, 5, constants.DEFAULT_CONVENTION).rmse < 0.004
    # A wrong material does not.
    grey = real.constant_material(64, 64, **real.FLAT_GREY)
    assert real.score_rerenders(grey, photos, scene, 0, constants.DEFAULT_CONVENTION).rmse > 0.03


def test_parameters_json_is_read_like_the_text_files(tmp_path):
    folder = write_scene(tmp_path / "scene", known_material(16), positions_cm())
    from_text = real.load_scene(folder)
    for name in real.POSITION_FILES:
        (folder / name).unlink()
    (folder / "parameters.json").write_text(json.dumps({"camera_pos": positions_cm().tolist(),
                                                        "light_pos": positions_cm().tolist(), "image_size": SIDE_CM}))
    from_json = real.load_scene(folder)
    torch.testing.assert_close(from_json.cameras, from_text.cameras)
    assert real.is_calibrated(folder) and real.is_calibrated(tmp_path)


@pytest.mark.parametrize("damage,message", [
    (lambda f: (f / "light_pos.txt").write_text((f / "light_pos.txt").read_text().replace("0.40000,-0.30000,20.00000",
                                                                                          "9.0,-0.3,20.0")),
     "wrong light position"),
    (lambda f: (f / "camera_pos.txt").write_text((f / "camera_pos.txt").read_text().replace("20.00000", "-20.0")),
     "above the sample"),
    (lambda f: (f / "03.png").unlink(), "photo 03.png is missing"),
    (lambda f: (f / "light_pos.txt").write_text("1,2\n" + (f / "light_pos.txt").read_text()), "line 1: expected 3"),
    (lambda f: (f / "image_size.txt").unlink(), "image_size.txt: missing"),
    (lambda f: (f / "08.png").unlink(), "8 camera positions for... "[:0] + "9 camera positions for 8 photos"),
])
def test_bad_scene_files_are_one_line(tmp_path, damage, message):
    folder = write_scene(tmp_path / "scene", known_material(16), positions_cm())
    damage(folder)
    with pytest.raises(InputError, match=message) as raised:
        real.load_scene(folder)
    assert "\n" not in str(raised.value) and str(folder) in str(raised.value)


def tiny_model(folder):
    """An untrained tiny model's checkpoint in ``folder``."""
    import mideepbasis.model.checkpoint as checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    return checkpoint.save_checkpoint(folder / "tiny.safetensors", DeepBasisNet(preset("tiny")).eval())


def test_the_command_runs_the_protocol_and_skips_a_bad_scene(tmp_path, capsys):
    model = tiny_model(tmp_path)
    data = tmp_path / "scenes"
    write_scene(data / "good", known_material(64), positions_cm())
    write_scene(data / "broken", known_material(64), positions_cm())
    (data / "broken" / "02.png").unlink()
    out = tmp_path / "out"
    assert cli.main(["evaluate", "--data", str(data), "--model", str(model), "-o", str(out), "--symmetries", "1",
                     "--resolution", "64", "--upsampled-from", "32"]) == 0
    printed = capsys.readouterr().out
    assert "photo 02.png is missing" in printed and "1 scenes" in printed
    summary = json.loads((out / "summary.json").read_text())
    rows = summary["rows"]
    assert set(rows) == {real.CAPTURE_ROW, real.UNREFINED_ROW, real.GREY_ROW, real.LAMBERTIAN_ROW, real.TRUTH_ROW,
                         real.PAPER_ROW, real.upsampled_row(32)}
    assert rows[real.TRUTH_ROW]["rmse"] < 0.004 and rows[real.PAPER_ROW]["rmse"] == real.PAPER_REAL_RMSE
    assert all(0 <= rows[row]["ssim"] <= 1 and rows[row]["flip"] >= 0 for row in rows if row != real.PAPER_ROW)
    assert (out / "sheets" / "good.png").is_file() and "| capture (default) |" in (out / "table.md").read_text()


def test_every_input_photo_has_its_own_figure_beside_the_mean(tmp_path, capsys):
    model = tiny_model(tmp_path)
    data = tmp_path / "scenes"
    write_scene(data / "good", known_material(64), positions_cm())
    common = ["--data", str(data), "--model", str(model), "--symmetries", "1", "--refine-steps", "0",
              "--resolution", "64"]
    assert cli.main(["evaluate", *common, "-o", str(tmp_path / "all"), "--input-photo", "all"]) == 0
    assert cli.main(["evaluate", *common, "-o", str(tmp_path / "third"), "--input-photo", "3"]) == 0
    capsys.readouterr()
    every = json.loads((tmp_path / "all" / "summary.json").read_text())
    third = json.loads((tmp_path / "third" / "summary.json").read_text())
    per_input = every["per_input"]["good"]
    assert per_input["inputs"] == list(range(9))
    captured = per_input["rmse"][real.CAPTURE_ROW]
    # Each input's figure is the one a run from that photo alone gives; the mean is theirs.
    assert captured[3] == pytest.approx(third["rows"][real.CAPTURE_ROW]["rmse"], abs=1e-6)
    assert sum(captured) / 9 == pytest.approx(every["rows"][real.CAPTURE_ROW]["rmse"], abs=1e-9)
    assert len(set(round(value, 6) for value in captured)) > 1
    table = (tmp_path / "all" / "table.md").read_text()
    assert "RMSE of good per input photo" in table and f"| {captured[3]:.5f} |" in table
    assert "per input photo" not in (tmp_path / "third" / "table.md").read_text()


def test_native_resolution_compares_each_scene_at_its_photos_own_size(tmp_path, capsys):
    model = tiny_model(tmp_path)
    data = tmp_path / "scenes"
    write_scene(data / "small", known_material(64), positions_cm())
    out = tmp_path / "out"
    assert cli.main(["evaluate", "--data", str(data), "--model", str(model), "-o", str(out), "--symmetries", "1",
                     "--refine-steps", "0", "--resolution", "native"]) == 0
    capsys.readouterr()
    summary = json.loads((out / "summary.json").read_text())
    # At the photos' own 64 px, where capture's default would resample them to 256 px.
    assert summary["working_resolution"] == "native" and summary["compared_at"] == {"small": 64}
    assert summary["rows"][real.CAPTURE_ROW]["rmse"] > 0


def test_the_evaluation_resolution_is_native_or_pixels_with_a_one_line_error():
    from mideepbasis.evaluation.run import evaluation_resolution

    assert evaluation_resolution("native") == "native" and evaluation_resolution("512") == 512
    with pytest.raises(ValueError, match="expected native or a size in pixels, got 'nat'"):
        evaluation_resolution("nat")
    with pytest.raises(ValueError, match="positive integer, got 0"):
        evaluation_resolution("0")


def test_validation_scenes_are_calibrated_scenes_with_their_truth(tmp_path):
    from mideepbasis.data.scenes import PHOTOS_PER_SCENE, make_scenes

    folders = make_scenes(tmp_path, 2, size=32, progress=False)
    assert [f.name for f in folders] == ["scene0000", "scene0001"]
    for folder in folders:
        scene = real.load_scene(folder)
        assert len(scene.photos) == PHOTOS_PER_SCENE and scene.truth is not None
        assert 20.0 <= scene.fov(0) <= 75.0
        assert Material.load(scene.truth).width == 32
    # The same seeds give the same scenes.
    again = make_scenes(tmp_path / "again", 1, size=32, progress=False)[0]
    assert (again / "04.png").read_bytes() == (folders[0] / "04.png").read_bytes()


def test_a_smaller_capture_upsampled_is_scored_at_the_working_resolution(tmp_path, monkeypatch):
    # The capture at 32 px is stood in by the true material area-averaged to 32 px: upsampled
    # back, it loses only the fine texture, and its row scores between the truth and flat grey.
    from mideepbasis.capturing import CaptureConfig, Capturer
    from mideepbasis.resampling import downsample_maps

    material = known_material(64)
    scene = real.load_scene(write_scene(tmp_path / "scene", material, positions_cm()))
    photos = real.scene_photos(scene, 64)

    class Captured:
        def __init__(self, size):
            self.material = Material.from_tensor(downsample_maps(material.to_tensor()[None], size)[0])

    monkeypatch.setattr(Capturer, "capture", lambda self, image, progress=False: Captured(self.config.resolution))
    capturer = Capturer(tiny_model(tmp_path), CaptureConfig(resolution=64, symmetries=1))
    upsampled = real.materials_of_scene(capturer, scene, 0, photos[0], upsampled_from=32)[real.upsampled_row(32)]
    assert upsampled.shape == (10, 64, 64)
    truth_rmse = real.score_rerenders(material.to_tensor(), photos, scene, 0, constants.DEFAULT_CONVENTION).rmse
    rmse = real.score_rerenders(upsampled, photos, scene, 0, constants.DEFAULT_CONVENTION).rmse
    grey = real.score_rerenders(real.constant_material(64, 64, **real.FLAT_GREY), photos, scene, 0,
                                constants.DEFAULT_CONVENTION).rmse
    assert truth_rmse < 0.004 < rmse < grey
    with pytest.raises(InputError, match="not below the working resolution"):
        real.evaluate_scene(capturer, scene, [0], upsampled_from=64)


def test_upsampled_from_is_refused_on_synthetic_data(tmp_path):
    from mideepbasis.evaluation import EvaluationConfig, run_evaluation

    (tmp_path / "data").mkdir()
    with pytest.raises(InputError, match="calibrated scenes only"):
        run_evaluation(EvaluationConfig(data=str(tmp_path / "data"), out=str(tmp_path / "out"), upsampled_from=32))
