"""The capture engine end to end: its outputs, its failures, its imports, the public function."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from mideepbasis import constants
from mideepbasis.capturing import RefineConfig, SearchConfig, capture
from mideepbasis.evaluation import flash_photos
from mideepbasis.export import save_capture
from mideepbasis.imageio import write_image
from mideepbasis.material import Material
from mideepbasis.render import render_flash

from .helpers import material


def test_capture_outputs_load_back_render_and_validate(tmp_path, tiny_checkpoint):
    truth = material(4, size=64)
    photos, _ = flash_photos(truth, torch.tensor([[0.1, -0.1]]))
    write_image(tmp_path / "shot.png", photos[0].permute(1, 2, 0).numpy(), encode_srgb=True)
    # One pass: the untrained tiny model's bases disagree from copy to copy, and their averaged
    # normals change from pixel to pixel more than the footprint comparison below allows.
    result = capture(tmp_path / "shot.png", model=tiny_checkpoint, resolution=64, refine=RefineConfig(steps=20),
                     search=SearchConfig(resolution=32, grid=9), symmetries=1)
    out = save_capture(result, tmp_path / "out", exr=True, environment_spp=4)

    loaded = Material.load(out)
    assert torch.allclose(loaded.to_tensor(), result.material.to_tensor(), atol=1.5 / 255)
    exr = {name: out / f"{name}.exr" for name in ("normal", "diffuse", "roughness", "specular")}
    assert all(p.is_file() for p in exr.values())
    light = json.loads((out / "light.json").read_text())
    assert light["offset"] == pytest.approx(list(result.offset)) and light["fov_source"] == "default"
    for name in ("photo.png", "rerender.png", "error.png", "environment.png", "report.png", "report.html"):
        assert (out / name).is_file(), name

    import mitsuba as mi

    scene = mi.load_file(str(out / "scene.xml"), spp="64")
    traced = np.array(mi.render(scene, spp=64))[..., :3]
    with torch.no_grad():
        expected = render_flash(loaded.to_tensor()[None], result.light_position.view(1, 1, 3))[0, 0].permute(1, 2, 0).numpy()
    # The tiny untrained model's maps change from pixel to pixel, and the path tracer averages over
    # each pixel's footprint with bilinear textures: compare 8 x 8 blocks.
    def blocks(image):
        return image.reshape(8, 8, 8, 8, 3).mean(axis=(1, 3))

    assert np.abs(blocks(traced) - blocks(expected)).mean() / expected.mean() < 0.03

    import pygltflib

    gltf = pygltflib.GLTF2().load(str(out / "material.gltf"))
    assert gltf.asset.version == "2.0" and len(gltf.materials) == 1
    assert "KHR_materials_specular" in gltf.materials[0].extensions
    for image in gltf.images:
        assert (out / image.uri).is_file(), image.uri
    assert len(gltf.binary_blob() or gltf.decode_data_uri(gltf.buffers[0].uri)) == gltf.buffers[0].byteLength

    # The MaterialX and USD files displace by height.png over the range height.json records.
    import MaterialX as mx

    height = json.loads((out / "height.json").read_text())
    span = height["png_white"] - height["png_black"]
    document = mx.createDocument()
    mx.readFromXmlFile(document, str(out / "material.mtlx"))
    assert document.getNodes("displacement")[0].getInputValue("scale") == pytest.approx(span, rel=1e-5)
    assert "@height.png@" in (out / "material.usda").read_text()
    try:
        from pxr import Usd, UsdShade
    except ImportError:  # usd-core is optional (the ``usd`` extra)
        return
    stage = Usd.Stage.Open(str(out / "material.usda"))
    texture = UsdShade.Shader(stage.GetPrimAtPath("/sample/captured_material/height_texture"))
    assert texture.GetInput("scale").Get()[0] == pytest.approx(span, rel=1e-5)
    assert texture.GetInput("bias").Get()[0] == pytest.approx(height["png_black"], rel=1e-5)


def test_a_preview_that_fails_to_trace_fails_the_writing_and_leaves_nothing(tmp_path, tiny_checkpoint, monkeypatch):
    """The tracer thread hands the previews over one by one: a failure in the second one (the
    first already written beside the exports) ends the writing with that error, without waiting
    for a preview that never comes, and no output folder nor staging folder is left."""
    import mideepbasis.render.scenes as scenes

    truth = material(4, size=64)
    photos, _ = flash_photos(truth, torch.tensor([[0.1, -0.1]]))
    write_image(tmp_path / "shot.png", photos[0].permute(1, 2, 0).numpy(), encode_srgb=True)
    result = capture(tmp_path / "shot.png", model=tiny_checkpoint, resolution=64, refine=RefineConfig(steps=0),
                     light=(0.1, -0.1), symmetries=1)
    traced = []
    real_render = scenes.render

    def render(scene, *args, **kwargs):
        if traced:
            raise RuntimeError("the sphere's trace failed")
        traced.append(scene)
        return real_render(scene, *args, **kwargs)

    monkeypatch.setattr(scenes, "render", render)
    with pytest.raises(RuntimeError, match="the sphere's trace failed"):
        save_capture(result, tmp_path / "out", environment_spp=4)
    assert len(traced) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shot.png"]


def test_a_capture_imports_neither_dynamo_nor_plotting_libraries(tmp_path):
    # torch._dynamo (pulled in by torch.optim), matplotlib and colour-science cost seconds of start-up;
    # pxr, loaded beside the preview thread, deadlocked about one capture in ten (the USD file is text).
    import subprocess
    import sys

    script = ("import sys\n"
              "from mideepbasis.capturing import capture, CaptureConfig, RefineConfig\n"
              "from mideepbasis.export import save_capture\n"
              "from mideepbasis.render.api import example_capture_dir\n"
              "result = capture(example_capture_dir() / 'photo.jpg', config=CaptureConfig(refine=RefineConfig(steps=2)))\n"
              f"save_capture(result, {str(tmp_path / 'out')!r})\n"
              "print(sorted(m for m in ('torch._dynamo', 'matplotlib', 'colour', 'sympy', 'pxr') if m in sys.modules))\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_importing_the_package_sets_a_short_openmp_spin_unless_the_user_chose():
    # Set before torch loads OpenMP (which reads it once): a short spin, not passive waiting.
    import os
    import subprocess
    import sys

    script = "import mideepbasis, os; print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))"
    clean = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}

    def printed(**extra):
        result = subprocess.run([sys.executable, "-c", script], env={**clean, **extra}, capture_output=True,
                                text=True, timeout=120)
        return result.stdout.split()

    assert printed() == ["1000", "None"]
    assert printed(OMP_WAIT_POLICY="PASSIVE") == ["None", "PASSIVE"]
    assert printed(GOMP_SPINCOUNT="5") == ["5", "None"]


def test_the_public_capture_is_a_plain_function(tmp_path):
    # docs/ARCHITECTURE.md section 10: `from mideepbasis import capture; capture("photo.jpg")`, in a fresh
    # process; a function, whatever was imported before or after it.
    import subprocess
    import sys

    script = ("import inspect\n"
              "from mideepbasis import capture\n"
              "from mideepbasis.capturing import RefineConfig, capture as function\n"
              "from mideepbasis.render.api import example_capture_dir\n"
              "import mideepbasis\n"
              "assert inspect.isfunction(capture) and capture is function is mideepbasis.capture\n"
              "result = capture(example_capture_dir() / 'photo.jpg', refine=RefineConfig(steps=0))\n"
              "print(type(result).__name__, result.material.width, capture.__name__)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["CaptureResult", "256", "capture"]


def test_the_report_of_a_large_capture_shows_its_images_averaged_to_the_panel(tmp_path):
    from mideepbasis.capturing import CaptureResult
    from mideepbasis.reporting import REPORT_TILE, REPORT_TITLE, capture_report

    size = 4 * REPORT_TILE  # beyond the panels' limit of twice their size: averaged first
    rows = torch.linspace(0, 1, size).view(1, size, 1)
    photo = torch.cat([rows.expand(1, size, size), (1 - rows).expand(1, size, size),
                       (torch.arange(size) % 2).float().view(1, 1, size).expand(1, size, size)])  # stripes of 1 px
    maps = F.interpolate(material(5, size=64), size=(size, size), mode="nearest")[0]
    result = CaptureResult(material=Material.from_tensor(maps), photo=photo, offset=(0.0, 0.0), fov=45.0,
                           fov_source="argument", searched=False)
    folder = tmp_path / "report"
    folder.mkdir()
    for name in ("normal", "diffuse", "roughness", "specular"):
        write_image(folder / f"{name}.png", np.zeros((8, 8, 3), np.float32))  # the viewer embeds the maps
    capture_report(result, folder, rerender=photo, error=photo * 0, environment=np.zeros((32, 32, 3), np.float32),
                   rerender_rmse=0.0)
    sheet = np.asarray(Image.open(folder / "report.png")).astype(np.float64) / 255
    panel = sheet[REPORT_TITLE + 4:REPORT_TITLE + REPORT_TILE - 4, 4:REPORT_TILE - 4]
    # The 1-px stripes average to linear 0.5 (sRGB 0.735), not to a blend of their sRGB values (0.5).
    blue = panel[8:-8, 8:-8, 2]
    assert abs(blue.mean() - 0.735) < 0.01 and blue.std() < 0.01
    # The ramps: linear red at the panel's middle row is about 0.5.
    middle = panel[panel.shape[0] // 2, 8:-8]
    assert abs(middle[:, 0].mean() - 0.735) < 0.03 and abs(middle[:, 1].mean() - 0.735) < 0.03


def test_grey_specular_greys_the_refined_maps_specular_but_for_its_metal_share(tiny_checkpoint):
    from mideepbasis.material import grey_dielectric_specular

    photo = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(5)) * 0.6 + 0.1
    common = dict(model=tiny_checkpoint, light=(0.0, 0.0), symmetries=1, refine=RefineConfig(steps=3))
    coloured = capture(photo, **common).material.to_tensor()
    grey = capture(photo, grey_specular=True, **common).material.to_tensor()
    torch.testing.assert_close(grey[:7], coloured[:7])  # normal, diffuse, roughness as they were
    expected = grey_dielectric_specular(coloured[3:6], coloured[7:10], constants.EXPORT_METAL_F0)
    torch.testing.assert_close(grey[7:10], expected, rtol=0, atol=1e-6)
    assert (coloured[7:10].amax(0) - coloured[7:10].amin(0)).max() > 1e-3  # the tiny model's specular has colour


@pytest.mark.parametrize("floor", [constants.SPECULAR_FLOOR, 0.0])
def test_the_captured_specular_is_floored_and_nothing_else_changes(floor):
    from .helpers import OracleModel

    truth = material(4)
    truth[:, 7:10, :, :32] = torch.tensor([0.004, 0.012, 0.008]).view(3, 1, 1)  # under water's F0, tinted
    photos, _ = flash_photos(truth, torch.tensor([[0.1, 0.2]]))
    captured = capture(photos[0], model=OracleModel(truth), light=(0.1, 0.2), symmetries=1, detail=False,
                       refine=RefineConfig(steps=0), specular_floor=floor, normal_strength=1.0,
                       lobe_variation=1.0).material.to_tensor()
    torch.testing.assert_close(captured[:7], truth[0, :7], rtol=0, atol=1e-5)
    torch.testing.assert_close(captured[7:], truth[0, 7:].clamp(min=floor), rtol=0, atol=1e-5)
    if floor:
        assert captured[7:, :, :32].eq(floor).all()  # the dark tinted part is now grey


def test_the_normal_strength_scales_the_captured_slopes_and_nothing_else():
    from .helpers import OracleModel

    truth = material(4)
    photos, _ = flash_photos(truth, torch.tensor([[0.1, 0.2]]))
    common = dict(model=OracleModel(truth), light=(0.1, 0.2), symmetries=1, detail=False, specular_floor=0.0,
                  lobe_variation=1.0, refine=RefineConfig(steps=0))
    full = capture(photos[0], normal_strength=1.0, **common).material.to_tensor()
    half = capture(photos[0], normal_strength=0.5, **common).material.to_tensor()
    torch.testing.assert_close(half[3:], full[3:], rtol=0, atol=0)
    slopes = lambda maps: maps[:2] / maps[2:3]  # noqa: E731
    torch.testing.assert_close(slopes(half), 0.5 * slopes(full), rtol=1e-4, atol=1e-5)
    assert slopes(full).abs().max() > 0.1  # the material has relief to scale


@pytest.mark.parametrize("share", [0.0, 0.5])
def test_the_lobe_variation_pulls_the_captured_roughness_and_specular_toward_their_means(share):
    from .helpers import OracleModel

    truth = material(4)
    truth[:, 7:10, :, :32] = torch.tensor([0.10, 0.12, 0.14]).view(3, 1, 1)  # a second, glossier half
    photos, _ = flash_photos(truth, torch.tensor([[0.1, 0.2]]))
    common = dict(model=OracleModel(truth), light=(0.1, 0.2), symmetries=1, detail=False, specular_floor=0.0,
                  normal_strength=1.0, refine=RefineConfig(steps=0))
    captured = capture(photos[0], lobe_variation=share, **common).material.to_tensor()
    # The oracle has one basis of weight 1: its mean is the map's mean over the image.
    lobe = truth[0, 6:]
    expected = lobe.mean(dim=(1, 2), keepdim=True) + share * (lobe - lobe.mean(dim=(1, 2), keepdim=True))
    torch.testing.assert_close(captured[6:], expected, rtol=0, atol=1e-5)
    torch.testing.assert_close(captured[:6], truth[0, :6], rtol=0, atol=1e-5)
    assert float(lobe.std(dim=(1, 2)).min()) > 0.01  # the truth's lobe varies


def test_a_lobe_variation_outside_zero_to_one_is_refused_by_the_python_api_too():
    from mideepbasis.capturing import CaptureConfig

    with pytest.raises(ValueError, match=r"lobe_variation must lie in \[0, 1\], got 1.5"):
        CaptureConfig(lobe_variation=1.5)


def _noisy_photo_file(tmp_path, size=1024):
    """A flash-lit gradient with strong pixel noise, 8-bit PNG: reading it with its codes averaged
    and averaging it in linear light differ most in its dark half."""
    rng = np.random.default_rng(3)
    ramp = np.linspace(0.02, 0.9, size, dtype=np.float32)[None, :, None] * np.ones((size, 1, 3), np.float32)
    noisy = (ramp + rng.normal(0.0, 0.08, ramp.shape).astype(np.float32)).clip(0.0, 1.0)
    path = tmp_path / "noisy.png"
    write_image(path, noisy, encode_srgb=True)
    return path


def test_a_larger_working_resolution_gives_the_default_captures_answer_below_the_network(tmp_path, tiny_checkpoint,
                                                                                          monkeypatch):
    """At 1024 px the search, the network and the refinement read the photo as a 256 px capture
    reads it (its 8-bit codes averaged while read), not the 1024 px photo's linear means: the
    network's answer is the default capture's bit for bit, and so are the search's and the
    refinement's photos."""
    from dataclasses import replace

    import mideepbasis.capturing.pipeline as pipeline
    from mideepbasis.capturing import CaptureConfig, Capturer
    from mideepbasis.capturing.photo import load_photo
    from mideepbasis.resampling import downsample

    read = {"search": [], "refine": []}

    def recording(stage, function):
        def call(*args, **kwargs):
            read[stage].append(args[1])
            return function(*args, **kwargs)
        return call

    monkeypatch.setattr(pipeline, "search_light", recording("search", pipeline.search_light))
    monkeypatch.setattr(pipeline, "refine_global_bases", recording("refine", pipeline.refine_global_bases))
    path = _noisy_photo_file(tmp_path)
    config = CaptureConfig(network_resolution=128, symmetries=1, detail=False, refine=RefineConfig(steps=1),
                           search=SearchConfig(passes=1))
    large, default = (Capturer(tiny_checkpoint, replace(config, resolution=size)) for size in (1024, 256))
    photo = large.load(path)
    assert photo.pixels.shape[-1] == 1024
    torch.testing.assert_close(photo.default_reading, load_photo(path, resolution=256)[0], rtol=0, atol=0)
    # The two readings differ where it matters: the dark half's noise averaged in codes is darker.
    linear_means = downsample(photo.pixels[None], 128)[0]
    coarse = downsample(photo.default_reading[None], 128)[0]
    assert float((linear_means - coarse)[..., :32].mean()) > 2e-3

    results = [capturer.capture(path) for capturer in (large, default)]
    assert results[0].offset == results[1].offset
    assert results[0].material.diffuse.shape[-1] == 1024
    for stage in ("search", "refine"):
        assert torch.equal(read[stage][0], read[stage][1])
    light = pipeline.flash_position(results[1].offset, photo.fov)[None]
    assert torch.equal(large.predict(photo, results[1].offset).output.maps,
                       default.predict(default.load(path), results[1].offset).output.maps)
    # The 1024 px photo's linear means would have given another answer.
    assert not torch.allclose(pipeline.predict_small(large.model, photo.pixels[None], light, network_resolution=128)
                              .output.maps, pipeline.predict_small(large.model, coarse[None], light,
                                                                   network_resolution=128).output.maps)


def test_a_network_without_a_resolution_limit_reads_the_working_photo_itself(tmp_path, tiny_checkpoint):
    from mideepbasis.capturing import CaptureConfig, Capturer

    path = _noisy_photo_file(tmp_path, size=640)
    config = CaptureConfig(resolution=640, network_resolution=0, symmetries=1, detail=False,
                           refine=RefineConfig(steps=0), light=(0.1, -0.1))
    capturer = Capturer(tiny_checkpoint, config)
    photo = capturer.load(path)
    assert photo.default_reading.shape[-1] == constants.DEFAULT_RESOLUTION
    assert capturer.predict(photo, (0.1, -0.1)).output.maps.shape[-1] == 640
