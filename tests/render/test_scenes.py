"""Full Mitsuba scenes: the path-traced flash capture against the per-pixel path, and the previews."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mideepbasis import export
from mideepbasis.render import bridge, scenes

#: Mean relative difference allowed between the path-traced flash scene and the per-pixel path.
FLASH_SCENE_MEAN_RTOL = 5e-3


def smooth_material(size: int) -> torch.Tensor:
    """A (10, H, W) material whose maps vary slowly, so pixel-footprint filtering barely matters."""
    y, x = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    normal = torch.stack([0.2 * torch.sin(3 * x), 0.2 * torch.cos(2 * y), torch.ones_like(x)])
    normal = normal / normal.norm(dim=0, keepdim=True)
    diffuse = torch.stack([0.5 + 0.3 * x, 0.4 + 0.2 * y, torch.full_like(x, 0.3)])
    roughness = (0.4 + 0.2 * x * y)[None]
    specular = torch.stack([torch.full_like(x, 0.04), 0.3 + 0.2 * y, torch.full_like(x, 0.1)])
    return torch.cat([normal, diffuse, roughness, specular])


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.3, -0.2)])
def test_path_traced_flash_scene_agrees_with_per_pixel_path(offset, fov_height):
    fov, height = fov_height
    maps = smooth_material(64)
    traced = scenes.render(scenes.flash_scene(maps, offset=offset, fov=fov, spp=256))
    light = torch.tensor([[[offset[0], offset[1], height]]])
    per_pixel = bridge.render_flash(maps[None], light, math.pi * height**2)[0, 0].permute(1, 2, 0).numpy()
    assert traced.shape == per_pixel.shape == (64, 64, 3)
    assert np.abs(traced - per_pixel).mean() / per_pixel.mean() < FLASH_SCENE_MEAN_RTOL
    # A mirrored image (wrong texture orientation) would be far off on this asymmetric material.
    assert np.abs(traced - per_pixel[::-1]).mean() / per_pixel.mean() > 10 * FLASH_SCENE_MEAN_RTOL


def test_preview_maps_are_kept_up_to_their_size_and_block_averaged_above():
    small = smooth_material(export.PREVIEW_MAP_SIZE)
    assert export.preview_maps(small) is small  # a 256 px capture's previews see its own maps
    large = smooth_material(2 * export.PREVIEW_MAP_SIZE)
    shown = export.preview_maps(large)
    assert shown.shape == (10, export.PREVIEW_MAP_SIZE, export.PREVIEW_MAP_SIZE)
    # Each texel is its 2 x 2 block's mean (the reference: a reshape), the normal renormalised.
    blocks = large.reshape(10, export.PREVIEW_MAP_SIZE, 2, export.PREVIEW_MAP_SIZE, 2).mean(dim=(2, 4))
    torch.testing.assert_close(shown[3:], blocks[3:])
    torch.testing.assert_close(shown[:3], blocks[:3] / blocks[:3].norm(dim=0, keepdim=True))
    wide = export.preview_maps(smooth_material(2 * export.PREVIEW_MAP_SIZE)[:, :300])
    assert wide.shape == (10, 150, export.PREVIEW_MAP_SIZE)  # the longer side sets the scale


@pytest.mark.parametrize("environment", ["studio", "sunsky"])
def test_environment_preview_shows_the_sample(environment):
    maps = smooth_material(32)
    image = scenes.render(scenes.preview_scene(maps, environment=environment, spp=16, resolution=64))
    assert image.shape == (64, 64, 3) and np.isfinite(image).all()
    centre = image[28:36, 28:36].mean()
    assert centre > 0.02  # the lit sample fills the middle of the frame
    darker = scenes.render(scenes.preview_scene(maps * torch.tensor([1, 1, 1, .2, .2, .2, 1, 1, 1, 1]).view(10, 1, 1),
                                                 environment=environment, spp=16, resolution=64))
    assert darker[28:36, 28:36].mean() < 0.8 * centre  # and its material is what we see


def test_unknown_environment_is_a_clear_error(tmp_path):
    with pytest.raises(Exception, match="neither"):
        scenes.preview_scene(smooth_material(8), environment=str(tmp_path / "missing.exr"))


def test_scene_files_are_installed_with_the_package():
    folder = scenes.scenes_dir()
    for name in ["flash.xml", "sample.xml", "preview_camera.xml", "preview_envmap.xml", "preview_sunsky.xml",
                 "preview_uniform.xml", "preview_shape.xml", "shape_sphere.xml", "shape_cloth.xml", "env_envmap.xml",
                 "env_sunsky.xml", "env_uniform.xml", "meshes/cloth.ply", "envmaps/studio.exr"]:
        assert (folder / name).is_file(), name


def test_a_white_lambertian_sphere_under_a_uniform_sky_renders_to_its_known_value():
    from mideepbasis.render.scenes import render, shape_scene

    from ..helpers import directional_albedo

    maps = torch.zeros(10, 8, 8)
    maps[2], maps[3:6], maps[6] = 1.0, 1.0, 1.0  # flat, white, rough, specular 0
    image = render(shape_scene(maps, "sphere", environment="uniform", spp=2048, resolution=33))
    # The centre pixel sees the ball head-on: a convex object under a uniform sky is lit by all of
    # its hemisphere, so it reflects the directional albedo at normal incidence.
    assert image[16, 16].mean() == pytest.approx(directional_albedo(0.0), abs=0.01)
    assert image[0, 0].mean() == pytest.approx(1.0, abs=1e-6)  # the sky itself behind the ball


def test_the_cloth_preview_is_shaded_and_tiles_the_maps():
    from mideepbasis.data.procedural import GeneratorConfig, generate
    from mideepbasis.errors import InputError
    from mideepbasis.render.scenes import render, shape_scene

    maps = generate(3, config=GeneratorConfig(size=32)).to_tensor()
    images = [render(shape_scene(maps, "cloth", tiles=tiles, spp=8, resolution=48)) for tiles in (1, 4)]
    for image in images:
        assert np.isfinite(image).all() and image.std() > 0.01
    assert np.abs(images[0] - images[1]).mean() > 0.005  # more tiles, another pattern on the same cloth
    with pytest.raises(InputError, match="unknown preview shape"):
        shape_scene(maps, "teapot")


def checker_scene(rfilter: str, spp: int = 64, resolution: int = 48):
    """A tilted checkerboard, diffuse, under a constant sky, seen through ``rfilter``: with BSDF
    samples alone each sample's value is the checker's albedo exactly, so the image differs from
    the filter's expectation only by where its samples fall in their pixels."""
    import mitsuba as mi

    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 0, "bsdf_samples": 1},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -2.2, 1.6], target=[0, 0, 0], up=[0, 0, 1]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "pixel_format": "rgb",
                            "rfilter": {"type": rfilter}}},
        "board": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([1.4, 1.4, 1.0]),
                  "bsdf": {"type": "diffuse", "reflectance": {
                      "type": "checkerboard", "color0": {"type": "rgb", "value": [0.05, 0.1, 0.2]},
                      "color1": {"type": "rgb", "value": [0.9, 0.7, 0.5]},
                      "to_uv": mi.ScalarTransform4f().scale([6.0, 6.0, 1.0])}}},
    })


def test_a_box_filtered_render_developed_by_film_gaussian_is_mitsubas_gaussian_film():
    # Checker edges everywhere and the board running off the image's borders: the filter's
    # weights and its renormalisation at the edges both show. The yardstick is Mitsuba's film
    # against itself: two Gaussian-filtered renders with other seeds.
    gaussian = scenes.render(checker_scene("gaussian"), seed=1)
    other_seed = scenes.render(checker_scene("gaussian"), seed=2)
    box = scenes.render(checker_scene("box"), seed=2)
    developed = scenes.film_gaussian(box)
    assert developed.shape == box.shape and developed.dtype == np.float32

    def rmse(a, b):
        return float(np.sqrt(((a - b) ** 2).mean()))

    noise = rmse(other_seed, gaussian)  # 0.015 here
    # Developed: 0.020 (a pixel's mean keeps no trace of where its samples fell); the filter
    # averaged over each pixel's width gave 0.027, the box image itself 0.057.
    assert rmse(developed, gaussian) < 1.5 * noise
    assert rmse(box, gaussian) > 2.5 * rmse(developed, gaussian)
    border = np.ones(gaussian.shape[:2], dtype=bool)
    border[2:-2, 2:-2] = False
    assert np.abs(developed - gaussian)[border].mean() < 2 * np.abs(other_seed - gaussian)[border].mean()


def test_film_gaussian_weights_are_mitsubas_filter_at_the_pixel_offsets():
    weights = scenes.film_gaussian_weights()
    # Mitsuba's windowed Gaussian, stddev 0.5 px: exp(-x^2 / (2 * 0.25)) - exp(-2^2 / (2 * 0.25)),
    # zero from 2 px on, at x = -1, 0, 1.
    expected = np.exp(-2.0 * np.array([1.0, 0.0, 1.0])) - math.exp(-8.0)
    np.testing.assert_allclose(weights, expected / expected.sum(), rtol=1e-12)
    wider = scenes.film_gaussian_weights(1.0)  # 4 px of reach: 7 taps, symmetric
    assert wider.shape == (7,) and wider.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(wider, wider[::-1])


def test_film_gaussian_keeps_a_constant_image_to_its_edges():
    image = np.full((9, 7, 3), 0.25, dtype=np.float32)
    np.testing.assert_allclose(scenes.film_gaussian(image), image, rtol=1e-6)
