"""HDF5 files written through a guarded Python file object: a full disk is one error, not a segfault.

h5py's own (sec2) driver meets a failed write (ENOSPC: no space left, EDQUOT: quota, EFBIG: the
file-size limit of `ulimit -f`) inside HDF5's deferred flushes — a chunk evicted from the cache
while an object is garbage-collected — where h5py can only print "Exception ignored" and carry
on, and closing the broken file then segfaults (measured: qcm-simulate and qcm-import under
`ulimit -f`, exit 139 after thousands of traceback lines). Written through `GuardedFile`, every
byte passes through Python: the first failed write is recorded, later writes are dropped (the
file is incomplete already and will be deleted), HDF5 closes cleanly, and the writer raises one
`DatasetError` naming the file (`raise_if_failed`).

    handle, guard = open_guarded(tmp)      # h5py.File(guard, "w")
    ... write ...
    handle.close(); guard.close()
    raise_if_failed(guard, target)          # DatasetError if any write failed
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import h5py

from hybridqcm import interrupt
from hybridqcm.errors import DatasetError

# errnos of a write that can never succeed on this disk: the caller is told in one line
DISK_FULL = tuple(e for e in (errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", None)) if e is not None)


class GuardedFile(io.RawIOBase):
    """A binary file for h5py's fileobj driver that records the first failed write and drops the rest."""

    def __init__(self, path: str | os.PathLike, mode: str = "w+b"):
        super().__init__()
        self.path = Path(path)
        self._file = open(self.path, mode, buffering=0)  # noqa: SIM115 - closed in close()
        self.error: OSError | None = None
        # A stop request raised while HDF5 called in here: kept, and re-raised by raise_if_failed
        # (raising through HDF5's C frames would leave the file as broken as a failed write).
        self.interrupted: KeyboardInterrupt | None = None

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        while True:
            try:
                return self._file.readinto(buffer)
            except KeyboardInterrupt as stop:
                self.interrupted = stop

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while self.error is None and done < len(view):  # a write at the size limit is short before it fails
            try:
                done += self._file.write(view[done:])
            except OSError as error:
                self.error = error
            except KeyboardInterrupt as stop:  # Ctrl-C / SIGTERM: finish this write, raise at a safe point
                self.interrupted = stop
        return len(view)  # HDF5 must not see a failure: it would leave the file unclosable

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def truncate(self, size: int | None = None) -> int:
        try:
            return self._file.truncate(size)
        except OSError as error:
            self.error = self.error or error
            return self.tell() if size is None else size

    def flush(self) -> None:
        pass  # unbuffered

    def close(self) -> None:
        if not self.closed:
            self._file.close()
        super().close()


def open_guarded(path: str | os.PathLike, **kwargs) -> tuple[h5py.File, GuardedFile]:
    """A new HDF5 file at `path` (created or truncated) written through a GuardedFile."""
    guard = GuardedFile(path)
    try:
        return h5py.File(guard, "w", **kwargs), guard
    except BaseException:
        guard.close()
        raise


@contextlib.contextmanager
def writing(path: str | os.PathLike) -> Iterator[tuple[h5py.File, GuardedFile]]:
    """(h5py.File, GuardedFile) of a new file at `path`, both closed when the block ends. A stop request
    (Ctrl-C, SIGTERM) waits for the block and is raised after it: never inside h5py's C code."""
    with interrupt.deferred():
        handle, guard = open_guarded(path)
        with guard, handle:
            yield handle, guard


def disk_error_message(
    path: str | os.PathLike, error: OSError, after: str = "nothing was written", folder: str | os.PathLike | None = None
) -> str:
    """One line: which file could not be written, why, how much room the disk has (that of `folder`,
    default the file's), and what was left."""
    path = Path(path)
    try:
        free = f"{shutil.disk_usage(folder or path.parent).free / 2**20:.0f} MiB free on its disk"
    except OSError:
        free = "free space unknown"
    reason = error.strerror or str(error)
    if error.errno == errno.EFBIG:
        reason += " (the file-size limit: ulimit -f)"
    return f"{path}: could not be written: {reason}; {free}; {after}"


def raise_if_failed(guard: GuardedFile, target: str | os.PathLike) -> None:
    """DatasetError (one line naming `target`) if a write to the guarded file failed; a stop
    request that arrived while HDF5 was writing is raised here."""
    if guard.interrupted is not None:
        raise guard.interrupted
    if guard.error is not None:
        raise DatasetError(disk_error_message(target, guard.error))


__all__ = ["DISK_FULL", "GuardedFile", "open_guarded", "writing", "disk_error_message", "raise_if_failed"]
