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
