"""Capture: lighting search, refinement, outputs (material, Mitsuba scene, glTF, report), batch and bad input."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from mideepbasis import cli, constants, geometry
from mideepbasis.capturing import (CaptureConfig, Capturer, Photo, RefineConfig, SearchConfig, capture,
                                 field_of_view_from_focal, load_photo, predict, refine_global_bases)
from mideepbasis.evaluation import flash_photos, light_error_deg
from mideepbasis.export import save_capture
from mideepbasis.imageio import write_image
from mideepbasis.material import Material
from mideepbasis.model.checkpoint import load_model, save_checkpoint
from mideepbasis.model.network import (DeepBasisNet, DeepBasisOutput, NetworkConfig, normalize_basis_normals, preset,
                                       to_maps, to_signed)
from mideepbasis.render import render_flash


class OracleModel(DeepBasisNet):
    """Predicts the true material whatever it is shown (one basis: global mean plus per-pixel deviations).

    It isolates the lighting search and the refinement from the quality of a trained network.
    """

    def __init__(self, truth: torch.Tensor):
        super().__init__(preset("tiny", num_bases=1, use_local=True))
        self.truth = truth
        self.config = NetworkConfig(encoder_channels=(8,), decoder_channels=(), num_bases=1)

    def forward(self, inputs, lights=None, fov=constants.DEFAULT_FOV_DEG):
        signed = to_signed(self.truth)
        global_bases = signed.mean(dim=(2, 3)).view(1, 1, 10)
        deviations = (signed - global_bases.view(1, 10, 1, 1)).view(1, 1, 10, *signed.shape[-2:])
        weights = torch.ones(1, 1, *signed.shape[-2:])
        return DeepBasisOutput(maps=maps_by_hand(global_bases, deviations), weights=weights, global_bases=global_bases,
                               deviations=deviations)


def maps_by_hand(global_bases: torch.Tensor, deviations: torch.Tensor) -> torch.Tensor:
    """The maps of one basis with weight 1, written out here (not through the package's blend):
    signed basis = global + deviation, its normal part unit length with z >= 0, the other seven
    channels mapped from [-1, 1] to [0, 1]."""
    signed = global_bases.view(1, 10, 1, 1) + deviations[:, 0]
    normal = signed[:, :3] / signed[:, :3].norm(dim=1, keepdim=True)
    normal = torch.cat([normal[:, :2], normal[:, 2:].clamp(min=0.0)], dim=1)
    normal = normal / normal.norm(dim=1, keepdim=True)
    return torch.cat([normal, (signed[:, 3:].clamp(-1.0, 1.0) * 0.5 + 0.5).clamp(0.0, 1.0)], dim=1)


def oracle_search(truth, photo, config: SearchConfig):
    """The lighting search of capture's engine, with the oracle as its network."""
    return Capturer(OracleModel(truth), CaptureConfig(search=config)).search(Photo(photo, 45.0, "argument"))


def material(seed=3, size=64):
    from mideepbasis.data.procedural import GeneratorConfig, generate

    return generate(seed, config=GeneratorConfig(size=size, mix_probability=0.0, weathering=False)).to_tensor()[None]


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("model") / "tiny.safetensors"
    return save_checkpoint(path, DeepBasisNet(preset("tiny")).eval())


@pytest.mark.parametrize("seed,offset_deg", [(3, (6.0, -4.0)), (8, (-10.0, 3.0)), (21, (2.0, 9.0)), (30, (0.0, 0.0))])
def test_lighting_search_finds_the_flash(seed, offset_deg):
    truth = material(seed)
    height = constants.camera_height(45.0)
    offset = torch.tensor([[height * math.tan(math.radians(a)) for a in offset_deg]])
    photos, _ = flash_photos(truth, offset)
    found = oracle_search(truth, photos[0], SearchConfig(resolution=64))
    assert light_error_deg(found.offset, offset[0].tolist()) < 1.0, (found.offset, offset, found.history)
    assert 2 <= len(found.history) <= SearchConfig().passes + 1


def test_the_search_prior_pulls_toward_the_centre_only_where_the_photo_does_not_decide():
    truth = material(8)
    height = constants.camera_height(45.0)
    offset = torch.tensor([[height * math.tan(math.radians(a)) for a in (-10.0, 3.0)]])
    photos, _ = flash_photos(truth, offset)
    config = SearchConfig(resolution=64)
    # The default weight leaves a clear highlight where it is ...
    found = oracle_search(truth, photos[0], config).offset
    assert light_error_deg(found, offset[0].tolist()) < 1.0
    # ... and one far stronger than any photo error (mean L1 <= 1) puts the flash at the centre.
    centred = oracle_search(truth, photos[0], replace(config, prior=100.0)).offset
    assert centred == pytest.approx((0.0, 0.0), abs=1e-6)


#: The passes as the steered tests below follow them: from the centre, until the light stays.
FROM_THE_CENTRE = {"start": "centre", "settle_steps": 0.0}


class SteeredSearch:
    """A network and an objective for ``search_light`` that send the search along fixed lights:
    the material predicted under the flash at ``route[i]`` (grid steps (i, j) from the centre, where
    every search starts) makes the objective point at ``route[i + 1]``, and the last one's at
    ``route[loop_to]``, so that the passes can be made to go round a cycle."""

    def __init__(self, route: list[tuple[int, int]], loop_to: int, fov: float = 45.0):
        from mideepbasis.capturing.search import candidate_offsets

        self.fov = fov
        self.step = 2 * geometry.max_offset(fov, constants.MAX_OFFSET_DEG) / (SearchConfig().grid - 1)
        self.candidates = candidate_offsets(fov, constants.MAX_OFFSET_DEG, SearchConfig().grid)
        self.route = [torch.tensor(stop, dtype=torch.float32) * self.step for stop in [(0, 0), *route]]
        self.loop_to = loop_to + 1
        self.predictions = 0
        self.predicted_under = []

    def target(self, light: torch.Tensor) -> torch.Tensor:
        at = next(i for i, stop in enumerate(self.route) if torch.allclose(stop, light, atol=1e-5))
        return self.route[at + 1] if at + 1 < len(self.route) else self.route[self.loop_to]

    def predict(self, photos, lights):
        from types import SimpleNamespace

        self.predictions += 1
        self.predicted_under.append(lights[0, :2].clone())
        maps = torch.zeros(1, 10, 4, 4)
        maps[:, 2] = 1.0
        maps[:, 3:5] = lights[0, :2].view(1, 2, 1, 1)  # the light it was predicted under, kept in the diffuse
        return SimpleNamespace(maps=maps)

    def objective(self, maps, photo, offsets, fov, convention, extent=1.0):
        return torch.linalg.vector_norm(offsets - self.target(maps[0, 3:5, 0, 0]), dim=-1)

    def reference(self, passes: int) -> tuple[tuple[float, float], torch.Tensor]:
        """The search as documented, every pass run: the passes until the light stays, then the fine
        grid around the last candidate with the last pass's material. Returns the offset found and
        the light the last pass predicted under."""
        from mideepbasis.capturing.search import candidate_offsets

        def nearest(offsets, target):
            return offsets[int(torch.argmin(torch.linalg.vector_norm(offsets - target, dim=-1)))]

        current = torch.zeros(2)
        for _ in range(passes):
            predicted_under = current
            best = nearest(self.candidates, self.target(current))
            if torch.allclose(best, current, atol=1e-5):
                break
            current = best
        fine = candidate_offsets(self.fov, constants.MAX_OFFSET_DEG, 9, centre=tuple(current.tolist()), span=self.step)
        found = nearest(fine, self.target(predicted_under))
        return (float(found[0]), float(found[1])), predicted_under


@pytest.mark.parametrize("route, loop_to", [([(3, 0), (-4, 2), (2, 5)], 0), ([(3, 0), (-4, 2), (2, 5), (0, -6)], 1),
                                            ([(4, 4)], -1)])
def test_a_search_going_round_a_cycle_stops_early_where_all_its_passes_would_end(monkeypatch, route, loop_to):
    from mideepbasis.capturing import search as search_module

    photo = torch.zeros(3, 8, 8)
    for passes in range(1, 9):
        steered = SteeredSearch(route, loop_to)
        monkeypatch.setattr(search_module, "light_objective", steered.objective)
        found = search_module.search_light(steered.predict, photo, 45.0, "physical",
                                           config=SearchConfig(resolution=4, prior=0.0, passes=passes, **FROM_THE_CENTRE))
        offset, last_light = steered.reference(passes)
        assert found.offset == pytest.approx(offset, abs=1e-5), passes
        # One network pass per light until the cycle closes, never more than allowed.
        lights, cycle_start = len(steered.route), steered.loop_to
        assert steered.predictions == min(passes, lights), passes
        # Its prediction is the last pass's, as if every pass had run: where the last pass would
        # have been another than the latest, that one's prediction again, once, when first read.
        torch.testing.assert_close(found.output.maps[0, 3:5, 0, 0], last_light, atol=1e-5, rtol=0)
        found.output
        last = cycle_start + (passes - 1 - cycle_start) % (lights - cycle_start)
        expected = passes if passes <= lights else lights + (last != lights - 1)
        assert steered.predictions == expected, passes


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.4, -0.2), (-0.5, 0.3)])
def test_the_brightest_spot_of_a_flash_photo_lies_below_the_flash(offset):
    # A flat, uniform material: its photo is brightest where the flash is nearest and mirrors into
    # the camera, the plane point (tx, ty) below it. The estimate's pixel is 1/16 of the width.
    from mideepbasis.capturing.search import HIGHLIGHT_GRID, highlight_offset

    flat = torch.zeros(1, 10, 64, 64)
    flat[:, 2], flat[:, 3:6], flat[:, 6], flat[:, 7:10] = 1.0, 0.3, 0.35, 0.04
    photos, _ = flash_photos(flat, torch.tensor([offset]))
    found = highlight_offset(photos[0])
    assert found.tolist() == pytest.approx(offset, abs=1.01 / HIGHLIGHT_GRID)


def test_the_search_starts_at_the_candidate_below_the_photos_brightest_spot(monkeypatch):
    from mideepbasis.capturing import search as search_module

    steered = SteeredSearch([(3, -2)], loop_to=0)
    monkeypatch.setattr(search_module, "light_objective", steered.objective)
    photo = torch.full((3, 64, 64), 0.1)
    spot = steered.route[1] + torch.tensor([0.3, -0.2]) * steered.step  # off the grid, nearest (3, -2)
    column, row = int((spot[0] + 1) / 2 * 64), int((1 - spot[1]) / 2 * 64)
    photo[:, row - 1:row + 2, column - 1:column + 2] = 1.0
    found = search_module.search_light(steered.predict, photo, 45.0, "physical",
                                       config=SearchConfig(resolution=4, prior=0.0, start="highlight"))
    assert [tuple(round(float(v) / steered.step) for v in light) for light in steered.predicted_under] == [(3, -2)]
    assert len(found.history) == 2  # that one pass settles at once (its best is where it is), then the fine grid
    centred = SteeredSearch([(3, -2)], loop_to=0)
    monkeypatch.setattr(search_module, "light_objective", centred.objective)
    search_module.search_light(centred.predict, photo, 45.0, "physical", config=SearchConfig(resolution=4, prior=0.0,
                                                                                            start="centre"))
    assert [tuple(round(float(v) / centred.step) for v in light) for light in centred.predicted_under][0] == (0, 0)


def test_a_settled_search_stops_once_the_light_moves_by_a_grid_step_or_less(monkeypatch):
    from mideepbasis.capturing import search as search_module

    # From the centre one step right, then one more each pass: the light creeps, then stays.
    steered = SteeredSearch([(1, 0), (2, 0), (3, 0)], loop_to=2)
    monkeypatch.setattr(search_module, "light_objective", steered.objective)
    photo = torch.zeros(3, 8, 8)
    creeping = search_module.search_light(steered.predict, photo, 45.0, "physical",
                                          config=SearchConfig(resolution=4, prior=0.0, **FROM_THE_CENTRE))
    assert steered.predictions == 4  # three moves of one step, then the light stays
    assert creeping.offset == pytest.approx(steered.reference(SearchConfig().passes)[0], abs=1e-5)
    steered.predictions = 0
    settled = search_module.search_light(steered.predict, photo, 45.0, "physical",
                                         config=SearchConfig(resolution=4, prior=0.0, start="centre", settle_steps=1.0))
    assert steered.predictions == 1
    # Its material (predicted at the centre) holds the fine grid at the first step.
    assert settled.offset == pytest.approx((steered.step, 0.0), abs=1e-5)
    assert creeping.offset == pytest.approx((3 * steered.step, 0.0), abs=1e-5)
    # A move of two steps along one axis is not settled: the passes go on to where the light stays.
    leaping = SteeredSearch([(1, 2), (1, 3)], loop_to=1)
    monkeypatch.setattr(search_module, "light_objective", leaping.objective)
    found = search_module.search_light(leaping.predict, photo, 45.0, "physical",
                                       config=SearchConfig(resolution=4, prior=0.0, start="centre", settle_steps=1.0))
    assert leaping.predictions == 2
    assert found.offset == pytest.approx((leaping.step, 3 * leaping.step), abs=1e-5)


def test_an_over_relaxed_search_moves_past_the_best_candidate_on_the_grid(monkeypatch):
    from mideepbasis.capturing import search as search_module

    # A light that creeps one step right each pass until it stays at four steps.
    photo = torch.zeros(3, 8, 8)
    for relaxation, lights in ((1.0, [(0, 0), (1, 0), (2, 0), (3, 0), (4, 0)]), (2.0, [(0, 0), (2, 0), (4, 0)])):
        steered = SteeredSearch([(1, 0), (2, 0), (3, 0), (4, 0)], loop_to=3)
        monkeypatch.setattr(search_module, "light_objective", steered.objective)
        found = search_module.search_light(steered.predict, photo, 45.0, "physical",
                                           config=SearchConfig(resolution=4, prior=0.0, relaxation=relaxation,
                                                               **FROM_THE_CENTRE))
        assert [tuple(round(float(v) / steered.step) for v in light) for light in steered.predicted_under] == lights
        assert found.offset == pytest.approx((4 * steered.step, 0.0), abs=1e-5)


@pytest.mark.parametrize("normal_unit", [False, True])
def test_the_search_passes_run_the_normal_unit_only_when_asked_and_the_prediction_always(normal_unit):
    torch.manual_seed(3)
    model = DeepBasisNet(preset("tiny", normal_unit_width=4, normal_unit_blocks=(1, 1))).eval()
    with torch.no_grad():  # a unit that changes the normals, so that its absence shows
        model.normal_unit.ending.bias.fill_(0.3)
    calls = []
    slope = model.normal_slope
    model.normal_slope = lambda *args, **kwargs: calls.append(1) or slope(*args, **kwargs)
    capturer = Capturer(model, CaptureConfig(fov=45.0, symmetries=1, network_resolution=0,
                                             search=SearchConfig(grid=5, resolution=16, passes=2, normal_unit=normal_unit)))
    photo = Photo(torch.rand(3, 32, 32) * 0.5, 45.0, "argument")
    found = capturer.search(photo)
    passes = sum(isinstance(entry["pass"], int) for entry in found.history)
    assert len(calls) == (passes if normal_unit else 0)
    # The search's last pass is the network's answer with or without the unit at its light.
    last_light = torch.tensor(found.history[-2]["offset"])
    inputs_light = geometry.light_positions(last_light[None], 45.0)
    reference = predict(model, photo.pixels[None], inputs_light, 45.0, network_resolution=0).maps
    unit_off = model(encode(photo.pixels[None], inputs_light, model), inputs_light, fov=45.0,
                     with_normal_unit=False).maps
    torch.testing.assert_close(found.output.maps, reference if normal_unit else unit_off, atol=1e-6, rtol=0)
    assert (reference[:, :2] - unit_off[:, :2]).abs().max() > 0.01
    calls.clear()
    capturer.predict(photo, found.offset)  # the material itself: always with the unit
    assert len(calls) == 1


def encode(photos, lights, model):
    from mideepbasis.model.inputs import encode_inputs

    return encode_inputs(photos, lights, 45.0, model.config.convention, model.config.plane_extent,
                         model.config.extra_inputs)


def test_refinement_lowers_the_error_and_moves_only_the_global_bases():
    truth = material(5)
    photos, lights = flash_photos(truth, torch.tensor([[0.2, 0.1]]))
    output = OracleModel(truth)(None)
    output = replace(output, global_bases=output.global_bases
                     + torch.tensor([0.0, 0.0, 0.0, 0.3, -0.2, 0.25, 0.4, -0.3, 0.2, 0.1]).view(1, 1, 10))
    weights, deviations = output.weights.clone(), output.deviations.clone()

    def error(global_bases):
        maps = maps_by_hand(global_bases, output.deviations)
        rendered = render_flash(maps, lights.view(1, 1, 3))[:, 0].clamp(0, 1)
        return float((rendered - photos).abs().mean())

    # The package's rebuild of the maps from the bases agrees with the one written out here.
    assert torch.allclose(output.compose(output.global_bases).maps, maps_by_hand(output.global_bases, output.deviations),
                          atol=1e-6)
    before = error(output.global_bases)
    refined, losses = refine_global_bases(output, photos[0], lights[0], 45.0, "physical",
                                          config=RefineConfig(steps=150, resolution=32, lr=0.02, normals=True))
    assert error(refined) < 0.5 * before
    assert losses[-1] < losses[0]
    assert torch.equal(output.weights, weights) and torch.equal(output.deviations, deviations)


def test_refinement_can_keep_the_normals_and_be_pulled_to_the_prediction():
    truth = material(5)
    photos, lights = flash_photos(truth, torch.tensor([[0.2, 0.1]]))
    output = OracleModel(truth)(None)
    wrong = torch.tensor([0.3, -0.2, 0.0, 0.3, -0.2, 0.25, 0.4, -0.3, 0.2, 0.1]).view(1, 1, 10)
    output = replace(output, global_bases=output.global_bases + wrong)
    predicted = output.global_bases.clone()

    def refine(**options):
        config = RefineConfig(**{"steps": 60, "resolution": 32, "lr": 0.02, "normals": True, **options})
        return refine_global_bases(output, photos[0], lights[0], 45.0, "physical", config=config)[0]

    free, kept = refine(), refine(normals=False)
    assert not torch.allclose(free[..., :3], predicted[..., :3], atol=1e-3)
    assert torch.equal(kept[..., :3], predicted[..., :3])
    assert not torch.allclose(kept[..., 3:], predicted[..., 3:], atol=1e-3)
    # An L1 pull of weight w stops a basis parameter from moving once the photo term's gradient on
    # it falls below w / 10 (the mean over 10 channels); a pull far stronger than any photo gradient
    # leaves the bases within the Adam step size of where they started (the refinement keeps them
    # inside the signed space [-1, 1]).
    pulled = refine(prior=1000.0)
    assert (pulled - predicted.clamp(-1.0, 1.0)).abs().max() < 0.05
    assert (free - predicted).abs().max() > 0.2


#: Tolerances of the drjit refinement loop against the torch one (float32 sums in another order).
REFINE_LOOP_TOLERANCES = {"bases": 2e-3, "loss": 1e-5}


@pytest.mark.parametrize("options", [{"normals": False}, {"normals": True}, {"normals": False, "prior": 0.5},
                                     {"skip_clipped": True, "achromatic_specular": True},
                                     {"encoded_loss": True, "prior": 0.2},
                                     {"normals": True, "achromatic_specular": True}])
def test_the_frozen_drjit_refinement_loop_is_the_torch_loop(options):
    from mideepbasis.capturing import refine as refinement

    truth = material(5)
    photos, lights = flash_photos(truth, torch.tensor([[0.2, 0.1]]))
    output = OracleModel(truth)(None)
    wrong = torch.tensor([0.3, -0.2, 0.0, 0.3, -0.2, 0.25, 0.4, -0.3, 0.2, 0.1]).view(1, 1, 10)
    config = RefineConfig(steps=80, resolution=32, lr=0.02, **options)
    if config.achromatic_specular:  # the same error in the three: a dielectric's specular stays one
        wrong[..., 7:] = 0.2
    output = replace(output, global_bases=output.global_bases + wrong)
    weights, deviations = refinement.refinement_inputs(output, config.resolution)
    target = refinement.downsample(photos, config.resolution)
    predicted = output.global_bases.detach()
    movable = torch.ones(10)
    movable[:3] = float(config.normals)
    settings = refinement.loss_settings(photos[0] * 3.0, predicted, config)  # x 3: some pixels clip
    arguments = (weights, deviations, predicted, movable, target, lights[0], 45.0, "physical", 1.0, config, False,
                 *settings)
    if config.skip_clipped:
        assert 0 < int((settings[0] == 0).sum()) < settings[0].numel() // 2
    reference, reference_losses = refinement._fit_torch(*arguments)
    for _ in range(2):  # recorded at the first call, replayed at the second
        bases, losses = refinement._fit_drjit(*arguments)
        assert (bases - reference).abs().max() < REFINE_LOOP_TOLERANCES["bases"]
        assert np.abs(np.subtract(losses, reference_losses)).max() < REFINE_LOOP_TOLERANCES["loss"]
    assert (reference - predicted).abs().max() > 0.05  # the bases moved
    if not config.normals:
        assert torch.equal(bases[..., :3], predicted[..., :3])
    if config.achromatic_specular:  # the specular moved by one shift in all three channels
        shift = (bases - predicted)[0, 0, 7:]
        assert shift.abs().max() > 0.01 and (shift - shift.mean()).abs().max() < 1e-4


def test_speculars_tie_unless_a_metal_s():
    from mideepbasis.capturing.refine import tie_specular_gradient, tied_speculars

    bases = torch.zeros(3, 10)
    bases[0, 7:] = torch.tensor([-0.9, -0.9, -0.88])  # a dielectric's F0 (0.05, 0.05, 0.06)
    bases[1, 7:] = torch.tensor([0.8, 0.4, -0.2])  # gold-like: a metal's
    bases[2, 7:] = torch.tensor([0.5, 0.5, 0.5])  # a grey metal: no colour to keep
    assert tied_speculars(bases).tolist() == [True, False, True]
    gradient = torch.arange(30.0).view(1, 3, 10)
    tied = tie_specular_gradient(gradient, torch.tensor([True, False, False]))
    assert tied[0, 0, 7:].tolist() == [8.0, 8.0, 8.0] and torch.equal(tied[0, 1:], gradient[0, 1:])
    assert torch.equal(tied[0, 0, :7], gradient[0, 0, :7])


def test_the_refinement_keeping_the_normals_renders_them_blended_once_with_the_same_result():
    """Where the normals stay, each step blends and differentiates the seven other channels alone,
    the normal blended before the loop: the same bases and losses as differentiating all ten."""
    from mideepbasis.render.fit import fit_global_bases

    rng = np.random.default_rng(3)
    bases, size = 3, 16
    weights = rng.random((bases, size, size)).astype(np.float32)
    weights /= weights.sum(axis=0, keepdims=True)
    deviations = (0.2 * rng.standard_normal((bases, 10, size, size))).astype(np.float32)
    predicted = rng.uniform(-0.6, 0.6, (bases, 10)).astype(np.float32)
    predicted[:, 2] = 0.9  # normals toward the camera
    target = rng.uniform(0.05, 0.6, (3, size, size)).astype(np.float32)
    movable = np.ones(10, dtype=np.float32)
    movable[:3] = 0.0
    arguments = (weights, deviations, predicted, movable, target, np.array([0.2, -0.1, 2.0]), 3.0, "physical", 1.0,
                 40, 0.02, 0.1)
    seen = []

    def progress(steps):  # a bar's view of the loop: the steps, waited for every PROGRESS_SYNC_STEPS
        for step in steps:
            seen.append(step)
            yield step

    quick, quick_losses = fit_global_bases(*arguments, progress=progress)
    assert seen == list(range(1, 41))
    reference, reference_losses = fit_global_bases(*arguments, every_channel=True)
    np.testing.assert_allclose(quick, reference, atol=1e-6, rtol=0)
    np.testing.assert_allclose(quick_losses, reference_losses, atol=1e-7, rtol=0)
    assert np.array_equal(quick[:, :3], predicted[:, :3]) and np.abs(quick - predicted).max() > 0.05


def test_the_network_runs_at_its_training_resolution_and_the_prediction_is_upsampled(tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / "m.safetensors", DeepBasisNet(preset("tiny")).eval(),
                           metadata={"training": {"config": {"size": 32}}})
    model = load_model(path)
    assert model.info.training_size == 32
    truth = material(7, size=64)
    photos, lights = flash_photos(truth, torch.tensor([[0.1, -0.2]]))
    limited = predict(model, photos, lights)
    assert limited.maps.shape == (1, 10, 64, 64) and limited.deviations.shape[-2:] == (64, 64)
    torch.testing.assert_close(limited.weights.sum(dim=1), torch.ones(1, 64, 64), atol=1e-5, rtol=0)
    # The global bases are those of the 32 px photo; the maps are the blend of the bilinearly
    # upsampled weights and deviations (what the refinement and the exports use).
    small = predict(model, F.interpolate(photos, size=(32, 32), mode="area"), lights)
    torch.testing.assert_close(limited.global_bases, small.global_bases)
    weights = F.interpolate(small.weights, size=(64, 64), mode="bilinear")
    deviations = F.interpolate(small.deviations.flatten(1, 2), size=(64, 64), mode="bilinear").view(1, -1, 10, 64, 64)
    torch.testing.assert_close(limited.weights, weights)
    torch.testing.assert_close(limited.deviations, deviations)
    bases = normalize_basis_normals(small.global_bases[..., None, None] + deviations, dim=2).clamp(-1.0, 1.0)
    torch.testing.assert_close(limited.maps, to_maps((weights[:, :, None] * bases).sum(dim=1)), atol=1e-5, rtol=0)
    full = predict(model, photos, lights, network_resolution=0)
    assert not torch.allclose(full.global_bases, small.global_bases, atol=1e-4)


def test_a_prediction_kept_at_the_network_resolution_gives_the_upsampled_maps_and_refinement(tmp_path):
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / "m.safetensors", DeepBasisNet(preset("tiny")).eval(),
                           metadata={"training": {"config": {"size": 32}}})
    capturer = Capturer(load_model(path), CaptureConfig(refine=RefineConfig(steps=5, resolution=16)))
    photos, lights = flash_photos(material(7, size=64), torch.tensor([[0.1, -0.2]]))
    upsampled = predict(capturer.model, photos[0][None], lights,  # the photo as the capturer passes it
                        symmetries=capturer.config.symmetries)
    prediction = capturer.predict(Photo(photos[0], 45.0, "argument"), (0.1, -0.2))
    # Nothing of the prediction is held at the photo's size, yet its maps are the upsampled ones.
    assert prediction.output.deviations.shape[-2:] == (32, 32) and prediction.size == (64, 64)
    assert torch.equal(prediction.maps, upsampled.maps)
    assert torch.equal(prediction.output.maps_at(64, 64), upsampled.maps)
    # The refinement sees the same inputs (its matrices, to float rounding, what upsampling the
    # weights and deviations to the photo's size and averaging them gives) ...
    from mideepbasis.capturing.refine import refinement_inputs

    resolution = capturer.config.refine.resolution
    for small, large in zip(refinement_inputs(prediction.output, resolution, prediction.size),
                            refinement_inputs(upsampled, resolution)):
        torch.testing.assert_close(small, large, rtol=0.0, atol=1e-6)
    # ... and gives the same bases (to float rounding).
    refined, losses = capturer.refine(prediction, Photo(photos[0], 45.0, "argument"), (0.1, -0.2))
    bases, reference_losses = refine_global_bases(upsampled, photos[0], lights[0], 45.0, capturer.convention,
                                                  config=capturer.config.refine)
    assert np.abs(np.subtract(losses, reference_losses)).max() < 3e-7  # a few float32 steps of a loss near 0.7
    assert (refined.maps - upsampled.compose(bases).maps).abs().max() < 1e-6


@pytest.mark.parametrize("small,large,resolution", [(32, 64, 16), (37, 150, 16), (128, 2048, 64), (20, 20, 8)])
def test_the_refinement_resamples_by_one_matrix_per_axis(small, large, resolution):
    from mideepbasis.capturing.refine import upsample_then_average
    from mideepbasis.resampling import downsample
    from mideepbasis.model.network import upsample_bilinear

    image = torch.rand(2, 3, small, small + 5, generator=torch.Generator().manual_seed(small))
    expected = downsample(upsample_bilinear(image.double(), large, large + 9), resolution)
    rows, columns = upsample_then_average(small, large, resolution), upsample_then_average(small + 5, large + 9, resolution)
    assert rows.shape == (resolution, small)
    torch.testing.assert_close(rows.sum(dim=1), torch.ones(resolution))  # averages of interpolations
    torch.testing.assert_close(torch.einsum("rh,...hw,sw->...rs", rows, image, columns).double(), expected,
                               rtol=0.0, atol=1e-6)


def test_field_of_view_from_the_exif_focal_length():
    # A 36 x 24 frame with a 50 mm lens sees 39.6 deg across its width; its centre 24 x 24 square less.
    assert field_of_view_from_focal(50.0, 3600, 2400) == pytest.approx(2 * math.degrees(math.atan(12 / 50)), rel=1e-6)
    assert field_of_view_from_focal(26.0, 4000, 3000) == pytest.approx(2 * math.degrees(math.atan(
        math.tan(math.atan(21.633 / 26.0)) * 3000 / 5000)), rel=1e-4)


def photo_file(tmp_path, name="photo.jpg", size=(96, 80), focal=None, value=0.4):
    pixels = (np.random.default_rng(0).uniform(0.2, 0.8, size[::-1] + (3,)) * 255 * value / 0.4).clip(0, 255)
    image = Image.fromarray(pixels.astype(np.uint8))
    exif = Image.Exif()
    if focal:
        exif.get_ifd(0x8769)[0xA405] = focal
    path = tmp_path / name
    image.save(path, exif=exif)
    return path


def test_photo_loading_crops_resamples_and_reads_the_field_of_view(tmp_path):
    photo, fov, source, notes = load_photo(photo_file(tmp_path, focal=28), resolution=64)
    assert photo.shape == (3, 64, 64) and source == "exif"
    assert fov == pytest.approx(field_of_view_from_focal(28, 96, 80))
    assert any("centre 80x80 square" in note for note in notes)
    _, fov, source, _ = load_photo(photo_file(tmp_path, "plain.png"), fov=60.0, resolution=64)
    assert (fov, source) == (60.0, "argument")
    _, fov, source, notes = load_photo(photo_file(tmp_path, "plain2.png"), resolution=64)
    assert (fov, source) == (45.0, "default") and any("45 deg assumed" in n for n in notes)


def test_capture_outputs_load_back_render_and_validate(tmp_path, tiny_checkpoint):
    truth = material(4, size=64)
    photos, _ = flash_photos(truth, torch.tensor([[0.1, -0.1]]))
    write_image(tmp_path / "shot.png", photos[0].permute(1, 2, 0).numpy(), encode_srgb=True)
    # One pass: the untrained tiny model's bases disagree from copy to copy, and their averaged
    # normals change from pixel to pixel more than the footprint comparison below allows.
    result = capture(tmp_path / "shot.png", model=tiny_checkpoint, resolution=64, refine=RefineConfig(steps=20),
                     search=SearchConfig(resolution=32, grid=9), symmetries=1)
    out = save_capture(result, tmp_path / "out", exr=True, environment_spp=4)

    loaded = Material.load(out)
    assert torch.allclose(loaded.to_tensor(), result.material.to_tensor(), atol=1.5 / 255)
    exr = {name: out / f"{name}.exr" for name in ("normal", "diffuse", "roughness", "specular")}
    assert all(p.is_file() for p in exr.values())
    light = json.loads((out / "light.json").read_text())
    assert light["offset"] == pytest.approx(list(result.offset)) and light["fov_source"] == "default"
    for name in ("photo.png", "rerender.png", "error.png", "environment.png", "report.png", "report.html"):
        assert (out / name).is_file(), name

    import mitsuba as mi

    scene = mi.load_file(str(out / "scene.xml"), spp="64")
    traced = np.array(mi.render(scene, spp=64))[..., :3]
    with torch.no_grad():
        expected = render_flash(loaded.to_tensor()[None], result.light_position.view(1, 1, 3))[0, 0].permute(1, 2, 0).numpy()
    # The tiny untrained model's maps change from pixel to pixel, and the path tracer averages over
    # each pixel's footprint with bilinear textures: compare 8 x 8 blocks.
    def blocks(image):
        return image.reshape(8, 8, 8, 8, 3).mean(axis=(1, 3))

    assert np.abs(blocks(traced) - blocks(expected)).mean() / expected.mean() < 0.03

    import pygltflib

    gltf = pygltflib.GLTF2().load(str(out / "material.gltf"))
    assert gltf.asset.version == "2.0" and len(gltf.materials) == 1
    assert "KHR_materials_specular" in gltf.materials[0].extensions
    for image in gltf.images:
        assert (out / image.uri).is_file(), image.uri
    assert len(gltf.binary_blob() or gltf.decode_data_uri(gltf.buffers[0].uri)) == gltf.buffers[0].byteLength


def test_a_preview_that_fails_to_trace_fails_the_writing_and_leaves_nothing(tmp_path, tiny_checkpoint, monkeypatch):
    """The tracer thread hands the previews over one by one: a failure in the second one (the
    first already written beside the exports) ends the writing with that error, without waiting
    for a preview that never comes, and no output folder nor staging folder is left."""
    import mideepbasis.render.scenes as scenes

    truth = material(4, size=64)
    photos, _ = flash_photos(truth, torch.tensor([[0.1, -0.1]]))
    write_image(tmp_path / "shot.png", photos[0].permute(1, 2, 0).numpy(), encode_srgb=True)
    result = capture(tmp_path / "shot.png", model=tiny_checkpoint, resolution=64, refine=RefineConfig(steps=0),
                     light=(0.1, -0.1), symmetries=1)
    traced = []
    real_render = scenes.render

    def render(scene, *args, **kwargs):
        if traced:
            raise RuntimeError("the sphere's trace failed")
        traced.append(scene)
        return real_render(scene, *args, **kwargs)

    monkeypatch.setattr(scenes, "render", render)
    with pytest.raises(RuntimeError, match="the sphere's trace failed"):
        save_capture(result, tmp_path / "out", environment_spp=4)
    assert len(traced) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shot.png"]


def run_cli(*args) -> int:
    return cli.main([str(a) for a in args])


def test_batch_survives_a_corrupt_photo(tmp_path, tiny_checkpoint, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in ("a.png", "b.jpg"):
        photo_file(folder, name, size=(64, 64))
    (folder / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    status = run_cli("capture", folder, "-o", tmp_path / "out", "--model", tiny_checkpoint, "--resolution", "64",
                     "--refine-steps", "5", "--light", "0,0")
    assert status == 1
    assert (tmp_path / "out" / "a" / "material.json").is_file() and (tmp_path / "out" / "b" / "material.json").is_file()
    assert not (tmp_path / "out" / "broken").exists()
    captured = capsys.readouterr()
    assert "captured 2 of 3 photos" in captured.out and "broken.jpg" in captured.out + captured.err


def test_bad_input_gives_one_line_and_writes_nothing(tmp_path, tiny_checkpoint, capsys):
    cases = {}
    (tmp_path / "text.jpg").write_text("not an image")
    cases["text.jpg"] = "not an image"
    photo_file(tmp_path, "good.png", size=(64, 64))
    data = (tmp_path / "good.png").read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 3])
    cases["truncated.png"] = "truncated"
    photo_file(tmp_path, "small.png", size=(40, 40))
    cases["small.png"] = "smaller than the 64 pixels"
    for name, message in cases.items():
        out = tmp_path / f"out_{name}"
        assert run_cli("capture", tmp_path / name, "-o", out, "--model", tiny_checkpoint, "--resolution", "64") == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mideepbasis: error:") and "\n" not in err and message in err, (name, err)
        assert not out.exists()
        assert not list(tmp_path.glob(".out_*"))

    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "keep.txt").write_text("mine")
    assert run_cli("capture", tmp_path / "good.png", "-o", occupied, "--model", tiny_checkpoint, "--resolution", "64") == 2
    assert "--overwrite" in capsys.readouterr().err and (occupied / "keep.txt").read_text() == "mine"

    not_a_model = tmp_path / "model.safetensors"
    not_a_model.write_bytes(b"\x00" * 64)
    assert run_cli("capture", tmp_path / "good.png", "-o", tmp_path / "x", "--model", not_a_model) == 2
    assert "not a safetensors checkpoint" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_dark_clipped_and_broken_exif_photos_warn_but_go_through(tmp_path):
    with pytest.warns(UserWarning, match="nearly black"):
        load_photo(photo_file(tmp_path, "dark.png", size=(64, 64), value=0.002), resolution=64)
    write_image(tmp_path / "white.png", np.ones((64, 64, 3), np.float32))
    with pytest.warns(UserWarning, match="clipped"):
        load_photo(tmp_path / "white.png", resolution=64)
    # An EXIF block whose Exif-IFD pointer leads nowhere.
    import struct

    image = Image.fromarray((np.ones((64, 64, 3)) * 120).astype(np.uint8))
    broken = b"Exif\x00\x00II*\x00" + struct.pack("<IH", 8, 1) + struct.pack("<HHII", 0x8769, 4, 1, 10_000_000) + b"\0" * 4
    image.save(tmp_path / "broken_exif.jpg", exif=broken)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, fov, source, notes = load_photo(tmp_path / "broken_exif.jpg", resolution=64)
    assert (fov, source) == (45.0, "default")
    assert any("EXIF block of 'broken_exif.jpg' could not be parsed" in note for note in notes)


def test_small_adam_is_torch_adam_to_the_bit():
    from mideepbasis.capturing import SmallAdam

    torch.manual_seed(0)
    a = torch.randn(1, 10, 10, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    target = torch.randn(1, 10, 10)
    reference, ours = torch.optim.Adam([a], lr=0.01), SmallAdam(b, lr=0.01)
    for _ in range(200):
        for parameter, optimizer in ((a, reference), (b, ours)):
            parameter.grad = None
            ((parameter - target).abs().mean() + (parameter**3).mean()).backward()
            optimizer.step()
    assert torch.equal(a, b)


def test_a_capture_imports_neither_dynamo_nor_plotting_libraries(tmp_path):
    # torch._dynamo (pulled in by torch.optim), matplotlib and colour-science cost seconds of start-up;
    # pxr, loaded beside the preview thread, deadlocked about one capture in ten (the USD file is text).
    import subprocess
    import sys

    script = ("import sys\n"
              "from mideepbasis.capturing import capture, CaptureConfig, RefineConfig\n"
              "from mideepbasis.export import save_capture\n"
              "from mideepbasis.render.api import example_capture_dir\n"
              "result = capture(example_capture_dir() / 'photo.jpg', config=CaptureConfig(refine=RefineConfig(steps=2)))\n"
              f"save_capture(result, {str(tmp_path / 'out')!r})\n"
              "print(sorted(m for m in ('torch._dynamo', 'matplotlib', 'colour', 'sympy', 'pxr') if m in sys.modules))\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_importing_the_package_sets_a_short_openmp_spin_unless_the_user_chose():
    # Set before torch loads OpenMP (which reads it once): a short spin, not passive waiting.
    import os
    import subprocess
    import sys

    script = "import mideepbasis, os; print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))"
    clean = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}

    def printed(**extra):
        result = subprocess.run([sys.executable, "-c", script], env={**clean, **extra}, capture_output=True,
                                text=True, timeout=120)
        return result.stdout.split()

    assert printed() == ["1000", "None"]
    assert printed(OMP_WAIT_POLICY="PASSIVE") == ["None", "PASSIVE"]
    assert printed(GOMP_SPINCOUNT="5") == ["5", "None"]


def test_the_public_capture_is_a_plain_function(tmp_path):
    # docs/ARCHITECTURE.md section 10: `from mideepbasis import capture; capture("photo.jpg")`, in a fresh
    # process; a function, whatever was imported before or after it.
    import subprocess
    import sys

    script = ("import inspect\n"
              "from mideepbasis import capture\n"
              "from mideepbasis.capturing import RefineConfig, capture as function\n"
              "from mideepbasis.render.api import example_capture_dir\n"
              "import mideepbasis\n"
              "assert inspect.isfunction(capture) and capture is function is mideepbasis.capture\n"
              "result = capture(example_capture_dir() / 'photo.jpg', refine=RefineConfig(steps=0))\n"
              "print(type(result).__name__, result.material.width, capture.__name__)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["CaptureResult", "256", "capture"]


def test_a_batch_refuses_clashing_names_and_a_model_that_does_not_load_before_any_work(tmp_path, capsys):
    for name in ("a/shot.png", "b/shot.jpg"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        Image.fromarray(np.full((80, 80, 3), 128, np.uint8)).save(tmp_path / name)
    out = tmp_path / "out"
    assert cli.main(["capture", str(tmp_path / "a"), str(tmp_path / "b"), "-o", str(out)]) == 2
    assert "would both be written to" in capsys.readouterr().err
    (tmp_path / "b" / "shot.jpg").rename(tmp_path / "b" / "other.jpg")
    assert cli.main(["capture", str(tmp_path / "a"), str(tmp_path / "b"), "-o", str(out),
                     "--model", str(tmp_path / "missing.safetensors")]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "missing.safetensors: no such checkpoint file" in error[0]
    assert not out.exists() or not any(out.iterdir())


def test_the_report_of_a_large_capture_shows_its_images_averaged_to_the_panel(tmp_path):
    from mideepbasis.capturing import CaptureResult
    from mideepbasis.reporting import REPORT_TILE, REPORT_TITLE, capture_report

    size = 4 * REPORT_TILE  # beyond the panels' limit of twice their size: averaged first
    rows = torch.linspace(0, 1, size).view(1, size, 1)
    photo = torch.cat([rows.expand(1, size, size), (1 - rows).expand(1, size, size),
                       (torch.arange(size) % 2).float().view(1, 1, size).expand(1, size, size)])  # stripes of 1 px
    maps = F.interpolate(material(5, size=64), size=(size, size), mode="nearest")[0]
    result = CaptureResult(material=Material.from_tensor(maps), photo=photo, offset=(0.0, 0.0), fov=45.0,
                           fov_source="argument", searched=False)
    folder = tmp_path / "report"
    folder.mkdir()
    for name in ("normal", "diffuse", "roughness", "specular"):
        write_image(folder / f"{name}.png", np.zeros((8, 8, 3), np.float32))  # the viewer embeds the maps
    capture_report(result, folder, rerender=photo, error=photo * 0, environment=np.zeros((32, 32, 3), np.float32),
                   rerender_rmse=0.0)
    sheet = np.asarray(Image.open(folder / "report.png")).astype(np.float64) / 255
    panel = sheet[REPORT_TITLE + 4:REPORT_TITLE + REPORT_TILE - 4, 4:REPORT_TILE - 4]
    # The 1-px stripes average to linear 0.5 (sRGB 0.735), not to a blend of their sRGB values (0.5).
    blue = panel[8:-8, 8:-8, 2]
    assert abs(blue.mean() - 0.735) < 0.01 and blue.std() < 0.01
    # The ramps: linear red at the panel's middle row is about 0.5.
    middle = panel[panel.shape[0] // 2, 8:-8]
    assert abs(middle[:, 0].mean() - 0.735) < 0.03 and abs(middle[:, 1].mean() - 0.735) < 0.03


def test_a_field_of_view_given_wins_over_the_exif_one(tmp_path):
    path = photo_file(tmp_path, focal=28)
    _, fov, source, _ = load_photo(path, fov=23.0, resolution=64)
    assert (fov, source) == (23.0, "argument")
    _, fov, source, _ = load_photo(path, resolution=64)
    assert source == "exif" and fov == pytest.approx(field_of_view_from_focal(28, 96, 80))
