"""The symmetries of the square sample (model.symmetry) against the geometry they stand for."""

import pytest
import torch

from mideepbasis import geometry
from mideepbasis.model.symmetry import SYMMETRY_SETS, Symmetry, symmetrised_field


def surface_slope(image: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
    """A field that is exactly equivariant: the image's gradient on the plane (central differences,
    x with the column, y against the row) plus the flash position's x and y."""
    padded = torch.nn.functional.pad(image[:, :1], (1, 1, 1, 1))
    d_x = padded[..., 1:-1, 2:] - padded[..., 1:-1, :-2]
    d_y = padded[..., :-2, 1:-1] - padded[..., 2:, 1:-1]
    return torch.cat([d_x, d_y], dim=1) + lights[:, :2, None, None]


@pytest.mark.parametrize("symmetry", SYMMETRY_SETS[8])
def test_symmetry_maps_the_pixel_grid_onto_itself(symmetry):
    # Moving the scene moves what pixel q sees to the pixel of the moved point: the field of the
    # pixels' own plane points, moved as a field (pixels and vectors), is that field again.
    points = geometry.pixel_points(6, 6)[None]  # (1, 3, 6, 6)
    assert torch.allclose(symmetry.field(points), points, atol=1e-6)
    assert not torch.allclose(symmetry.image(points), points) or symmetry == Symmetry()


@pytest.mark.parametrize("symmetry", SYMMETRY_SETS[8])
def test_inverse_undoes_symmetry(symmetry):
    field = torch.randn(2, 3, 5, 5)
    assert torch.equal(symmetry.field(symmetry.field(field), inverse=True), field)
    lights = torch.randn(4, 3)
    assert torch.equal(symmetry.vectors(symmetry.vectors(lights), inverse=True), lights)


def test_group_is_closed_and_has_eight_distinct_elements():
    field = torch.randn(1, 2, 4, 4)
    moved = [s.field(field) for s in SYMMETRY_SETS[8]]
    for i, a in enumerate(moved):
        for b in moved[i + 1:]:
            assert not torch.allclose(a, b)
    # Each composition of two elements is one of the eight.
    for first in SYMMETRY_SETS[8]:
        for second in SYMMETRY_SETS[8]:
            twice = second.field(first.field(field))
            assert any(torch.equal(twice, m) for m in moved)


@pytest.mark.parametrize("count", [1, 2, 4, 8])
def test_symmetrised_equivariant_field_is_unchanged(count):
    generator = torch.Generator().manual_seed(3)
    image = torch.rand(2, 3, 8, 8, generator=generator)
    lights = torch.tensor([[0.3, -0.2, 2.4], [-0.1, 0.5, 2.4]])
    expected = surface_slope(image, lights)
    assert torch.allclose(symmetrised_field(surface_slope, image, lights, count), expected, atol=1e-6)


def test_symmetrised_field_removes_the_part_that_breaks_the_symmetry():
    # A constant bias in x is undone by the mirror of the columns: the mean over the group is the
    # equivariant part alone.
    image = torch.rand(1, 3, 8, 8, generator=torch.Generator().manual_seed(5))
    lights = torch.tensor([[0.2, 0.1, 2.4]])

    def biased(image, lights):
        field = surface_slope(image, lights)
        return field + torch.tensor([0.7, 0.0]).view(1, 2, 1, 1)

    assert torch.allclose(symmetrised_field(biased, image, lights, 4), surface_slope(image, lights), atol=1e-6)


def test_bad_symmetry_count_and_non_square_are_refused():
    image, lights = torch.rand(1, 3, 8, 6), torch.zeros(1, 3)
    with pytest.raises(ValueError, match="symmetries must be one of 1, 2, 4, 8, got 3"):
        symmetrised_field(surface_slope, image, lights, 3)
    with pytest.raises(ValueError, match="square"):
        symmetrised_field(surface_slope, image, lights, 8)
    assert symmetrised_field(surface_slope, image, lights, 4).shape == (1, 2, 8, 6)


# --- the network averaged over the group -------------------------------------------------------


def _network_and_photo(size=32, **overrides):
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    network = DeepBasisNet(preset("tiny", **overrides)).eval()
    if hasattr(network, "normal_unit"):
        for parameter in network.normal_unit.parameters():  # away from the identity-initialised blocks
            parameter.data.normal_(0.0, 0.3)
    photo = torch.rand(1, 3, size, size, generator=torch.Generator().manual_seed(1)) * 0.8
    return network, photo, torch.tensor([[0.25, -0.15, 2.4]])


def _predict(network, photo, light, symmetries):
    from mideepbasis.model.inputs import encode_inputs

    with torch.no_grad():
        return network(encode_inputs(photo, light, extra_inputs=network.config.extra_inputs), light,
                       symmetries=symmetries)


def _moved_maps(symmetry, maps, inverse=False):
    """(B, 10, H, W) maps moved: pixels, and the normal's x and y."""
    return symmetry.vectors(symmetry.image(maps, inverse), dim=1, inverse=inverse)


@pytest.mark.parametrize("overrides", [{"normal_unit_width": 4}, {}, {"use_local": False}, {"use_bases": False},
                                       {"extra_inputs": ("view",)}],
                         ids=["normal unit", "local unit", "global only", "direct", "view input"])
def test_symmetrised_network_is_exactly_equivariant(overrides):
    # The plain network is not: its answer for a turned photo, turned back, differs from its answer
    # for the photo. Averaged over the whole group it must agree to float rounding, for every
    # symmetry, the flash moved with the photo.
    network, photo, light = _network_and_photo(16, **overrides)
    reference = _predict(network, photo, light, 8).maps
    plain = _predict(network, photo, light, 1).maps
    # The normal unit's relief inputs are made once, of the photo as given, and moved: a moved
    # photo's own differ from them by float rounding (the blur's passes in the other order), which
    # this unit's random weights amplify (the shipped model's answers agree to 2e-7).
    atol = 1e-4 if "normal_unit_width" in overrides else 2e-5
    for symmetry in SYMMETRY_SETS[8][1:]:
        moved = _predict(network, symmetry.image(photo), symmetry.vectors(light), 8).maps
        torch.testing.assert_close(_moved_maps(symmetry, moved, inverse=True), reference, atol=atol, rtol=0)
        unsymmetrised = _predict(network, symmetry.image(photo), symmetry.vectors(light), 1).maps
        assert (_moved_maps(symmetry, unsymmetrised, inverse=True) - plain).abs().max() > 1e-3


def test_symmetrised_output_is_a_basis_output_that_refines_like_any_other():
    network, photo, light = _network_and_photo(normal_unit_width=4)
    output = _predict(network, photo, light, 8)
    assert output.weights.shape[1] == network.config.num_bases
    torch.testing.assert_close(output.weights.sum(dim=1), torch.ones(1, 32, 32), atol=1e-5, rtol=0)
    # Rebuilt from its own global bases (what refinement does), the maps are the same.
    torch.testing.assert_close(output.compose(output.global_bases).maps, output.maps, atol=1e-6, rtol=0)
    # Its maps are unit normals in the upper hemisphere, the rest in [0, 1].
    assert torch.allclose(output.maps[:, :3].norm(dim=1), torch.ones(1, 32, 32), atol=1e-5)
    assert output.maps[:, 3:].min() >= 0 and output.maps[:, 3:].max() <= 1


def test_one_symmetry_through_forward_is_the_plain_network():
    network, photo, light = _network_and_photo(normal_unit_width=4)
    from mideepbasis.model.inputs import encode_inputs

    with torch.no_grad():
        plain = network(encode_inputs(photo, light), light)
    assert torch.equal(_predict(network, photo, light, 1).maps, plain.maps)


@pytest.mark.parametrize("chunk", [1, 3, 8])
def test_symmetrised_network_in_chunks_is_the_same(monkeypatch, chunk):
    import mideepbasis.model.symmetry as symmetry_module

    network, photo, light = _network_and_photo(16, normal_unit_width=4)
    reference = _predict(network, photo, light, 8)
    monkeypatch.setattr(symmetry_module, "SYMMETRY_CHUNK", chunk)
    chunked = _predict(network, photo, light, 8)
    # Convolutions of batches of other sizes round differently (up to 5e-5 seen in the maps).
    torch.testing.assert_close(chunked.maps, reference.maps, atol=1e-4, rtol=0)
    torch.testing.assert_close(chunked.global_bases, reference.global_bases, atol=1e-4, rtol=0)


def test_the_slope_averaged_over_the_group_is_each_moved_photos_slope_moved_back():
    """``symmetrised_slope`` (relief inputs made once and moved, one batch through the unit)
    against the slope of each moved photo under its moved flash, made from its own relief inputs
    and moved back, averaged."""
    from mideepbasis.model.inputs import decode_photo, encode_inputs, octave_relief_inputs
    from mideepbasis.model.symmetry import symmetrised_slope

    network, photo, light = _network_and_photo(16, normal_unit_width=4)
    config = network.config
    inputs = encode_inputs(photo, light)
    group = SYMMETRY_SETS[8]
    expected = 0
    with torch.no_grad():
        for symmetry in group:
            moved_light = symmetry.vectors(light)
            reliefs = octave_relief_inputs(decode_photo(symmetry.image(inputs)), moved_light,
                                           len(config.normal_unit_octaves), convention=config.convention,
                                           extent=config.plane_extent)
            expected = expected + symmetry.field(network.octave_slope(reliefs), inverse=True) / len(group)
        got = symmetrised_slope(network, inputs, light, 45.0, group)
    assert got.shape == (1, 2, 16, 16) and expected.abs().max() > 0.1
    torch.testing.assert_close(got, expected, atol=1e-4, rtol=0)  # the relief inputs' rounding, amplified


def test_the_identity_alone_through_the_averaging_is_the_plain_network():
    # The averaging's own arithmetic (per-basis normals, the slope added after) must not change
    # what the network computes: with the identity alone it is ``forward``.
    network, photo, light = _network_and_photo(normal_unit_width=4)
    from mideepbasis.model.inputs import encode_inputs

    with torch.no_grad():
        inputs = encode_inputs(photo, light)
        plain = network(inputs, light)
        averaged = network.symmetrised(inputs, light, symmetries=1)
    assert (plain.deviations[:, :, :2].abs().max() > 0.1)  # the unit's slope is there to be got wrong
    torch.testing.assert_close(averaged.maps, plain.maps, atol=1e-5, rtol=0)


@pytest.mark.parametrize("symmetry", SYMMETRY_SETS[8][1:])
def test_the_renderer_agrees_with_the_moves(symmetry):
    # Tied to the renderer, not to the moves themselves: the moved material under the moved flash
    # renders to the moved photo (the normals' x and y turned as vectors).
    from mideepbasis.render import render_flash

    generator = torch.Generator().manual_seed(2)
    maps = torch.rand(1, 10, 16, 16, generator=generator)
    maps[:, :3] = torch.nn.functional.normalize(maps[:, :3] - torch.tensor([0.5, 0.5, -2.0]).view(1, 3, 1, 1), dim=1)
    light = torch.tensor([[0.3, -0.2, 2.414]])
    photo = render_flash(maps, light.view(1, 1, 3))[:, 0]
    moved_maps = torch.cat([symmetry.field(maps[:, :3]), symmetry.image(maps[:, 3:])], dim=1)
    moved = render_flash(moved_maps, symmetry.vectors(light).view(1, 1, 3))[:, 0]
    torch.testing.assert_close(moved, symmetry.image(photo), atol=1e-5, rtol=1e-5)
    # A wrong sign (the normal's x not turned) is caught.
    wrong = moved_maps.clone()
    wrong[:, 0] = -wrong[:, 0]
    assert (render_flash(wrong, symmetry.vectors(light).view(1, 1, 3))[:, 0] - symmetry.image(photo)).abs().max() > 1e-3


def test_capture_config_refuses_a_count_that_is_not_a_symmetry_set():
    from mideepbasis.capturing import CaptureConfig

    with pytest.raises(ValueError, match="symmetries must be one of 1, 2, 4, 8, got 3"):
        CaptureConfig(symmetries=3)


def mirrored_and_turned(image: torch.Tensor, vector_channel: int | None, mirror: bool, turns: int) -> torch.Tensor:
    """The reference of ``dihedral``, written with torch's own turn: flip the columns, then
    ``rot90`` quarter turn by quarter turn, the vector's x and y mirrored and turned alongside."""
    image = image.flip(-1) if mirror else image.clone()
    x = vector_channel
    if x is not None and mirror:
        image[..., x, :, :] = -image[..., x, :, :]
    for _ in range(turns % 4):
        image = image.rot90(1, dims=(-2, -1))
        if x is not None:
            image[..., [x, x + 1], :, :] = torch.stack([-image[..., x + 1, :, :], image[..., x, :, :]], dim=-3)
    return image


@pytest.mark.parametrize("mirror", [False, True])
@pytest.mark.parametrize("turns", [-1, 0, 1, 2, 3, 4])
def test_dihedral_is_the_mirror_then_the_quarter_turns_bit_for_bit(mirror, turns):
    # Training draws its moves as (mirror, turns): the same tensors as before they became symmetries.
    from mideepbasis.model.symmetry import dihedral, mirror_and_turns

    image = torch.randn(2, 7, 6, 6)
    for channel in (None, 0, 3, 5):
        moved = dihedral(image, channel, mirror, turns)
        assert torch.equal(moved, mirrored_and_turned(image, channel, mirror, turns)), channel
        assert moved.data_ptr() != image.data_ptr()
    assert mirror_and_turns(mirror, turns) in SYMMETRY_SETS[8]
