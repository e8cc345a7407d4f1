"""A folder the cell writes that cannot take the write: a full disk, a read-only file system, a folder that is
not ours. One clear message naming the path and what to do, never a traceback, never a half-made run.

Three moments, three outcomes: before a command writes anything, :func:`require_writable` refuses the output
folder (ConfigError, exit code 2: nothing was written); while a run folder is made, :func:`new_folder`
removes what it made and refuses the same way; once a run is under way, the controller turns the error into
a pause (:class:`cell.errors.StorageError`): every view on disk is whole, and the run resumes once there is
room. The CLI turns any other such error into one line (exit code 1).
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cell.errors import ConfigError, StorageError

STORAGE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG}
_WHY = {
    errno.ENOSPC: ("the disk is full", "free space on it"),
    errno.EDQUOT: ("the disk quota is used up", "free space or raise the quota"),
    errno.EFBIG: ("a file would exceed the file system's size limit", "choose another disk"),
    errno.EROFS: ("it is on a read-only file system", "choose a writable folder"),
    errno.EACCES: ("permission denied", "choose a folder you may write to, or fix its permissions"),
    errno.EPERM: ("permission denied", "choose a folder you may write to, or fix its permissions"),
}


FULL_BELOW_BYTES = 1 << 20  # a disk with less room than this is full: the next view would not fit


def fsync_path(path: str | Path) -> None:
    """Flush a file or a folder to disk (a folder: so that a rename into it survives a power cut)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def disk_full(path: str | Path) -> bool:
    """The file system holding ``path`` (or its nearest existing parent) has less than 1 MiB free."""
    return shutil.disk_usage(_nearest_existing(Path(path))).free < FULL_BELOW_BYTES


def is_storage_error(exc: BaseException, folder: str | Path | None = None) -> bool:
    """An OSError that says the disk or folder cannot take a write (full, read-only, not permitted); with
    ``folder``, also one without an errno while that folder's disk is full (numpy's short write: 'N requested
    and M written')."""
    if not isinstance(exc, OSError):
        return False
    if exc.errno in STORAGE_ERRNOS:
        return True
    return exc.errno is None and folder is not None and disk_full(folder)


def require_room(folder: str | Path) -> None:
    """OSError(ENOSPC) naming ``folder`` when its disk is full: a writer that fails without a word
    (cv2.imwrite returns False) may have left a file short, so what was written there is not kept."""
    if disk_full(folder):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(folder))


def describe(exc: OSError, folder: str | Path | None = None) -> str:
    """'cannot write <folder>: <why> (<file>); <what to do>'."""
    why, todo = _WHY.get(exc.errno or errno.ENOSPC, (exc.strerror or str(exc), "check the folder"))
    where = str(folder if folder is not None else exc.filename or "the output folder")
    file = exc.filename if exc.filename is not None and str(exc.filename) != where else None
    return f"cannot write {where}: {why}{f' ({file})' if file else ''}; {todo}"


def storage_error(exc: OSError, folder: str | Path | None = None) -> StorageError:
    """The StorageError of ``exc`` met while writing into ``folder``."""
    where = folder if folder is not None else exc.filename
    error = StorageError(describe(exc, folder), path=None if where is None else str(where))
    error.__cause__ = exc
    return error


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def require_writable(folder: str | Path, field: str | None = "--out") -> None:
    """ConfigError (exit 2) unless ``folder`` (existing or not) can take a file: a probe file is written,
    synced and removed in the folder or in its nearest existing parent. Nothing is left behind."""
    folder = Path(folder)
    target = _nearest_existing(folder)
    if not target.is_dir():
        raise ConfigError(f"{target} is a file, not a folder", path=str(folder), field=field)
    try:
        with tempfile.NamedTemporaryFile(dir=target, prefix=".cell-write-probe-") as probe:
            probe.write(b"probe")
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as exc:
        if not is_storage_error(exc):
            raise
        raise ConfigError(describe(exc, folder), path=None, field=field) from exc


@contextmanager
def new_folder(path: str | Path, shown: str | Path | None = None) -> Iterator[Path]:
    """Make ``path`` (absent or empty before) within the block: when the block fails for want of space or
    permission, what was put into it (and the folder, if it was made here) is removed and a ConfigError (exit
    2: nothing was written) names it (or ``shown``: the name it was being made for); any other error also
    removes it and propagates."""
    path = Path(path)
    existed = path.exists()
    was_empty = existed and path.is_dir() and not any(path.iterdir())  # else the block refuses it
    try:
        yield path
    except BaseException as exc:
        storage = is_storage_error(exc, path)  # judged while what was written still fills the disk
        if not existed:
            shutil.rmtree(path, ignore_errors=True)
        elif was_empty:
            for child in path.iterdir():
                shutil.rmtree(child, ignore_errors=True) if child.is_dir() else child.unlink(missing_ok=True)
        if storage:
            assert isinstance(exc, OSError)
            raise ConfigError(describe(exc, shown if shown is not None else path)) from exc
        raise
