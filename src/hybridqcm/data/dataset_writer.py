"""Writing a dataset file (the layout of data/hdf5.py) atomically, one writer at a time.

with DatasetWriter(path, attrs) as writer: create_split, write (slabs), then rename into place
acquire_write_lock(path)     the dataset's write lock (a second writer is refused, a dead one's lock taken over)
remove_stale_partials(path)  temporary files a killed writer left beside the target
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import h5py
import numpy as np

from hybridqcm.atomic import forget, new_temporary
from hybridqcm.data.h5file import GuardedFile, open_guarded, raise_if_failed
from hybridqcm.data.hdf5 import LAYOUT, SCHEMA, trailing_shape
from hybridqcm.errors import DatasetError
from hybridqcm.interrupt import check_stop, deferred, pending
from hybridqcm.runfiles import pid_alive


class DatasetWriter:
    """Writes a dataset atomically: into a temporary file beside `path`, renamed on success.

        with DatasetWriter(path, attrs={...}) as writer:
            writer.create_split("train", n_samples, n_steps)
            writer.write("train", start, accel=..., vel=..., ...)

    If the block raises (or the process dies), the target is untouched and the temporary
    file is removed (or, after a hard kill, left under a name that no reader takes for data).

    Exclusive: a lock file `.<name>.lock` (O_EXCL, holding the writer's pid) makes a second
    concurrent writer to the same path fail at once; with overwrite=False the finished file is
    put in place with os.link, which fails if the path appeared meanwhile (never replaced).
    Stale `.partial` files and locks of dead writers are removed and reported (`self.stale`).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        attrs: Mapping | None = None,
        overwrite: bool = False,
        compression: str | None = "gzip",
        compression_level: int | None = 1,
        chunk_samples: int = 256,
    ) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise DatasetError(f"{self.path} is a directory, not a file path")
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists; pass overwrite=true to replace it")
        if compression not in (None, "gzip", "lzf"):
            raise DatasetError(f"{self.path}: compression = {compression!r} is not supported; use gzip, lzf or null")
        self.attrs = dict(attrs or {})
        self.compression = compression
        self.compression_opts = compression_level if compression == "gzip" else None
        self.chunk_samples = chunk_samples
        self.overwrite = bool(overwrite)
        self._handle: h5py.File | None = None
        self._guard: GuardedFile | None = None
        self._tmp: Path | None = None
        self._lock: Path | None = None
        self.stale: list[Path] = []

    def __enter__(self) -> DatasetWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = acquire_write_lock(self.path)
        self.stale = remove_stale_partials(self.path)
        if self.stale:  # reported only now: before the lock, a live writer's partial looks the same
            print(
                f"note: removed {len(self.stale)} stale partial file(s) of killed runs: "
                f"{', '.join(p.name for p in self.stale)}",
                file=sys.stderr,
            )
        try:
            self._tmp = new_temporary(self.path, ".partial")
        except BaseException:
            self._release()
            raise
        # While the file is open a stop request is recorded, never raised where it lands: HDF5 writes through
        # the GuardedFile's Python methods also when h5py objects are garbage-collected in the middle of other
        # work, and an exception raised in there breaks the file (the close then segfaulted). It is raised at
        # the next safe point: write()'s check_stop, once per chunk, or __exit__.
        self._stops = deferred(raise_on_exit=False)
        self._stops.__enter__()
        try:
            # through a GuardedFile: a full disk is one DatasetError, never HDF5's segfault (data/h5file.py)
            self._handle, self._guard = open_guarded(self._tmp)
            self._handle.attrs["schema"] = SCHEMA
            for key, value in self.attrs.items():
                self._handle.attrs[key] = json.dumps(value) if isinstance(value, (dict, list, tuple)) else value
        except BaseException:  # __exit__ is not called when __enter__ fails: clean up here
            if self._handle is not None:
                self._handle.close()
                self._handle = None
            if self._guard is not None:
                self._guard.close()
            self._tmp.unlink(missing_ok=True)
            self._release()
            self._stops.__exit__(None, None, None)
            raise
        return self

    def _release(self) -> None:
        if self._tmp is not None:  # renamed into place or removed by now (a stopped one: the app's exit removes it)
            forget(self._tmp)
        if self._lock is not None:
            self._lock.unlink(missing_ok=True)
            self._lock = None

    def create_split(
        self,
        split: str,
        n_samples: int,
        n_steps: int,
        keys: Iterable[str] = tuple(LAYOUT),
        extra: Mapping[str, tuple[np.dtype, tuple[int, ...]]] | None = None,
    ) -> None:
        """Create /<split> with LAYOUT's `keys` and the `extra` keys {key: (dtype, trailing shape)}."""
        assert self._handle is not None, "use DatasetWriter as a context manager"
        group = self._handle.create_group(split)
        shapes = {key: (LAYOUT[key][0], trailing_shape(key, n_steps)) for key in keys}
        shapes.update({key: (np.dtype(dtype), tuple(tail)) for key, (dtype, tail) in (extra or {}).items()})
        for key, (dtype, tail) in shapes.items():
            shape = (n_samples, *tail)
            chunks = (max(1, min(self.chunk_samples, n_samples)), *shape[1:]) if n_samples else None
            group.create_dataset(
                key,
                shape=shape,
                dtype=dtype,
                chunks=chunks,
                compression=self.compression if n_samples else None,
                compression_opts=self.compression_opts if n_samples else None,
                shuffle=bool(self.compression) and n_samples > 0,
            )

    def write(self, split: str, start: int, **arrays: np.ndarray) -> None:
        """Write rows [start, start + len) of each given key."""
        check_stop()  # a Ctrl-C swallowed inside a GC callback is raised here, once per chunk
        assert self._handle is not None
        group = self._handle[split]
        for key, array in arrays.items():
            array = np.asarray(array)
            if key not in group:
                raise DatasetError(f"{self.path}: /{split} has no dataset {key!r}; created: {sorted(group.keys())}")
            target = group[key]
            if (
                array.ndim != target.ndim
                or array.shape[1:] != target.shape[1:]
                or not 0 <= start <= target.shape[0] - array.shape[0]
            ):
                raise DatasetError(
                    f"{self.path}: cannot write {key} of shape {array.shape} at row {start} into "
                    f"/{split}/{key} of shape {target.shape}"
                )
            if array.dtype.kind == "f" and not np.isfinite(array).all():
                raise DatasetError(
                    f"{self.path}: refusing to write non-finite values into /{split}/{key} at rows {start}.."
                )
            with deferred():  # a stop request waits for h5py's write (see interrupt.deferred)
                group[key][start : start + array.shape[0]] = array
        if self._guard is not None:
            raise_if_failed(self._guard, self.path)  # the disk is full: stop now, not at the end

    def set_split_attr(self, split: str, key: str, value) -> None:
        assert self._handle is not None
        self._handle[split].attrs[key] = value

    def set_dataset_attr(self, split: str, key: str, name: str, value) -> None:
        """An attribute of /<split>/<key> (a list of strings is stored as a string array: the column
        names of a half-car / full-car file, e.g. accel's ``dofs``)."""
        assert self._handle is not None
        if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            value = np.array(value, dtype=h5py.string_dtype())
        self._handle[split][key].attrs[name] = value

    def set_attr(self, key: str, value) -> None:
        assert self._handle is not None
        self._handle.attrs[key] = json.dumps(value) if isinstance(value, (dict, list, tuple)) else value

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._handle is not None and self._tmp is not None
        try:
            self._handle.flush()
            self._handle.close()
        finally:
            self._handle = None
            if self._guard is not None:
                self._guard.close()
            self._stops.__exit__(None, None, None)  # the app's handlers again; a stop request is raised below
        if exc_type is None and pending() is not None:
            self._tmp.unlink(missing_ok=True)
            self._release()
            check_stop()
        try:
            if self._guard is not None and (self._guard.error is not None or self._guard.interrupted is not None):
                self._tmp.unlink(missing_ok=True)
                raise_if_failed(self._guard, self.path)  # whatever else was raised, a full disk is the cause
            if exc_type is None:
                os.chmod(self._tmp, 0o644)  # mkstemp creates 0600; a dataset is meant to be shared
                if self.overwrite:
                    os.replace(self._tmp, self.path)
                else:
                    try:
                        os.link(self._tmp, self.path)  # atomic create-if-absent: never replaces another's file
                    except FileExistsError:
                        raise FileExistsError(
                            f"{self.path} appeared while this run was writing it; "
                            f"not replaced (pass overwrite=true to replace it)"
                        ) from None
                    finally:
                        self._tmp.unlink(missing_ok=True)
            else:
                self._tmp.unlink(missing_ok=True)
        finally:
            self._release()


def acquire_write_lock(path: str | os.PathLike) -> Path:
    """Create `.<name>.lock` beside `path` exclusively (O_EXCL) with our pid; FileExistsError if a live writer holds it.

    A lock left by a dead process (same host) is removed and taken over."""
    path = Path(path)
    lock = path.parent / f".{path.name}.lock"
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid > 0 and not pid_alive(pid):
                lock.unlink(missing_ok=True)  # its writer died: the lock is stale
                continue
            raise FileExistsError(
                f"{path} is being written by another process (pid {pid or '?'}, lock {lock}); "
                f"wait for it or choose another output"
            ) from None
        with os.fdopen(fd, "w") as handle:
            handle.write(f"{os.getpid()}\n")
        return lock
    raise FileExistsError(f"{path}: could not take the write lock {lock}")


def remove_stale_partials(path: str | os.PathLike) -> list[Path]:
    """Remove `.partial` files of `path` left by killed writers; call only while holding its write lock.

    Holding the lock means no other writer of `path` is alive, so every partial of it is stale."""
    path = Path(path)
    stale = sorted(path.parent.glob(f".{path.name}.*.partial"))
    for partial in stale:
        partial.unlink(missing_ok=True)
    return stale
