"""Finding an LLVM that drjit 1.5 can use, and the one-line error where there is none."""

from __future__ import annotations

import pytest

from mideepbasis.render import LLVMNotFoundError, ensure_llvm, find_libllvm, llvm_major_version


def fake_libraries(folder, *names):
    for name in names:
        (folder / name).write_bytes(b"")
    return folder


def test_version_is_read_from_debian_and_generic_names(tmp_path):
    assert llvm_major_version("/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1") == 19
    assert llvm_major_version("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert llvm_major_version("/opt/homebrew/opt/llvm/lib/libLLVM-17.dylib") == 17
    (tmp_path / "libLLVM-18.so.1").write_bytes(b"")
    (tmp_path / "libLLVM.so").symlink_to(tmp_path / "libLLVM-18.so.1")
    assert llvm_major_version(tmp_path / "libLLVM.so") == 18


def test_newest_compatible_llvm_is_chosen(tmp_path, monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")
    folder = fake_libraries(tmp_path, "libLLVM-15.so.1", "libLLVM-19.so.1", "libLLVM-17.so", "libfoo.so")
    assert [version for version, _ in find_libllvm([folder])] == [19, 17, 15]
    assert ensure_llvm([folder]) == folder / "libLLVM-19.so.1"
    import os
    assert os.environ["DRJIT_LIBLLVM_PATH"] == str(folder / "libLLVM-19.so.1")


def test_only_incompatible_llvm_stops_with_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")
    folder = fake_libraries(tmp_path, "libLLVM-15.so.1", "libLLVM-16.so.1")
    with pytest.raises(LLVMNotFoundError) as error:
        ensure_llvm([folder])
    message = str(error.value)
    assert "\n" not in message and "apt-get install libllvm19" in message and "LLVM 16" in message


def test_no_llvm_at_all_names_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")
    with pytest.raises(LLVMNotFoundError, match="no libLLVM at all.*apt-get install libllvm19"):
        ensure_llvm([tmp_path])


def test_explicit_incompatible_path_is_refused(tmp_path, monkeypatch):
    library = fake_libraries(tmp_path, "libLLVM-15.so.1") / "libLLVM-15.so.1"
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(library))
    with pytest.raises(LLVMNotFoundError, match="LLVM 15.*apt-get install libllvm19"):
        ensure_llvm([tmp_path])
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))
    with pytest.raises(LLVMNotFoundError, match="does not exist"):
        ensure_llvm([tmp_path])


@pytest.mark.parametrize("skip", [False, True])
def test_the_commands_variant_switch_leaves_out_only_mitsubas_python_integrators(skip):
    import os
    import subprocess
    import sys

    from mideepbasis.render import SKIP_PYTHON_INTEGRATORS

    program = """
import mitsuba as mi
import torch
import mideepbasis.render
from mideepbasis.render import render_flash
maps = torch.cat([torch.tensor([0.0, 0.0, 1.0]), torch.full((7,), 0.5)]).view(1, 10, 1, 1).expand(1, 10, 8, 8)
image = render_flash(maps.contiguous(), torch.tensor([[[0.0, 0.0, 2.0]]]))
assert image.shape == (1, 1, 3, 8, 8) and float(image.min()) > 0, image.shape
try:
    mi.load_dict({"type": "prb"})
    print(mi.variant(), "prb")
except Exception:
    print(mi.variant(), "no prb")
"""
    environment = {key: value for key, value in os.environ.items() if key != SKIP_PYTHON_INTEGRATORS}
    if skip:
        environment[SKIP_PYTHON_INTEGRATORS] = "1"
    done = subprocess.run([sys.executable, "-c", program], env=environment, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["llvm_ad_rgb", "no", "prb"] if skip else done.stdout.split() == ["llvm_ad_rgb", "prb"]
