"""Gradients through the torch <-> drjit bridge: against the torch reference and finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from mideepbasis.render import bridge, reference

from .conftest import random_maps

#: Tolerance of the bridge's gradients against the torch reference's, relative to the largest one.
GRADIENT_RTOL = 1e-3

#: Finite differences in float32: step and tolerance on a directional derivative.
FD_STEP = {"maps": 2e-3, "lights": 2e-3}
FD_RTOL = 2e-2


def weighted_loss(render, maps, lights, weights, intensity, convention):
    return (render(maps, lights, intensity, convention) * weights).sum()


def gradients(render, maps, lights, weights, intensity, convention):
    maps = maps.clone().requires_grad_()
    lights = lights.clone().requires_grad_()
    weighted_loss(render, maps, lights, weights, intensity, convention).backward()
    return maps.grad, lights.grad


@pytest.mark.parametrize("convention", ["physical", "deepbasis"])
def test_gradients_match_torch_reference(convention, fov_height):
    _, height = fov_height
    maps = random_maps(2, 24, 20, seed=11, min_roughness=0.2)
    lights = torch.tensor([[[0.2, -0.1, height], [-0.3, 0.3, height]], [[0.0, 0.4, height], [0.1, 0.0, height]]])
    weights = torch.rand(2, 2, 3, 24, 20, generator=torch.Generator().manual_seed(2))
    intensity = math.pi * height**2 if convention == "physical" else 1.0
    maps_grad, lights_grad = gradients(bridge.render_flash, maps, lights, weights, intensity, convention)
    maps_expected, lights_expected = gradients(reference.render_flash, maps, lights, weights, intensity, convention)
    for name, slices in {"normal": slice(0, 3), "diffuse": slice(3, 6), "roughness": slice(6, 7),
                         "specular": slice(7, 10)}.items():
        got, expected = maps_grad[:, slices], maps_expected[:, slices]
        assert expected.abs().max() > 0, name
        torch.testing.assert_close(got, expected, rtol=GRADIENT_RTOL, atol=GRADIENT_RTOL * expected.abs().max().item(),
                                   msg=lambda m, name=name: f"{name}: {m}")
    torch.testing.assert_close(lights_grad, lights_expected, rtol=GRADIENT_RTOL,
                               atol=GRADIENT_RTOL * lights_expected.abs().max().item())


@pytest.mark.parametrize("wrt", ["maps", "lights"])
def test_gradients_match_finite_differences(wrt, fov_height):
    _, height = fov_height
    generator = torch.Generator().manual_seed(4)
    maps = random_maps(1, 16, 16, seed=12, min_roughness=0.3, max_tilt_deg=30.0)
    lights = torch.tensor([[[0.25, -0.15, height]]])
    weights = torch.rand(1, 1, 3, 16, 16, generator=generator)
    intensity = math.pi * height**2
    maps_grad, lights_grad = gradients(bridge.render_flash, maps, lights, weights, intensity, "physical")
    point, grad = (maps, maps_grad) if wrt == "maps" else (lights, lights_grad)
    direction = torch.randn(point.shape, generator=generator)
    step = FD_STEP[wrt]

    def loss_at(t):
        probe = point + t * direction
        args = (probe, lights) if wrt == "maps" else (maps, probe)
        with torch.no_grad():
            return weighted_loss(bridge.render_flash, *args, weights, intensity, "physical").double()

    finite_difference = (loss_at(step) - loss_at(-step)) / (2 * step)
    analytic = (grad.double() * direction.double()).sum()
    assert analytic.abs() > 0
    assert finite_difference.item() == pytest.approx(analytic.item(), rel=FD_RTOL)
