"""Blender as the judge of the exports: a capture's glTF and USD, imported into Blender 4.5 and
rendered in Cycles under the capture's own flash, look like ``mideepbasis render --light flash``
after one gain (``scripts/blender_render.py``). Runs where a Python with ``bpy`` is found
(``$MIDEEPBASIS_BLENDER_PYTHON``, or ``.venv-blender/`` as ``.ci/run`` makes it); skips otherwise."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "blender_render.py"

#: Largest relative RMSE (RMSE over the reference's mean) of Blender's render after one gain.
TOLERANCE = {"gltf": 0.01, "usd": 0.02}


def blender_python() -> str | None:
    candidates = [os.environ.get("MIDEEPBASIS_BLENDER_PYTHON"), str(ROOT / ".venv-blender" / "bin" / "python")]
    for candidate in filter(None, candidates):
        if Path(candidate).is_file() and subprocess.run([candidate, "-c", "import bpy"], capture_output=True).returncode == 0:
            return candidate
    return None


BLENDER = blender_python()
pytestmark = pytest.mark.skipif(BLENDER is None, reason="no Python with bpy (Blender 4.5): set "
                                "MIDEEPBASIS_BLENDER_PYTHON or run .ci/run, which makes .venv-blender/")


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """The bundled photo captured (default settings), its folder and its flash offset."""
    from mideepbasis.capturing import capture
    from mideepbasis.export import save_capture
    from mideepbasis.render.api import example_capture_dir

    folder = tmp_path_factory.mktemp("capture") / "material"
    result = capture(example_capture_dir() / "photo.jpg")
    save_capture(result, folder, shape_previews=False)
    return folder, tuple(result.offset)


def relative_rmse(blender: np.ndarray, reference: np.ndarray) -> float:
    """RMSE over the reference's mean after the one gain that fits Blender's image to it best,
    both area-averaged by 2 (the renders sample the maps at their own size)."""
    def halved(image):
        return image.reshape(image.shape[0] // 2, 2, image.shape[1] // 2, 2, 3).mean(axis=(1, 3))

    blender, reference = halved(blender[..., :3]), halved(reference)
    gain = (blender * reference).sum() / (blender * blender).sum()
    return float(np.sqrt(((gain * blender - reference) ** 2).mean()) / reference.mean())


def blender_render(folder: Path, kind: str, offset, out: Path) -> tuple[np.ndarray, dict]:
    from mideepbasis.imageio import read_image
    from mideepbasis.material import Material

    size = Material.load(folder).width
    nodes = out.with_suffix(".json")
    result = subprocess.run([BLENDER, str(SCRIPT), str(folder), kind, str(out), "--offset", f"{offset[0]},{offset[1]}",
                             "--resolution", str(size), "--nodes", str(nodes)], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Blender's EXR has an alpha channel
        return read_image(out), json.loads(nodes.read_text())


def reference_render(folder: Path, offset) -> np.ndarray:
    from mideepbasis.material import Material
    from mideepbasis.render.api import render_material

    material = Material.load(folder)
    return render_material(material, light="flash", offset=offset, resolution=material.width)


@pytest.mark.parametrize("kind", ["gltf", "usd"])
def test_blender_renders_the_export_as_mideepbasis_does(captured, tmp_path, kind):
    folder, offset = captured
    image, nodes = blender_render(folder, kind, offset, tmp_path / f"{kind}.exr")
    # What the shader reads, and how: colour data in sRGB, the rest as data.
    assert nodes["images"]["base_color.png"] == "sRGB"
    assert nodes["images"]["metallic_roughness.png"] == nodes["images"]["normal.png"] == "Non-Color"
    assert {"Base Color", "Metallic", "Roughness", "Normal"} <= set(nodes["principled_linked"]) and nodes["normal_map"]
    if kind == "gltf":
        assert nodes["images"]["specular_color.png"] == "sRGB" and "Specular Tint" in nodes["principled_linked"]
        assert nodes["displacement"] is None  # glTF has no displacement
    else:  # USD's only input for a grey dielectric F0: its index of refraction
        from mideepbasis.export import dielectric_f0
        from mideepbasis.interchange import ior_of_f0
        from mideepbasis.material import Material

        assert nodes["ior"] == pytest.approx(ior_of_f0(dielectric_f0(Material.load(folder))), abs=1e-3)
        # The displacement as Blender reads it: height.png (data) from its black to its white, zero height at
        # the midlevel. Blender displaces the quad's four corners by it; the tolerance below holds with that.
        height = json.loads((folder / "height.json").read_text())
        span = height["png_white"] - height["png_black"]
        assert nodes["images"]["height.png"] == "Non-Color" and nodes["displacement"]["images"] == ["height.png"]
        assert nodes["displacement"]["scale"] == pytest.approx(span, rel=1e-4)
        assert nodes["displacement"]["midlevel"] == pytest.approx(-height["png_black"] / span, rel=1e-4)
    assert relative_rmse(image, reference_render(folder, offset)) <= TOLERANCE[kind]


def test_a_normal_map_with_its_green_flipped_fails_the_check(captured, tmp_path):
    import cv2

    folder, offset = captured
    flipped = tmp_path / "flipped"
    subprocess.run(["cp", "-r", str(folder), str(flipped)], check=True)
    normal = cv2.imread(str(flipped / "normal.png"), cv2.IMREAD_UNCHANGED)
    normal[..., 1] = np.iinfo(normal.dtype).max - normal[..., 1]  # OpenCV's BGR: index 1 is green
    cv2.imwrite(str(flipped / "normal.png"), normal)
    image, _ = blender_render(flipped, "gltf", offset, tmp_path / "flipped.exr")
    assert relative_rmse(image, reference_render(folder, offset)) > 2 * TOLERANCE["gltf"]
