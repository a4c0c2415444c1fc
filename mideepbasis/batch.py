"""Many photos at once: worker processes that each load the model once and capture and write
their share of the photos, so that one photo's writing (the path-traced previews, the report)
overlaps with another's search and refinement.

Each worker runs torch on one thread, one worker per core: on two cores two photos are in
flight at any time. A photo that fails with a ``MideepbasisError`` (unreadable, too small, ...)
costs only its own line; the others go on.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

#: The worker's state: set once per process by ``_start_worker``.
_WORKER: dict = {}


@dataclass(frozen=True)
class SaveOptions:
    """What ``export.save_capture`` writes for each photo of a batch."""

    exr: bool = False
    """Also write the maps as linear EXR."""

    preview_tiles: float = 2.0
    """Times the maps repeat across the sphere and cloth previews."""

    overwrite: bool = True
    """Replace a photo's existing output folder (a batch's folders are its own)."""

    shape_previews: bool = False
    """Also path trace the sphere and cloth previews (two more images per photo: off in a batch)."""


@dataclass(frozen=True)
class BatchItem:
    """The outcome of one photo of a batch."""

    photo: Path
    """The photo file."""

    target: Path
    """Its material folder."""

    error: str | None = None
    """Why it failed (None: it did not)."""

    offset_angle_deg: float = 0.0
    """The flash offset found [deg]."""

    seconds: float = 0.0
    """Capture and writing, in its worker [s]."""

    notes: list[str] = field(default_factory=list)
    """The capture's notes."""

    repeated: bool = False
    """The photo's folder was written by this batch already (a cluster's task run again after its
    worker died): nothing was written."""


#: Peak memory of one capture [GiB] by working resolution [pixels]: the whole command on the
#: bundled photo (``benchmarks/capture.py``: 0.76, 1.23, 2.37 and 2.65 GiB; above 2048 px the maps
#: are blended and detailed in bands), rounded up; linear in the side between these sizes.
CAPTURE_MEMORY_GIB = ((256, 0.8), (1024, 1.3), (2048, 2.5), (4096, 2.8))


def capture_memory_gib(resolution: int) -> float:
    """About the most memory [GiB] one capture at ``resolution`` pixels takes (``CAPTURE_MEMORY_GIB``)."""
    sizes = CAPTURE_MEMORY_GIB
    if resolution <= sizes[0][0]:
        return sizes[0][1]
    for (small, low), (large, high) in zip(sizes, sizes[1:]):
        if resolution <= large:
            return low + (high - low) * (resolution - small) / (large - small)
    return sizes[-1][1]


def available_memory_gib() -> float | None:
    """Memory free for new processes [GiB]: Linux's MemAvailable, else the free physical pages;
    None where neither is known."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2**20  # kB
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**30
    except (AttributeError, ValueError, OSError):
        return None


def largest_working_resolution(photos: list[Path], config) -> int:
    """The largest working resolution [pixels] among the photos under ``config`` (a ``CaptureConfig``):
    its resolution, or for ``native`` the side of each photo's centre square (or crop) up to the
    most, read from the headers; the most where a header cannot be read."""
    from .capturing.photo import MAX_NATIVE_RESOLUTION, working_resolution

    if config.resolution != "native":
        return int(config.resolution)
    if config.crop is not None:
        return working_resolution(min(config.crop[2:]), "native")
    from .errors import MideepbasisError
    from .imageio import image_size

    largest = 0
    for photo in photos:
        try:
            largest = max(largest, working_resolution(min(image_size(photo)), "native"))
        except (MideepbasisError, OSError):
            return MAX_NATIVE_RESOLUTION  # its worker says what is wrong with it
        if largest >= MAX_NATIVE_RESOLUTION:
            break
    return largest


def default_workers(photos: int, memory_gib: float | None = None, available_gib: float | None = None) -> int:
    """One worker per core, at most one per photo, and no more than ``available_gib`` [GiB] holds
    when each takes ``memory_gib`` (either None: no such bound); at least one."""
    workers = max(1, min(photos, os.cpu_count() or 1))
    if memory_gib and available_gib is not None:
        workers = max(1, min(workers, int(available_gib // memory_gib)))
    return workers


def memory_need(photos: list[Path], config) -> tuple[int, float, float | None]:
    """(the largest working resolution [pixels] of ``photos`` under ``config``, one capture's memory
    there [GiB], the memory free [GiB] or None where it is not known)."""
    resolution = largest_working_resolution(photos, config)
    return resolution, capture_memory_gib(resolution), available_memory_gib()


def memory_note(photo: Path, config) -> str | None:
    """A note where one capture of ``photo`` under ``config`` needs more memory than is free (it
    would swap), else None."""
    resolution, memory, available = memory_need([photo], config)
    if available is None or memory <= available:
        return None
    return (f"a capture at {resolution} px takes about {memory:.1f} GiB and {available:.1f} GiB is free: "
            "it may swap (a lower --resolution takes less)")


def batch_workers(photos: list[Path], config) -> tuple[int, str | None]:
    """The workers a local batch of ``photos`` starts under ``config`` (``default_workers`` bounded by
    this machine's free memory at the largest working resolution), and a note where memory, not
    the cores, set their number."""
    resolution, memory, available = memory_need(photos, config)
    workers, by_cores = default_workers(len(photos), memory, available), default_workers(len(photos))
    if workers >= by_cores:
        return workers, None
    return workers, (f"{workers} worker{'s' * (workers > 1)} rather than {by_cores}: a capture at {resolution} px "
                     f"takes about {memory:.1f} GiB and {available:.1f} GiB is free (set --workers to choose)")


def die_with_parent(parent: int) -> None:
    """Have the kernel kill this process when its parent ``parent`` dies, however it dies (Linux's
    PR_SET_PDEATHSIG; elsewhere nothing), and end now if it is already gone."""
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (AttributeError, OSError):
        return
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


#: prctl's request that a signal be sent to this process when its parent dies (linux/prctl.h).
_PR_SET_PDEATHSIG = 1


def prepare_worker(model, config, options: SaveOptions, workers: int) -> None:
    """Load the model once in this worker process and share the machine's cores with ``workers``
    workers in all (a local batch's processes, or a cluster's workers on one machine)."""
    import drjit as dr
    import torch

    from .capturing.pipeline import Capturer

    # A share of the cores each for torch (one, with a worker per core): the workers, not the
    # threads inside them, share the machine.
    # (drjit keeps its pool: Mitsuba's path tracer waits forever on a pool of one thread.)
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))
    _WORKER["capturer"] = Capturer(model, config)
    _WORKER["drjit_threads"] = dr.thread_count()
    # With fewer workers than cores (a batch of one photo), the capture keeps its share of them.
    _WORKER["capture_threads"] = max(1, _WORKER["drjit_threads"] // workers)
    _WORKER["options"] = options


def _start_worker(model, config, options: SaveOptions, workers: int, parent: int) -> None:
    import signal

    die_with_parent(parent)
    # Ctrl-C is the main process's to handle: it stops the workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    prepare_worker(model, config, options, workers)


def capture_one(photo: Path, target: Path, batch: str | None = None) -> BatchItem:
    """Capture ``photo`` and write its folder ``target`` in this worker (``prepare_worker``). With a
    ``batch`` token the folder's manifest records it, and a folder that already holds it (written
    by this batch before its worker died, the task then run again elsewhere) is left as it is."""
    import drjit as dr

    from .errors import MideepbasisError
    from .export import save_capture
    from .outputs import OutputFolder, manifest_of

    started = time.perf_counter()
    options = _WORKER["options"]
    if batch is not None and (manifest_of(target) or {}).get("batch") == batch:
        return BatchItem(photo, target, notes=["written by this batch already"], seconds=0.0, repeated=True)
    try:
        # Checked and locked before the work; a photo's folder is replaced only where the tool wrote it.
        folder = OutputFolder(target, overwrite=options.overwrite, inputs=[photo],
                              record={"batch": batch, "photo": str(photo)} if batch else None)
    except MideepbasisError as error:
        return BatchItem(photo, target, error=str(error))
    try:
        # The capture's kernels are small (64 - 128 px renders): a second drjit thread mostly waits
        # for the first, and with two workers on two cores that waiting is the other photo's time
        # (1.1 against 1.5 CPU-s a capture). The writing's path tracing keeps the pool: it divides
        # well, and Mitsuba's scene loading never returns on a pool of one thread.
        dr.set_thread_count(_WORKER["capture_threads"])
        try:
            result = _WORKER["capturer"].capture(photo)
        finally:
            dr.set_thread_count(_WORKER["drjit_threads"])
        result.output = None  # the network's tensors are not written: free them before the renders
        save_capture(result, folder, exr=options.exr, preview_tiles=options.preview_tiles,
                     shape_previews=options.shape_previews)
    except BaseException as error:
        folder.abort()  # after save_capture's own failure, nothing is left to do
        if isinstance(error, MideepbasisError):
            return BatchItem(photo, target, error=str(error))
        if isinstance(error, Exception):  # one photo's failure (a full disk, a bug) is its own line
            return BatchItem(photo, target, error=f"{type(error).__name__}: {error}")
        raise
    return BatchItem(photo, target, offset_angle_deg=result.offset_angle_deg,
                     seconds=time.perf_counter() - started, notes=list(result.notes))


def check_batch(photos: list[Path], out: Path, model=None, overwrite: bool = False) -> None:
    """Refuse, before any work, a batch whose output folder may not be written (``outputs.check_target``;
    not empty, without ``overwrite``), whose photos share a name (they would share ``out/<name>``)
    or whose model does not load (the workers would each fail to start). Makes ``out``."""
    from .errors import InputError
    from .model.checkpoint import read_checkpoint, shipped_model_path
    from .outputs import check_target, probe_writable, refuse_occupied

    check_target(out, photos)
    if not overwrite:  # (with it, each photo's folder is replaced only where the tool wrote it)
        refuse_occupied(out)

    seen: dict[str, Path] = {}
    for photo in photos:
        if photo.stem in seen:
            raise InputError(f"'{seen[photo.stem]}' and '{photo}' would both be written to {out / photo.stem}: "
                             "rename one or capture them separately")
        seen[photo.stem] = photo
    read_checkpoint(model if model is not None else shipped_model_path())
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise InputError(f"cannot make the folder {out}: {error.strerror or error}") from None
    probe_writable(out)


def capture_batch(photos: list[Path], out: Path, model=None, config=None, options: SaveOptions = SaveOptions(),
                  workers: int | None = None, overwrite: bool = False) -> Iterator[BatchItem]:
    """Capture every photo into ``out/<photo stem>/``; yields each outcome as it completes.

    Args:
        photos: the photo files: distinct names, checked with the model (``check_batch``) before
            this returns, so that a refusal comes before any work.
        out: the folder that receives one material folder per photo.
        model: a checkpoint path, or None for the shipped model (each worker loads it once).
        config: the ``CaptureConfig`` of every capture (None: the defaults).
        options: what is written per photo.
        workers: worker processes (None: ``batch_workers``: one per core, at most one per photo,
            as many as the free memory holds).
        overwrite: write into an ``out`` that is not empty (each photo's folder is replaced only
            where the tool wrote it, ``outputs.OutputFolder``).

    Raises:
        InputError: photos that share a name, a model that does not load (on the call).
        MideepbasisError: a worker died (the batch cannot go on; while iterating).
    """
    check_batch(photos, out, model, overwrite)
    return _run_batch(photos, out, model, config, options, workers)


def _run_batch(photos: list[Path], out: Path, model, config, options: SaveOptions,
               workers: int | None) -> Iterator[BatchItem]:
    import multiprocessing
    from concurrent.futures.process import BrokenProcessPool

    from .errors import MideepbasisError
    from .capturing.pipeline import CaptureConfig

    config = config or CaptureConfig()
    workers = workers or batch_workers(photos, config)[0]
    model = str(model) if model is not None else None
    # spawn, not fork: drjit's and torch's thread pools do not survive a fork.
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_start_worker,
                               initargs=(model, config, options, workers, os.getpid()))
    try:
        # At most two photos queued per worker: results come back in order of completion.
        queue = iter(photos)
        running = set()

        def submit() -> bool:
            photo = next(queue, None)
            if photo is None:
                return False
            running.add(pool.submit(capture_one, photo, out / photo.stem))
            return True

        for _ in range(2 * workers):
            if not submit():
                break
        while running:
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                running.discard(future)
                submit()
                try:
                    yield future.result()
                except BrokenProcessPool:
                    raise MideepbasisError("a capture worker process died (out of memory?); the batch stopped") from None
    except BaseException:
        # Ctrl-C, or the caller stopped reading: drop what is queued and stop the workers now.
        pool.shutdown(wait=False, cancel_futures=True)
        for process in list(getattr(pool, "_processes", {}).values()):
            process.terminate()
        raise
    pool.shutdown(wait=True)
