"""The wheel installs: built from the repository, installed into a clean virtual environment
outside the checkout, it holds every package and runs capture, train and data preview."""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel of a copy of the sources (an in-place build would reuse what an earlier one left
    in build/, hiding a package the list leaves out)."""
    folder = tmp_path_factory.mktemp("wheel")
    source = folder / "source"
    # Not the virtual environments (.ci/run makes a 3 GB .venv-blender in the checkout) nor other outputs.
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".git", ".venv*", "runs", "build", "dist", "benchmarks",
                                                                "tests", "__pycache__", "*.egg-info", "demo"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(folder),
                    str(source)], check=True, capture_output=True, cwd=folder)
    return next(folder.glob("mideepbasis-*.whl"))


def source_packages() -> set[str]:
    """Every package of the source tree, as the wheel should hold it."""
    packages = {str(path.parent.relative_to(ROOT)).replace(os.sep, ".")
                for path in (ROOT / "mideepbasis").rglob("__init__.py")}
    return packages | {"mideepbasis.scenes"}


def test_the_wheel_holds_every_package_and_the_data_files(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    held = {name.rsplit("/", 1)[0].replace("/", ".") for name in names if name.endswith("/__init__.py")}
    assert source_packages() <= held, sorted(source_packages() - held)
    assert {"mideepbasis/scenes/flash.xml", "mideepbasis/scenes/envmaps/studio.exr",
            "mideepbasis/scenes/textures/flat_normal.exr", "mideepbasis/scenes/meshes/cloth.ply",
            "mideepbasis/assets/viewer/viewer.js", "mideepbasis/assets/example_capture/photo.jpg",
            "mideepbasis/models/deepbasis_compact.safetensors", "mideepbasis/models/MODEL.md"} <= names


def test_the_installed_wheel_captures_trains_and_previews(wheel, tmp_path):
    """A clean environment with the wheel alone; the pinned dependencies come from this one's
    site-packages (a path, so its editable install of the checkout is not read)."""
    environment = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(environment)], check=True)
    python = environment / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q", str(wheel)],
                   check=True, capture_output=True)
    installed = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                    check=True, capture_output=True, text=True).stdout.strip())
    dependencies = sysconfig.get_paths()["purelib"]
    (installed / "dependencies.pth").write_text(dependencies + "\n")
    work = tmp_path / "work"
    work.mkdir()
    command = environment / "bin" / "mideepbasis"
    run_environment = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}

    def run(*arguments: str) -> str:
        result = subprocess.run([str(command), *arguments], cwd=work, capture_output=True, text=True,
                                env=run_environment, timeout=600)
        assert result.returncode == 0, result.stderr[-3000:]
        return result.stdout

    where = subprocess.run([str(python), "-c", "import mideepbasis, mideepbasis.render.api as a; "
                            "print(mideepbasis.__file__); print(a.example_capture_dir() / 'photo.jpg')"],
                           cwd=work, capture_output=True, text=True, check=True, env=run_environment).stdout.split()
    assert Path(where[0]).is_relative_to(installed) and not Path(where[0]).is_relative_to(ROOT)
    assert site.getsitepackages()  # (the dependencies' folder exists in this environment)
    run("capture", where[1], "-o", "material", "--refine-steps", "0", "--no-shape-previews")
    assert (work / "material" / "material.json").is_file() and (work / "material" / "environment.png").is_file()
    run("train", "--out", "run", "--preset", "tiny", "--steps", "2", "--batch", "1", "--size", "32", "--workers", "0",
        "--validate-every", "0")
    assert (work / "run" / "model.safetensors").is_file()
    run("data", "preview", "--n", "2", "--size", "32", "-o", "sheet.png")
    assert (work / "sheet.png").is_file()
