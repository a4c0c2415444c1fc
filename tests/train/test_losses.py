"""The losses of training by hand, the re-rendering loss's lights and views, the learning-rate
schedule and the highlight weights of the diffuse loss."""

from __future__ import annotations

import math

import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.synth import Variation
from mideepbasis.model.network import DeepBasisOutput
from mideepbasis.train import (
    learning_rate_factor,
    rendering_loss,
    sample_render_geometry,
    saturation_penalty,
    variation_consistency_loss,
)


def test_variation_consistency_loss_by_hand():
    # One material, one basis, 1x1 pixel. The original prediction's basis, varied by xi, is compared
    # with the varied prediction's basis; plus the L1 of the varied maps against the varied truth.
    basis = torch.tensor([0.0, 0.0, 1.0, 0.2, -0.2, 0.0, 0.6, -1.0, -1.0, -1.0]).view(1, 1, 10, 1, 1)
    varied_basis = torch.zeros(1, 1, 10, 1, 1)
    variation = Variation(rotation=torch.tensor([0.0]), shift=torch.full((1, 7), 0.5))
    original = DeepBasisOutput(maps=torch.zeros(1, 10, 1, 1), bases=basis)
    truth = torch.zeros(1, 10, 1, 1)
    truth[:, 2] = 1.0  # flat normal, every other map 0 (signed: -1)
    varied = DeepBasisOutput(maps=truth.clone(), bases=varied_basis, signed=torch.zeros(1, 10, 1, 1))
    loss = variation_consistency_loss(original, varied, variation, truth)
    # xi on the basis: normal unchanged (rotation 0); others m -> (m + 0.5) / 1.5 in [0, 1] space.
    expected_basis = [0.0, 0.0, 1.0] + [2 * ((v * 0.5 + 0.5 + 0.5) / 1.5) - 1 for v in (0.2, -0.2, 0.0, 0.6, -1, -1, -1)]
    consistency = sum(abs(e - 0.0) for e in expected_basis) / 10
    supervised = (0 + 0 + 1 + 7 * 1) / 10  # signed maps 0 against truth [0, 0, 1, -1 x 7]
    assert loss.item() == pytest.approx(consistency + supervised, abs=1e-6)


def test_saturation_penalty_by_hand():
    raw = torch.tensor([0.5, -2.0, 3.0, -5.0], requires_grad=True).view(1, 4, 1, 1)
    penalty = saturation_penalty(raw, limit=2.0)
    assert penalty.item() == pytest.approx((0 + 0 + 1 ** 2 + 3 ** 2) / 4)
    (gradient,) = torch.autograd.grad(penalty, raw)
    # Zero inside the limit; outside, it points away from zero, so descent pulls back into range.
    assert gradient.flatten().tolist() == pytest.approx([0.0, 0.0, 2 * 1 / 4, -2 * 3 / 4])


def test_learning_rate_decays_by_cosine():
    assert learning_rate_factor(0, 100, 0.01) == 1.0
    assert learning_rate_factor(99, 100, 0.01) == pytest.approx(0.01)
    assert learning_rate_factor(49, 100, 0.0) == pytest.approx(0.5 * (1 + math.cos(math.pi * 49 / 99)))


def test_learning_rate_warms_up_linearly_then_decays():
    assert learning_rate_factor(0, 110, 0.01, warmup=10) == pytest.approx(0.1)
    assert learning_rate_factor(4, 110, 0.01, warmup=10) == pytest.approx(0.5)
    assert learning_rate_factor(10, 110, 0.01, warmup=10) == 1.0
    assert learning_rate_factor(109, 110, 0.01, warmup=10) == pytest.approx(0.01)


def test_mirror_pairs_put_a_highlight_on_the_sample():
    lights, views = sample_render_geometry(64, 6, torch.Generator().manual_seed(3))
    assert lights.shape == views.shape == (64, 6, 3)
    assert (lights[..., 2] >= 2.0 * 0.15 - 1e-6).all() and (views[..., 2] >= 2.0 * 0.15 - 1e-6).all()
    assert (torch.linalg.vector_norm(lights, dim=-1) <= 5.0 + 0.5 * 2**0.5 + 1e-5).all()
    # The last three pairs: the straight line from the light to the view mirrored below the plane
    # crosses the plane at q, where light and view directions are mirror images about +z.
    light, view = lights[:, 3:].reshape(-1, 3), views[:, 3:].reshape(-1, 3)
    below = view * torch.tensor([1.0, 1.0, -1.0])
    t = light[:, 2] / (light[:, 2] - below[:, 2])
    q = light + t[:, None] * (below - light)
    assert q[:, 2].abs().max() < 1e-5 and q[:, :2].abs().max() <= 0.7 + 1e-5
    to_light = torch.nn.functional.normalize(light - q, dim=-1)
    to_view = torch.nn.functional.normalize(view - q, dim=-1)
    assert torch.allclose(to_view, to_light * torch.tensor([-1.0, -1.0, 1.0]), atol=1e-5)
    # The first three are drawn independently: not mirror pairs.
    light, view = lights[:, :3].reshape(-1, 3), views[:, :3].reshape(-1, 3)
    assert ((light[:, :2] + view[:, :2]).abs().sum(-1) > 0.05).float().mean() > 0.9


def test_rendering_loss_against_a_hand_computed_reference(restore_render_backend):
    from mideepbasis import geometry
    from mideepbasis.render import reference, set_render_backend

    truth = torch.stack([generate(seed, config=GeneratorConfig(size=16)).to_tensor() for seed in range(2)])
    predicted = truth.clone()
    predicted[:, 3:6] *= 0.5
    lights, views = sample_render_geometry(2, 4, torch.Generator().manual_seed(0))
    intensity = geometry.flash_intensity()
    expected = (torch.log1p(reference.render_flash(predicted, lights, intensity, views=views))
                - torch.log1p(reference.render_flash(truth, lights, intensity, views=views))).abs().mean()
    for backend, tolerance in (("torch", 1e-6), ("mitsuba", 1e-4)):
        set_render_backend(backend)
        assert rendering_loss(truth, truth, lights, views).item() == 0.0
        assert rendering_loss(predicted, truth, lights, views).item() == pytest.approx(expected.item(), rel=tolerance)
    # Its gradient reaches the normals through the plugin.
    normals = truth.clone().requires_grad_(True)
    tilted = torch.cat([normals[:, :3] + torch.tensor([0.2, 0.0, 0.0]).view(1, 3, 1, 1), normals[:, 3:]], 1)
    rendering_loss(tilted, truth, lights, views).backward()
    assert normals.grad[:, :3].abs().sum() > 0


def test_the_highlight_weights_peak_under_the_flash_and_keep_the_loss_scale():
    from mideepbasis.train import highlight_weights

    size = 33
    maps = torch.zeros(2, 10, size, size)
    maps[:, 2] = 1.0  # flat
    maps[:, 3:6] = 0.3
    maps[:, 6] = 0.2
    maps[0, 7:] = 0.5
    # Flash straight above the centre: a flat sample mirrors it back from the centre pixel only,
    # and less the farther a pixel is from it.
    lights = torch.tensor([[0.0, 0.0, 2.0]]).expand(2, 3)
    weights = highlight_weights(maps, lights, 8.0, fov=45.0, convention="physical")
    assert weights.shape == (2, 1, size, size)
    torch.testing.assert_close(weights.mean(dim=(2, 3)), torch.ones(2, 1))
    glossy = weights[0, 0]
    centre = size // 2
    assert glossy[centre, centre] == glossy.max()  # the brightest 1 % share the full weight
    row = glossy[centre, centre:]
    assert bool((row[1:] <= row[:-1] + 1e-6).all()) and row[-1] < 0.5 * row[0]
    # The brightest 1 % weighs 1 + 8 against 1 for an unlit pixel (before the division by the mean).
    assert float(glossy.max() / glossy.min()) == pytest.approx(9.0, rel=0.05)
    # No specular: nothing to weigh.
    torch.testing.assert_close(weights[1], torch.ones(1, size, size))


def test_the_diffuse_weights_weigh_the_diffuse_error_of_each_pixel():
    from mideepbasis.train import supervised_loss

    truth = torch.full((1, 10, 2, 2), 0.5)
    predicted = truth.clone()
    predicted[0, 3, 0, 0] += 0.1  # one diffuse error
    predicted[0, 6, 1, 1] += 0.1  # one roughness error
    output = DeepBasisOutput(maps=predicted)
    weights = torch.ones(1, 1, 2, 2)
    plain = supervised_loss(output, truth)
    torch.testing.assert_close(supervised_loss(output, truth, diffuse_weights=weights), plain)
    weights[0, 0, 0, 0] = 3.0  # the diffuse error counts three times, the roughness's once
    torch.testing.assert_close(supervised_loss(output, truth, diffuse_weights=weights), 2.0 * plain)
    weights[0, 0, 0, 0], weights[0, 0, 1, 1] = 1.0, 5.0  # the roughness pixel: its diffuse is right
    torch.testing.assert_close(supervised_loss(output, truth, diffuse_weights=weights), plain)


def test_the_encoded_diffuse_loss_compares_srgb_albedos():
    import colour

    from mideepbasis.train import supervised_loss

    truth = torch.full((1, 10, 2, 2), 0.5)
    truth[0, 3:6] = torch.tensor([0.02, 0.2, 0.6]).view(3, 1, 1)  # a dark, a middle and a bright channel
    predicted = truth.clone()
    predicted[0, 3:6] *= 1.3  # the same relative error in each
    predicted[0, 6, 1, 1] += 0.1  # one roughness error, compared as before
    output = DeepBasisOutput(maps=predicted)
    # The independent reference: colour-science's sRGB encoding of both albedos, the other
    # channels' L1 in signed space (twice the maps' difference), over the 10 x 4 values.
    encode = lambda x: torch.from_numpy(colour.cctf_encoding(x.double().numpy(), "sRGB"))  # noqa: E731
    diffuse = (encode(predicted[0, 3:6]) - encode(truth[0, 3:6])).abs().sum()
    expected = (diffuse + 2 * 0.1) / 40
    encoded = supervised_loss(output, truth, diffuse_encoded=True)
    assert float(encoded) == pytest.approx(float(expected), rel=1e-5)


def glossy_flat_maps(size: int = 33, specular: float = 0.04, roughness: float = 0.15) -> torch.Tensor:
    """(1, 10, size, size) a flat, uniform, glossy material."""
    maps = torch.zeros(1, 10, size, size)
    maps[:, 2] = 1.0
    maps[:, 3:6] = 0.2
    maps[:, 6] = roughness
    maps[:, 7:] = specular
    return maps


def test_the_lobe_loss_against_the_reference_renderer(restore_render_backend):
    """The lobe loss written out with the reference renderer: the lobes alone, the floor at 1 % of
    the true photo's 99th percentile, the pixels weighed by the larger lobe over that peak."""
    from mideepbasis import geometry
    from mideepbasis.render import reference, set_render_backend
    from mideepbasis.train.losses import lobe_loss

    truth = glossy_flat_maps()
    predicted = glossy_flat_maps(specular=0.02, roughness=0.3)
    predicted[:, 3:6] = 0.7  # the diffuse does not count
    lights = torch.tensor([[0.1, -0.05, 2.0]])
    intensity = geometry.flash_intensity(45.0, "physical")

    def luminance(maps):
        rgb = reference.render_flash(maps.double(), lights.view(1, 1, 3).double(), intensity, "physical")[0, 0]
        return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]

    def lobe(maps):
        alone = maps.clone()
        alone[:, 3:6] = 0.0
        return luminance(alone)

    true_lobe, predicted_lobe = lobe(truth), lobe(predicted)
    peak = torch.quantile(luminance(truth).flatten(), 0.99)
    floor = 0.01 * peak
    miss = (torch.log(floor + predicted_lobe) - torch.log(floor + true_lobe)).abs()
    weights = (torch.maximum(true_lobe, predicted_lobe) / peak).clamp(max=1.0)
    expected = float((miss * weights).mean())
    assert expected > 0.01  # a lobe twice as rough and half as bright
    for backend, tolerance in (("torch", 1e-4), ("mitsuba", 1e-3)):
        set_render_backend(backend)
        assert lobe_loss(truth, truth, lights, 45.0, "physical").item() == pytest.approx(0.0, abs=1e-6)
        assert lobe_loss(predicted, truth, lights, 45.0, "physical").item() == pytest.approx(expected, rel=tolerance)


def test_the_lobe_loss_grows_with_the_log_of_the_miss_and_pulls_the_roughness():
    from mideepbasis.train.losses import lobe_loss

    lights = torch.tensor([[0.0, 0.0, 2.0]])
    truth = glossy_flat_maps(specular=0.03)
    faint, bright = ({factor: lobe_loss(glossy_flat_maps(specular=0.03 * factor**sign), truth, lights, 45.0,
                                        "physical").item() for factor in (4, 30)} for sign in (-1, 1))
    # A faint lobe weighs where the true one shows: the log of the miss where it is well above the
    # floor (less in its tails). A bright one shows on more pixels and costs more.
    assert faint[30] / faint[4] == pytest.approx(math.log(30) / math.log(4), rel=0.15)
    assert faint[4] < bright[4] and faint[30] < bright[30]
    # A lobe too rough is pulled smoother.
    rough = glossy_flat_maps(roughness=0.4).requires_grad_(True)
    lobe_loss(rough, truth, lights, 45.0, "physical").backward()
    assert rough.grad[:, 6].sum() > 0
    # Against a matte truth a faint lobe costs little, measured against the photo's own brightness.
    matte = glossy_flat_maps(specular=0.0, roughness=0.8)
    faint, strong = (lobe_loss(glossy_flat_maps(specular=specular, roughness=0.8), matte, lights, 45.0,
                               "physical").item() for specular in (0.01, 0.5))
    assert faint < 0.2 * strong


def test_a_run_with_the_lobe_loss_logs_it(tmp_path):
    from tests.train.helpers import tiny_config

    assert all(value >= 0 for value in _logged_in_a_run(tmp_path, "l_lobe", lobe_weight=0.5))
    with pytest.raises(ValueError, match="lobe_weight"):
        tiny_config(tmp_path, lobe_weight=-1.0)


def test_the_global_blend_loss_by_hand_sees_the_global_bases_and_not_the_deviations():
    from mideepbasis.train import global_blend_loss

    generator = torch.Generator().manual_seed(5)
    weights = torch.rand(2, 3, 4, 4, generator=generator)
    weights = weights / weights.sum(dim=1, keepdim=True)
    global_bases = torch.rand(2, 3, 10, generator=generator) * 2 - 1
    truth = torch.rand(2, 10, 4, 4, generator=generator)  # maps in [0, 1]; the normals do not count
    expected = 0.0
    for b in range(2):
        for y in range(4):
            for x in range(4):
                for c in range(3, 10):
                    blend = sum(float(weights[b, n, y, x]) * float(global_bases[b, n, c]) for n in range(3))
                    expected += abs(blend - (2 * float(truth[b, c, y, x]) - 1))
    expected /= 2 * 4 * 4 * 7
    for deviations in (None, torch.rand(2, 3, 10, 4, 4, generator=generator) - 0.5):
        output = DeepBasisOutput.from_bases(weights, global_bases, deviations)
        assert global_blend_loss(output, truth).item() == pytest.approx(expected, rel=1e-5)
    # Global bases that are the truth's piecewise-constant materials, picked by one-hot weights: zero.
    picked = torch.zeros(1, 2, 4, 4)
    picked[:, 0, :, :2], picked[:, 1, :, 2:] = 1.0, 1.0
    materials = torch.rand(1, 2, 10, generator=generator) * 2 - 1
    maps = ((picked[:, :, None] * materials[..., None, None]).sum(dim=1) + 1) / 2
    output = DeepBasisOutput.from_bases(picked, materials, torch.rand(1, 2, 10, 4, 4, generator=generator))
    assert global_blend_loss(output, maps).item() == pytest.approx(0.0, abs=1e-6)


def test_a_run_with_the_global_blend_loss_logs_it_and_the_pools_refuse_it(tmp_path):
    from tests.train.helpers import local_pool_config, pool_config, tiny_config

    assert all(value > 0 for value in _logged_in_a_run(tmp_path, "l_global", global_weight=0.5))
    with pytest.raises(ValueError, match="global_weight"):
        tiny_config(tmp_path, global_weight=-1.0)
    for pool in (local_pool_config, pool_config):
        with pytest.raises(ValueError, match="global_weight weighs the whole network's step"):
            pool(tmp_path, global_weight=0.5)
    with pytest.raises(ValueError, match="needs a network with bases"):
        tiny_config(tmp_path, global_weight=0.5, network={"use_bases": False})


def test_the_specular_colour_loss_by_hand_sees_ratios_not_levels():
    from mideepbasis.train import specular_colour_loss
    from mideepbasis.train.losses import COLOUR_FLOOR

    truth = torch.zeros(1, 10, 1, 2)
    truth[:, 7:10, 0, 0] = 0.04  # a dark grey dielectric
    truth[:, 7:10, 0, 1] = torch.tensor([0.9, 0.6, 0.3])  # a gold-like metal
    # Every pixel's specular scaled: the colour is the same; without the floor the loss is zero.
    scaled = truth.clone()
    scaled[:, 7:10] *= 1.7
    assert specular_colour_loss(scaled, truth, floor=0.0).item() == pytest.approx(0.0, abs=1e-6)
    # The dark pixel tinted by hand: one channel doubled.
    tinted = truth.clone()
    tinted[0, 7, 0, 0] = 0.08
    logs = [math.log(COLOUR_FLOOR + value) for value in (0.08, 0.04, 0.04)]
    expected = sum(abs(value - sum(logs) / 3) for value in logs) / 6  # the grey truth's log chromaticity is 0
    assert specular_colour_loss(tinted, truth).item() == pytest.approx(expected, rel=1e-5)
    # The same tint in reflectance on a bright grey costs less in ratios than on the dark one.
    bright = truth.clone()
    bright[:, 7:10, 0, 0] = 0.5
    bright_tinted = bright.clone()
    bright_tinted[0, 7, 0, 0] = 0.54
    assert specular_colour_loss(bright_tinted, bright).item() < specular_colour_loss(tinted, truth).item() / 5
    # The diffuse and the roughness do not count.
    other = truth.clone()
    other[:, 3:7] = torch.rand(1, 4, 1, 2)
    assert specular_colour_loss(other, truth).item() == pytest.approx(0.0, abs=1e-6)


def test_a_run_with_the_specular_colour_loss_logs_it_and_the_pools_refuse_it(tmp_path):
    from tests.train.helpers import local_pool_config, pool_config, tiny_config

    assert all(value >= 0 for value in _logged_in_a_run(tmp_path, "l_colour", colour_weight=0.5))
    with pytest.raises(ValueError, match="colour_weight"):
        tiny_config(tmp_path, colour_weight=-1.0)
    for pool in (local_pool_config, pool_config):
        with pytest.raises(ValueError, match="colour_weight weighs the whole network's step"):
            pool(tmp_path, colour_weight=0.5)


def _logged_in_a_run(tmp_path, key: str, **overrides) -> list[float]:
    """The values of ``key`` a two-step tiny run with ``overrides`` logged (at least one)."""
    import json

    from tests.train.helpers import tiny_config
    from mideepbasis.train import Trainer

    Trainer(tiny_config(tmp_path, steps=2, **overrides), progress=False).run()
    records = [json.loads(line) for line in (tmp_path / "run" / "train.jsonl").read_text().splitlines()]
    logged = [record[key] for record in records if key in record]
    assert logged
    return logged
