"""Starting quickly: imports without Python's cyclic garbage collector.

Importing torch, numpy, Pillow, drjit and Mitsuba makes about 200,000 objects that live as long
as the process. While they are made, the collector runs hundreds of times (twice over all of
them) and finds nothing to free: 0.14 s of the package's import and 0.1 s of Mitsuba's on this
project's two-core machine. ``collection_paused`` leaves it off while they are made and puts
them straight into its oldest generation, which it scans least often; the console command,
whose process is its own, leaves them out of every collection (``freeze_imports``).

The console's capture and render commands also start torch without what only tracing and
compiling use (``tracing_modules_deferred``): a third of torch's import.

Nothing here imports more than the standard library, so that it can come first.
"""

from __future__ import annotations

import contextlib
import gc
import importlib.abc
import importlib.machinery
import os
import sys
import types
from collections.abc import Iterator

#: Whether what the imports under ``collection_paused`` made is left out of every later
#: collection (``gc.freeze``) rather than put into the oldest generation. A setting of the whole
#: process: the console command sets it, a library user's program keeps its own collector.
freeze_imports = False


@contextlib.contextmanager
def collection_paused() -> Iterator[None]:
    """No cyclic garbage collection inside (reference counting still frees what it can). What was
    made inside goes to the collector's oldest generation, or out of it with ``freeze_imports``:
    the first young-generation collection after would otherwise scan all of it (0.08 s after
    torch's import). The collector is on afterwards if it was on before."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if gc.get_freeze_count() == 0 or freeze_imports:  # never thaw what a program froze itself
            gc.freeze()
            if not freeze_imports:
                gc.unfreeze()  # into the oldest generation, unscanned
        if enabled:
            gc.enable()


def freeze_startup_objects() -> None:
    """Leave every object alive now out of later collections (``gc.freeze``), and so what later
    imports make under ``collection_paused``: for a process of our own (the console command)."""
    global freeze_imports
    freeze_imports = True
    gc.freeze()


#: What torch imports at its start-up for tracing and compiling models: ``torch.export``, and the
#: Python meta kernels (``torch._meta_registrations``) with the decompositions and primitives they
#: import. They are 0.2 - 0.3 s of torch's 0.7 - 1.0 s import on this project's machine (``python
#: -X importtime``); the two together, since ``torch.export`` imports the decompositions too.
TRACING_MODULES = ("torch.export", "torch._meta_registrations")

#: The console sub-commands whose processes start torch without ``TRACING_MODULES``: those that
#: capture and render, where the start-up is a good part of the wait. Besides tracing and meta
#: tensors, constructing a ``torch.Generator`` needs them (the primitives give it its metaclass),
#: which these never do and evaluation and training do.
DEFERRING_COMMANDS = ("capture", "demo", "render")

#: Environment variable: ``1`` defers the tracing modules in any process that imports the package
#: first, ``0`` in none; unset, in ``DEFERRING_COMMANDS`` alone (``deferring_command``).
DEFER_TRACING_ENV = "MIDEEPBASIS_DEFER_TORCH_TRACING"


def console_arguments() -> list[str] | None:
    """The arguments of the ``mideepbasis`` command this process runs (its script, or ``python -m
    mideepbasis.cli``), from its command line as it was given; None in any other process."""
    arguments = getattr(sys, "orig_argv", sys.argv)
    if "-m" in arguments[1:]:  # while ``-m`` looks for its module, sys.argv[0] is "-m"
        after = arguments[arguments.index("-m", 1) + 1:]
        return after[1:] if after and after[0] == "mideepbasis.cli" else None
    return sys.argv[1:] if os.path.basename(sys.argv[0]) == "mideepbasis" else None


def deferring_command() -> bool:
    """Whether this process is one of the ``DEFERRING_COMMANDS`` (what ``DEFER_TRACING_ENV`` says,
    when it is set)."""
    setting = os.environ.get(DEFER_TRACING_ENV)
    if setting in ("0", "1"):
        return setting == "1"
    arguments = console_arguments()
    command = next((argument for argument in arguments or () if not argument.startswith("-")), None)
    return command in DEFERRING_COMMANDS


def _import_tracing_modules() -> None:
    """``TRACING_MODULES``, imported in torch's own order: what completes a deferred start-up."""
    for module in TRACING_MODULES:
        importlib.import_module(module)


class _EmptyModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports each of ``names`` as an empty module."""

    def __init__(self, names: tuple[str, ...]):
        self.names = names

    def find_spec(self, name, path=None, target=None):
        return importlib.machinery.ModuleSpec(name, self) if name in self.names else None

    def create_module(self, spec):
        return types.ModuleType(spec.name)

    def exec_module(self, module):
        pass


class _DeferredTorchStartUp(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finishes torch's start-up before the first import of a torch module it has not made: imports
    ``TRACING_MODULES`` in torch's own order, then lets that import go on.

    Before anything else: ``torch._meta_registrations`` and the decompositions, references and
    primitives that it imports work only when it comes first (imported first, ``torch._decomp``
    fails on a circular import). When the module asked for is one that this made, its import gets
    that module (a second run of its code would register its kernels twice)."""

    def __init__(self):
        self.made = {}

    def find_spec(self, name, path=None, target=None):
        if not name.startswith("torch."):
            return None
        sys.meta_path.remove(self)  # once: the imports below, and every later one, go without it
        _import_tracing_modules()
        if name not in sys.modules:
            return None
        # Out of sys.modules until this import puts it back: there, the import system would run
        # its code again (its spec then being the module's own).
        self.made[name] = sys.modules.pop(name)
        return importlib.machinery.ModuleSpec(name, self)

    def create_module(self, spec):
        return self.made.pop(spec.name)

    def exec_module(self, module):
        pass


@contextlib.contextmanager
def tracing_modules_deferred(enabled: bool = True) -> Iterator[None]:
    """torch imported inside starts without ``TRACING_MODULES``. They are imported, as torch
    would have, before the first import of any other torch module, and when first named
    (``torch.export``: one of torch's lazy modules). A capture imports neither. Eager work on CPU
    tensors runs no Python meta kernel; only meta-device tensors made before any further torch
    import would miss one, and a ``torch.Generator`` cannot be made before: which the commands
    that defer (``deferring_command``) never do, and why a library user's process keeps torch's
    whole start-up.

    No effect when torch is imported already, or not ``enabled``. A torch without lazy modules
    (``torch._lazy_modules``) gets the modules imported at the end, as if nothing was deferred."""
    if not enabled or "torch" in sys.modules:
        yield
        return
    finder = _EmptyModules(TRACING_MODULES)
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:  # the placeholders gone also after a failed import, so that another attempt is torch's own
        sys.meta_path.remove(finder)
        torch = sys.modules.get("torch")
        deferred = []
        for name in TRACING_MODULES:
            placeholder = sys.modules.get(name)
            if placeholder is None or placeholder.__spec__.loader is not finder:
                continue
            del sys.modules[name]
            attribute = name.rpartition(".")[2]
            if getattr(torch, attribute, None) is placeholder:
                delattr(torch, attribute)
            deferred.append(attribute)
    if not deferred:
        return
    lazy = getattr(torch, "_lazy_modules", None)
    if isinstance(lazy, set):
        lazy.update(deferred)
        sys.meta_path.insert(0, _DeferredTorchStartUp())
    else:
        _import_tracing_modules()
