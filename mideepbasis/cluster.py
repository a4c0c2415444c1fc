"""A batch larger than one machine: the photos sent to a Dask distributed cluster's workers.

    mideepbasis capture shots/ -o materials/ --cluster tcp://scheduler:8786    # an existing cluster
    mideepbasis capture shots/ -o materials/ --cluster local:2                 # one started here

Dask distributed (not Ray): a capture is one Python function of one photo, which is what Dask's
futures schedule, retry and report as they complete; its scheduler and workers are plain
processes started by ``dask scheduler`` and ``dask worker ADDRESS`` on any machine with this
package installed, with nothing else to run. Each worker loads the model once (a worker plugin,
``batch.prepare_worker``) and writes each photo's folder itself, atomically
(``outputs.OutputFolder``), so ``OUT`` and the photos must be on a file system every worker
reaches (the paths are sent as given: use absolute ones). A worker that dies costs nothing: the
scheduler runs its photos again elsewhere, and a photo whose folder this batch had already
written is left as it is (the batch's token in its manifest): none is lost, none written twice.

Without ``--cluster`` nothing here is imported.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Iterator

from distributed.diagnostics.plugin import WorkerPlugin

from .batch import BatchItem, SaveOptions, check_batch

#: Times a photo's task is run again after its worker died.
RETRIES = 3


class CapturePlugin(WorkerPlugin):
    """A Dask worker plugin: the model loaded once on each worker (``batch.prepare_worker``)."""

    name = "mideepbasis-capture"

    def __init__(self, model, config, options: SaveOptions):
        self.model, self.config, self.options = model, config, options

    def setup(self, worker) -> None:
        from .batch import prepare_worker

        relax_memory_trimming()
        # The worker's share of its machine: its own threads' worth of the cores.
        workers = max(1, (os.cpu_count() or 1) // max(1, worker.state.nthreads))
        prepare_worker(self.model, self.config, self.options, workers)


#: glibc's mallopt parameters (malloc.h): the trim and the mmap thresholds.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3

#: The thresholds a worker's allocator is given [bytes]: glibc's largest dynamic ones.
TRIM_THRESHOLD = MMAP_THRESHOLD = 32 * 2**20


def relax_memory_trimming() -> None:
    """Undo the trim threshold of 64 KiB that a Dask nanny gives its workers
    (``MALLOC_TRIM_THRESHOLD_``). Set at all, it also stops glibc from raising its mmap threshold
    as programs free large blocks: every buffer of torch over 128 KiB is then mapped and unmapped
    afresh, faulted in page by page, and a capture ran 2.5 times slower. Elsewhere than glibc,
    nothing."""
    import ctypes

    if "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    except (AttributeError, OSError):
        pass



def _capture_task(photo: str, target: str, batch: str) -> BatchItem:
    from .batch import capture_one

    return capture_one(Path(photo), Path(target), batch)


def cluster_client(address: str):
    """(a Dask client of the cluster at ``address``, a closing function); ``local:N`` starts a
    cluster of N single-threaded worker processes on this machine."""
    from distributed import Client, LocalCluster

    from .errors import InputError

    if address.startswith("local:"):
        count = address.removeprefix("local:")
        if not count.isdigit() or int(count) < 1:
            raise InputError(f"--cluster {address}: expected local:N with N workers")
        cluster = LocalCluster(n_workers=int(count), threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)

        def close() -> None:
            client.close()
            cluster.close()

        return client, close
    try:
        client = Client(address, timeout=30)
    except OSError as error:
        raise InputError(f"--cluster {address}: no scheduler answers there ({error})") from None
    return client, client.close


def cluster_batch(photos: list[Path], out: Path, address: str, model=None, config=None,
                  options: SaveOptions = SaveOptions(), overwrite: bool = False) -> Iterator[BatchItem]:
    """Capture every photo into ``out/<photo stem>/`` on the cluster at ``address``; yields each
    outcome as it completes, as ``batch.capture_batch`` does. Checked (``batch.check_batch``)
    before this returns."""
    from .capturing.pipeline import CaptureConfig

    check_batch(photos, out, model, overwrite)
    return _run(photos, out, address, None if model is None else str(Path(model).resolve()),
                config or CaptureConfig(), options)


def _run(photos: list[Path], out: Path, address: str, model, config, options: SaveOptions) -> Iterator[BatchItem]:
    from distributed import as_completed

    client, close = cluster_client(address)
    try:
        client.register_plugin(CapturePlugin(model, config, options))
        token = uuid.uuid4().hex
        futures = {client.submit(_capture_task, str(photo.resolve()), str((out / photo.stem).resolve()), token,
                                 key=f"capture-{token}-{index}", retries=RETRIES, pure=False): photo
                   for index, photo in enumerate(photos)}
        # The client's own loop: as_completed otherwise waits on the default client's, which differs
        # where the caller holds a client of its own ("bound to a different event loop").
        for future in as_completed(futures, loop=client.loop):
            item, photo = future.result(), futures[future]  # the photo as given, not as the worker saw it
            yield BatchItem(photo, out / photo.stem, item.error, item.offset_angle_deg, item.seconds,
                            list(item.notes), item.repeated)
    finally:
        close()
