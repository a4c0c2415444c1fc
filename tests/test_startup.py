"""The start-up's garbage-collector settings (``mideepbasis.startup``): imports without collections,
the collector as it was afterwards, a program's own frozen objects never thawed."""

from __future__ import annotations

import gc
import json
import subprocess
import sys

import pytest

from mideepbasis import startup


@pytest.fixture
def collector():
    """The collector's state restored after each test (these tests change it on purpose)."""
    enabled, frozen_setting = gc.isenabled(), startup.freeze_imports
    yield
    startup.freeze_imports = frozen_setting
    gc.unfreeze()
    gc.enable() if enabled else gc.disable()


class Node:
    def __init__(self):
        self.me = self  # a reference cycle: only the collector frees it


def test_nothing_is_collected_inside_and_the_collector_is_on_again_after(collector):
    gc.enable()
    collections = []
    callback = lambda phase, info: collections.append(info["generation"]) if phase == "stop" else None  # noqa: E731
    gc.callbacks.append(callback)
    try:
        with startup.collection_paused():
            assert not gc.isenabled()
            made = [Node() for _ in range(20_000)]  # far past the youngest generation's threshold (700)
            during = len(collections)
        assert during == 0
        assert gc.isenabled()
        # What was made went to the oldest generation: the young generations start empty.
        assert gc.get_count()[0] < 700 and gc.get_count()[1] == 0
        assert gc.get_freeze_count() == 0
    finally:
        gc.callbacks.remove(callback)
    del made


def test_a_paused_collector_stays_paused(collector):
    gc.disable()
    with startup.collection_paused():
        pass
    assert not gc.isenabled()


def _in_a_collected_generation(obj) -> bool:
    """Whether the collector would scan ``obj`` (frozen objects are in none of its generations)."""
    return any(candidate is obj for candidate in gc.get_objects())


def test_what_a_program_froze_itself_stays_frozen(collector):
    # Judged by the objects, not by ``gc.get_freeze_count()``: a frozen object freed meanwhile
    # (in a long test run) lowers the count without anything being thawed.
    frozen_before = Node()
    gc.freeze()
    assert not _in_a_collected_generation(frozen_before)
    with startup.collection_paused():
        made = Node()
    assert not _in_a_collected_generation(frozen_before)  # not thawed
    assert _in_a_collected_generation(made)  # and the new object not frozen with it


def test_with_freeze_imports_what_was_made_is_out_of_every_collection(collector):
    startup.freeze_imports = True
    with startup.collection_paused():
        made = [Node() for _ in range(1_000)]
    assert gc.get_freeze_count() >= 1_000
    gc.unfreeze()
    del made


def test_cycles_made_after_the_start_up_are_still_collected(collector):
    startup.freeze_startup_objects()
    assert startup.freeze_imports
    with startup.collection_paused():
        pass
    Node()  # garbage at once: only a collection frees it
    assert gc.collect() >= 1


def test_importing_the_package_leaves_a_programs_collector_as_it_was():
    """A library user's process: the collector on, nothing frozen, after the package and its
    rendering (drjit, Mitsuba) are imported."""
    script = ("import gc, json, mideepbasis, mideepbasis.render; "
              "print(json.dumps([gc.isenabled(), gc.get_freeze_count()]))")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert json.loads(result.stdout.strip().splitlines()[-1]) == [True, 0]


def _run(script: str, defer: str | None, *arguments: str) -> list:
    """``script``'s last printed line (JSON), run in a fresh process with ``DEFER_TRACING_ENV`` set to ``defer``."""
    import os

    environment = {k: v for k, v in os.environ.items() if k != startup.DEFER_TRACING_ENV}
    if defer is not None:
        environment[startup.DEFER_TRACING_ENV] = defer
    result = subprocess.run([sys.executable, "-c", script, *arguments], capture_output=True, text=True,
                            env=environment, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


#: A Python expression: whether each deferred module (and the decompositions) is loaded.
LOADED = "[m in sys.modules for m in ('torch.export', 'torch._meta_registrations', 'torch._decomp')]"


def test_a_library_users_torch_starts_whole_and_a_deferring_commands_without_tracing():
    script = f"import json, sys, mideepbasis; print(json.dumps({LOADED}))"
    assert _run(script, None) == [True, True, True]  # python -c: not the console command
    assert _run(script, "0") == [True, True, True]
    assert _run(script, "1") == [False, False, False]


@pytest.mark.parametrize("first", ["import torch._refs", "import torch._decomp.decompositions", "import torch._prims",
                                   "import torch._dynamo", "torch.export.graph_signature",
                                   "torch.optim.Adam([torch.zeros(2, requires_grad=True)]).step()"])
def test_a_deferred_torch_finishes_its_start_up_at_the_next_torch_import(first):
    # Whatever comes first (one of the modules that must follow the meta kernels, a torch module
    # that imports them, the deferred torch.export by name, an optimiser, which imports
    # torch._dynamo), torch then has all it would have had: the meta kernels (a meta-device
    # convolution needs Python's) and torch.export, which works.
    script = ("import json, sys, mideepbasis, torch\n"
              f"{first}\n"
              "shape = torch.nn.Conv2d(3, 4, 3, device='meta')(torch.ones(1, 3, 8, 8, device='meta')).shape\n"
              "program = torch.export.export(torch.nn.Linear(2, 3), (torch.ones(1, 2),))\n"
              f"print(json.dumps([list(shape), type(program).__name__, {LOADED}]))")
    assert _run(script, "1") == [[1, 4, 6, 6], "ExportedProgram", [True, True, True]]


@pytest.mark.parametrize("argv, expected", [
    (["/venv/bin/python", "/venv/bin/mideepbasis", "capture", "p.jpg"], True),
    (["/venv/bin/python", "/venv/bin/mideepbasis", "--help"], False),
    (["/venv/bin/python", "/venv/bin/mideepbasis", "evaluate", "--data", "d"], False),
    (["/venv/bin/python", "-m", "mideepbasis.cli", "demo"], True),
    (["/venv/bin/python", "-m", "mideepbasis.cli", "render", "m", "-o", "x.exr"], True),
    (["/venv/bin/python", "-m", "mideepbasis.cli", "train", "--steps", "2"], False),
    (["python", "-X", "importtime", "-m", "mideepbasis.cli", "capture", "p.jpg"], True),
    (["python", "-m", "pytest", "-q", "capture"], False),
    (["python", "-c", "import mideepbasis", "capture"], False),
    (["python", "my_script.py", "capture"], False),
])
def test_the_deferring_commands_are_told_from_their_command_line(monkeypatch, argv, expected):
    monkeypatch.delenv(startup.DEFER_TRACING_ENV, raising=False)
    monkeypatch.setattr(sys, "orig_argv", argv)
    # What sys.argv holds while the package is imported: "-m" first while -m looks for its module.
    script = argv.index("-m") + 1 if "-m" in argv else 1
    monkeypatch.setattr(sys, "argv", (["-m"] if "-m" in argv else argv[script:script + 1]) + argv[script + 1:])
    assert startup.deferring_command() is expected
    monkeypatch.setenv(startup.DEFER_TRACING_ENV, "0" if expected else "1")
    assert startup.deferring_command() is not expected


@pytest.mark.parametrize("command", [["evaluate", "--help"], ["capture", "--help"]])
def test_the_console_commands_torch_start_up(command):
    # The console's capture starts torch without its tracing modules; evaluation, which makes
    # torch.Generators (they need them), with its whole start-up (test_cli runs it).
    script = ("import json, sys\n"
              f"sys.argv = ['mideepbasis', *{command!r}]\n"
              "import mideepbasis\n"
              "print(json.dumps('torch._meta_registrations' in sys.modules))\n")
    assert _run(script, None) is (command[0] != "capture")


def _fake_torch(folder, lazy: bool, fails: bool = False) -> None:
    """A package named torch in ``folder`` that imports its two tracing modules at its start-up,
    as torch does; each module counts its runs in ``torch.runs``."""
    package = folder / "torch"
    package.mkdir()
    (package / "__init__.py").write_text(
        "runs = []\n"
        + ("_lazy_modules = set()\n" if lazy else "")
        + "from torch import export\n"
        + ("raise RuntimeError('broken start-up')\n" if fails else "")
        + "from torch import _meta_registrations\n")
    for name in ("export", "_meta_registrations"):
        (package / f"{name}.py").write_text(f"import torch\ntorch.runs.append({name!r})\nREAL = True\n")


def _with_stand_in(folder, body: str) -> list:
    """``body``'s last printed line (JSON), run in a process whose torch is the stand-in in
    ``folder``, with ``startup`` loaded from its file (the package itself would import the real torch)."""
    script = ("import importlib.util, json, sys\n"
              f"spec = importlib.util.spec_from_file_location('startup', {startup.__file__!r})\n"
              "startup = importlib.util.module_from_spec(spec); spec.loader.exec_module(startup)\n" + body)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=folder,
                            env={"PYTHONPATH": str(folder)}, timeout=60)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("lazy", [True, False])
def test_the_deferral_on_a_stand_in_torch(tmp_path, lazy):
    # Independent of the installed torch: a package that imports two modules at its start-up.
    # With lazy modules they run at the next import of a module of that package (not before);
    # without, at the end of the start-up. Either way once each, and the real ones.
    _fake_torch(tmp_path, lazy)
    (tmp_path / "torch" / "other.py").write_text("")
    after_start, runs, *real, lazy_modules = _with_stand_in(tmp_path, (
        "with startup.tracing_modules_deferred():\n"
        "    import torch\n"
        "after_start = list(torch.runs)\n"
        "import torch.other\n"
        "import torch.export, torch._meta_registrations\n"
        "print(json.dumps([after_start, torch.runs, torch.export.REAL, torch._meta_registrations.REAL,\n"
        "                  sorted(getattr(torch, '_lazy_modules', []))]))\n"))
    assert after_start == ([] if lazy else ["export", "_meta_registrations"])
    assert runs == ["export", "_meta_registrations"] and real == [True, True]
    assert lazy_modules == (["_meta_registrations", "export"] if lazy else [])


def test_a_failed_start_up_leaves_no_placeholder(tmp_path):
    # torch's own error, and a second attempt is torch's own import (no empty modules left).
    _fake_torch(tmp_path, lazy=True, fails=True)
    message, placeholder_left, finders = _with_stand_in(tmp_path, (
        "try:\n"
        "    with startup.tracing_modules_deferred():\n"
        "        import torch\n"
        "except RuntimeError as error:\n"
        "    message = str(error)\n"
        "print(json.dumps([message, 'torch.export' in sys.modules, len(sys.meta_path)]))\n"))
    assert message == "broken start-up" and not placeholder_left
    baseline = subprocess.run([sys.executable, "-c", "import sys; print(len(sys.meta_path))"], capture_output=True,
                              text=True, env={"PYTHONPATH": str(tmp_path)}).stdout.strip()
    assert finders == int(baseline)
