"""The lighting search: it finds the flash, its start, its stopping rules, its prior."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from mideepbasis import constants, geometry
from mideepbasis.capturing import CaptureConfig, Capturer, Photo, SearchConfig, predict
from mideepbasis.evaluation import flash_photos, light_error_deg
from mideepbasis.model.network import DeepBasisNet, preset

from .helpers import encode, material, oracle_search


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
