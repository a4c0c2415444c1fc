"""The relief reader: its inputs, their mirrorings, its weights file, and a resumable training run."""

from __future__ import annotations

import json
import math

import pytest
import torch

from mideepbasis import geometry
from mideepbasis.errors import InputError
from mideepbasis.model.relief_reader import (CONTRAST_LIMIT, READER_CHANNELS, ReliefReader, ReliefReaderConfig,
                                             load_reader, read_relief, reader_inputs, save_reader)
from mideepbasis.train.relief_reader import (ReliefTrainingConfig, framed_flashes, mirror, mirror_points, mirrored,
                                             rerender_error, train_reader)

FOV = 45.0


def _photo(seed: int = 0, size: int = 64) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return 0.05 + 0.5 * torch.rand(1, 3, size, size, generator=generator)


def test_the_inputs_of_a_uniform_photo_hold_no_contrast_and_point_at_the_flash():
    light = geometry.light_positions(torch.tensor([[0.2, -0.1]]), FOV)
    inputs = reader_inputs(torch.full((1, 3, 32, 32), 0.3), light, (8, 8), FOV)
    assert inputs.shape == (1, READER_CHANNELS, 32, 32)
    assert inputs[:, 0:4].abs().max() < 1e-5
    # The level channel: 1 + 2 log(0.3) / -log(1e-3).
    assert torch.allclose(inputs[:, 5], torch.tensor(1.0 + 2.0 * math.log(0.3) / -math.log(1e-3)), atol=1e-5)
    points = geometry.pixel_points(32, 32)
    towards = light.view(3, 1, 1) - points
    expected = towards / towards.norm(dim=0, keepdim=True)
    assert torch.allclose(inputs[0, 6:9], expected, atol=1e-5)


def test_the_contrast_is_the_photo_against_its_band_and_clipped():
    photo = torch.full((1, 3, 32, 32), 0.2)
    photo[..., 5, 7] = 0.3  # one brighter pixel in a 4 x 4 cell of the 8 px band
    photo[..., 20, 20] = 50.0  # a glint, clipped to 1 first
    inputs = reader_inputs(photo, torch.tensor([0.0, 0.0, 2.0]), (8, 8), FOV)
    # Away from the bright pixels the band holds the flat level: no contrast.
    assert inputs[0, 0:4, 28:, 0:4].abs().max() < 1e-5
    assert inputs[0, 0, 5, 7] > 0.3  # (0.3 - about 0.206) / 0.206
    assert inputs[0, 0:4].max() <= CONTRAST_LIMIT + 1e-6


@pytest.mark.parametrize("unit_inputs", [False, True])
@pytest.mark.parametrize("flips", [(True, False, False), (False, True, False), (False, False, True),
                                   (True, True, True)])
def test_mirrored_inputs_are_the_inputs_of_the_mirrored_photo(flips, unit_inputs):
    """The training's mirrorings turn the vector channels as the photo's geometry turns them:
    mirroring the inputs of a photo gives the inputs of the mirrored photo under the mirrored flash."""
    photo = _photo()
    light = torch.tensor([[0.3, -0.2, 2.5]])
    inputs = reader_inputs(photo, light, (16, 16), FOV, unit_inputs=unit_inputs)
    mirrored_inputs, _ = mirrored(inputs, torch.zeros(1, 2, 64, 64), flips)
    turned_photo, (x, y) = photo, (0.3, -0.2)
    if flips[0]:
        turned_photo, x = turned_photo.flip(-1), -x
    if flips[1]:
        turned_photo, y = turned_photo.flip(-2), -y
    if flips[2]:
        turned_photo, (x, y) = turned_photo.transpose(-1, -2), (-y, -x)
    expected = reader_inputs(turned_photo, torch.tensor([[x, y, 2.5]]), (16, 16), FOV, unit_inputs=unit_inputs)
    assert torch.allclose(mirrored_inputs, expected, atol=1e-5)


def test_a_reader_from_the_normal_unit_reads_as_the_unit():
    from mideepbasis.model.checkpoint import load_model
    from mideepbasis.model.inputs import relief_inputs
    from mideepbasis.model.relief_reader import from_normal_unit

    model = load_model(None)
    reader = from_normal_unit(model).eval()
    photo, light = _photo(size=64), torch.tensor([[0.2, 0.1, 2.4]])
    with torch.no_grad():
        read = reader(reader_inputs(photo, light, (16, 16), FOV, unit_inputs=True))
        unit = torch.tanh(model.normal_unit(relief_inputs(photo, light, FOV)))
    assert float(unit.abs().max()) > 1e-3
    assert torch.allclose(read, unit, atol=1e-5)


def test_mirrored_targets_turn_as_the_normals_of_a_mirrored_surface():
    # A ramp rising to the right has a normal leaning left (x < 0) everywhere; mirrored left-right it
    # leans right; transposed (rows down, y up) the ramp rises downward and leans up.
    target = torch.zeros(1, 2, 8, 8)
    target[:, 0] = -0.3
    _, flipped = mirrored(torch.zeros(1, READER_CHANNELS, 8, 8), target, (True, False, False))
    assert torch.allclose(flipped[:, 0], torch.tensor(0.3))
    _, transposed = mirrored(torch.zeros(1, READER_CHANNELS, 8, 8), target, (False, False, True))
    assert torch.allclose(transposed[:, 1], torch.tensor(0.3)) and transposed[:, 0].abs().max() == 0


def test_a_mirrored_crop_framed_as_a_sample_renders_as_that_part_of_the_image():
    """The re-rendering loss renders each crop on its own, mirrored: it must be the crop of the
    whole image's render, mirrored."""
    from mideepbasis.data.procedural import generate
    from mideepbasis.render import render_flash

    maps = generate(3, size=64).to_tensor()[None]
    flashes = torch.tensor([[0.3, -0.2, 2.2], [-0.5, 0.1, 2.6]])
    whole = render_flash(maps, flashes[None], intensity=5.0)[0]
    top, left, crop = 8, 24, 32
    part = whole[..., top:top + crop, left:left + crop]
    for flips in ((False, False, False), (True, False, True), (False, True, False), (True, True, True)):
        crop_maps = mirror(maps[..., top:top + crop, left:left + crop], ((0, 1),), flips)
        lights = mirror_points(framed_flashes(flashes, top, left, crop, 64), flips)
        rendered = render_flash(crop_maps, lights[None], intensity=5.0, extent=crop / 64)[0]
        expected = part
        if flips[0]:
            expected = expected.flip(-1)
        if flips[1]:
            expected = expected.flip(-2)
        if flips[2]:
            expected = expected.transpose(-1, -2)
        assert torch.allclose(rendered, expected, atol=1e-4, rtol=1e-3), flips


def test_the_rerendering_error_is_zero_for_the_true_slope_and_grows_with_a_misread_one():
    from mideepbasis.data.procedural import generate
    from mideepbasis.evaluation import above_band

    maps = generate(5, size=64, family="concrete").to_tensor()[None]
    target = above_band(maps[:, 0:2], 8)
    lights = torch.tensor([[[0.2, 0.1, 2.4], [-0.3, 0.2, 2.2]]])
    intensity = torch.tensor([math.pi * 2.3**2])
    assert float(rerender_error(maps, target, target, lights, 1.0, intensity)) < 1e-10
    flat = float(rerender_error(maps, torch.zeros_like(target), target, lights, 1.0, intensity))
    doubled = float(rerender_error(maps, 2 * target, target, lights, 1.0, intensity))
    assert flat > 1e-5 and doubled > 1e-5


def test_a_reader_round_trips_through_its_file_and_reads_above_the_band(tmp_path):
    torch.manual_seed(0)
    reader = ReliefReader(ReliefReaderConfig(width=8, encoder_blocks=(1, 1), middle_blocks=1))
    path = save_reader(tmp_path / "reader.safetensors", reader, {"step": 3})
    loaded, document, others = load_reader(path)
    assert document["step"] == 3 and not others
    assert loaded.config == reader.config
    photo = _photo(size=80)
    slope = read_relief(loaded, photo, torch.tensor([0.0, 0.0, 2.5]), FOV, (10, 10), max_size=40)
    # Area-averaged to 40 px, a multiple of the reader's 4; its 10 px band taken out.
    assert slope.shape == (1, 2, 40, 40)
    from mideepbasis.resampling import downsample
    with torch.no_grad():
        direct = reader(reader_inputs(torch.nn.functional.avg_pool2d(photo, 2), torch.tensor([0.0, 0.0, 2.5]),
                                      (10, 10), FOV))
    assert torch.allclose(slope, direct - torch.nn.functional.interpolate(
        downsample(direct, (10, 10)), size=(40, 40), mode="bilinear", align_corners=False), atol=1e-5)


def test_a_file_that_is_not_a_reader_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a safetensors file")
    with pytest.raises(InputError, match="bad.safetensors: not a safetensors file") as error:
        load_reader(bad)
    assert "\n" not in str(error.value)
    with pytest.raises(InputError, match="no such relief reader file"):
        load_reader(tmp_path / "missing.safetensors")


def test_a_training_run_validates_checkpoints_and_resumes_where_it_stopped(tmp_path):
    config = ReliefTrainingConfig(out=str(tmp_path / "run"), steps=24, batch=2, crop=48, size=64, band=8, pool=2,
                                  refresh_every=4, learning_rate=2e-3, validate_every=12, validation_count=2,
                                  width=8, threads=1, render_weight=1.0, render_lights=2)
    train_reader(config, resume=False, progress=False)
    reader, document, tensors = load_reader(tmp_path / "run" / "checkpoint.safetensors")
    assert document["step"] == 24 and document["next_material"] == 2 + 24 // 4
    assert any(name.startswith("adam.") for name in tensors)
    records = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [record["step"] for record in records if "validation" in record] == [12, 24]
    assert (tmp_path / "run" / "best.safetensors").exists()
    with pytest.raises(InputError, match="already holds a run"):
        train_reader(config, resume=False, progress=False)
    train_reader(config.__class__(**{**config.__dict__, "steps": 36}), resume=True, progress=False)
    _, document, _ = load_reader(tmp_path / "run" / "checkpoint.safetensors")
    assert document["step"] == 36 and document["next_material"] == 2 + 36 // 4


def test_a_run_from_the_normal_unit_keeps_its_architecture_and_inputs(tmp_path):
    config = ReliefTrainingConfig(out=str(tmp_path / "unit"), steps=2, batch=1, crop=48, size=64, band=8, pool=1,
                                  refresh_every=10, validate_every=0, threads=1, init_from_unit=True)
    train_reader(config, resume=False, progress=False)
    reader, document, _ = load_reader(tmp_path / "unit" / "checkpoint.safetensors")
    assert reader.config.unit_inputs and reader.config.bounded
    assert reader.net.intro.weight.shape[1] == reader.config.in_channels == READER_CHANNELS + 7
    assert document["training"]["init_from_unit"] is True
