"""``benchmarks/capture.py``'s phone frame: the bundled scene as a phone's 4:3 JPEG."""

import numpy as np
from PIL import Image

from .helpers import benchmark_module


def test_the_phone_frame_has_the_size_asked_for_and_the_bundled_scene(tmp_path):
    capture = benchmark_module("capture")
    path = capture.phone_photo(tmp_path / "phone.jpg", (400, 300))
    frame = Image.open(path)
    assert frame.format == "JPEG" and frame.size == (400, 300)
    # The centre of the frame is the centre of the bundled photo, upscaled.
    from mideepbasis.render.api import example_capture_dir

    bundled = Image.open(example_capture_dir() / "photo.jpg").convert("RGB").resize((400, 400), Image.BICUBIC)
    centre = np.asarray(frame.convert("L").crop((150, 100, 250, 200)), dtype=np.float32)
    expected = np.asarray(bundled.convert("L").crop((150, 150, 250, 250)), dtype=np.float32)
    assert np.abs(centre - expected).mean() < 3.0  # [8-bit codes]: JPEG's loss alone
