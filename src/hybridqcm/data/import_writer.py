"""Writing imported recordings as a dataset file (hdf5.py's layout, schema hybridqcm.dataset/2).

    import_recordings(path, output, ...)  scan the CSV, then write its windows as they are read (any size)
    write_windows(output, layout, windows, ...)  the writer: slabs of windows, atomically and exclusively
    write_recordings(output, data, ...)   ImportedRecordings held in memory (small files, tests)

The file appears complete or not at all: written to a temporary file beside the output and renamed into
place when complete (an existing output is refused unless overwrite); the temporary file is removed on
any error, Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from hybridqcm.atomic import forget, new_temporary
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.h5file import open_guarded, raise_if_failed, writing
from hybridqcm.data.importer import ImportedRecordings, RecordingLayout, iter_windows, scan_recordings
from hybridqcm.interrupt import check_stop, deferred

SCHEMA_V2 = "hybridqcm.dataset/2"


def _file_attrs(data, source: str, created_by: str, extra: Mapping | None = None) -> dict:
    """The file attributes of an imported dataset (module docstring); ``data``: ImportedRecordings or a layout."""
    attrs = {
        "schema": SCHEMA_V2,
        "h": float(data.h),
        "n_steps": int(data.n_steps),
        "created_by": created_by,
        "source": str(source),
        "units": json.dumps(
            {"accel": "m/s2", "road": "m", "time": "s"}
            | ({"known_mass": "kg"} if getattr(data, "known_mass", None) is not None else {})
        ),
        "source_units": json.dumps(data.source_units),
        "source_columns": json.dumps(data.source_columns),
        "channels": json.dumps(list(data.channels)),
        "recordings": json.dumps(data.recordings),
    }
    if data.window is not None:
        attrs.update(window=int(data.window), stride=int(data.stride))
    attrs.update(dict(extra or {}))
    return attrs


def _temporary(output: Path, overwrite: bool, split: str) -> Path:
    """Checks of the output path; the temporary file beside it that is renamed into place when complete."""
    if output.is_dir():
        raise RecordingError(f"{output} is a directory, not a file path")
    if output.exists() and not overwrite:
        raise FileExistsError(f"output={output} exists; pass overwrite=true to replace it")
    if not split or "/" in split:
        raise RecordingError(f"{output}: split = {split!r} is not a valid group name")
    output.parent.mkdir(parents=True, exist_ok=True)
    return new_temporary(output, ".partial")


def write_windows(
    output: str | os.PathLike,
    layout,
    windows,
    split: str = "test",
    source: str = "",
    overwrite: bool = False,
    created_by: str = "qcm-import",
    attrs: Mapping | None = None,
    slab: int = 64,
) -> Path:
    """Write samples as they come — ``windows`` yields (m, accel float32 [T, 3], road [T] or None) in order
    m = 0.. M-1 — into a schema-2 file with ``layout``'s attributes, profile_id and t_start; atomically (a
    temporary file renamed when complete, removed on any error). Memory: ``slab`` samples at a time.

    Through a guarded file (data/h5file.py): a full disk is one DatasetError naming the file, never HDF5's
    segfault. A stop request (Ctrl-C, SIGTERM) waits for the h5py call it interrupts (interrupt.deferred
    around each write, not around the whole file: the samples may come from a pass over an hour's CSV)."""
    output = Path(output)
    tmp = _temporary(output, overwrite, split)
    guard = None
    try:
        with deferred(raise_on_exit=False):  # a stop request here is raised at the first slab's check_stop
            handle, guard = open_guarded(tmp)
        try:
            _write_slabs(handle, guard, output, layout, windows, split, source, created_by, attrs, slab)
        finally:
            with deferred(raise_on_exit=False):  # a stop request during the close: raised below
                handle.close()
                guard.close()
        check_stop()
        raise_if_failed(guard, output)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; a dataset is meant to be shared
        os.replace(tmp, output)
        forget(tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        forget(tmp)
        if guard is not None:
            raise_if_failed(guard, output)  # a full disk is the cause of whatever HDF5 raised
        raise
    return output


def _write_slabs(handle, guard, output: Path, layout, windows, split, source, created_by, attrs, slab: int) -> None:
    """write_windows' body: the datasets created, then the samples written ``slab`` at a time (each h5py
    call under interrupt.deferred; the disk checked after each slab: a full one stops the import now)."""
    M, T = layout.n_samples, layout.n_steps
    with deferred():
        handle.attrs.update(_file_attrs(layout, source, created_by, attrs))
        group = handle.create_group(split)
        rows = max(1, min(M, (1 << 20) // max(1, T * 12)))  # about 1 MiB per chunk
        gz = {"compression": "gzip", "compression_opts": 1} if M > 0 else {}
        accel = group.create_dataset(
            "accel", shape=(M, T, 3), dtype=np.float32, chunks=(rows, T, 3) if M else None, **gz
        )
        road = (
            group.create_dataset("road", shape=(M, T), dtype=np.float32, chunks=(rows, T) if M else None, **gz)
            if layout.has_road
            else None
        )
        group.create_dataset("profile_id", data=layout.profile_id)
        group.create_dataset("t_start", data=np.asarray(layout.t_start, dtype=np.float64))
        if getattr(layout, "known_mass", None) is not None:
            group.create_dataset("known_mass", data=np.asarray(layout.known_mass, dtype=np.float64))
    raise_if_failed(guard, output)
    block_a = np.empty((slab, T, 3), dtype=np.float32)
    block_r = np.empty((slab, T), dtype=np.float32) if road is not None else None

    def flush(first: int, filled: int) -> None:
        check_stop()  # a stop request swallowed inside a GC callback is raised here
        with deferred():
            accel[first : first + filled] = block_a[:filled]
            if road is not None:
                road[first : first + filled] = block_r[:filled]
        raise_if_failed(guard, output)

    first, filled = 0, 0
    for m, a, r in windows:
        if m != first + filled:
            raise RecordingError(f"{output}: sample {m} arrived out of order (expected {first + filled})")
        block_a[filled] = a
        if block_r is not None:
            block_r[filled] = r
        filled += 1
        if filled == slab:
            flush(first, filled)
            first, filled = first + filled, 0
    if filled:
        flush(first, filled)
    if first + filled != M:
        raise RecordingError(f"{output}: {first + filled} of {M} samples were written")


def import_recordings(
    path: str | os.PathLike,
    output: str | os.PathLike,
    *,
    split: str = "test",
    overwrite: bool = False,
    progress: bool = False,
    **options,
) -> RecordingLayout:
    """read_recordings + write_recordings for a file of any length: two passes over the CSV (checks, then
    the samples), each window written as it is cut; memory holds the time column (16 bytes a row) and a
    block of rows, never the recording. ``options``: read_recordings' keys. Returns the layout."""
    layout = scan_recordings(path, progress=progress, **options)
    write_windows(output, layout, iter_windows(layout, progress), split=split, source=str(path), overwrite=overwrite)
    return layout


def write_recordings(
    output: str | os.PathLike,
    data: ImportedRecordings,
    split: str = "test",
    source: str = "",
    overwrite: bool = False,
    created_by: str = "qcm-import",
) -> Path:
    """Write `data` as a schema-2 dataset file, atomically (temporary file beside it, renamed when complete).

    No `physics` attribute (module docstring). dataset_writer.DatasetWriter is not used because it refuses
    non-finite values, and NaN is how a channel that was not recorded is marked.
    """
    output = Path(output)
    tmp = _temporary(output, overwrite, split)
    guard = None
    try:
        # a full disk: one DatasetError, not HDF5's segfault; Ctrl-C / SIGTERM after h5py's calls (data/h5file.py)
        with writing(tmp) as (handle, guard):
            handle.attrs.update(_file_attrs(data, source, created_by))
            group = handle.create_group(split)
            arrays = {"accel": data.accel, "profile_id": data.profile_id, "t_start": data.t_start}
            if data.road is not None:
                arrays["road"] = data.road
            if data.known_mass is not None:
                arrays["known_mass"] = np.asarray(data.known_mass, dtype=np.float64)
            for key, array in arrays.items():
                chunked = array.ndim > 1 and array.shape[0] > 0
                group.create_dataset(
                    key, data=array, compression="gzip" if chunked else None, compression_opts=1 if chunked else None
                )
        raise_if_failed(guard, output)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; a dataset is meant to be shared
        os.replace(tmp, output)
        forget(tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        forget(tmp)
        if guard is not None:
            raise_if_failed(guard, output)  # a full disk is the cause of whatever HDF5 raised
        raise
    return output
