"""The relightable viewer of report.html in headless Chromium: agreement with the renderer, time to the first frame.

    .venv/bin/python benchmarks/viewer.py [-o benchmarks/results/viewer.json]

Captures the bundled photo (no refinement), opens its report.html in headless Chromium (software
WebGL, SwiftShader) with the viewer's test hook for a few flash positions, and compares the canvas
with ``render_flash`` (the Mitsuba plugin, camera above the centre, flash apart) in 8-bit sRGB
levels: max and 99th percentile of |difference| per channel. Times: the viewer script's start
to its first frame as the page measures it, and the whole Chromium run (start, load, first
frame, DOM dump) from outside. Writes a screenshot of the report to benchmarks/results/viewer.png.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import mideepbasis  # noqa: F401
import numpy as np
import torch
from common import RESULTS, write_report

from mideepbasis import constants
from mideepbasis.capturing import CaptureConfig, RefineConfig, capture
from mideepbasis.export import save_capture
from mideepbasis.imageio import linear_to_srgb
from mideepbasis.material import Material
from mideepbasis.render import render_flash
from mideepbasis.render.api import example_capture_dir
from mideepbasis.viewer import headless_readback, screenshot

LIGHTS = ((0.4, -0.3, 1.8), (-0.7, 0.5, 0.9), (0.0, 0.0, 2.4), (0.9, 0.9, 0.5))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "viewer.json")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary) / "capture"
        save_capture(capture(example_capture_dir() / "photo.jpg", config=CaptureConfig(refine=RefineConfig(steps=0))), folder)
        fov = json.loads((folder / "light.json").read_text())["fov_deg"]
        height = constants.camera_height(fov)
        maps = Material.load(folder).to_tensor()[None]
        rows = []
        for light in LIGHTS:
            started = time.perf_counter()
            image, first_frame_ms = headless_readback(folder / "report.html", light=light)
            chromium_seconds = time.perf_counter() - started
            linear = render_flash(maps, torch.tensor([[light]]), views=torch.tensor([[[0.0, 0.0, height]]]),
                                  intensity=math.pi * height**2)[0, 0]
            reference = linear_to_srgb(linear.clamp(0, 1)).permute(1, 2, 0).numpy().astype(np.float64) * 255
            difference = np.abs(image.astype(np.float64) - reference)
            rows.append({"light": light, "max_levels": difference.max(axis=(0, 1)).round(3).tolist(),
                         "p99_levels": np.percentile(difference, 99, axis=(0, 1)).round(3).tolist(),
                         "share_within_2_levels": float((difference <= 2).mean()),
                         "first_frame_ms": first_frame_ms, "chromium_wall_s": round(chromium_seconds, 2)})
            print(rows[-1])
        screenshot(folder / "report.html", RESULTS / "viewer.png")
    write_report(args.output, "viewer", {"resolution": int(maps.shape[-1]), "rows": rows,
                                         "screenshot": "viewer.png"})


if __name__ == "__main__":
    main()
