"""Atomic file writes: a temporary file beside the target, renamed into place once complete,
so a reader never sees a half-written table or summary.

Every temporary file is made by :func:`new_temporary`, which this process remembers until the file is renamed or
removed: a stop request (Ctrl-C, SIGTERM) is held while the file is made and named, and the apps' exit after a stop
(apps/common.interrupted_exit) removes whatever is still remembered, so no signal, wherever it lands between the
file's creation and its writer's own cleanup, can leave a temporary file behind.
"""

from __future__ import annotations

import contextlib
import csv
import io
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

from hybridqcm.interrupt import deferred

# the temporary files this process made and has not yet renamed or removed (names; set operations hold the GIL)
_LIVE: set[str] = set()


def new_temporary(path: str | Path, suffix: str = "") -> Path:
    """A new empty file beside ``path`` (mkstemp: mode 0600, a name no one else has), remembered until
    :func:`forget`. A stop request that arrives while it is made is raised once it is remembered."""
    path = Path(path)
    with deferred():
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
        _LIVE.add(name)
        os.close(fd)
    return Path(name)


def forget(tmp: str | Path) -> None:
    """``tmp`` was renamed into place or removed: nothing of it is left to clean up."""
    _LIVE.discard(str(tmp))


def remove_temporaries() -> list[Path]:
    """Remove the remembered temporary files that still exist (a stopped writer's); returns them."""
    removed = []
    for name in list(_LIVE):
        path = Path(name)
        if path.exists():
            path.unlink(missing_ok=True)
            removed.append(path)
        _LIVE.discard(name)
    return removed


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write `text` to `path`, complete or not at all, replacing what was there."""
    return atomic_create_text(path, text, overwrite=True)


def atomic_write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence]) -> Path:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(header)
    writer.writerows(rows)
    return atomic_write_text(path, buffer.getvalue())


@contextlib.contextmanager
def replacing(path: str | Path, suffix: str = ""):
    """The path of a new temporary file beside ``path``, for a writer that writes by name (torch.save, savefig):
    it replaces ``path`` (mode 0644: results are meant to be shared), complete, when the block ends, and is
    removed if the block raises."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_temporary(path, suffix)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        forget(tmp)


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", **kwargs):
    """A file handle for a large output written piece by piece: it appears at `path`, complete,
    when the block ends, and never appears if the block raises (the temporary file is removed)."""
    with replacing(path) as tmp, open(tmp, mode, **kwargs) as handle:
        yield handle


def atomic_create_text(path: str | Path, text: str, overwrite: bool = False) -> Path:
    """Write `text` to a new file `path`, complete or not at all: exclusively (os.link of the finished
    temporary file fails with FileExistsError if `path` exists or appeared meanwhile: another's file is
    never replaced), or replacing it with ``overwrite``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_temporary(path)
    try:
        with open(tmp, "w") as handle:
            handle.write(text)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; results are meant to be shared
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        forget(tmp)
    return path
