"""The refinement of the global bases: what it moves, its drjit loop against the torch one, its levers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from mideepbasis import constants
from mideepbasis.capturing import CaptureConfig, Capturer, Photo, RefineConfig, predict, refine_global_bases
from mideepbasis.evaluation import flash_photos
from mideepbasis.model.checkpoint import load_model, save_checkpoint
from mideepbasis.model.network import DeepBasisNet, DeepBasisOutput, normalize_basis_normals, preset, to_maps
from mideepbasis.render import render_flash

from .helpers import OracleModel, maps_by_hand, material


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
    # inside [-1, 1], the signed space, or [-2, 2] with unclamped_moves: ``basis_bound``).
    pulled = refine(prior=1000.0)
    assert (pulled - predicted).abs().max() < 0.05
    assert (refine(prior=1000.0, unclamped_moves=False) - predicted.clamp(-1.0, 1.0)).abs().max() < 0.05
    assert (free - predicted).abs().max() > 0.2


#: Tolerances of the drjit refinement loop against the torch one (float32 sums in another order).
REFINE_LOOP_TOLERANCES = {"bases": 2e-3, "loss": 1e-5}


@pytest.mark.parametrize("options", [{"normals": False}, {"normals": True}, {"normals": False, "prior": 0.5},
                                     {"skip_clipped": True, "achromatic_specular": True},
                                     {"encoded_loss": True, "prior": 0.2},
                                     {"normals": True, "achromatic_specular": True}, {"unclamped_moves": False},
                                     {"normals": False, "normal_strength": 0.5},
                                     {"normals": True, "normal_strength": 0.5}, {"lr_schedule": "constant"}])
def test_the_frozen_drjit_refinement_loop_is_the_torch_loop(options):
    from mideepbasis.capturing import refine as refinement

    options = dict(options)
    strength = options.pop("normal_strength", 1.0)
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
    reference, reference_losses = refinement._fit_torch(*arguments, normal_strength=strength)
    if strength != 1.0:  # the renders see the flatter normals: another fit
        assert (refinement._fit_torch(*arguments)[0] - reference).abs().max() > 1e-3
    for _ in range(2):  # recorded at the first call, replayed at the second
        bases, losses = refinement._fit_drjit(*arguments, normal_strength=strength)
        assert (bases - reference).abs().max() < REFINE_LOOP_TOLERANCES["bases"]
        assert np.abs(np.subtract(losses, reference_losses)).max() < REFINE_LOOP_TOLERANCES["loss"]
    assert (reference - predicted).abs().max() > 0.05  # the bases moved
    if not config.normals:
        assert torch.equal(bases[..., :3], predicted[..., :3])
    if config.achromatic_specular:  # the specular moved by one shift in all three channels
        shift = (bases - predicted)[0, 0, 7:]
        assert shift.abs().max() > 0.01 and (shift - shift.mean()).abs().max() < 1e-4


def test_the_rate_falls_along_half_a_cosine_or_stays():
    from mideepbasis.capturing.refine import step_rates

    assert step_rates(0.02, 5, "constant") == [0.02] * 5
    rates = step_rates(0.02, 100)
    assert rates[0] == 0.02 and all(later < earlier for earlier, later in zip(rates, rates[1:]))
    assert abs(rates[50] - 0.01) < 1e-12  # half way, half the rate
    assert abs(rates[-1] - 0.02 * (np.pi / 100) ** 2 / 4) < 1e-7
    assert abs(np.mean(rates) - 0.01) < 0.02 / 100  # as far as half the rate held throughout
    with pytest.raises(ValueError, match="lr_schedule: unknown schedule 'linear'"):
        RefineConfig(lr_schedule="linear")


def test_the_cosine_schedule_lets_the_bases_settle_where_a_constant_rate_keeps_them_moving():
    """Near the optimum each Adam step moves a basis by about the rate: at a constant rate a photo
    changed far below its 8-bit steps ends elsewhere; along the cosine it ends where it was."""
    truth = material(5)
    photos, lights = flash_photos(truth, torch.tensor([[0.2, 0.1]]))
    output = OracleModel(truth)(None)
    wrong = torch.tensor([0.0, 0.0, 0.0, 0.3, -0.2, 0.25, 0.4, -0.3, 0.2, 0.1]).view(1, 1, 10)
    output = replace(output, global_bases=output.global_bases + wrong)
    noise = torch.randn(photos[0].shape, generator=torch.Generator().manual_seed(1))
    jittered = photos[0] * (1.0 + 1e-5 * noise)

    def spread(schedule: str) -> float:
        config = RefineConfig(resolution=32, lr_schedule=schedule)
        first = refine_global_bases(output, photos[0], lights[0], 45.0, "physical", config=config)[0]
        second = refine_global_bases(output, jittered, lights[0], 45.0, "physical", config=config)[0]
        return float((first - second).abs().max())

    constant, cosine = spread("constant"), spread("cosine")
    assert cosine < 0.2 * constant  # 3e-5 against 4e-4 here


def single_channel_speculars(size: int = 32) -> DeepBasisOutput:
    """A grey specular as the trained network often makes it: three bases of equal weight, each
    giving one channel (global -0.99 plus a deviation of +0.5) and pushed past zero in the other two
    (global -0.5 plus a deviation of -1). Flat, diffuse 0.2, roughness 0.4; specular 0.085 grey."""
    global_bases = torch.zeros(1, 3, 10)
    global_bases[..., 2], global_bases[..., 3:6], global_bases[..., 6], global_bases[..., 7:] = 1.0, -0.6, -0.2, -0.5
    deviations = torch.zeros(1, 3, 10, size, size)
    for basis in range(3):
        global_bases[0, basis, 7 + basis] = -0.99
        deviations[0, basis, 7:] = -1.0
        deviations[0, basis, 7 + basis] = 0.5
    return DeepBasisOutput.from_bases(torch.full((1, 3, size, size), 1.0 / 3.0), global_bases, deviations)


def test_unsaturated_deviations_keep_the_maps_and_let_every_pixel_of_a_basis_move():
    output = single_channel_speculars()
    unsaturated = output.unsaturated()
    torch.testing.assert_close(unsaturated.compose(unsaturated.global_bases).maps, output.maps, atol=1e-6, rtol=0)
    assert abs(float(output.maps[0, 7:].mean()) - 0.085) < 1e-3
    raised = output.global_bases.clone()
    raised[0, 0, 8] += 0.3  # basis 0's green: pushed past -1 by its deviation
    # Before: the change moves no pixel; after: every pixel, by its weight times the change.
    torch.testing.assert_close(output.compose(raised).signed_maps, output.signed_maps)
    moved = unsaturated.compose(raised).signed_maps - output.signed_maps
    torch.testing.assert_close(moved[0, 8], torch.full_like(moved[0, 8], 0.1), atol=1e-6, rtol=0)
    assert moved[0, torch.arange(10) != 8].abs().max() < 1e-6


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_shrunk_deviations_pull_each_basis_lobe_toward_its_weighted_mean(share):
    generator = torch.Generator().manual_seed(11)
    weights = torch.softmax(3 * torch.randn(1, 3, 16, 16, generator=generator), dim=1)
    global_bases = torch.rand(1, 3, 10, generator=generator) * 1.6 - 0.8
    deviations = torch.randn(1, 3, 10, 16, 16, generator=generator) * 0.6  # some past the bounds
    output = DeepBasisOutput.from_bases(weights, global_bases, deviations)
    shrunk = output.with_shrunk_deviations(constants.LOBE, share)
    # By hand, basis by basis and channel by channel: what the maps showed, its weighted mean, the pull.
    for basis in range(3):
        for channel in range(10):
            # A reflectance channel (3 on) is shown clipped to the signed space.
            visible = (lambda value: value.clamp(-1, 1)) if channel >= 3 else (lambda value: value)  # noqa: E731
            shown = visible(global_bases[0, basis, channel] + deviations[0, basis, channel])
            if channel in range(6, 10):
                weight = weights[0, basis]
                mean = (shown * weight).sum() / weight.sum()
                shown = mean + share * (shown - mean)
            torch.testing.assert_close(visible(global_bases[0, basis, channel] + shrunk.deviations[0, basis, channel]),
                                       shown, atol=1e-6, rtol=0)
    torch.testing.assert_close(shrunk.global_bases, global_bases)
    # The other channels' deviations are the network's, past the bounds where they were (a clamped
    # refinement keeps those pixels where the local unit put them).
    assert torch.equal(shrunk.deviations[:, :, :6], output.deviations[:, :, :6])
    torch.testing.assert_close(shrunk.maps[:, :6], output.maps[:, :6], atol=1e-6, rtol=0)
    if share == 1.0:
        torch.testing.assert_close(shrunk.maps, output.maps, atol=1e-6, rtol=0)
    else:
        assert (shrunk.maps[:, 6:] - output.maps[:, 6:]).abs().max() > 0.05


def test_a_specular_of_single_channel_bases_stays_grey_when_refined_towards_a_dimmer_one():
    """Real photos whose highlight is dimmer than predicted used to end with a green specular: the
    refinement lowered the channels it could move and left the one whose global basis sat at the
    bound (``RefineConfig.unclamped_moves``)."""
    output = single_channel_speculars()
    truth = output.maps.clone()
    truth[:, 7:] = 0.03
    photos, lights = flash_photos(truth, torch.tensor([[0.2, 0.1]]))
    config = RefineConfig(steps=150, resolution=32, lr=0.02, moving_maps=("specular",))
    unsaturated = output.unsaturated()
    refined = unsaturated.compose(refine_global_bases(unsaturated, photos[0], lights[0], 45.0, "physical",
                                                      config=config)[0]).maps[0, 7:].mean(dim=(1, 2))
    assert (refined - 0.03).abs().max() < 0.01 and float(refined.max() - refined.min()) < 0.01
    clamped = output.compose(refine_global_bases(output, photos[0], lights[0], 45.0, "physical",
                                                 config=replace(config, unclamped_moves=False))[0]).maps
    assert float(clamped[0, 7:].mean(dim=(1, 2)).min()) > 0.07  # each channel held by a basis at the bound


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
                 [0.02] * 40, 0.1)
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


def test_a_batch_of_refinements_records_the_frozen_step_once_for_all():
    """The frozen step is recorded for the first refinements only: later ones, with other values,
    replay it (drjit warns after 10 recordings, and each one is kept in memory)."""
    from mideepbasis.render import fit

    movable = np.ones(10, dtype=np.float32)
    movable[:3] = 0.0
    recordings = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        weights = rng.random((3, 16, 16)).astype(np.float32)
        weights /= weights.sum(axis=0, keepdims=True)
        predicted = rng.uniform(-0.6, 0.6, (3, 10)).astype(np.float32)
        predicted[:, 2] = 0.9
        fit.fit_global_bases(weights, (0.2 * rng.standard_normal((3, 10, 16, 16))).astype(np.float32), predicted,
                             movable, rng.uniform(0.05, 0.6, (3, 16, 16)).astype(np.float32), np.array([0.2, -0.1, 2.0]),
                             3.0, "physical", 1.0, [0.02] * 10, 0.0)
        recordings.append(fit._frozen_step.n_recordings)
    assert recordings[2:] == [recordings[1]] * 10


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
    # The network's own maps: the capture's finishing (lobe variation, normal strength, specular floor) left out.
    capturer = Capturer(load_model(path), CaptureConfig(refine=RefineConfig(steps=5, resolution=16), detail=False,
                                                        normal_strength=1.0, specular_floor=0.0, lobe_variation=1.0))
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
    from mideepbasis.model.network import upsample_bilinear
    from mideepbasis.resampling import downsample

    image = torch.rand(2, 3, small, small + 5, generator=torch.Generator().manual_seed(small))
    expected = downsample(upsample_bilinear(image.double(), large, large + 9), resolution)
    rows, columns = upsample_then_average(small, large, resolution), upsample_then_average(small + 5, large + 9, resolution)
    assert rows.shape == (resolution, small)
    torch.testing.assert_close(rows.sum(dim=1), torch.ones(resolution))  # averages of interpolations
    torch.testing.assert_close(torch.einsum("rh,...hw,sw->...rs", rows, image, columns).double(), expected,
                               rtol=0.0, atol=1e-6)


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


class SaturatingOracle(OracleModel):
    """The oracle with its diffuse deviations pushed past the signed space's bound on the top rows,
    as the local unit often pushes them: the same maps (they are clipped there anyway)."""

    def forward(self, inputs, lights=None, fov=constants.DEFAULT_FOV_DEG):
        output = super().forward(inputs, lights, fov)
        deviations = output.deviations.clone()
        deviations[:, :, constants.DIFFUSE, :8] = 1.5 - output.global_bases[:, :, constants.DIFFUSE, None, None]
        return DeepBasisOutput(maps=maps_by_hand(output.global_bases, deviations), weights=output.weights,
                               global_bases=output.global_bases, deviations=deviations)


@pytest.mark.parametrize("unclamped", [True, False])
def test_a_capture_cuts_the_diffuse_deviations_only_for_an_unclamped_refinement(unclamped):
    truth = material(7, size=32)
    config = CaptureConfig(refine=RefineConfig(steps=0, unclamped_moves=unclamped), detail=False, lobe_variation=0.5,
                           symmetries=1)
    capturer = Capturer(SaturatingOracle(truth), config)
    photos, _ = flash_photos(truth, torch.tensor([[0.1, -0.2]]))
    raw = capturer.model(None)
    kept = capturer.predict(Photo(photos[0], 45.0, "argument"), (0.1, -0.2)).output
    diffuse = (slice(None), slice(None), constants.DIFFUSE)
    # Unclamped, the refinement moves every pixel of a basis: the deviations are cut to what the maps
    # show (1 in the signed space on the top rows). Clamped, they stay past the bound where the
    # local unit put them. The maps are the same either way.
    expected = raw.unsaturated() if unclamped else raw
    assert (raw.unsaturated().deviations[diffuse] - raw.deviations[diffuse]).abs().max() > 0.4
    torch.testing.assert_close(kept.deviations[diffuse], expected.deviations[diffuse], atol=1e-6, rtol=0)
    torch.testing.assert_close(kept.maps[:, :6], raw.maps[:, :6], atol=1e-6, rtol=0)
