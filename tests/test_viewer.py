"""The relightable viewer of report.html, in a real (headless) Chromium: its canvas against our
per-pixel flash render, its lobe and normal-map toggles against hand-computed shading, its studio
environment against the irradiance of the map, its height map against height.png, and the page
without WebGL. Without Chromium, only the page's height-map option is checked."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from mideepbasis import constants
from mideepbasis.imageio import linear_to_srgb, srgb_to_linear
from mideepbasis.material import Material
from mideepbasis.viewer import find_chromium, headless_dom, headless_readback, write_viewer_page

needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no Chromium on this machine (Debian: apt-get install chromium; .ci/run does)")

#: Agreement asked of the viewer: within 2/255 per channel on 99% of the pixels.
TOLERANCES = {"levels": 2, "share": 0.99, "irradiance_relative": 0.04}


def srgb_levels(linear: torch.Tensor) -> np.ndarray:
    """(3, H, W) linear radiance -> (H, W, 3) clipped sRGB in 8-bit units (not rounded)."""
    return linear_to_srgb(linear.clamp(0, 1)).permute(1, 2, 0).numpy().astype(np.float64) * 255


def agreement(image: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    difference = np.abs(image.astype(np.float64) - reference)
    return difference.max(axis=(0, 1)), np.percentile(difference, 99, axis=(0, 1))


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """The bundled photo captured (no refinement): its folder, report.html included."""
    from mideepbasis.capturing import CaptureConfig, RefineConfig, capture
    from mideepbasis.export import save_capture
    from mideepbasis.render.api import example_capture_dir

    folder = tmp_path_factory.mktemp("capture") / "out"
    result = capture(example_capture_dir() / "photo.jpg", config=CaptureConfig(refine=RefineConfig(steps=0)))
    save_capture(result, folder)
    return folder


@needs_chromium
def test_the_viewer_draws_our_flash_render(captured):
    from mideepbasis.render import render_flash

    fov = json.loads((captured / "light.json").read_text())["fov_deg"]
    height = constants.camera_height(fov)
    maps = Material.load(captured).to_tensor()[None]
    for light in ((0.4, -0.3, 1.8), (-0.7, 0.5, 0.9), (0.0, 0.0, height)):
        image, first_frame_ms = headless_readback(captured / "report.html", light=light)
        linear = render_flash(maps, torch.tensor([[light]]), views=torch.tensor([[[0.0, 0.0, height]]]),
                              intensity=math.pi * height**2)[0, 0]
        worst, p99 = agreement(image, srgb_levels(linear))
        difference = np.abs(image - srgb_levels(linear))
        assert (difference <= TOLERANCES["levels"]).mean(axis=(0, 1)).min() >= TOLERANCES["share"], (worst, p99)
        assert first_frame_ms > 0
        print(f"light {light}: max {worst.round(2)} p99 {p99.round(2)} [8-bit levels], first frame {first_frame_ms} ms")


@needs_chromium
def test_lobe_and_normal_toggles_shade_as_computed_by_hand(tmp_path):
    # Tilted normals, a diffuse-only view: L = d / pi max(n.l, 0) I / |c - p|^2, written out here.
    size, fov = 32, constants.DEFAULT_FOV_DEG
    height = constants.camera_height(fov)
    generator = torch.Generator().manual_seed(1)
    tilt = torch.randn(2, size, size, generator=generator) * 0.3
    normal = torch.nn.functional.normalize(torch.cat([tilt, torch.ones(1, size, size)]), dim=0)  # up to ~50 deg
    Material(normal, 0.2 + 0.6 * torch.rand(3, size, size, generator=generator), torch.full((1, size, size), 0.3),
             torch.full((3, size, size), 0.5)).save(tmp_path / "material")
    page = write_viewer_page(tmp_path / "material", light=(0.3, 0.2, 2.0), fov=fov)
    stored = Material.load(tmp_path / "material").to_tensor()  # the 8-bit maps the viewer reads
    light = torch.tensor([0.3, 0.2, 2.0]).view(3, 1, 1)
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    points = torch.stack([-1 + (2 * cols + 1) / size, 1 - (2 * rows + 1) / size, torch.zeros(size, size)])
    to_light = light - points
    distance2 = (to_light**2).sum(0)
    direction = to_light / distance2.sqrt()
    for normal_map in (True, False):
        n = torch.nn.functional.normalize(stored[:3], dim=0) if normal_map else torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
        view = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, height]).view(3, 1, 1) - points, dim=0)
        visible = ((n * view).sum(0) > 0) & ((n * direction).sum(0) > 0)
        cosine = (n * direction).sum(0).clamp(min=0) * visible
        expected = stored[3:6] / math.pi * cosine * (math.pi * height**2) / distance2
        image, _ = headless_readback(page, light=(0.3, 0.2, 2.0), normal=normal_map, specular=False)
        difference = np.abs(image - srgb_levels(expected))
        assert (difference <= TOLERANCES["levels"]).mean() >= TOLERANCES["share"], difference.max()


@needs_chromium
def test_the_studio_environment_lights_a_white_lambertian_with_the_maps_irradiance(tmp_path):
    from mideepbasis.imageio import read_image
    from mideepbasis.render.scenes import scenes_dir

    size = 16
    Material(torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, size, size).clone(), torch.ones(3, size, size),
             torch.ones(1, size, size), torch.zeros(3, size, size)).save(tmp_path / "white")
    page = write_viewer_page(tmp_path / "white", light=(0.0, 0.0, 2.4))
    image, _ = headless_readback(page, mode="env", specular=False)
    # The irradiance of the upward normal from the map itself, in Mitsuba's envmap frame turned so
    # that the map's +y is the world's +z (preview_envmap.xml): E = sum L max(y, 0) dw.
    radiance = read_image(scenes_dir() / "envmaps" / "studio.exr").astype(np.float64)
    rows, cols = radiance.shape[:2]
    theta = (np.arange(rows) + 0.5) / rows * math.pi
    solid = (2 * math.pi / cols) * (math.pi / rows) * np.sin(theta)
    up = np.clip(np.cos(theta), 0, None)
    irradiance = np.einsum("hwc,h->c", radiance, solid * up)
    expected = srgb_levels(torch.from_numpy(irradiance / math.pi).float().view(3, 1, 1))[0, 0]
    measured = image.reshape(-1, 3).mean(axis=0)
    assert np.allclose(srgb_to_linear(measured / 255), srgb_to_linear(expected / 255),
                       rtol=TOLERANCES["irradiance_relative"]), (measured, expected)


@needs_chromium
def test_without_webgl_the_page_says_so_and_keeps_the_static_report(captured):
    dom = headless_dom(captured / "report.html", flags=("--disable-3d-apis",))
    assert "WebGL 2 is not available in this browser" in dom
    assert '<img src="report.png"' in dom


@needs_chromium
def test_capture_keeps_a_screenshot_of_the_viewer(tmp_path):
    from mideepbasis import cli
    from mideepbasis.render.api import example_capture_dir

    out = tmp_path / "out"
    assert cli.main(["capture", str(example_capture_dir() / "photo.jpg"), "-o", str(out), "--refine-steps", "0",
                     "--viewer-screenshot"]) == 0
    from PIL import Image

    with Image.open(out / "viewer.png") as shot:
        pixels = np.asarray(shot.convert("RGB")).astype(float)
    assert shot.size[0] >= 800 and pixels.std() > 10  # a page with pictures, not a blank one


def bumpy_folder(folder, size: int = 32):
    """A material folder with a bumpy normal map and its height map (``export.write_height``)."""
    from mideepbasis.export import write_height

    generator = torch.Generator().manual_seed(2)
    tilt = torch.randn(2, size, size, generator=generator) * 0.3
    normal = torch.nn.functional.normalize(torch.cat([tilt, torch.ones(1, size, size)]), dim=0)
    material = Material(normal, torch.full((3, size, size), 0.5), torch.full((1, size, size), 0.4),
                        torch.full((3, size, size), 0.04))
    material.save(folder)
    return write_height(folder, material)


def height_levels(folder) -> np.ndarray:
    """height.png (16-bit) in 8-bit levels, as the viewer shows it."""
    import cv2

    return np.rint(cv2.imread(str(folder / "height.png"), cv2.IMREAD_UNCHANGED) / 257.0)


def test_the_page_offers_the_height_map_where_the_folder_has_one(tmp_path):
    """No browser needed: the page has a "height map" checkbox and embeds height.png as 8-bit grey
    with height.json's range; a folder without a height map gets neither."""
    import base64
    import io
    import re

    from PIL import Image

    record = bumpy_folder(tmp_path / "bumpy")
    page = write_viewer_page(tmp_path / "bumpy", light=(0.0, 0.0, 2.4)).read_text()
    assert re.search(r'<label><input type="checkbox" name="height"> height map</label>', page)
    data = json.loads(re.search(r'<script type="application/json" id="mdb-viewer-data">(.*?)</script>', page).group(1))
    assert (data["height"]["black"], data["height"]["white"]) == (record["png_black"], record["png_white"])
    embedded = Image.open(io.BytesIO(base64.b64decode(data["height"]["map"].split(",", 1)[1])))
    assert embedded.mode == "L" and np.array_equal(np.asarray(embedded), height_levels(tmp_path / "bumpy"))
    assert 'uniform sampler2D heightMap;' in page and 'bind("height", "height")' in page

    Material.constant(8, 8).save(tmp_path / "flat")
    page = write_viewer_page(tmp_path / "flat", light=(0.0, 0.0, 2.4)).read_text()
    assert 'name="height"' not in page and '"height":null' in page


@needs_chromium
def test_the_height_option_shows_height_png_in_place_of_the_shading(tmp_path):
    bumpy_folder(tmp_path / "bumpy")
    page = write_viewer_page(tmp_path / "bumpy", light=(0.3, 0.2, 2.0))
    shown, _ = headless_readback(page, light=(0.3, 0.2, 2.0), height=True)
    levels = height_levels(tmp_path / "bumpy")
    assert np.abs(shown.astype(float) - levels[..., None]).max() <= 1, "the grey levels of height.png"
    shaded, _ = headless_readback(page, light=(0.3, 0.2, 2.0))
    assert np.abs(shaded.astype(float) - levels[..., None]).mean() > 10  # unchecked: the shading again


@needs_chromium
def test_the_report_of_a_capture_offers_its_height_map(captured):
    assert '<input type="checkbox" name="height">' in (captured / "report.html").read_text()
    shown, _ = headless_readback(captured / "report.html", height=True)
    assert np.abs(shown.astype(float) - height_levels(captured)[..., None]).max() <= 1


def test_the_page_says_when_it_shows_the_maps_smaller_than_the_files(tmp_path, monkeypatch):
    from mideepbasis import viewer

    Material.constant(32, 32).save(tmp_path / "flat")
    page = write_viewer_page(tmp_path / "flat", light=(0.0, 0.0, 2.4)).read_text()
    assert "box-filtered" not in page
    monkeypatch.setattr(viewer, "MAX_VIEWER_SIZE", 16)
    page = write_viewer_page(tmp_path / "flat", light=(0.0, 0.0, 2.4)).read_text()
    assert "The viewer shows the maps box-filtered to 16 px; the map files are 32 px." in page
