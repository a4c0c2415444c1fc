"""The `mideepbasis` command: render outputs and one-line errors for bad input, with nothing written."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from mideepbasis import cli, constants
from mideepbasis.imageio import read_image, write_image
from mideepbasis.material import Material
from mideepbasis.render import reference


@pytest.fixture
def material_dir(tmp_path):
    generator = torch.Generator().manual_seed(0)
    normal = torch.nn.functional.normalize(torch.randn(3, 24, 24, generator=generator) * 0.2
                                           + torch.tensor([0, 0, 1.0]).view(3, 1, 1), dim=0)
    material = Material(normal=normal, diffuse=torch.rand(3, 24, 24, generator=generator) * 0.8,
                        roughness=0.2 + 0.6 * torch.rand(1, 24, 24, generator=generator),
                        specular=torch.full((3, 24, 24), 0.04))
    folder = tmp_path / "material"
    material.save(folder, format="exr")
    return folder


def run(*args) -> int:
    return cli.main([str(a) for a in args])


def test_flash_render_is_the_per_pixel_formula(material_dir, tmp_path):
    out = tmp_path / "out" / "flash.exr"
    assert run("render", material_dir, "-o", out, "--offset", "0.2,-0.1") == 0
    image = read_image(out)
    material = Material.load(material_dir)
    height = constants.camera_height(45.0)
    expected = reference.render_flash(material.to_tensor()[None], torch.tensor([[[0.2, -0.1, height]]]),
                                      math.pi * height**2)[0, 0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(image, expected, rtol=1e-4, atol=1e-6)
    png = read_image(out.with_suffix(".png"), decode_srgb=True)
    # Half an 8-bit step, through the steepest part of the sRGB decoding curve (slope < 2.3).
    np.testing.assert_allclose(png, np.clip(expected, 0, 1), atol=0.5 / 255 * 2.3)


@pytest.mark.parametrize("extra", [["--light", "env", "--spp", "4", "--resolution", "32"],
                                   ["--light", "env", "--env", "sunsky", "--spp", "4", "--resolution", "32"],
                                   ["--light", "flash", "--spp", "8"]])
def test_path_traced_renders_write_both_files(material_dir, tmp_path, extra):
    out = tmp_path / "render.exr"
    assert run("render", material_dir, "-o", out, *extra) == 0
    image = read_image(out)
    assert np.isfinite(image).all() and image.mean() > 0.01
    assert read_image(out.with_suffix(".png")).shape == image.shape


def corrupt_cases(tmp_path, material_dir):
    """Each case: (name, material folder) whose render must fail with a one-line message naming the problem."""
    cases = {}

    def copy(name):
        folder = tmp_path / name
        folder.mkdir()
        for file in material_dir.iterdir():
            (folder / file.name).write_bytes(file.read_bytes())
        return folder

    folder = copy("not_an_image")
    (folder / "diffuse.exr").write_text("hello")
    cases["not_an_image"] = (folder, "diffuse")
    folder = copy("missing_map")
    (folder / "roughness.exr").unlink()
    cases["missing_map"] = (folder, "roughness")
    folder = copy("wrong_size")
    write_image(folder / "specular.exr", np.full((12, 24, 3), 0.04, np.float32))
    cases["wrong_size"] = (folder, "size")
    folder = copy("nan")
    diffuse = np.full((24, 24, 3), 0.5, np.float32)
    diffuse[3, 4, 1] = np.nan
    (folder / "diffuse.exr").unlink()
    import OpenEXR
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": diffuse}).write(str(folder / "diffuse.exr"))
    cases["nan"] = (folder, "NaN")
    folder = copy("out_of_range")
    write_image(folder / "roughness.exr", np.full((24, 24, 1), 1.7, np.float32))
    cases["out_of_range"] = (folder, "range")
    folder = tmp_path / "truncated_png"
    Material.load(material_dir).save(folder, format="png")
    data = (folder / "normal.png").read_bytes()
    (folder / "normal.png").write_bytes(data[: len(data) // 2])
    cases["truncated_png"] = (folder, "truncated")
    return cases


def test_bad_input_gives_one_clear_line_and_writes_nothing(material_dir, tmp_path, capsys):
    for name, (folder, expected) in corrupt_cases(tmp_path, material_dir).items():
        out = tmp_path / "renders" / f"{name}.exr"
        assert run("render", folder, "-o", out) == 2, name
        message = capsys.readouterr().err.strip()
        assert message.startswith("mideepbasis: error:") and "\n" not in message, (name, message)
        assert expected.lower() in message.lower(), (name, message)
        assert not out.exists() and not out.with_suffix(".png").exists(), name
    assert not (tmp_path / "renders").exists() or not any((tmp_path / "renders").iterdir())


def test_output_must_be_exr(material_dir, tmp_path, capsys):
    assert run("render", material_dir, "-o", tmp_path / "x.png") == 2
    assert ".exr" in capsys.readouterr().err


def test_the_console_command_exits_with_mains_status_and_its_message(tmp_path):
    # run() ends the process without the interpreter's teardown: the status and the flushed
    # error line must still come out.
    result = subprocess.run([sys.executable, "-m", "mideepbasis.cli", "render", str(tmp_path / "missing"), "-o",
                             str(tmp_path / "x.exr")], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    assert result.stderr.startswith("mideepbasis: error:") and result.stderr.count("\n") == 1, result.stderr
    assert not (tmp_path / "x.exr").exists()


def test_the_console_evaluation_runs_with_its_seeded_generators(evaluation_dataset, tmp_path):
    # Evaluation makes torch.Generators, which a torch started without its tracing modules cannot
    # (startup.DEFERRING_COMMANDS): the console's evaluate must still run, in its own process.
    folder, model = evaluation_dataset
    result = subprocess.run([sys.executable, "-m", "mideepbasis.cli", "evaluate", "--data", str(folder), "--format",
                             "folder", "--model", str(model), "-o", str(tmp_path / "out")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert (tmp_path / "out" / "summary.json").is_file()


def test_console_command_runs_the_demo(tmp_path):
    # The README's first command: capture the bundled photo with the shipped model, compare with its truth.
    result = subprocess.run([sys.executable, "-m", "mideepbasis.cli", "demo", "-o", str(tmp_path / "demo")],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    for name in ["normal.png", "diffuse.png", "roughness.png", "specular.png", "material.json", "light.json",
                 "rerender.png", "environment.png", "preview_sphere.png", "preview_cloth.png", "scene.xml",
                 "material.gltf", "material.mtlx", "material.usda", "report.html", "report.png"]:
        assert (tmp_path / "demo" / name).is_file(), name
    assert "map RMSE against the ground truth: normal" in result.stdout
    material = Material.load(tmp_path / "demo")
    assert tuple(material.normal.shape) == (3, 256, 256)
    # Bounds on what it prints, with room above a good capture of the bundled photo (light off by
    # 0.6 deg; normal 0.013, diffuse 0.035, roughness 0.067, specular 0.004) and tight enough to fail
    # a capture whose diffuse map keeps the flash's smudge (4.9 deg; 0.013, 0.047, 0.149, 0.018).
    import re

    light_error = float(re.search(r"true offset off by ([0-9.]+) deg", result.stdout).group(1))
    errors = dict(re.findall(r"(normal|diffuse|roughness|specular) ([0-9.]+)", result.stdout.split("ground truth:")[1]))
    assert light_error < 3.0
    bounds = {"normal": 0.03, "diffuse": 0.042, "roughness": 0.11, "specular": 0.01}
    assert all(float(errors[name]) < bound for name, bound in bounds.items()), errors


def test_capture_with_its_true_material_renders_both_and_their_difference(tmp_path, capsys):
    from mideepbasis.render.api import example_capture_dir

    photo, truth = example_capture_dir() / "photo.jpg", example_capture_dir() / "truth"
    out = tmp_path / "captured"
    assert run("capture", str(photo), "-o", str(out), "--truth", str(truth), "--refine-steps", "0") == 0
    captured, true = read_image(out / "environment.png"), read_image(out / "environment_truth.png")
    difference = read_image(out / "environment_difference.png")
    # Both are 8-bit sRGB files of the same scene; the difference file is 4 |a - b| of them.
    assert np.allclose(difference, np.clip(4 * np.abs(true - captured), 0, 1), atol=4 * 1.5 / 255)
    assert 0.005 < np.abs(true - captured).mean() < 0.2  # a capture is close to, not equal to, its truth
    # Several photos and one truth make no sense: one line, nothing written.
    assert run("capture", str(photo), str(photo), "-o", str(tmp_path / "two"), "--truth", str(truth)) == 2
    assert "give one photo" in capsys.readouterr().err and not (tmp_path / "two").exists()


def test_demo_never_replaces_a_folder_unasked(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "precious.txt").write_text("mine")
    assert run("demo", "-o", str(out)) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert (out / "precious.txt").read_text() == "mine"


@pytest.mark.parametrize("argv", [
    ["capture", "photo.jpg", "-o", "out", "--light", "0.1,-0.2", "--refine-steps", "10"],
    ["train", "--out", "runs/x", "--steps", "7", "--network-num-bases", "4"],
    ["evaluate", "--data", "somewhere", "-o", "out"],
    ["data", "preview", "--n", "4", "-o", "sheet.png"],
])
def test_a_parser_built_for_its_command_parses_as_the_whole_one(argv):
    assert vars(cli.build_parser(argv[0]).parse_args(argv)) == vars(cli.build_parser().parse_args(argv))
    whole = cli.build_parser().format_help()
    assert cli.build_parser(argv[0]).format_help() == whole  # every command still listed, with its line
    # Without the fields' help (no -h on the line): the same options, parsed the same.
    assert vars(cli.build_parser(argv[0], describe=False).parse_args(argv)) == vars(cli.build_parser().parse_args(argv))


def test_the_options_help_is_their_fields_docstrings_when_help_is_asked_for(capsys):
    with pytest.raises(SystemExit):
        cli.main(["capture", "--help-all"])
    # SearchConfig.relaxation's docstring, folded by argparse.
    assert "How far a pass moves the light toward the best" in " ".join(capsys.readouterr().out.split())


def test_bad_environment_material_and_preview_settings_are_one_line(material_dir, tmp_path, capsys):
    text = tmp_path / "passwd"
    text.write_text("root:x:0:0:root:/root:/bin/bash\n")
    deep = tmp_path / "deep"
    Material.load(material_dir).save(deep)
    (deep / "material.json").write_text("[" * 100_000 + "]" * 100_000)
    cases = [(["render", material_dir, "-o", tmp_path / "e.exr", "--light", "env", "--env", text], "not an image"),
             (["render", deep, "-o", tmp_path / "d.exr"], "nests too deeply"),
             (["data", "preview", "--n", "1", "--size", "1", "-o", tmp_path / "s.png"], "at least 8 pixels")]
    for arguments, message in cases:
        assert run(*arguments) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mideepbasis: error:") and "\n" not in err and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["deep", "material", "passwd"]


def test_a_grey_normal_map_is_refused_not_read_as_a_tilt(material_dir, tmp_path, capsys):
    grey = tmp_path / "grey"
    Material.load(material_dir).save(grey)
    write_image(grey / "normal.png", np.full((24, 24, 3), 128 / 255, np.float32))
    (grey / "normal.exr").unlink(missing_ok=True)
    (grey / "material.json").unlink()  # PNG maps with the default encodings
    for name in ("diffuse", "roughness", "specular"):
        source = grey / f"{name}.exr"
        if source.exists():
            write_image(grey / f"{name}.png", read_image(source).clip(0, 1), encode_srgb=name == "diffuse")
            source.unlink()
    assert run("render", grey, "-o", tmp_path / "r.exr") == 2
    err = capsys.readouterr().err.strip()
    assert "not unit vectors" in err and "\n" not in err and not (tmp_path / "r.exr").exists()


class _RunsCode:
    def __reduce__(self):
        return (print, ("a pickle that runs code",))


def test_an_import_error_is_one_clean_sentence(tmp_path, capsys):
    # torch's refusal of a pickle that names a function holds terminal escapes and several paragraphs.
    weights = tmp_path / "g.pth"
    torch.save({"weight": _RunsCode()}, weights)
    assert run("import-weights", weights, weights, "--fov", "45", "-o", tmp_path / "m.safetensors") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mideepbasis: error:") and all(c.isprintable() for c in err)
    assert "Unsupported global" in err and err.endswith(".)") and len(err) < 300, err
    assert not (tmp_path / "m.safetensors").exists()


@pytest.mark.parametrize("command,most", [("capture", 80), ("train", 150), ("evaluate", 80)])
def test_help_fits_a_screen_and_help_all_explains_every_option(command, most, capsys):
    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    brief = capsys.readouterr().out
    assert len(brief.splitlines()) <= most
    with pytest.raises(SystemExit):
        cli.main([command, "--help-all"])
    full = capsys.readouterr().out
    assert len(full.splitlines()) > len(brief.splitlines())
    listed, advanced = False, []
    for line in brief.splitlines():
        if line.startswith("advanced"):
            listed = True
        elif listed:
            advanced += [word for word in line.split() if word.startswith("--")]
    assert advanced and all(f"  {option} " in full or f"  {option}," in full or f"  {option}\n" in full
                            for option in advanced)


def test_an_advanced_option_parses_though_the_brief_help_only_names_it():
    args = cli.build_parser("capture", describe=False).parse_args(["capture", "p.jpg", "-o", "o", "--search-grid",
                                                                    "9"])
    from mideepbasis.capturing import CaptureConfig
    from mideepbasis.configs import config_from_arguments

    assert config_from_arguments(CaptureConfig, args).search.grid == 9


def _png_header_only(path, width: int, height: int) -> None:
    """A PNG whose header says width x height (8-bit RGB), its pixel data cut short: what a
    reader sees of a huge photo before it decodes a pixel."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 1024)) + chunk(b"IEND", b""))


def test_a_16k_photo_at_native_resolution_is_refused_in_one_line_naming_the_limit(tmp_path, capsys):
    huge = tmp_path / "huge.png"
    _png_header_only(huge, 16384, 16384)
    assert run("capture", huge, "-o", tmp_path / "out", "--resolution", "native") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "16384x16384" in err and f"limit of {constants.MAX_IMAGE_PIXELS} pixels" in err, err
    assert not (tmp_path / "out").exists()


def test_a_four_by_three_photo_at_native_resolution_gets_maps_of_its_short_side(tmp_path, capsys):
    from PIL import Image

    from mideepbasis.render.api import example_capture_dir

    # A phone's 4:3 frame whose short side, the working size, is no multiple of the network's 128 px.
    square = Image.open(example_capture_dir() / "photo.jpg").convert("RGB").resize((400, 400), Image.BICUBIC)
    photo = tmp_path / "phone.jpg"
    square.crop((0, 50, 400, 350)).save(photo, quality=95)
    assert run("capture", photo, "-o", tmp_path / "out", "--resolution", "native", "--refine-steps", "20") == 0
    maps = Material.load(tmp_path / "out")
    assert (maps.height, maps.width) == (300, 300)
    provenance = maps.provenance["capture"]
    assert provenance["detail_added"] and provenance["network_size"] == [128, 128]
