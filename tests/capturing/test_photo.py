"""Reading a photo for capture: crop, resampling, field of view (EXIF or given), warnings."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from PIL import Image

from mideepbasis.capturing import field_of_view_from_focal, load_photo
from mideepbasis.imageio import write_image

from .helpers import photo_file


def test_field_of_view_from_the_exif_focal_length():
    # A 36 x 24 frame with a 50 mm lens sees 39.6 deg across its width; its centre 24 x 24 square less.
    assert field_of_view_from_focal(50.0, 3600, 2400) == pytest.approx(2 * math.degrees(math.atan(12 / 50)), rel=1e-6)
    assert field_of_view_from_focal(26.0, 4000, 3000) == pytest.approx(2 * math.degrees(math.atan(
        math.tan(math.atan(21.633 / 26.0)) * 3000 / 5000)), rel=1e-4)


def test_photo_loading_crops_resamples_and_reads_the_field_of_view(tmp_path):
    photo, fov, source, notes = load_photo(photo_file(tmp_path, focal=28), resolution=64)
    assert photo.shape == (3, 64, 64) and source == "exif"
    assert fov == pytest.approx(field_of_view_from_focal(28, 96, 80))
    assert any("centre 80x80 square" in note for note in notes)
    _, fov, source, _ = load_photo(photo_file(tmp_path, "plain.png"), fov=60.0, resolution=64)
    assert (fov, source) == (60.0, "argument")
    _, fov, source, notes = load_photo(photo_file(tmp_path, "plain2.png"), resolution=64)
    assert (fov, source) == (45.0, "default") and any("45 deg assumed" in n for n in notes)


def test_dark_clipped_and_broken_exif_photos_warn_but_go_through(tmp_path):
    with pytest.warns(UserWarning, match="nearly black"):
        load_photo(photo_file(tmp_path, "dark.png", size=(64, 64), value=0.002), resolution=64)
    write_image(tmp_path / "white.png", np.ones((64, 64, 3), np.float32))
    with pytest.warns(UserWarning, match="clipped"):
        load_photo(tmp_path / "white.png", resolution=64)
    # An EXIF block whose Exif-IFD pointer leads nowhere.
    import struct

    image = Image.fromarray((np.ones((64, 64, 3)) * 120).astype(np.uint8))
    broken = b"Exif\x00\x00II*\x00" + struct.pack("<IH", 8, 1) + struct.pack("<HHII", 0x8769, 4, 1, 10_000_000) + b"\0" * 4
    image.save(tmp_path / "broken_exif.jpg", exif=broken)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, fov, source, notes = load_photo(tmp_path / "broken_exif.jpg", resolution=64)
    assert (fov, source) == (45.0, "default")
    assert any("EXIF block of 'broken_exif.jpg' could not be parsed" in note for note in notes)


def test_a_field_of_view_given_wins_over_the_exif_one(tmp_path):
    path = photo_file(tmp_path, focal=28)
    _, fov, source, _ = load_photo(path, fov=23.0, resolution=64)
    assert (fov, source) == (23.0, "argument")
    _, fov, source, _ = load_photo(path, resolution=64)
    assert source == "exif" and fov == pytest.approx(field_of_view_from_focal(28, 96, 80))


def test_native_resolution_stops_at_its_most_and_says_so(tmp_path, monkeypatch):
    from mideepbasis.capturing import photo as photo_module

    rng = np.random.default_rng(0)
    write_image(tmp_path / "big.png", rng.uniform(0.2, 0.8, (300, 300, 3)).astype(np.float32))
    monkeypatch.setattr(photo_module, "MAX_NATIVE_RESOLUTION", 128)
    reads = []
    real_read = photo_module.read_image
    monkeypatch.setattr(photo_module, "read_image", lambda *a, **k: reads.append(k["reduce"]) or real_read(*a, **k))
    photo, _, _, notes = load_photo(tmp_path / "big.png", fov=45.0, resolution="native")
    assert photo.shape == (3, 128, 128)
    assert any("worked at the most, 128 px" in note for note in notes)
    assert reads == [1]  # 300 // (2 x 128): decoded whole, at least twice the working size
    photo, _, _, notes = load_photo(tmp_path / "big.png", fov=45.0, resolution=64)
    assert reads[-1] == 2 and not any("most" in note for note in notes)
    small, _, _, notes = load_photo(photo_file(tmp_path, "small.png", size=(100, 100)), resolution="native")
    assert small.shape == (3, 100, 100) and not any("most" in note for note in notes)


def test_a_working_resolution_above_the_most_is_refused():
    from mideepbasis.capturing.photo import MAX_NATIVE_RESOLUTION, parse_resolution

    assert MAX_NATIVE_RESOLUTION == 4096
    assert parse_resolution("4096") == 4096 and parse_resolution("native") == "native"
    with pytest.raises(ValueError, match="64 to 4096 pixels, got 8192"):
        parse_resolution("8192")
