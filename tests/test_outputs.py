"""Output folders are written whole or not at all, and never lose what the tool did not write
(``mideepbasis.outputs``): refused targets, --overwrite with a manifest, kills at any instant,
two writers, batch workers that die with their parent, one-line errors."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mideepbasis import cli
from mideepbasis.errors import InputError
from mideepbasis.model.checkpoint import save_checkpoint
from mideepbasis.model.network import DeepBasisNet, preset

#: The manifest every folder the tool writes holds (``outputs.MANIFEST``; spelled out, so that the
#: command-line tests here run against any version of the package).
MANIFEST = ".mideepbasis-manifest.json"

#: A capture that is quick with the tiny model: a small photo, no search, no refinement, no shapes.
QUICK = ("--resolution", "64", "--refine-steps", "0", "--light", "0,0", "--symmetries", "1", "--no-shape-previews")


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("model") / "tiny.safetensors", DeepBasisNet(preset("tiny")).eval())


def photo(folder: Path, name: str = "photo.png", seed: int = 0) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    pixels = np.random.default_rng(seed).uniform(40, 200, (64, 64, 3)).astype(np.uint8)
    Image.fromarray(pixels).save(folder / name)
    return folder / name


def run_cli(*args) -> int:
    return cli.main([str(a) for a in args])


def command(*args) -> list[str]:
    return [sys.executable, "-m", "mideepbasis.cli", *(str(a) for a in args)]


def snapshot(folder: Path) -> dict[str, str]:
    """Every file below ``folder`` (relative path) with the hash of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def whole(folder: Path) -> bool:
    """The folder holds exactly what its manifest lists, every one of them."""
    listed = json.loads((folder / MANIFEST).read_text())["entries"]
    present = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name != MANIFEST)
    return present == sorted(listed)


def leftovers(parent: Path, name: str) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith(f".{name}."))


# --- targets a command must refuse --------------------------------------------------------------


@pytest.mark.parametrize("target", [".", ".."])
def test_the_working_folder_and_its_parent_are_refused_and_kept(tmp_path, tiny_model, capsys, monkeypatch, target):
    work = tmp_path / "a" / "b"
    shot = photo(work)
    (work / "notes.txt").write_text("k")
    (tmp_path / "a" / "thesis.tex").write_text("t")
    before = snapshot(tmp_path)
    monkeypatch.chdir(work)
    assert run_cli("capture", "photo.png", "-o", target, "--overwrite", "--model", tiny_model, *QUICK) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mideepbasis: error:") and "\n" not in err and "working folder" in err
    assert snapshot(tmp_path) == before and shot.is_file()


def test_a_folder_holding_the_input_photo_is_refused(tmp_path, tiny_model, capsys):
    shot = photo(tmp_path / "shots")
    for target in (tmp_path / "shots", tmp_path):
        assert run_cli("capture", shot, "-o", target, "--overwrite", "--model", tiny_model, *QUICK) == 2
        assert "holds the input" in capsys.readouterr().err
    assert shot.is_file()
    # A batch into the folder of its photos, too.
    photo(tmp_path / "shots", "second.png", seed=1)
    assert run_cli("capture", tmp_path / "shots", "-o", tmp_path / "shots", "--overwrite", "--model", tiny_model,
                   *QUICK) == 2
    assert "holds the input" in capsys.readouterr().err and len(list((tmp_path / "shots").iterdir())) == 2


def test_home_and_root_are_refused(tmp_path, monkeypatch):
    from mideepbasis.outputs import OutputFolder

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    (tmp_path / "home").mkdir()
    for target in (tmp_path / "home", Path("/")):
        with pytest.raises(InputError, match="root or the home folder|working folder"):
            OutputFolder(target, overwrite=True)


def test_a_symbolic_link_and_a_file_are_refused_in_one_line(tmp_path, tiny_model, capsys):
    shot = photo(tmp_path)
    (tmp_path / "real").mkdir()
    (tmp_path / "real" / "keep.txt").write_text("mine")
    (tmp_path / "link").symlink_to(tmp_path / "real")
    (tmp_path / "file").write_text("a file")
    for target, message in ((tmp_path / "link", "symbolic link"), (tmp_path / "file", "not a folder")):
        assert run_cli("capture", shot, "-o", target, "--overwrite", "--model", tiny_model, *QUICK) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and message in err
    assert (tmp_path / "real" / "keep.txt").read_text() == "mine" and (tmp_path / "file").read_text() == "a file"


def immutable(folder: Path) -> bool:
    """Make ``folder`` immutable (chattr +i), or False where this machine cannot."""
    result = subprocess.run(["chattr", "+i", str(folder)], capture_output=True)
    return result.returncode == 0


def test_an_immutable_output_folder_is_refused_before_the_work(tmp_path, tiny_model, capsys, evaluation_dataset):
    shot = photo(tmp_path)
    locked = tmp_path / "locked"
    locked.mkdir()
    if not immutable(locked):
        pytest.skip("chattr +i is not available here")
    try:
        for target in (locked, locked / "inside"):
            started = time.perf_counter()
            assert run_cli("capture", shot, "-o", target, "--overwrite", "--model", tiny_model, *QUICK) == 2
            err = capsys.readouterr().err.strip()
            assert "\n" not in err and "cannot" in err and str(locked) in err
            assert time.perf_counter() - started < 5
        folder, model = evaluation_dataset
        assert run_cli("evaluate", "--data", folder, "--format", "folder", "--model", model, "-o", locked / "e") == 2
        assert "cannot" in capsys.readouterr().err
    finally:
        subprocess.run(["chattr", "-i", str(locked)])


def test_evaluate_refuses_a_file_and_writes_nothing_for_a_refused_model(tmp_path, evaluation_dataset, capsys):
    folder, model = evaluation_dataset
    (tmp_path / "result").write_text("a file")
    assert run_cli("evaluate", "--data", folder, "--format", "folder", "--model", model, "-o", tmp_path / "result") == 2
    assert "not a folder" in capsys.readouterr().err and (tmp_path / "result").read_text() == "a file"
    (tmp_path / "bad.safetensors").write_bytes(b"\0" * 64)
    out = tmp_path / "evaluation"
    assert run_cli("evaluate", "--data", folder, "--format", "folder", "--model", tmp_path / "bad.safetensors",
                   "-o", out) == 2
    assert "not a safetensors checkpoint" in capsys.readouterr().err
    assert not out.exists() and not leftovers(tmp_path, "evaluation")


# --- --overwrite replaces only what the tool wrote -----------------------------------------------


def test_overwrite_refuses_a_folder_with_files_the_tool_did_not_write(tmp_path, tiny_model, capsys):
    shot = photo(tmp_path / "in")
    out = tmp_path / "out"
    assert run_cli("capture", shot, "-o", out, "--model", tiny_model, *QUICK) == 0
    assert whole(out)
    (out / "my_notes.txt").write_text("notes")
    (out / "sub").mkdir()
    (out / "sub" / "thesis.tex").write_text("thesis")
    before = snapshot(out)
    assert run_cli("capture", shot, "-o", out, "--overwrite", "--model", tiny_model, *QUICK) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "my_notes.txt" in err and "sub/thesis.tex" in err
    assert snapshot(out) == before
    # A folder the tool did not write at all (no manifest) is not replaced either.
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "data.csv").write_text("1,2")
    assert run_cli("capture", shot, "-o", foreign, "--overwrite", "--model", tiny_model, *QUICK) == 2
    assert "not written by mideepbasis" in capsys.readouterr().err and (foreign / "data.csv").read_text() == "1,2"
    # What the tool wrote alone is replaced.
    (out / "my_notes.txt").unlink()
    (out / "sub" / "thesis.tex").unlink()
    (out / "sub").rmdir()
    assert run_cli("capture", shot, "-o", out, "--overwrite", "--model", tiny_model, *QUICK) == 0
    assert whole(out) and not leftovers(tmp_path, "out")


def test_remove_tree_deletes_only_what_this_module_stages(tmp_path):
    from mideepbasis.outputs import remove_tree

    user = tmp_path / "photos"
    user.mkdir()
    with pytest.raises(ValueError, match="refusing to delete"):
        remove_tree(user)
    staged = tmp_path / ".out.mideepbasis-new-123"
    (staged / "sub").mkdir(parents=True)
    remove_tree(staged)
    assert not staged.exists() and user.is_dir()


# --- kills and concurrent writers --------------------------------------------------------------


def test_a_kill_at_any_instant_leaves_the_old_result_or_the_new_one(tmp_path, tiny_model):
    """20 instants over an --overwrite capture, and the two critical steps of the swap by hook."""
    photos = [photo(tmp_path / "in", f"{name}.png", seed) for seed, name in enumerate("ab")]
    references = {}
    for shot in photos:  # what a whole capture of each photo writes
        reference = tmp_path / f"reference_{shot.stem}"
        subprocess.run(command("capture", shot, "-o", reference, "--model", tiny_model, *QUICK), check=True,
                       capture_output=True)
        references[shot.stem] = reference
    out = tmp_path / "out"
    subprocess.run(command("capture", photos[0], "-o", out, "--model", tiny_model, *QUICK), check=True,
                   capture_output=True)
    started = time.perf_counter()
    subprocess.run(command("capture", photos[1], "-o", out, "--overwrite", "--model", tiny_model, *QUICK),
                   check=True, capture_output=True)
    duration = time.perf_counter() - started
    # Up to twice the measured duration: on a loaded machine the later captures run slower than the timed one.
    instants = [("time", duration * (0.15 + 2.0 * i / 19)) for i in range(20)] + [("hook", "staged"),
                                                                                    ("hook", "exchanged")]
    outcomes = []
    for index, (kind, when) in enumerate(instants):
        shot = photos[index % 2]
        before = snapshot(out)
        environment = dict(os.environ, MIDEEPBASIS_KILL_AT=when) if kind == "hook" else None
        process = subprocess.Popen(command("capture", shot, "-o", out, "--overwrite", "--model", tiny_model, *QUICK),
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=environment)
        if kind == "time":
            try:
                process.wait(timeout=when)
            except subprocess.TimeoutExpired:
                process.kill()
        process.wait()
        after = snapshot(out)
        assert whole(out), (kind, when)
        new = {name: digest for name, digest in snapshot(references[shot.stem]).items() if name != MANIFEST}
        is_new = all(after.get(name) == digest for name, digest in new.items()
                     if name in ("photo.png", "normal.png", "diffuse.png", "material.json"))
        assert after == before or is_new, (kind, when)
        outcomes.append("old" if after == before else "new")
    assert "old" in outcomes and "new" in outcomes  # the sweep straddles the swap
    # The next whole run removes every leftover of the killed ones.
    subprocess.run(command("capture", photos[0], "-o", out, "--overwrite", "--model", tiny_model, *QUICK),
                   check=True, capture_output=True)
    assert whole(out) and not leftovers(tmp_path, "out")


def test_an_old_result_left_beside_by_a_two_rename_swap_is_put_back(tmp_path):
    """Where the file system cannot exchange two names, a kill between the two renames leaves the
    old result under its old name: the next writer puts it back before anything else."""
    from mideepbasis.outputs import OutputFolder

    out = tmp_path / "out"
    with OutputFolder(out) as folder:
        (folder.staging / "a.txt").write_text("old")
    os.rename(out, tmp_path / ".out.mideepbasis-old-999999")
    with OutputFolder(out, overwrite=True) as folder:
        assert (out / "a.txt").read_text() == "old"  # back before the new result is written
        (folder.staging / "a.txt").write_text("new")
    assert (out / "a.txt").read_text() == "new" and not leftovers(tmp_path, "out")


def test_two_writers_into_one_target_one_wins_the_other_gets_one_line(tmp_path, tiny_model):
    from mideepbasis.outputs import OutputFolder

    with OutputFolder(tmp_path / "out") as first:
        (first.staging / "a.txt").write_text("first")
        with pytest.raises(InputError, match="another mideepbasis command is writing"):
            OutputFolder(tmp_path / "out", overwrite=True)
    assert (tmp_path / "out" / "a.txt").read_text() == "first"
    # Two captures of different photos started together into one new folder.
    shots = [photo(tmp_path / "in", f"{name}.png", seed) for seed, name in enumerate("ab")]
    out = tmp_path / "together"
    processes = [subprocess.Popen(command("capture", shot, "-o", out, "--model", tiny_model, *QUICK),
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for shot in shots]
    results = [(process.wait(), process.stderr.read()) for process in processes]
    assert sorted(code for code, _ in results) == [0, 2], results
    loser = next(err for code, err in results if code == 2).strip()
    assert "\n" not in loser and loser.startswith("mideepbasis: error:")
    assert whole(out) and not leftovers(tmp_path, "together")


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads processes from /proc")
@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_batch_workers_die_with_their_parent(tmp_path, tiny_model, how):
    for seed in range(12):
        photo(tmp_path / "in", f"p{seed}.png", seed)
    process = subprocess.Popen(command("capture", tmp_path / "in", "-o", tmp_path / "out", "--workers", "1",
                                       "--model", tiny_model, *QUICK),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not children(process.pid):
        assert time.monotonic() < deadline and process.poll() is None
        time.sleep(0.05)
    time.sleep(1.0)  # the worker has started
    assert process.poll() is None
    spawned = children(process.pid)
    assert spawned
    process.send_signal(how)
    process.wait(timeout=30)
    time.sleep(1.0)
    assert not [pid for pid in spawned if running(pid)]


def test_a_probe_left_by_a_killed_process_goes_at_the_next_probe(tmp_path):
    from mideepbasis.outputs import probe_writable

    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # its pid is free (reaped)
    stale = out / f".out.mideepbasis-probe-{dead.pid}"
    stale.write_bytes(b"")
    alive = out / f".out.mideepbasis-probe-{os.getppid()}"  # a live process's: kept
    alive.write_bytes(b"")
    not_a_probe = out / f".out.mideepbasis-probe-{dead.pid}x"
    not_a_probe.write_bytes(b"")
    probe_writable(out)
    assert not stale.exists() and alive.exists() and not_a_probe.exists()
    assert sorted(p.name for p in out.iterdir()) == sorted([alive.name, not_a_probe.name])
