"""Seamless maps: the wrap-around step looks like any step inside, the interior is untouched."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.errors import InputError
from mideepbasis.tiling import DEFAULT_BAND, make_tileable

#: The wrap-around step may be at most this many times the interior steps' mean (and 90th percentile).
WRAP_RATIO = 1.5

#: The largest step inside the tileable maps may be at most this many times the original's largest.
NEW_STEP_RATIO = 2.5

MAPS = {"normal": slice(0, 3), "diffuse": slice(3, 6), "roughness": slice(6, 7), "specular": slice(7, 10)}


def steps(maps: torch.Tensor, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(interior steps between neighbours, steps across the wrap-around edge) along ``dim``,
    each the mean absolute difference over channels and the other axis."""
    other = 1 if dim == 2 else 2
    interior = (maps.narrow(dim, 1, maps.shape[dim] - 1) - maps.narrow(dim, 0, maps.shape[dim] - 1)).abs()
    wrap = (maps.narrow(dim, 0, 1) - maps.narrow(dim, maps.shape[dim] - 1, 1)).abs()
    return interior.mean(dim=(0, other)).numpy(), wrap.mean(dim=(0, other)).numpy()


def seamed_material(seed: int, size: int = 96) -> torch.Tensor:
    """A procedural material with a ramp across it and down it in every map: its opposite edges
    differ far more than neighbouring pixels do."""
    maps = generate(seed, config=GeneratorConfig(size=size, tileable=False)).to_tensor()
    ramp = torch.linspace(0.0, 1.0, size)
    both = 0.5 * (ramp.view(1, size) + ramp.view(size, 1))
    maps[3:] = (0.3 * maps[3:] + 0.6 * both).clamp(0, 1)
    tilt = torch.stack([ramp.view(1, size).expand(size, size) - 0.5, ramp.view(size, 1).expand(size, size) - 0.5,
                        torch.zeros(size, size)])
    relief = maps[:3] * torch.tensor([0.3, 0.3, 1.0]).view(3, 1, 1)  # the material's own relief, flattened
    maps[:3] = torch.nn.functional.normalize(relief + 1.2 * tilt, dim=0)
    return maps


def seam_ratio(maps: torch.Tensor, dim: int) -> float:
    """The wrap-around step over the larger of the interior steps' mean and 90th percentile."""
    interior, wrap = steps(maps, dim)
    return float(wrap.mean() / max(interior.mean(), np.percentile(interior, 90)))


@pytest.mark.parametrize("seed", [2, 5, 11])
def test_the_wrap_around_step_has_the_statistics_of_the_interior(seed):
    material = seamed_material(seed)
    tileable = make_tileable(material)
    for name, channels in MAPS.items():
        for dim in (1, 2):
            assert seam_ratio(material[channels], dim) > 2 * WRAP_RATIO, (seed, name, dim)  # a real seam before
            assert seam_ratio(tileable[channels], dim) <= WRAP_RATIO, (seed, name, dim)  # none after
            original_interior, _ = steps(material[channels], dim)
            interior, _ = steps(tileable[channels], dim)
            # No new seam: the cross-fade of two shifted ramps may be steeper in its band, not a jump.
            assert interior.max() <= NEW_STEP_RATIO * original_interior.max() + 1e-6, (seed, name, dim)


def test_the_interior_is_not_blurred_and_normals_stay_unit():
    material = generate(4, config=GeneratorConfig(size=64)).to_tensor()
    tileable = make_tileable(material)
    band = int(np.ceil(64 * DEFAULT_BAND))
    inner = (slice(None), slice(band, 64 - band), slice(band, 64 - band))
    assert torch.allclose(tileable[inner][3:], material[inner][3:])
    assert torch.allclose(tileable[inner][:3], torch.nn.functional.normalize(material[inner][:3], dim=0), atol=1e-6)
    assert torch.allclose(tileable[:3].norm(dim=0), torch.ones(64, 64), atol=1e-5)


def test_too_small_maps_are_refused_in_one_line():
    with pytest.raises(InputError, match="16x16 pixels is too small to make tileable"):
        make_tileable(torch.rand(10, 16, 16), source="tiny.png")


def test_capture_tileable_on_a_16_pixel_photo_writes_nothing(tmp_path, capsys):
    from mideepbasis import cli
    from mideepbasis.imageio import write_image

    photo = tmp_path / "tiny.png"
    write_image(photo, np.full((16, 16, 3), 0.5, np.float32))
    assert cli.main(["capture", str(photo), "-o", str(tmp_path / "out"), "--tileable"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "16x16 pixels" in error[0]
    assert not (tmp_path / "out").exists()


def test_no_seam_at_2048_pixels():
    """The seam test at a working resolution of 2048 px (the material upsampled: the generator is
    slow at that size), where a 4096 px capture's maps are made tileable the same way."""
    from mideepbasis.resampling import upsample_bilinear

    material = upsample_bilinear(seamed_material(5)[None], 2048, 2048)[0]
    material[:3] = torch.nn.functional.normalize(material[:3], dim=0)
    tileable = make_tileable(material)
    for name, channels in MAPS.items():
        for dim in (1, 2):
            assert seam_ratio(material[channels], dim) > 2 * WRAP_RATIO, (name, dim)
            assert seam_ratio(tileable[channels], dim) <= WRAP_RATIO, (name, dim)
    # In place (as capture does, to spare a copy): the same maps, written over the input.
    assert torch.equal(make_tileable(material, in_place=True), tileable)
    assert torch.equal(material, tileable)
