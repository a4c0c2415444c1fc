"""The relightable viewer in a capture's ``report.html``: WebGL 2, self-contained, offline.

The page embeds the capture's four PNG maps (as data URIs, so that WebGL may read them from
``file://``), the shader (``assets/viewer/shading.frag``: the ``physical`` formula of docs/ARCHITECTURE.md section 4, as
``render/shading.py`` has it), the viewer's script (``assets/viewer/viewer.js``) and the studio
environment prefiltered for split-sum lighting (``assets/viewer/studio_prefiltered.json``, made by
``scripts/make_viewer_environment.py``). The camera sits above the sample's centre at the capture's
height H = 1 / tan(fov / 2); the flash starts where the capture found it and has the capture's
intensity (pi H^2). In flash mode every pixel is the per-pixel flash render of ``render_flash``
with ``views`` at the camera, clipped and sRGB-encoded (checked in headless Chromium by
``tests/test_viewer.py``). Where the folder has ``height.png``, the page embeds it too, as 8-bit
grey, and its "height map" checkbox shows those grey levels in place of the shading (the status
line gives the black and white of ``height.json``).

``headless_readback`` and ``screenshot`` drive a headless Chromium (Debian's ``chromium``), when
there is one, for tests and for people who want a picture of the viewer.
"""

from __future__ import annotations

import base64
import json
import math
import os
import re
import shutil
import subprocess
import tempfile
from importlib import resources
from pathlib import Path

import numpy as np

from . import constants

#: The four maps the viewer reads, as the capture folder holds them (8-bit PNG).
VIEWER_MAPS = ("normal", "diffuse", "roughness", "specular")

#: Flags of a headless Chromium that does nothing on the network and renders WebGL in software.
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars")


def _asset(name: str) -> str:
    return (resources.files("mideepbasis") / "assets" / "viewer" / name).read_text()


def _script_json(value) -> str:
    """JSON that is safe inside a <script> element."""
    return json.dumps(value, separators=(",", ":")).replace("</", "<\\/")


def viewer_data(folder: Path, light: tuple[float, float, float], fov: float) -> dict:
    """What the viewer's script reads: maps (data URIs), camera, flash, intensity, environment."""
    folder = Path(folder)
    maps = {name: "data:image/png;base64," + base64.b64encode(_viewer_png(folder / f"{name}.png")).decode()
            for name in VIEWER_MAPS}
    height = constants.camera_height(fov)
    return {"maps": maps, "camera": [0.0, 0.0, height], "light": [float(v) for v in light],
            "intensity": math.pi * height**2, "extent": 1.0, "fov": fov, "height": viewer_height(folder),
            "environment": json.loads(_asset("studio_prefiltered.json"))}


def viewer_height(folder: Path) -> dict | None:
    """The folder's height map as the viewer shows it: ``map``, ``height.png`` as an 8-bit grey PNG
    (data URI; ``_viewer_png``'s size), and ``black`` and ``white``, its range [patch half-widths]
    from ``height.json`` (None where that is missing); None without ``height.png``."""
    from io import BytesIO

    from PIL import Image

    folder = Path(folder)
    if not (folder / "height.png").is_file():
        return None
    with Image.open(folder / "height.png") as image:
        wide = image.mode.startswith("I")  # 16-bit grey, as export.write_height writes it
        values = np.asarray(image if wide else image.convert("L"), dtype=np.float64) / (65535.0 if wide else 255.0)
    if values.shape[1] > MAX_VIEWER_SIZE:
        size = (MAX_VIEWER_SIZE, round(values.shape[0] * MAX_VIEWER_SIZE / values.shape[1]))
        values = np.asarray(Image.fromarray(values.astype(np.float32), mode="F").resize(size, Image.Resampling.BOX))
    buffer = BytesIO()
    Image.fromarray(np.rint(values.clip(0, 1) * 255).astype(np.uint8), mode="L").save(buffer, format="PNG")
    record = folder / "height.json"
    limits = json.loads(record.read_text()) if record.is_file() else {}
    return {"map": "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode(),
            "black": limits.get("png_black"), "white": limits.get("png_white")}


#: Largest map side the viewer embeds [pixels]; larger maps are box-filtered down for it.
MAX_VIEWER_SIZE = 1024


def viewer_size(width: int) -> int:
    """The viewer's canvas size for maps ``width`` pixels wide."""
    return min(width, MAX_VIEWER_SIZE)


def _viewer_png(path: Path) -> bytes:
    """The PNG's bytes, or a box-filtered copy at most ``MAX_VIEWER_SIZE`` wide (keeps pages small)."""
    from io import BytesIO

    from PIL import Image

    with Image.open(path) as image:
        if image.width <= MAX_VIEWER_SIZE:
            return path.read_bytes()
        size = (MAX_VIEWER_SIZE, round(image.height * MAX_VIEWER_SIZE / image.width))
        buffer = BytesIO()
        image.resize(size, Image.Resampling.BOX).save(buffer, format="PNG")
        return buffer.getvalue()


def viewer_section(folder: Path, light: tuple[float, float, float], fov: float, size: int) -> str:
    """The HTML of the viewer: canvas (``size`` pixels, one per map texel), controls, data and code."""
    data = viewer_data(folder, light, fov)
    from PIL import Image

    with Image.open(Path(folder) / "normal.png") as normal:
        width = normal.width
    # Said where the maps are larger than the canvas: the viewer then shows a box-filtered copy.
    smaller = (f'\n<p class="mdb-viewer-note">The viewer shows the maps box-filtered to {size} px; '
               f'the map files are {width} px.</p>' if width > size else "")
    # The height map's checkbox, where there is a height map to show.
    height = ('\n&nbsp;|&nbsp;\n<label><input type="checkbox" name="height"> height map</label>'
              if data["height"] else "")
    return f"""<section id="mdb-viewer">
<h2>Relight</h2>
<p>Drag on the sample to move the flash over it, scroll to move it nearer or farther.</p>{smaller}
<canvas width="{size}" height="{size}" style="width:{max(size, 512)}px;height:{max(size, 512)}px;image-rendering:pixelated;touch-action:none;cursor:crosshair"></canvas>
<div class="mdb-viewer-controls">
<label><input type="radio" name="light" value="flash" checked> flash</label>
<label><input type="radio" name="light" value="env"> studio environment</label>
&nbsp;|&nbsp;
<label><input type="checkbox" name="normal" checked> normal map</label>
<label><input type="checkbox" name="diffuse" checked> diffuse lobe</label>
<label><input type="checkbox" name="specular" checked> specular lobe</label>{height}
</div>
<p class="mdb-viewer-status">starting WebGL...</p>
<script type="application/json" id="mdb-viewer-data">{_script_json(data)}</script>
<script type="x-shader/x-fragment" id="mdb-viewer-fragment">
{_asset("shading.frag")}</script>
<script>
{_asset("viewer.js")}</script>
</section>"""


def write_viewer_page(folder: Path, light: tuple[float, float, float], fov: float = constants.DEFAULT_FOV_DEG,
                      name: str = "viewer.html") -> Path:
    """A page with the viewer alone for the material folder ``folder`` (8-bit PNG maps), written
    into it atomically; returns its path."""
    from PIL import Image

    folder = Path(folder)
    with Image.open(folder / "normal.png") as image:
        size = viewer_size(image.width)
    page = (f"<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>{folder.name}: relight</title>"
            "<style>body{font-family:sans-serif;margin:2em}</style></head><body>\n"
            f"{viewer_section(folder, light, fov, size)}\n</body></html>\n")
    path = folder / name
    temporary = path.with_name(f".{name}.tmp-{os.getpid()}")
    temporary.write_text(page)
    os.replace(temporary, path)
    return path


# --- headless Chromium -----------------------------------------------------------------------------


def find_chromium() -> str | None:
    """The path of a Chromium or Chrome binary on this machine, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _chromium(arguments: list[str], timeout: float, flags: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    binary = find_chromium()
    if binary is None:
        raise FileNotFoundError("no Chromium on this machine (Debian: apt-get install chromium)")
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run([binary, *CHROMIUM_FLAGS, *flags, f"--user-data-dir={profile}", *arguments],
                              capture_output=True, text=True, timeout=timeout)


def headless_readback(report: Path, light: tuple[float, float, float] | None = None, mode: str = "flash",
                      normal: bool = True, diffuse: bool = True, specular: bool = True, height: bool = False,
                      timeout: float = 120.0) -> tuple[np.ndarray, float]:
    """Open ``report`` in headless Chromium with the viewer's test hook and read its canvas back
    (``height``: the height map shown instead of the shading).

    Returns:
        (the canvas, (H, W, 3) uint8 with row 0 at the top; milliseconds from the script's start
        to its first frame).
    """
    fragment = f"viewer-test&mode={mode}&normal={int(normal)}&diffuse={int(diffuse)}&specular={int(specular)}"
    if height:
        fragment += "&height=1"
    if light is not None:
        fragment += "&light=" + ",".join(f"{v:.9g}" for v in light)
    url = Path(report).resolve().as_uri() + "#" + fragment
    result = _chromium(["--virtual-time-budget=10000", "--dump-dom", url], timeout)
    match = re.search(r'<pre id="mdb-viewer-readback" data-width="(\d+)" data-height="(\d+)" '
                      r'data-first-frame-ms="([0-9.]+)">([^<]*)</pre>', result.stdout)
    if match is None:
        raise RuntimeError(f"{report}: the viewer gave no readback (Chromium said: {result.stderr.strip()[-500:]})")
    width, height = int(match.group(1)), int(match.group(2))
    pixels = np.frombuffer(base64.b64decode(match.group(4)), np.uint8).reshape(height, width, 4)
    return pixels[::-1, :, :3].copy(), float(match.group(3))


def headless_dom(page: Path, flags: tuple[str, ...] = (), timeout: float = 120.0) -> str:
    """The page's DOM after its scripts ran in headless Chromium (``flags``: extra switches)."""
    return _chromium(["--virtual-time-budget=10000", "--dump-dom", Path(page).resolve().as_uri()], timeout,
                     flags).stdout


def screenshot(report: Path, output: Path, width: int = 1100, height: int = 1400, timeout: float = 120.0) -> Path:
    """A PNG of ``report`` as headless Chromium shows it (the viewer's first frame included)."""
    output = Path(output)
    temporary = output.with_name(f".{output.stem}.tmp-{os.getpid()}.png")
    try:
        _chromium([f"--window-size={width},{height}", "--virtual-time-budget=10000",
                   f"--screenshot={temporary}", Path(report).resolve().as_uri()], timeout)
        if not temporary.is_file():
            raise RuntimeError(f"{report}: Chromium wrote no screenshot")
        os.replace(temporary, output)
    finally:
        temporary.unlink(missing_ok=True)
    return output
