"""Atomic file writes: a temporary file beside the target, renamed into place once complete,
so a reader never sees a half-written table or summary."""

from __future__ import annotations

import contextlib
import csv
import io
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path


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
def atomic_open(path: str | Path, mode: str = "w", **kwargs):
    """A file handle for a large output written piece by piece: it appears at `path`, complete,
    when the block ends, and never appears if the block raises (the temporary file is removed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **kwargs) as handle:
            yield handle
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_create_text(path: str | Path, text: str, overwrite: bool = False) -> Path:
    """Write `text` to a new file `path`, complete or not at all: exclusively (os.link of the finished
    temporary file fails with FileExistsError if `path` exists or appeared meanwhile: another's file is
    never replaced), or replacing it with ``overwrite``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; results are meant to be shared
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path
