"""setup.sh's choice of interpreter (``./setup.sh --which-python``): the quickest Python 3.11
found, not the first on the PATH."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

SETUP = Path(__file__).resolve().parents[1] / "setup.sh"

#: A Python 3.11 made slow: every call and return of whatever it runs goes through a profile hook
#: (``sitecustomize`` in the folder given), about twice the probe's time.
SLOW_WRAPPER = """#!/bin/sh
PYTHONPATH={site} exec {python} "$@"
"""


def write_script(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(0o755)
    return path


NEEDED = ("bash", "awk", "dirname", "realpath")


def which_python(folder: Path) -> subprocess.CompletedProcess:
    """``setup.sh --which-python`` with ``folder`` as the whole PATH (the tools it needs linked in)."""
    for tool in NEEDED[1:]:
        os.symlink(shutil.which(tool), folder / tool)
    return subprocess.run([shutil.which("bash"), str(SETUP), "--which-python"], capture_output=True, text=True,
                          env={"PATH": str(folder), "HOME": os.environ.get("HOME", "/")}, timeout=120)


@pytest.mark.skipif(any(shutil.which(tool) is None for tool in NEEDED), reason="needs " + ", ".join(NEEDED))
def test_the_quickest_interpreter_is_chosen_not_the_first_on_the_path(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text("import sys\nsys.setprofile(lambda *args: None)\n")
    slow = write_script(tmp_path / "python3.11", SLOW_WRAPPER.format(site=site, python=sys.executable))
    quick = write_script(tmp_path / "python3", f'#!/bin/sh\nexec {sys.executable} "$@"\n')
    result = which_python(tmp_path)
    assert result.returncode == 0, result.stderr
    chosen = result.stdout.strip()
    # Another quick 3.11 outside the PATH (/usr/bin/python3.11) may win too; the slow one never.
    assert chosen != str(slow)
    assert chosen == str(quick) or Path(chosen).is_absolute() and Path(chosen).parent != tmp_path


@pytest.mark.skipif(any(shutil.which(tool) is None for tool in NEEDED), reason="needs " + ", ".join(NEEDED))
def test_an_interpreter_that_is_not_3_11_is_never_chosen(tmp_path):
    not_python = write_script(tmp_path / "python3.11", "#!/bin/sh\necho 3.12 >&2\nexit 1\n")
    result = which_python(tmp_path)
    assert str(not_python) not in result.stdout
    if result.returncode:  # no 3.11 anywhere else: the one-line error
        assert "Python 3.11 with its venv module is required" in result.stderr
