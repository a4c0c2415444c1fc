"""The per-pixel flash path against the torch reference, a float64 transcription of
docs/ARCHITECTURE.md section 4, and hand-made cases."""

from __future__ import annotations

import math

import drjit as dr
import numpy as np
import pytest
import torch

from mideepbasis.render import bridge, reference

from .conftest import random_maps

#: Relative tolerance of the per-pixel path against the torch reference (both float32).
FORWARD_RTOL = {"physical": 1e-4, "deepbasis": 1e-4}


def design_formula_float64(maps: np.ndarray, light: np.ndarray, fov_deg: float) -> np.ndarray:
    """The `physical` formula of docs/ARCHITECTURE.md section 4 in float64 numpy, for one (10, H, W)
    material -> (3, H, W)."""
    height, width = maps.shape[1:]
    camera_height = 1 / math.tan(math.radians(fov_deg) / 2)
    i, j = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    p = np.stack([-1 + (2 * j + 1) / width, 1 - (2 * i + 1) / height, np.zeros((height, width))])
    c = light.reshape(3, 1, 1).astype(np.float64)
    v = (c - p) / np.linalg.norm(c - p, axis=0)
    n = maps[0:3].astype(np.float64)
    n = n / np.linalg.norm(n, axis=0)
    d, r, s = maps[3:6].astype(np.float64), maps[6:7].astype(np.float64), maps[7:10].astype(np.float64)
    alpha = r**2
    n_dot_h = n_dot_l = np.sum(n * v, axis=0)  # h = normalize(l + v) = v for a co-located flash
    ndf = alpha**2 / (np.pi * (n_dot_h**2 * (alpha**2 - 1) + 1) ** 2)

    def g1(x):
        return 2 * x / (x + np.sqrt(alpha**2 + (1 - alpha**2) * x**2))

    fresnel = s + (1 - s) * (1 - np.sum(v * v, axis=0)) ** 5
    with np.errstate(divide="ignore", invalid="ignore"):
        f = d / np.pi + ndf * g1(n_dot_l) * g1(n_dot_l) * fresnel / (4 * n_dot_l * n_dot_l)
    radiance = f * np.maximum(n_dot_l, 0) * np.pi * camera_height**2 / np.sum((c - p) ** 2, axis=0)
    return np.where(n_dot_l > 0, radiance, 0.0)


@pytest.mark.parametrize("convention", ["physical", "deepbasis"])
def test_per_pixel_path_matches_torch_reference(convention, fov_height):
    fov, height = fov_height
    maps = random_maps(2, 48, 40, seed=3)
    lights = torch.tensor([[[0.0, 0.0, height], [0.4, -0.3, height]], [[-0.2, 0.5, height], [0.1, 0.1, 2.0]]])
    intensity = math.pi * height**2 if convention == "physical" else 1.0
    image = bridge.render_flash(maps, lights, intensity, convention)
    expected = reference.render_flash(maps, lights, intensity, convention)
    assert image.shape == expected.shape == (2, 2, 3, 48, 40)
    assert (expected > 0).float().mean() > 0.9
    torch.testing.assert_close(image, expected, rtol=FORWARD_RTOL[convention], atol=1e-6 * expected.max().item())


def test_per_pixel_path_is_the_design_formula(fov_height):
    fov, height = fov_height
    maps = random_maps(1, 33, 35, seed=5, min_roughness=0.05)
    light = np.array([0.3, -0.25, height])
    image = bridge.render_flash(maps, torch.tensor(light, dtype=torch.float32).view(1, 1, 3), math.pi * height**2)
    expected = design_formula_float64(maps[0].numpy(), light, fov)
    np.testing.assert_allclose(image[0, 0].numpy(), expected, rtol=1e-4, atol=1e-6 * expected.max())


def test_white_lambertian_renders_one_at_the_centre(fov_height):
    _, height = fov_height
    size = 65  # odd, so the centre pixel sees the plane point (0, 0)
    maps = torch.zeros(1, 10, size, size)
    maps[:, 2] = 1.0  # flat normal
    maps[:, 3:6] = 1.0  # white diffuse
    maps[:, 6] = 0.5  # roughness does not matter: s = 0 and F(v.h = 1) = 0
    image = bridge.render_flash(maps, torch.tensor([[[0.0, 0.0, height]]]), math.pi * height**2)
    assert image[0, 0, :, size // 2, size // 2].tolist() == pytest.approx([1.0, 1.0, 1.0], abs=1e-6)
    # Away from the centre the inverse-square law and the cosine darken it: cos^3 of the view angle.
    corner_cos = height / math.sqrt(height**2 + 2 * (1 - 1 / size) ** 2)
    assert image[0, 0, 0, 0, 0].item() == pytest.approx(corner_cos**3, rel=1e-5)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.45, 0.2), (-0.3, -0.5)])
def test_highlight_of_a_smooth_material_sits_under_the_light(offset, fov_height):
    _, height = fov_height
    size = 101
    maps = torch.zeros(1, 10, size, size)
    maps[:, 2] = 1.0
    maps[:, 3:6] = 0.05
    maps[:, 6] = 0.1
    maps[:, 7:10] = 0.04
    tx, ty = offset
    image = bridge.render_flash(maps, torch.tensor([[[tx, ty, height]]]), math.pi * height**2)[0, 0, 0]
    row, col = divmod(int(torch.argmax(image)), size)
    # The pixel whose plane point is nearest to (tx, ty): x = -1 + (2j + 1) / w, y = 1 - (2i + 1) / h.
    assert abs(col - ((tx + 1) * size / 2 - 0.5)) <= 1.0
    assert abs(row - ((1 - ty) * size / 2 - 0.5)) <= 1.0


def test_new_light_positions_reuse_the_compiled_kernel(fov_height):
    _, height = fov_height
    maps = random_maps(1, 32, 32, seed=9)
    bridge.render_flash(maps, torch.tensor([[[0.1, 0.2, height]] * 8]), 10.0)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clear
        lights = torch.rand(1, 8, 3) * 0.5 + torch.tensor([0.0, 0.0, height])
        bridge.render_flash(maps, lights, 12.0)
        launches = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert launches and all(k["cache_hit"] for k in launches)


@pytest.mark.parametrize("convention", ["physical", "deepbasis"])
def test_separate_views_match_torch_reference(convention):
    maps = random_maps(2, 24, 28, seed=8)
    generator = torch.Generator().manual_seed(0)
    lights = torch.randn(2, 3, 3, generator=generator) * 0.8 + torch.tensor([0.0, 0.0, 3.0])
    views = torch.randn(2, 3, 3, generator=generator) * 0.8 + torch.tensor([0.0, 0.0, 2.5])
    image = bridge.render_flash(maps, lights, 9.0, convention, views=views)
    expected = reference.render_flash(maps, lights, 9.0, convention, views=views)
    torch.testing.assert_close(image, expected, rtol=FORWARD_RTOL[convention], atol=1e-6 * expected.max().item())
    # A viewpoint at the light gives the flash render back.
    torch.testing.assert_close(bridge.render_flash(maps, lights, 9.0, convention, views=lights),
                               bridge.render_flash(maps, lights, 9.0, convention), rtol=1e-6, atol=1e-7)


#: The search objective reduced in the plugin's kernel against the reference render's mean, float32 sums.
L1_RTOL = 1e-5


@pytest.mark.parametrize("convention", ["physical", "deepbasis"])
def test_mean_l1_in_the_kernel_is_the_mean_of_the_reference_render(convention, fov_height):
    from mideepbasis.render import flash_l1

    fov, height = fov_height
    maps = random_maps(1, 30, 26, seed=8, min_roughness=0.05)  # not square: rows and columns stay apart
    photo = torch.rand(1, 3, 30, 26, generator=torch.Generator().manual_seed(9))
    lights = torch.tensor([[0.0, 0.0, height], [0.5, -0.2, height], [-0.3, 0.6, 1.5], [0.1, 0.1, height]])
    intensity = 4.0 * math.pi * height**2 if convention == "physical" else 4.0  # bright: clipping matters
    rendered = reference.render_flash(maps.double(), lights[None].double(), intensity, convention)[0]
    assert (rendered > 1).any()
    expected = (rendered.clamp(0, 1) - photo.double()).abs().mean(dim=(1, 2, 3))
    for backend in ("mitsuba", "torch"):
        errors = flash_l1(maps, photo, lights, intensity=intensity, convention=convention, backend=backend)
        assert errors.shape == (4,) and errors.dtype == torch.float32
        torch.testing.assert_close(errors.double(), expected, rtol=L1_RTOL, atol=0.0)
    with pytest.raises(ValueError, match="photo must have shape"):
        bridge.flash_l1(maps, photo[..., :-1], lights, intensity, convention)


def test_a_render_in_tiles_is_the_render_in_one_piece():
    """The tiles move the flash by minus their centre and frame themselves as samples of their own:
    the same radiance as the whole image at once, to float32 rounding."""
    from mideepbasis.render import render_flash, render_flash_tiled

    generator = torch.Generator().manual_seed(3)
    maps = torch.rand(1, 10, 96, 96, generator=generator)
    tilt = maps[:, 0:3] * 0.6 - 0.3
    tilt[:, 2] = 1.0
    maps[:, 0:3] = tilt / tilt.norm(dim=1, keepdim=True)
    light = torch.tensor([0.4, -0.3, 2.2])
    whole = render_flash(maps, light.view(1, 1, 3), fov=35.0)[0, 0]
    tiled = render_flash_tiled(maps, light, fov=35.0, tile=32)
    assert torch.allclose(tiled, whole, rtol=1e-5, atol=1e-6)
    assert torch.equal(render_flash_tiled(maps, light, fov=35.0, tile=40), whole)  # 96 is no whole number of 40s
