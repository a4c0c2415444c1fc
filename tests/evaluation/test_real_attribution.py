"""``benchmarks/real_attribution.py``: each swapped material takes exactly one map from the other
model, and a tilt scales the normals' slope (0 flat, 1 unchanged)."""

import pytest
import torch

from mideepbasis import constants
from mideepbasis.geometry import unit_vectors

from ..helpers import benchmark_module

TOLERANCES = {"unchanged": 1e-6, "slope": 1e-5}


def _maps(seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    maps = torch.rand(constants.BASIS_CHANNELS, 8, 8, generator=generator)
    maps[constants.NORMAL] = unit_vectors(maps[constants.NORMAL] - torch.tensor([0.5, 0.5, -0.5]).view(3, 1, 1), dim=0)
    return maps


def test_a_swapped_material_takes_one_map_from_the_other_and_keeps_the_rest():
    attribution = benchmark_module("real_attribution")
    model, other = _maps(0), _maps(1)
    rows = attribution.variants(model, other, tilts=[])
    assert torch.equal(rows["model"], model) and torch.equal(rows["other"], other)
    for name, channels in constants.MAP_SLICES.items():
        mask = torch.zeros(constants.BASIS_CHANNELS, dtype=torch.bool)
        mask[channels] = True
        swapped, converse = rows[f"model + other's {name}"], rows[f"other + model's {name}"]
        assert torch.equal(swapped[mask], other[mask]) and torch.equal(swapped[~mask], model[~mask])
        assert torch.equal(converse[mask], model[mask]) and torch.equal(converse[~mask], other[~mask])


@pytest.mark.parametrize("tilt", [0.0, 0.5, 1.0, 2.0])
def test_a_tilt_scales_the_normals_slope_and_nothing_else(tilt):
    attribution = benchmark_module("real_attribution")
    maps = _maps(2)
    result = attribution.tilted(maps, tilt)
    normals, before = result[constants.NORMAL], maps[constants.NORMAL]
    assert torch.allclose(normals.norm(dim=0), torch.ones(8, 8), atol=TOLERANCES["unchanged"])
    # The slope x / z and y / z is what a tilt multiplies.
    assert torch.allclose(normals[0:2] / normals[2:3], tilt * before[0:2] / before[2:3], atol=TOLERANCES["slope"])
    assert torch.equal(result[constants.NORMAL.stop:], maps[constants.NORMAL.stop:])
