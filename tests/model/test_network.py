"""DeepBasisNet: shapes at any stride multiple, convex blending, the ablation switches, preset sizes."""

from __future__ import annotations

import pytest
import torch

from mideepbasis import geometry
import numpy as np

from mideepbasis.model.nafnet import LayerNorm2d, NAFNet
from mideepbasis.model.network import (DeepBasisNet, WeightDecoder, blend, count_parameters, normalize_weights, preset,
                                       to_maps, to_signed, upsampled_conv)


def run(config, size=64, batch=2, seed=0):
    torch.manual_seed(seed)
    net = DeepBasisNet(config).eval()
    inputs = torch.rand(batch, 9, size, size) * 2 - 1
    lights = geometry.light_positions(torch.zeros(batch, 2))
    with torch.no_grad():
        return net, net(inputs, lights)


@pytest.mark.parametrize("size", [32, 64, 96])
def test_any_multiple_of_the_stride(size):
    config = preset("tiny")
    assert config.stride == 16
    _, out = run(config, size=size)
    n = config.num_bases
    assert out.maps.shape == (2, 10, size, size)
    assert out.weights.shape == (2, n, size, size) and out.global_bases.shape == (2, n, 10)
    assert out.bases.shape == out.deviations.shape == (2, n, 10, size, size)
    assert out.error.shape == (2, 3, size, size)


def test_size_that_is_not_a_multiple_is_refused():
    net = DeepBasisNet(preset("tiny"))
    with pytest.raises(ValueError, match="multiple of the network's stride 16"):
        net(torch.zeros(1, 9, 40, 40), torch.zeros(1, 3))


def test_blend_is_a_convex_combination_of_the_bases():
    _, out = run(preset("tiny"))
    weights = out.weights
    assert weights.min() >= 0
    assert torch.allclose(weights.sum(1), torch.ones_like(weights[:, 0]), atol=1e-5)
    signed = out.signed_maps
    # The blend written out independently: a sum over the bases' axis of weight times basis.
    reference = (weights.double().unsqueeze(2) * out.bases.double()).sum(dim=1)
    assert torch.allclose(signed.double(), reference, atol=1e-6)
    # Every blended parameter lies between the smallest and the largest basis value at its pixel.
    low, high = out.bases.min(dim=1).values, out.bases.max(dim=1).values
    assert (signed >= low - 1e-5).all() and (signed <= high + 1e-5).all()
    # And by hand: two bases, weights 0.25 / 0.75.
    w = torch.tensor([0.25, 0.75]).view(1, 2, 1, 1)
    b = torch.tensor([[1.0] * 10, [-1.0] * 10]).view(1, 2, 10)
    assert torch.allclose(blend(w, b), torch.full((1, 10, 1, 1), -0.5))


def test_weight_normalisation_by_hand():
    raw = torch.tensor([1.0, -1.0, 0.0]).view(1, 3, 1, 1)  # -> 1, 0, 0.5 -> 2/3, 0, 1/3
    assert normalize_weights(raw).flatten().tolist() == pytest.approx([2 / 3, 0.0, 1 / 3], abs=1e-5)


def test_signed_space_round_trip():
    maps = torch.rand(2, 10, 4, 4)
    maps[:, :3] = torch.nn.functional.normalize(maps[:, :3] + torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1), dim=1)
    assert torch.allclose(to_maps(to_signed(maps)), maps, atol=1e-6)


@pytest.mark.parametrize("switches,present,absent", [
    ({"use_local": False}, ["global_bases"], ["bases", "deviations"]),
    ({"use_global": False}, ["bases", "deviations"], []),
    ({"use_bases": False}, [], ["weights", "global_bases", "bases"]),
    ({"num_bases": 3}, ["bases"], []),
])
def test_ablations(switches, present, absent):
    config = preset("tiny", **switches)
    net, out = run(config)
    assert out.maps.shape == (2, 10, 64, 64)
    assert torch.allclose((out.maps[:, :3] ** 2).sum(1), torch.ones(2, 64, 64), atol=1e-4)
    for name in present:
        assert getattr(out, name) is not None, name
    for name in absent:
        assert getattr(out, name) is None, name
    if switches.get("use_global") is False:
        assert torch.equal(out.global_bases, torch.zeros_like(out.global_bases))
    if "num_bases" in switches:
        assert out.bases.shape[1] == 3
    if switches.get("use_bases") is False:
        assert not hasattr(net, "global_unit") and not hasattr(net, "local_unit")


def test_nafnet_constant_planes_equal_the_full_input():
    torch.manual_seed(0)
    net = NAFNet(5 + 12, 6, width=4, encoder_blocks=(1, 1), middle_blocks=1, decoder_blocks=(1, 1))
    x, planes = torch.randn(2, 5, 21, 30), torch.randn(2, 12)
    full = torch.cat([x, planes[:, :, None, None].expand(-1, -1, 21, 30)], 1)
    assert torch.allclose(net(full), net(x, planes=planes), atol=1e-5)


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_layer_norm_2d_normalises_each_pixel_over_its_channels(layout):
    torch.manual_seed(0)
    norm = LayerNorm2d(6, eps=1e-6)
    with torch.no_grad():
        norm.weight.copy_(torch.randn(6))
        norm.bias.copy_(torch.randn(6))
    x = torch.randn(2, 6, 5, 7) * 3 + 1
    # Independent reference in float64: standardise the channel vector of every pixel.
    a = x.double().numpy()
    mean = a.mean(axis=1, keepdims=True)
    std = np.sqrt(((a - mean) ** 2).mean(axis=1, keepdims=True) + 1e-6)
    expected = norm.weight.detach().double().numpy()[None, :, None, None] * (a - mean) / std \
        + norm.bias.detach().double().numpy()[None, :, None, None]
    out = norm(x.contiguous(memory_format=layout))
    assert out.shape == x.shape
    np.testing.assert_allclose(out.detach().double().numpy(), expected, rtol=1e-5, atol=1e-5)


def test_nafnet_gives_a_contiguous_answer_whatever_the_input_layout():
    torch.manual_seed(0)
    net = NAFNet(5, 6, width=4, encoder_blocks=(1, 1), middle_blocks=1, decoder_blocks=(1, 1))
    for block in net.modules():  # non-zero residual scales, so that every block takes part
        if hasattr(block, "beta"):
            torch.nn.init.normal_(block.beta)
            torch.nn.init.normal_(block.gamma)
    x = torch.randn(2, 5, 21, 30)
    out = net(x)
    assert out.shape == (2, 6, 21, 30) and out.is_contiguous()
    assert torch.allclose(net(x.contiguous(memory_format=torch.channels_last)), out, atol=1e-5)
    out.square().mean().backward()  # trains: every parameter gets a gradient
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


@pytest.mark.parametrize("shape", [(2, 5, 7, 3), (1, 16, 16, 16), (3, 4, 1, 1)])
def test_a_convolution_that_folds_in_the_upsampling_is_the_convolution_of_the_upsampled_image(shape):
    """``upsampled_conv`` against the upsampled copy convolved (values and gradients), odd and
    one-pixel sizes included: the borders' zero padding is the same."""
    torch.manual_seed(1)
    batch, channels, height, width = shape
    conv = torch.nn.Conv2d(channels, 6, 3, padding=1)
    x = torch.randn(shape, requires_grad=True)
    reference = conv(torch.nn.functional.interpolate(x, scale_factor=2, mode="nearest"))
    folded = upsampled_conv(x, conv)
    assert folded.shape == (batch, 6, 2 * height, 2 * width)
    torch.testing.assert_close(folded, reference, atol=2e-6, rtol=1e-5)
    weights = torch.randn_like(reference)
    expected = torch.autograd.grad((reference * weights).sum(), (x, conv.weight, conv.bias))
    got = torch.autograd.grad((folded * weights).sum(), (x, conv.weight, conv.bias))
    for a, b in zip(got, expected, strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)  # sums of up to 4,000 products


def test_the_decoder_is_the_same_whichever_levels_fold_their_upsampling(monkeypatch):
    """The decoder with every level upsampling its input and with every level folding it in."""
    import mideepbasis.model.network as network

    torch.manual_seed(2)
    channels = (4, 6, 8, 8)
    decoder = WeightDecoder(channels, (8, 6, 4), 3, global_size=5)
    levels = [torch.randn(2, c, 32 // 2 ** i, 32 // 2 ** i) for i, c in enumerate(channels)]
    features = torch.randn(2, 5)
    with torch.no_grad():
        monkeypatch.setattr(network, "PHASE_CONVOLUTION_MIN_SIZE", 10 ** 6)
        upsampled = decoder(levels, features)
        monkeypatch.setattr(network, "PHASE_CONVOLUTION_MIN_SIZE", 1)
        folded = decoder(levels, features)
    assert folded.shape == (2, 3, 64, 64)
    torch.testing.assert_close(folded, upsampled, atol=1e-5, rtol=1e-5)


def test_preset_sizes():
    compact = count_parameters(DeepBasisNet(preset("compact")))
    assert compact <= 4_000_000
    paper = DeepBasisNet(preset("paper"))
    # The published layout: 8 encoder levels from 64 to 512 channels, an MLP of width 512,
    # a NAFNet of width 16 with blocks (2, 2, 4, 8), 12 middle blocks and (2, 2, 2, 2).
    assert [conv.out_channels for conv in paper.encoder.convs] == [64, 128, 256, 512, 512, 512, 512, 512]
    assert paper.global_unit[0].out_features == 512
    assert paper.local_unit.intro.out_channels == 16
    assert [len(e) for e in paper.local_unit.encoders] == [2, 2, 4, 8] and len(paper.local_unit.middle_blks) == 12
    assert paper.local_unit.intro.in_channels == 9 + 3 + 10 + 100


def test_the_normal_unit_adds_its_slope_to_the_normal_deviation_of_every_basis():
    from mideepbasis.model.inputs import relief_inputs

    torch.manual_seed(0)
    plain = DeepBasisNet(preset("tiny")).eval()
    with_unit = DeepBasisNet(preset("tiny", normal_unit_width=4)).eval()
    missing, unexpected = with_unit.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(name.startswith("normal_unit.") for name in missing)
    for parameter in with_unit.normal_unit.parameters():  # away from the identity-initialised blocks
        parameter.data.normal_(0.0, 0.3)
    inputs = torch.rand(2, 9, 32, 32) * 2 - 1
    lights = torch.tensor([[0.1, 0.0, 2.4], [0.0, -0.2, 2.4]])
    with torch.no_grad():
        a, b = plain(inputs, lights), with_unit(inputs, lights)
        slope = torch.tanh(with_unit.normal_unit(relief_inputs(inputs[:, :3] * 0.5 + 0.5, lights)))
    assert slope.abs().max() > 0.1
    added = b.deviations - a.deviations
    torch.testing.assert_close(added[:, :, :2], slope[:, None].expand(-1, added.shape[1], -1, -1, -1))
    assert torch.equal(added[:, :, 2:], torch.zeros_like(added[:, :, 2:]))
    assert torch.equal(a.weights, b.weights) and torch.equal(a.global_bases, b.global_bases)
    # Left out, the unit adds nothing: the network without one.
    with torch.no_grad():
        c = with_unit(inputs, lights, with_normal_unit=False)
    assert torch.equal(c.deviations, a.deviations) and torch.equal(c.maps, a.maps)
    with pytest.raises(ValueError, match="needs use_bases and use_local"):
        preset("tiny", normal_unit_width=4, use_local=False)


def test_a_normal_unit_of_two_octaves_adds_its_slope_on_the_photo_averaged_to_half_the_size():
    import torch.nn.functional as F

    from mideepbasis.model.inputs import relief_inputs

    torch.manual_seed(1)
    one = DeepBasisNet(preset("tiny", normal_unit_width=4, normal_unit_blocks=(1, 1, 1))).eval()
    two = DeepBasisNet(preset("tiny", normal_unit_width=4, normal_unit_blocks=(1, 1, 1),
                              normal_unit_octaves=(1.0, 0.5))).eval()
    for parameter in one.normal_unit.parameters():
        parameter.data.normal_(0.0, 0.3)
    two.load_state_dict(one.state_dict())  # the octaves need no weights of their own
    inputs = torch.rand(2, 9, 32, 32) * 2 - 1
    lights = torch.tensor([[0.1, 0.0, 2.4], [0.0, -0.2, 2.4]])
    photo = inputs[:, :3] * 0.5 + 0.5
    with torch.no_grad():
        a, b = one(inputs, lights), two(inputs, lights)
        coarse = torch.tanh(one.normal_unit(relief_inputs(F.avg_pool2d(photo, 2), lights)))
    # Written out: the half-size slope upsampled with half-pixel centres (pixel 2i + 1/2 of the full
    # size lies a quarter of the way from coarse pixel i to i + 1), clamped at the edges.
    index = (torch.arange(32) + 0.5) / 2 - 0.5
    low = index.floor().clamp(0, 15).long()
    high = (low + 1).clamp(max=15)
    fraction = (index - index.floor()).clamp(0, 1)
    fraction = torch.where(index < 0, torch.zeros_like(fraction), fraction)
    rows = coarse[:, :, low] * (1 - fraction)[:, None] + coarse[:, :, high] * fraction[:, None]
    upsampled = rows[..., low] * (1 - fraction) + rows[..., high] * fraction
    added = b.deviations - a.deviations
    assert 0.5 * upsampled.abs().max() > 0.05
    torch.testing.assert_close(added[:, :, :2], 0.5 * upsampled[:, None].expand(-1, added.shape[1], -1, -1, -1),
                               atol=1e-5, rtol=0)
    assert torch.equal(added[:, :, 2:], torch.zeros_like(added[:, :, 2:]))
    with pytest.raises(ValueError, match="octaves"):
        preset("tiny", normal_unit_width=4, normal_unit_octaves=(1.0, 0.5))  # 4 levels + 1 octave > the encoder's 4
    with pytest.raises(ValueError, match="other than 0"):
        preset("tiny", normal_unit_width=4, normal_unit_octaves=(0.0,))


def test_a_scaled_slope_tilts_every_basis_as_it_tilts_a_flat_unit_normal():
    from mideepbasis.model.network import add_slope, compose_bases, normalize_basis_normals

    torch.manual_seed(2)
    global_bases = normalize_basis_normals(torch.rand(2, 3, 10) * 2 - 1, dim=2)
    global_bases[:, :, 2] = global_bases[:, :, 2].abs() + 0.5
    deviations = (torch.rand(2, 3, 10, 4, 4) * 2 - 1) * 0.5
    deviations[:, :, 2] += 0.7  # sums longer than 1, as the shipped local unit makes them
    slope = (torch.rand(2, 2, 4, 4) * 2 - 1) * 0.4
    weights = torch.zeros(2, 3, 4, 4)
    weights[:, 1] = 1.0  # one basis shows
    sums = global_bases[:, 1, :3, None, None] + deviations[:, 1, :3]
    unit = sums / sums.norm(dim=1, keepdim=True)
    for scaled in (False, True):
        _, blended = compose_bases(weights, global_bases, add_slope(global_bases, deviations, slope, scaled))
        expected = (unit if scaled else sums) + torch.cat([slope, torch.zeros_like(slope[:, :1])], dim=1)
        torch.testing.assert_close(blended[:, :3], expected / expected.norm(dim=1, keepdim=True), atol=1e-5, rtol=0)
    # Unscaled, a sum of length 1.7 takes the slope's tilt down by as much; scaled, a flat basis
    # of any length tilts as unit-normal(slope, 1).
    flat = torch.zeros(1, 1, 10)
    flat[0, 0, 2] = 1.0
    long = torch.zeros(1, 1, 10, 1, 1)
    long[0, 0, 2] = 0.7
    tilt = torch.tensor([[[[0.3]], [[0.0]]]])
    _, plain = compose_bases(torch.ones(1, 1, 1, 1), flat, add_slope(flat, long, tilt, False))
    _, scaled = compose_bases(torch.ones(1, 1, 1, 1), flat, add_slope(flat, long, tilt, True))
    assert float(plain[0, 0] / plain[0, 2]) == pytest.approx(0.3 / 1.7, abs=1e-6)
    assert float(scaled[0, 0] / scaled[0, 2]) == pytest.approx(0.3, abs=1e-6)


@pytest.mark.parametrize("size", [(128, 100), (128, 128), (120, 96), (48, 40)])
def test_maps_built_in_bands_are_the_upsampled_outputs(monkeypatch, size):
    """Bands of 24 rows (not a multiple of the 8x upsampling) against the whole upsampled output;
    120 and 48 rows (7.5x and 3x) take the unbanded path."""
    from mideepbasis.model import network

    torch.manual_seed(2)
    weights = normalize_weights(torch.rand(2, 4, 16, 12) * 2 - 1)
    output = network.DeepBasisOutput.from_bases(weights, torch.rand(2, 4, 10) * 2 - 1,
                                                (torch.rand(2, 4, 10, 16, 12) * 2 - 1) * 0.5, keep_bases=False)
    whole = output.upsample(*size).maps
    assert torch.equal(output.maps_at(*size), whole)  # one band of every row
    monkeypatch.setattr(network, "BAND_PIXELS", 24 * size[1])
    torch.testing.assert_close(output.maps_at(*size), whole, rtol=0.0, atol=1e-6)
    assert network.exact_in_bands(16, size[0]) == (size[0] == 128)


@pytest.mark.parametrize("error_map", ["clipped", "log_ratio"])
def test_the_error_map_is_the_global_blends_render_against_the_photo(error_map):
    """Both error maps against the reference renderer: the clipped render minus the photo, or the
    log ratio of the unclipped render (brighter than the photo where it clipped: that counts as the
    photo's value) over the photo, floored at 0.01 and bounded by 4."""
    from dataclasses import replace

    from mideepbasis import constants
    from mideepbasis.render import reference

    torch.manual_seed(3)
    net = DeepBasisNet(replace(preset("tiny"), error_map=error_map)).eval()
    weights = normalize_weights(torch.rand(1, net.config.num_bases, 16, 16) * 2 - 1)
    global_bases = torch.rand(1, net.config.num_bases, 10) * 2 - 1
    global_bases[..., :3] = torch.tensor([0.0, 0.0, 1.0])  # flat: one highlight
    global_bases[..., 6] = -0.8  # smooth: the render passes 1 under the highlight
    lights = geometry.light_positions(torch.tensor([[0.05, -0.02]]))
    fov = constants.DEFAULT_FOV_DEG
    maps = to_maps(blend(weights, global_bases), upper_hemisphere=False).double()
    rendered = reference.render_flash(maps, lights.view(1, 1, 3).double(), geometry.flash_intensity(fov, net.config.convention),
                                      net.config.convention)[:, 0].numpy()
    highlight = torch.from_numpy(rendered > 1.5)
    assert 0 < highlight.sum() < highlight.numel() / 4  # the case the two maps differ on
    photo = torch.rand(1, 3, 16, 16) * 0.5
    photo[highlight] = 1.0  # the photo clipped there
    with torch.no_grad():
        error = net.error_map(weights, global_bases, photo, lights, fov)
    seen = photo.double().numpy()
    if error_map == "clipped":
        expected = np.clip(rendered, 0, 1) - seen
    else:
        rendered = np.where((seen >= 0.98) & (rendered > seen), seen, rendered)
        expected = np.clip(np.log((rendered + 0.01) / (seen + 0.01)), -4, 4)
    assert np.abs(error.double().numpy() - expected).max() < 2e-3


def test_an_unknown_error_map_is_refused():
    from dataclasses import replace

    with pytest.raises(ValueError, match="unknown error map 'log'"):
        replace(preset("tiny"), error_map="log")
