"""Batches of photos (mideepbasis.batch) and the capture command's bad input."""

from __future__ import annotations

import numpy as np
from PIL import Image

from mideepbasis import cli

from .capturing.helpers import photo_file


def run_cli(*args) -> int:
    return cli.main([str(a) for a in args])


def test_batch_survives_a_corrupt_photo(tmp_path, tiny_checkpoint, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in ("a.png", "b.jpg"):
        photo_file(folder, name, size=(64, 64))
    (folder / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    status = run_cli("capture", folder, "-o", tmp_path / "out", "--model", tiny_checkpoint, "--resolution", "64",
                     "--refine-steps", "5", "--light", "0,0")
    assert status == 1
    assert (tmp_path / "out" / "a" / "material.json").is_file() and (tmp_path / "out" / "b" / "material.json").is_file()
    assert not (tmp_path / "out" / "broken").exists()
    captured = capsys.readouterr()
    assert "captured 2 of 3 photos" in captured.out and "broken.jpg" in captured.out + captured.err


def test_bad_input_gives_one_line_and_writes_nothing(tmp_path, tiny_checkpoint, capsys):
    cases = {}
    (tmp_path / "text.jpg").write_text("not an image")
    cases["text.jpg"] = "not an image"
    photo_file(tmp_path, "good.png", size=(64, 64))
    data = (tmp_path / "good.png").read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 3])
    cases["truncated.png"] = "truncated"
    photo_file(tmp_path, "small.png", size=(40, 40))
    cases["small.png"] = "smaller than the 64 pixels"
    for name, message in cases.items():
        out = tmp_path / f"out_{name}"
        assert run_cli("capture", tmp_path / name, "-o", out, "--model", tiny_checkpoint, "--resolution", "64") == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mideepbasis: error:") and "\n" not in err and message in err, (name, err)
        assert not out.exists()
        assert not list(tmp_path.glob(".out_*"))

    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "keep.txt").write_text("mine")
    assert run_cli("capture", tmp_path / "good.png", "-o", occupied, "--model", tiny_checkpoint, "--resolution", "64") == 2
    assert "--overwrite" in capsys.readouterr().err and (occupied / "keep.txt").read_text() == "mine"

    not_a_model = tmp_path / "model.safetensors"
    not_a_model.write_bytes(b"\x00" * 64)
    assert run_cli("capture", tmp_path / "good.png", "-o", tmp_path / "x", "--model", not_a_model) == 2
    assert "not a safetensors checkpoint" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_a_batch_refuses_clashing_names_and_a_model_that_does_not_load_before_any_work(tmp_path, capsys):
    for name in ("a/shot.png", "b/shot.jpg"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        Image.fromarray(np.full((80, 80, 3), 128, np.uint8)).save(tmp_path / name)
    out = tmp_path / "out"
    assert cli.main(["capture", str(tmp_path / "a"), str(tmp_path / "b"), "-o", str(out)]) == 2
    assert "would both be written to" in capsys.readouterr().err
    (tmp_path / "b" / "shot.jpg").rename(tmp_path / "b" / "other.jpg")
    assert cli.main(["capture", str(tmp_path / "a"), str(tmp_path / "b"), "-o", str(out),
                     "--model", str(tmp_path / "missing.safetensors")]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "missing.safetensors: no such checkpoint file" in error[0]
    assert not out.exists() or not any(out.iterdir())


def test_capture_memory_follows_the_measured_sizes_and_is_linear_between():
    from mideepbasis.batch import CAPTURE_MEMORY_GIB, capture_memory_gib

    for size, memory in CAPTURE_MEMORY_GIB:
        assert capture_memory_gib(size) == memory
    (small, low), (large, high) = CAPTURE_MEMORY_GIB[1:3]
    assert abs(capture_memory_gib((small + large) // 2) - (low + high) / 2) < 1e-9
    assert capture_memory_gib(64) == CAPTURE_MEMORY_GIB[0][1] and capture_memory_gib(8192) == CAPTURE_MEMORY_GIB[-1][1]


def test_default_workers_are_the_cores_bounded_by_the_photos_and_the_free_memory(monkeypatch):
    from mideepbasis import batch

    monkeypatch.setattr(batch.os, "cpu_count", lambda: 4)
    assert batch.default_workers(10) == 4 and batch.default_workers(3) == 3
    assert batch.default_workers(10, memory_gib=2.8, available_gib=6.0) == 2  # 6 // 2.8
    assert batch.default_workers(10, memory_gib=2.8, available_gib=1.0) == 1  # one at least
    assert batch.default_workers(10, memory_gib=0.8, available_gib=64.0) == 4
    assert batch.default_workers(10, memory_gib=2.8, available_gib=None) == 4  # not known: the cores


def test_batch_workers_read_native_sizes_from_the_headers_and_say_when_memory_bounds_them(tmp_path, monkeypatch):
    from mideepbasis import batch
    from mideepbasis.capturing import CaptureConfig

    photos = [photo_file(tmp_path, "wide.png", size=(300, 200)), photo_file(tmp_path, "small.jpg", size=(120, 90))]
    assert batch.largest_working_resolution(photos, CaptureConfig(resolution="native")) == 200
    assert batch.largest_working_resolution(photos, CaptureConfig(resolution="native", crop=(0, 0, 150, 100))) == 100
    assert batch.largest_working_resolution(photos, CaptureConfig(resolution=1024)) == 1024
    assert batch.largest_working_resolution([tmp_path / "missing.jpg"], CaptureConfig(resolution="native")) == 4096

    monkeypatch.setattr(batch.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(batch, "available_memory_gib", lambda: 64.0)
    assert batch.batch_workers(photos, CaptureConfig(resolution=4096)) == (2, None)
    monkeypatch.setattr(batch, "available_memory_gib", lambda: 3.0)
    workers, note = batch.batch_workers(photos, CaptureConfig(resolution=4096))
    assert workers == 1 and "1 worker rather than 2" in note and "4096 px" in note and "3.0 GiB is free" in note


def test_the_command_says_when_memory_bounds_the_workers(tmp_path, monkeypatch, capsys):
    from mideepbasis import batch

    folder = tmp_path / "photos"
    folder.mkdir()
    for name in ("a.png", "b.png"):
        photo_file(folder, name, size=(64, 64))
    monkeypatch.setattr(batch.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(batch, "available_memory_gib", lambda: 1.0)
    started = {}

    def no_capture(photos, out, model, config, options, workers, overwrite=False):
        started["workers"] = workers
        return iter(())

    monkeypatch.setattr(batch, "capture_batch", no_capture)
    assert run_cli("capture", folder, "-o", tmp_path / "out", "--resolution", "64") == 0
    assert started["workers"] == 1
    assert "mideepbasis: note: 1 worker rather than 2" in capsys.readouterr().out


def test_one_capture_says_when_it_needs_more_memory_than_is_free(tmp_path, monkeypatch, capsys):
    from mideepbasis import batch
    from mideepbasis.capturing import CaptureConfig

    photo = photo_file(tmp_path, "big.png", size=(300, 200))
    monkeypatch.setattr(batch, "available_memory_gib", lambda: 1.0)
    note = batch.memory_note(photo, CaptureConfig(resolution=4096))
    assert "4096 px takes about 2.8 GiB and 1.0 GiB is free" in note
    assert batch.memory_note(photo, CaptureConfig(resolution="native")) is None  # 200 px: 0.8 GiB
    monkeypatch.setattr(batch, "available_memory_gib", lambda: None)
    assert batch.memory_note(photo, CaptureConfig(resolution=4096)) is None  # not known: nothing said


def test_the_capture_command_prints_the_memory_note(tmp_path, tiny_checkpoint, monkeypatch, capsys):
    from mideepbasis import batch

    photo = photo_file(tmp_path, "a.png", size=(64, 64))
    monkeypatch.setattr(batch, "available_memory_gib", lambda: 0.5)
    assert run_cli("capture", photo, "-o", tmp_path / "out", "--model", tiny_checkpoint, "--resolution", "64",
                   "--refine-steps", "5", "--light", "0,0", "--no-shape-previews") == 0
    assert "mideepbasis: note: a.png: a capture at 64 px takes about 0.8 GiB and 0.5 GiB is free" in capsys.readouterr().out
