"""Output folders, written whole or not at all: the one place that replaces or deletes a folder.

Every command that writes a folder (``capture``, its batches, ``demo``, ``evaluate``) goes through
``OutputFolder``:

1. **Checked before the work.** The target must not be the working folder or one of its
   ancestors (``.``, ``..``), the home folder, a file-system root, a symbolic link, a file, an
   input or a folder holding one; its parent must be writable (a file is made and removed there,
   and inside an existing target). Another command writing the same target holds its lock: the
   second gets one line, never a silent loss.
2. **Written beside.** Everything goes into a staging folder ``.NAME.mideepbasis-new-PID`` next
   to the target, which ends with the manifest ``.mideepbasis-manifest.json``: every file and
   folder the tool wrote.
3. **Swapped in atomically.** The staging folder and the old target are exchanged in one
   ``renameat2(RENAME_EXCHANGE)``: a kill at any instant leaves the old result or the new one,
   whole. (Where the file system cannot exchange, two renames; a kill between them leaves the
   old result beside, and the next run puts it back.)
4. **Replacing only what the tool wrote.** ``overwrite`` replaces a non-empty target only when
   its manifest lists everything in it; otherwise the command refuses, naming what it would lose.
5. **Leftovers cleaned.** Staging and old folders of a killed run are removed by the next run
   into the same target (it holds the lock, so their writer is gone).

Shapes of the folder's contents are the caller's; this module sees only paths.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
import re
import shutil
import signal
from pathlib import Path
from typing import Iterable

from .errors import InputError

#: The file in every folder the tool writes that lists what it wrote.
MANIFEST = ".mideepbasis-manifest.json"

#: Test hook: the environment variable naming a step (``staged``, ``exchanged``) at which the
#: process kills itself, so that tests can stop a write at its critical instants.
KILL_AT_ENV = "MIDEEPBASIS_KILL_AT"

#: Names of what this module makes beside a target NAME, and may delete: staging and old folders
#: (``.NAME.mideepbasis-new-PID``, ``-old-``), the writability probe (``-probe-``); and the staging
#: folders that other versions name ``.NAME.tmp-PID``. (The lock, ``.NAME.mideepbasis-lock``, is not
#: deleted by name: its holder removes it.)
_BESIDE = re.compile(r"^\.(?P<name>.+)\.(?:mideepbasis-(?P<kind>new|old|probe)|tmp)-(?P<pid>\d+)$")

_RENAME_NOREPLACE, _RENAME_EXCHANGE = 1, 2
_AT_FDCWD = -100


class OutputFolder:
    """A folder this tool writes whole: ``check`` on creation, ``staging`` to write into,
    ``commit`` to swap it in (or ``abort``). As a context manager it commits on success and
    aborts on an exception; an ``OSError`` inside, or an error that names the staging folder, is
    re-raised as one line naming the target instead.

    Args:
        target: the folder to write.
        overwrite: replace an existing, non-empty target (only what the tool wrote there).
        inputs: files the command reads (photos, data folders): the target may not hold them.
        kind: what the folder holds (``capture``, ``evaluation``, ``batch``), in the manifest.
        record: more for the manifest (JSON-able): a batch's token and the photo, say.
    """

    def __init__(self, target: str | os.PathLike, overwrite: bool = False, inputs: Iterable[str | os.PathLike] = (),
                 kind: str = "capture", record: dict | None = None):
        self.target, self.overwrite, self.kind, self.record = Path(target), overwrite, kind, record or {}
        self._lock_fd: int | None = None
        self._staging: Path | None = None
        check_target(self.target, inputs)
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise InputError(f"cannot make the folder {self.target.parent}: {error.strerror or error}") from None
        self._lock()
        try:
            _recover(self.target)
            probe_writable(self.target.parent)
            if self.target.is_dir():
                check_replaceable(self.target, overwrite)
                probe_writable(self.target)  # an immutable folder cannot be swapped out either
        except BaseException:
            self._unlock()
            raise

    # --- writing ---------------------------------------------------------------------------------

    @property
    def staging(self) -> Path:
        """The folder to write into (made on first use)."""
        if self._staging is None:
            self._staging = self.target.parent / f".{self.target.name}.mideepbasis-new-{os.getpid()}"
            remove_tree(self._staging)
            self._staging.mkdir()
        return self._staging

    def commit(self) -> Path:
        """Write the manifest, swap the staging folder in for the target, remove the old result."""
        staging = self.staging
        written = sorted(str(path.relative_to(staging)) for path in staging.rglob("*") if path.name != MANIFEST)
        (staging / MANIFEST).write_text(json.dumps({"written_by": "mideepbasis", "kind": self.kind, **self.record,
                                                    "entries": written}, indent=1))
        _fsync_folder(staging)
        _kill_hook("staged")
        try:
            if self.target.exists():
                old = _exchange(staging, self.target)
                _kill_hook("exchanged")
                remove_tree(old)
            else:
                _rename_new(staging, self.target)
            _fsync_folder(self.target.parent)
        except OSError as error:
            self.abort()
            raise InputError(f"cannot put the result into {self.target}: {error.strerror or error}") from None
        self._staging = None
        self._unlock()
        return self.target

    def abort(self) -> None:
        """Remove what was staged; the target stays as it was."""
        if self._staging is not None:
            remove_tree(self._staging)
            self._staging = None
        self._unlock()

    def __enter__(self) -> OutputFolder:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if error is None:
            self.commit()
            return
        staging = self._staging
        self.abort()
        # A write's error names the file it failed on: the user's folder, not the staging one.
        if isinstance(error, OSError) or (staging is not None and str(staging) in str(error)):
            raise InputError(self.described(error, staging)) from None

    def described(self, error: BaseException, staging: Path | None = None) -> str:
        """The error's message with the staging folder's path replaced by the target's."""
        text = " ".join(str(error).split())
        staging = staging or self._staging
        return text.replace(str(staging), str(self.target)) if staging is not None else text

    # --- the lock ----------------------------------------------------------------------------------

    def _lock_path(self) -> Path:
        return self.target.parent / f".{self.target.name}.mideepbasis-lock"

    def _lock(self) -> None:
        path = self._lock_path()
        while True:
            try:
                descriptor = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
            except OSError as error:
                raise InputError(f"cannot write into {self.target.parent}: {error.strerror}") from None
            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(descriptor)
                raise InputError(f"{self.target}: another mideepbasis command is writing this folder now; "
                                 "wait for it to finish or choose another") from None
            # The holder before us may have removed the lock file as it let go: lock the file that is there.
            try:
                if os.fstat(descriptor).st_ino == os.stat(path).st_ino:
                    self._lock_fd = descriptor
                    return
            except FileNotFoundError:
                pass
            os.close(descriptor)

    def _unlock(self) -> None:
        if self._lock_fd is None:
            return
        try:
            self._lock_path().unlink(missing_ok=True)
        finally:
            os.close(self._lock_fd)
            self._lock_fd = None


def check_target(target: Path, inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Refuse, in one line, a target no command may replace: the working folder or an ancestor of
    it, the home folder, a file-system root, a symbolic link, a file, an input or a folder that
    holds one."""
    target = Path(target)
    if target.is_symlink():
        raise InputError(f"output {target} is a symbolic link: give the folder it points to, or another")
    if target.exists() and not target.is_dir():
        raise InputError(f"output {target} exists and is not a folder")
    resolved = target.resolve()
    working = Path.cwd().resolve()
    if resolved == working or resolved in working.parents:
        raise InputError(f"output {target} is the working folder or holds it: give a folder of its own")
    if resolved == Path(resolved.anchor) or resolved == Path.home().resolve():
        raise InputError(f"output {target} is the file system's root or the home folder: give a folder of its own")
    for item in inputs:
        path = Path(item).resolve()
        if resolved == path or resolved in path.parents:
            raise InputError(f"output {target} holds the input {item}: give a folder of its own")


def refuse_occupied(target: Path) -> None:
    """Refuse, in one line, an existing folder that is not empty (the user did not ask to overwrite)."""
    if target.is_dir() and any(target.iterdir()):
        raise InputError(f"output folder {target} exists and is not empty: choose another or pass --overwrite")


def check_replaceable(target: Path, overwrite: bool) -> None:
    """Refuse an existing, non-empty target unless ``overwrite`` and its manifest lists all it holds."""
    entries = sorted(str(path.relative_to(target)) for path in target.rglob("*"))
    if not entries:
        return
    if not overwrite:
        refuse_occupied(target)
    written = written_entries(target)
    if written is None:
        raise InputError(f"output folder {target} was not written by mideepbasis (it has no {MANIFEST}): "
                         "--overwrite replaces only folders the tool wrote; move its files or choose another")
    foreign = [entry for entry in entries if entry != MANIFEST and entry not in written]
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise InputError(f"output folder {target} holds what mideepbasis did not write ({shown}): "
                         "--overwrite would lose it; move it or choose another folder")


def manifest_of(folder: Path) -> dict | None:
    """The manifest of ``folder`` (a folder the tool wrote), or None."""
    try:
        document = json.loads((Path(folder) / MANIFEST).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(document, dict) or document.get("written_by") != "mideepbasis":
        return None
    return document


def written_entries(folder: Path) -> set[str] | None:
    """The entries the manifest of ``folder`` lists, or None without a readable manifest."""
    document = manifest_of(folder)
    try:
        return None if document is None else {str(entry) for entry in document["entries"]}
    except (KeyError, TypeError):
        return None


def remove_tree(path: Path) -> None:
    """Delete a staging or old folder this module made (``.NAME.mideepbasis-new-PID`` and the
    like), or nothing: the one deletion of a folder in the package, guarded by its name."""
    path = Path(path)
    if not _BESIDE.match(path.name):
        raise ValueError(f"refusing to delete {path}: not a folder this tool stages")
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.exists():
        shutil.rmtree(path)


def _recover(target: Path) -> None:
    """Clean up after killed writes into ``target`` (the caller holds its lock): put an old result
    back where a write stopped between its two renames, remove staging and old folders."""
    parent, name = target.parent, target.name
    leftovers = []
    for path in parent.iterdir() if parent.is_dir() else ():
        match = _BESIDE.match(path.name)
        if match and match["name"] == name and not (match["kind"] is None and _alive(int(match["pid"]))):
            leftovers.append((path, match["kind"]))
    if not target.exists():
        for path, kind in leftovers:
            if kind == "old" and written_entries(path) is not None:
                os.rename(path, target)
                break
    for path, _ in leftovers:
        if path.exists():
            remove_tree(path)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return pid != os.getpid()


def probe_writable(folder: Path) -> None:
    """Refuse, in one line, a folder a file cannot be made in (read-only, immutable, full). The
    probes that processes killed between making and removing theirs left in it go first."""
    _remove_dead_probes(folder)
    probe = folder / f".{folder.name}.mideepbasis-probe-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink(missing_ok=True)  # a thread of this process may have taken it first
    except OSError as error:
        raise InputError(f"cannot write into {folder}: {error.strerror or error}") from None


def _remove_dead_probes(folder: Path) -> None:
    """Delete the empty probe files of ``probe_writable`` (``.NAME.mideepbasis-probe-PID``, NAME the
    folder's) in ``folder`` whose process is gone."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return  # the probe itself says why
    for entry in entries:
        match = _BESIDE.match(entry.name)
        if match and match["kind"] == "probe" and match["name"] == folder.name and not _alive(int(match["pid"])):
            try:
                if entry.stat(follow_symlinks=False).st_size == 0:
                    os.unlink(entry.path)
            except OSError:
                pass  # another process removed it, or it cannot be: the probe goes on


def _renameat2(source: Path, destination: Path, flags: int) -> bool:
    """renameat2(2) with ``flags``; False where this system or file system lacks it."""
    try:
        function = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if function(_AT_FDCWD, os.fsencode(source), _AT_FDCWD, os.fsencode(destination), flags) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), str(destination))


def _exchange(staging: Path, target: Path) -> Path:
    """Put ``staging`` where ``target`` is, atomically; returns where the old result now lies."""
    if _renameat2(staging, target, _RENAME_EXCHANGE):
        return staging  # the names swapped: the old result sits under the staging name
    old = target.parent / f".{target.name}.mideepbasis-old-{os.getpid()}"
    os.rename(target, old)
    os.rename(staging, target)
    return old


def _rename_new(staging: Path, target: Path) -> None:
    """Put ``staging`` where nothing is; never onto a folder that appeared meanwhile."""
    if not _renameat2(staging, target, _RENAME_NOREPLACE):
        if target.exists():
            raise InputError(f"output folder {target} appeared while this command wrote it")
        os.rename(staging, target)


def _fsync_folder(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def _kill_hook(step: str) -> None:
    if os.environ.get(KILL_AT_ENV) == step:
        os.kill(os.getpid(), signal.SIGKILL)
