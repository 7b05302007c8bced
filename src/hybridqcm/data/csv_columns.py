"""A CSV recording's columns: units, delimiter, which column is which channel, cells to floats, the time column.

Shared by qcm-import's reader (data/importer.py) and the two-logger reader (data/logger_csv.py). Every
error is a one-line RecordingError naming the file, the column and the row (1-based data row, with the
file's line number beside it: the header is line 1).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from hybridqcm.data import csv_stream
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.physics.parameters import CHANNELS

STANDARD_GRAVITY = 9.80665  # m/s² per g (CGPM 1901, exact by definition)
ROAD = "road"
KNOWN_MASS = "known_mass"  # kg on the seat, one value per sample (qcm-calibrate's drives with known loads)
UNITS = {"m/s2": 1.0, "m/s^2": 1.0, "m/s²": 1.0, "g": STANDARD_GRAVITY}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
DEFAULT_TIME_COLUMNS = ("t", "time")
DELIMITERS = (",", ";", "\t")


def row_label(row: int) -> str:
    return f"row {row} (line {row + 1})"


def unit_factor(path: Path, column: str, channel: str, unit, key: str) -> float:
    if str(unit).strip() not in UNITS:
        raise RecordingError(
            f"{path}: column {column!r} ({channel}), header line 1: unknown unit {key} = {unit!r}; "
            f"use one of {sorted(set(UNITS) - {'m/s^2', 'm/s²'})}"
        )
    return UNITS[str(unit).strip()]
    return UNITS[key]


def sniff_delimiter(header_line: str) -> str:
    found = [d for d in DELIMITERS if d in header_line]
    if len(found) > 1:
        # the delimiter is the one that splits the header into the most fields
        found.sort(key=lambda d: -header_line.count(d))
    return found[0] if found else ","


def resolve_columns(
    path: Path,
    header: Sequence[str],
    columns: Mapping[str, str | None] | None,
    time_column: str | None,
    recording_column: str | None,
) -> tuple[str, dict[str, str]]:
    """(time column name, {channel or 'road': CSV column name}) for the columns to import."""
    present = set(header)
    columns = dict(columns or {})
    unknown = sorted(set(columns) - set(CHANNELS) - {ROAD, KNOWN_MASS})
    if unknown:
        raise RecordingError(
            f"{path}: columns.{unknown[0]} is not a channel; map a3, a2, a1, road or known_mass to a CSV column"
        )
    if time_column is None:
        time_column = next((name for name in DEFAULT_TIME_COLUMNS if name in present), None)
        if time_column is None:
            raise RecordingError(
                f"{path}: column 't' or 'time' (the time column) is missing from the header (line 1) "
                f"{list(header)}; name yours with time_column=NAME"
            )
    elif time_column not in present:
        raise RecordingError(
            f"{path}: column {time_column!r} (time_column) is missing from the header (line 1) {list(header)}"
        )
    mapping: dict[str, str] = {}
    for key in (*CHANNELS, ROAD, KNOWN_MASS):
        if key in columns:
            name = columns[key]
            if name is None:  # not named: the column of the channel's own name, when present
                if key in present:
                    mapping[key] = key
                continue
            if name is False or str(name) == "":
                continue  # explicitly not imported
            name = str(name)
            if name not in present:
                raise RecordingError(
                    f"{path}: column {name!r} (columns.{key}) is missing from the header (line 1) {list(header)}"
                )
            mapping[key] = name
        elif key in present:
            mapping[key] = key
    if not any(key in mapping for key in CHANNELS):
        raise RecordingError(
            f"{path}: no acceleration column: none of a3, a2, a1 in the header (line 1) {list(header)}; "
            f"map yours with columns.a3=NAME, columns.a2=NAME, columns.a1=NAME"
        )
    used = [time_column, *mapping.values()]
    if recording_column is not None:
        if recording_column not in present:
            raise RecordingError(
                f"{path}: column {recording_column!r} (recording_column) is missing from the header (line 1) {list(header)}"
            )
        used.append(recording_column)
    duplicated = sorted({name for name in used if used.count(name) > 1})
    if duplicated:
        raise RecordingError(
            f"{path}: column {duplicated[0]!r} is mapped to more than one role (time, a3, a2, a1, road, known_mass, recording)"
        )
    return time_column, mapping


def to_float(path: Path, name: str, cells: list[str], data_rows: np.ndarray, finite: bool = True) -> np.ndarray:
    """Cells of one column as float64; a non-numeric, empty, NaN or infinite cell is an error naming its row."""
    try:
        values = np.asarray(cells, dtype=str).astype(np.float64)
    except ValueError:
        values = None
        for i, cell in enumerate(cells):
            try:
                float(cell)
            except ValueError:
                what = "is empty" if cell.strip() == "" else f"= {cell!r} is not a number"
                raise RecordingError(f"{path}: column {name!r}, {row_label(int(data_rows[i]))}: cell {what}") from None
    if finite:
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            i = int(bad[0])
            raise RecordingError(
                f"{path}: column {name!r}, {row_label(int(data_rows[i]))}: cell = {cells[i].strip()!r} "
                f"(NaN or infinite values are not allowed in a recorded column)"
            )
    return values


def check_time(
    path: Path, name: str, t: np.ndarray, rows: np.ndarray, label: str, gap_factor: float, rate_tolerance: float
) -> float:
    """The sampling period of one recording's time column t [n] (seconds) after the checks.

    Checks, in this order: strictly increasing; no step above gap_factor x the median step
    (a gap: lost samples); every step within rate_tolerance x h of the mean step h (a constant
    rate: a jittery or drifting clock is a different discretisation). Returns h = (t[-1] - t[0]) / (n - 1).
    """
    if t.size < 2:
        raise RecordingError(
            f"{path}: column {name!r}{label}: {t.size} row(s) at {row_label(int(rows[0]))}; "
            f"a recording needs at least 2 rows to have a rate"
        )
    steps = np.diff(t)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        k = int(back[0])
        typical = (t[k] - t[0]) / k if k > 0 else 0.0
        restart = ""
        if typical > 0 and t[k] - t[k + 1] > 10 * typical:  # far back, not a jittered or repeated stamp
            restart = (
                f"; the clock restarted here (to {t[k + 1] - t[0]:+.6g} s from the first row): "
                f"several recordings in one file? give each its id with recording_column=NAME"
            )
        raise RecordingError(
            f"{path}: column {name!r}{label}, {row_label(int(rows[k + 1]))}: time {t[k + 1]:.9g} s is not after "
            f"the previous row's {t[k]:.9g} s (time must be strictly increasing){restart}"
        )
    median = float(np.median(steps))
    gaps = np.flatnonzero(steps > gap_factor * median)
    if gaps.size:
        k = int(gaps[0])
        raise RecordingError(
            f"{path}: column {name!r}{label}, {row_label(int(rows[k + 1]))}: gap of {steps[k]:.6g} s after "
            f"t = {t[k]:.9g} s (more than {gap_factor:g} x the median step {median:.6g} s: samples are missing)"
        )
    h = float((t[-1] - t[0]) / (t.size - 1))
    jitter = np.abs(steps - h) / h
    off = np.flatnonzero(jitter > rate_tolerance)
    if off.size:
        k = int(off[0])
        raise RecordingError(
            f"{path}: column {name!r}{label}, {row_label(int(rows[k + 1]))}: step {steps[k]:.6g} s differs from "
            f"the mean step {h:.6g} s by {jitter[k]:.2g} x h > rate_tolerance = {rate_tolerance:g} "
            f"(the rate is not constant; or the time is printed with too few digits)"
        )
    return h


def progress_bar(enabled: bool):
    """A byte-count progress bar for a pass over the file (rich; nothing when disabled)."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

    columns = (TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn())
    return Progress(*columns, TimeRemainingColumn(), disable=not enabled, transient=False)


def read_blocks(path: Path, header, sep: str, wanted, encoding: str, on_short_row=None):
    """csv_stream.iter_blocks with its row errors as RecordingError (one line naming the file and row)."""
    try:
        yield from csv_stream.iter_blocks(path, header, sep, wanted, encoding=encoding, on_short_row=on_short_row)
    except csv_stream.CsvStreamError as error:
        raise RecordingError(str(error)) from None


def column_floats(path: Path, name: str, block: csv_stream.Block) -> np.ndarray:
    """One block's cells of a column as float64: pyarrow's parser, and the exact one-line error of
    :func:`to_float` (naming the cell) for a block it cannot parse or that holds NaN/inf (a stray quote's
    swallowed lines named where the quote opens: Block.explain)."""
    cells = block.cells[name]
    values = csv_stream.to_float64(cells)
    if values is None or not np.isfinite(values).all():
        if values is None:
            block.explain(name)
        values = to_float(path, name, csv_stream.strings(cells), block.rows)
    return values


def short_row_error(path: Path, header: Sequence[str], wanted: Sequence[str]):
    def error(row: int, fields: int) -> RecordingError:
        missing = next((n for n in header[fields:] if n in wanted), header[fields] if fields < len(header) else "?")
        return RecordingError(
            f"{path}: column {missing!r}, {row_label(row)}: cell is empty (the row has {fields} of {len(header)} fields)"
        )

    return error
