"""Starting quickly: imports without Python's cyclic garbage collector.

Importing torch, numpy, Pillow, drjit and Mitsuba makes about 200,000 objects that live as long
as the process. While they are made, the collector runs hundreds of times (twice over all of
them) and finds nothing to free: 0.14 s of the package's import and 0.1 s of Mitsuba's on this
project's two-core machine. ``collection_paused`` leaves it off while they are made and puts
them straight into its oldest generation, which it scans least often; the console command,
whose process is its own, leaves them out of every collection (``freeze_imports``).
Nothing here imports more than the standard library, so that it can come first.
"""

from __future__ import annotations

import contextlib
import gc
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
