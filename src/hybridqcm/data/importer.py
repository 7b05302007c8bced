"""Recordings from a user's logger (CSV) into the dataset layout (SPEC §5, § 9).

A CSV recording has a header line and one row per sample:

    t,a3,a2[,a1][,road][,known_mass][,recording]    time in seconds, accelerations in m/s² or g, road in metres,
                                                     known_mass in kg

Any subset of the acceleration channels a3 (seat / occupant), a2 (chassis / seat base) and
a1 (wheel) may be present, under the user's own names (`columns={"a3": "seat_z"}`). The rate
may be anything, but it must be constant: the estimator's model is a discretisation with one
step h (SPEC § 9), so a gap or a jittery clock would silently become a different vehicle.

The result is in the layout of hdf5.py with the leading sample axis M:

    accel      float32 [M, T, 3]  (a3, a2, a1) in m/s², NaN in channels that were not recorded
    road       float32 [M, T]     u in metres, only when the CSV has a road column
    known_mass float64 [M]        kg, the known load on the seat (qcm-calibrate), only when the CSV has a
                                  known_mass column; constant within each sample, >= 0 and finite
    profile_id int32   [M]        index of the recording a sample was cut from (windows of one drive share a road)
    t_start    float64 [M]        the CSV time of each sample's first step [s]

M is the number of recordings (`recording_column`), or of windows of `window` steps taken every
`stride` steps from each recording. No params: a real recording has none. Files carry no
`physics` attribute: a recording is continuous-time physics with an unknown initial state,
which is what readers assume for files without one.

Every error is one line naming the file, the column and the row: the row is the 1-based data
row, and the line number in the file (the header is line 1) is given beside it.

Reading streams (an hour at 1 kHz is 3.6 million rows): :func:`scan_recordings` passes over the file
once for the time column and the recording ids (pyarrow's streaming reader, data/csv_stream.py; kept:
16 bytes a row) and makes every check, :func:`iter_windows` passes again and yields the samples one by
one; :func:`import_recordings` writes them to the file as they come (:func:`write_windows`), and
:func:`read_recordings` collects them in memory (small files, tests). Two loggers with their own clocks
(a seat and a floor recording): data/two_loggers.py.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridqcm.data import csv_checks, csv_stream
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.h5file import open_guarded, raise_if_failed, writing
from hybridqcm.interrupt import check_stop, deferred
from hybridqcm.physics.parameters import CHANNELS

SCHEMA_V2 = "hybridqcm.dataset/2"
STANDARD_GRAVITY = 9.80665  # m/s² per g (CGPM 1901, exact by definition)
ROAD = "road"
KNOWN_MASS = "known_mass"  # kg on the seat, one value per sample (qcm-calibrate's drives with known loads)
UNITS = {"m/s2": 1.0, "m/s^2": 1.0, "m/s²": 1.0, "g": STANDARD_GRAVITY}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
DEFAULT_TIME_COLUMNS = ("t", "time")
DELIMITERS = (",", ";", "\t")


@dataclass
class ImportedRecordings:
    """Arrays in the dataset layout plus what the summary and the file attributes need."""

    accel: np.ndarray  # float32 [M, T, 3], m/s², NaN where not recorded
    road: np.ndarray | None  # float32 [M, T] metres, or None
    known_mass: np.ndarray | None  # float64 [M] kg, or None
    profile_id: np.ndarray  # int32 [M]
    t_start: np.ndarray  # float64 [M] seconds
    h: float  # sampling period [s]
    channels: tuple[str, ...]  # recorded acceleration channels, in (a3, a2, a1) order
    source_columns: dict[str, str]  # channel (and road) -> CSV column name
    source_units: dict[str, str]  # channel -> unit in the CSV
    recordings: list[str]  # recording ids in order of appearance
    rows: list[int]  # data rows per recording
    window: int | None = None
    stride: int | None = None

    @property
    def n_samples(self) -> int:
        return int(self.accel.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.accel.shape[1])


def _where(row: int) -> str:
    return f"row {row} (line {row + 1})"


def _unit_factor(path: Path, column: str, channel: str, unit, key: str) -> float:
    if str(unit).strip() not in UNITS:
        raise RecordingError(
            f"{path}: column {column!r} ({channel}), header line 1: unknown unit {key} = {unit!r}; "
            f"use one of {sorted(set(UNITS) - {'m/s^2', 'm/s²'})}"
        )
    return UNITS[str(unit).strip()]
    return UNITS[key]


def _sniff_delimiter(header_line: str) -> str:
    found = [d for d in DELIMITERS if d in header_line]
    if len(found) > 1:
        # the delimiter is the one that splits the header into the most fields
        found.sort(key=lambda d: -header_line.count(d))
    return found[0] if found else ","


def _resolve_columns(
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


def _to_float(path: Path, name: str, cells: list[str], data_rows: np.ndarray, finite: bool = True) -> np.ndarray:
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
                raise RecordingError(f"{path}: column {name!r}, {_where(int(data_rows[i]))}: cell {what}") from None
    if finite:
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            i = int(bad[0])
            raise RecordingError(
                f"{path}: column {name!r}, {_where(int(data_rows[i]))}: cell = {cells[i].strip()!r} "
                f"(NaN or infinite values are not allowed in a recorded column)"
            )
    return values


def _check_time(
    path: Path, name: str, t: np.ndarray, rows: np.ndarray, label: str, gap_factor: float, rate_tolerance: float
) -> float:
    """The sampling period of one recording's time column t [n] (seconds) after the checks.

    Checks, in this order: strictly increasing; no step above gap_factor x the median step
    (a gap: lost samples); every step within rate_tolerance x h of the mean step h (a constant
    rate: a jittery or drifting clock is a different discretisation). Returns h = (t[-1] - t[0]) / (n - 1).
    """
    if t.size < 2:
        raise RecordingError(
            f"{path}: column {name!r}{label}: {t.size} row(s) at {_where(int(rows[0]))}; "
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
            f"{path}: column {name!r}{label}, {_where(int(rows[k + 1]))}: time {t[k + 1]:.9g} s is not after "
            f"the previous row's {t[k]:.9g} s (time must be strictly increasing){restart}"
        )
    median = float(np.median(steps))
    gaps = np.flatnonzero(steps > gap_factor * median)
    if gaps.size:
        k = int(gaps[0])
        raise RecordingError(
            f"{path}: column {name!r}{label}, {_where(int(rows[k + 1]))}: gap of {steps[k]:.6g} s after "
            f"t = {t[k]:.9g} s (more than {gap_factor:g} x the median step {median:.6g} s: samples are missing)"
        )
    h = float((t[-1] - t[0]) / (t.size - 1))
    jitter = np.abs(steps - h) / h
    off = np.flatnonzero(jitter > rate_tolerance)
    if off.size:
        k = int(off[0])
        raise RecordingError(
            f"{path}: column {name!r}{label}, {_where(int(rows[k + 1]))}: step {steps[k]:.6g} s differs from "
            f"the mean step {h:.6g} s by {jitter[k]:.2g} x h > rate_tolerance = {rate_tolerance:g} "
            f"(the rate is not constant; or the time is printed with too few digits)"
        )
    return h


@dataclass
class RecordingLayout:
    """What the first pass over a CSV found (time column, recordings, rate, windows): everything but the
    accelerations, which the second pass streams window after window (:func:`iter_windows`)."""

    path: Path
    header: list[str]
    sep: str
    encoding: str  # csv_checks.text_encoding's
    time_name: str
    mapping: dict[str, str]  # channel (and road) -> CSV column
    factors: dict[str, float]  # channel -> unit factor to m/s²
    cuts: list[tuple[int, int, int]]  # (recording, first data index, length) of every sample, in data order
    t_start: np.ndarray  # float64 [M] the CSV time of each sample's first step [s]
    h: float
    n_steps: int
    channels: tuple[str, ...]
    source_columns: dict[str, str]
    source_units: dict[str, str]
    recordings: list[str]
    rows: list[int]  # data rows per recording
    n_rows: int
    window: int | None
    stride: int | None
    file_bytes: int
    known_mass: np.ndarray | None = None  # float64 [M] kg, or None (no known_mass column)

    @property
    def n_samples(self) -> int:
        return len(self.cuts)

    @property
    def profile_id(self) -> np.ndarray:
        return np.asarray([r for r, _, _ in self.cuts], dtype=np.int32)

    @property
    def has_road(self) -> bool:
        return ROAD in self.mapping


def _progress(enabled: bool):
    """A byte-count progress bar for a pass over the file (rich; nothing when disabled)."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

    columns = (TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn())
    return Progress(*columns, TimeRemainingColumn(), disable=not enabled, transient=False)


def _blocks(path: Path, header, sep: str, wanted, encoding: str, on_short_row=None):
    """csv_stream.iter_blocks with its row errors as RecordingError (one line naming the file and row)."""
    try:
        yield from csv_stream.iter_blocks(path, header, sep, wanted, encoding=encoding, on_short_row=on_short_row)
    except csv_stream.CsvStreamError as error:
        raise RecordingError(str(error)) from None


def _floats(path: Path, name: str, block: csv_stream.Block) -> np.ndarray:
    """One block's cells of a column as float64: pyarrow's parser, and the exact one-line error of
    :func:`_to_float` (naming the cell) for a block it cannot parse or that holds NaN/inf (a stray quote's
    swallowed lines named where the quote opens: Block.explain)."""
    cells = block.cells[name]
    values = csv_stream.to_float64(cells)
    if values is None or not np.isfinite(values).all():
        if values is None:
            block.explain(name)
        values = _to_float(path, name, csv_stream.strings(cells), block.rows)
    return values


def _short_row(path: Path, header: Sequence[str], wanted: Sequence[str]):
    def error(row: int, fields: int) -> RecordingError:
        missing = next((n for n in header[fields:] if n in wanted), header[fields] if fields < len(header) else "?")
        return RecordingError(
            f"{path}: column {missing!r}, {_where(row)}: cell is empty (the row has {fields} of {len(header)} fields)"
        )

    return error


def scan_recordings(
    path: str | os.PathLike,
    *,
    units: str = "m/s2",
    column_units: Mapping[str, str] | None = None,
    columns: Mapping[str, str | None] | None = None,
    time_column: str | None = None,
    time_unit: str = "s",
    recording_column: str | None = None,
    window: int | None = None,
    stride: int | None = None,
    rate_tolerance: float = 1e-3,
    gap_factor: float = 1.5,
    delimiter: str | None = None,
    rate_range: Sequence[float] = csv_checks.RATE_RANGE,
    progress: bool = False,
) -> RecordingLayout:
    """First pass (read_recordings' keys): the header, units, the time column and recording ids streamed
    (csv_stream: 16 bytes a row kept, the time and its row number), every time check, the rate and the
    samples to cut. Raises RecordingError (one line naming the file, column and row)."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: input CSV does not exist")
    if time_unit not in TIME_UNITS:
        raise RecordingError(f"{path}: time_unit = {time_unit!r} is not supported; use one of {list(TIME_UNITS)}")
    if not (rate_tolerance > 0 and gap_factor > 1):
        raise RecordingError(
            f"{path}: rate_tolerance must be > 0 and gap_factor > 1, got {rate_tolerance} and {gap_factor}"
        )
    if window is not None and int(window) < 2:
        raise RecordingError(f"{path}: window must be >= 2 samples, got {window}")
    if stride is not None and (window is None or int(stride) < 1):
        raise RecordingError(f"{path}: stride = {stride} needs window=N and must be >= 1")
    column_units = {c: u for c, u in dict(column_units or {}).items() if u is not None}
    unknown = sorted(set(column_units) - set(CHANNELS))
    if unknown:
        raise RecordingError(f"{path}: column_units.{unknown[0]} is not an acceleration channel (a3, a2, a1)")

    encoding = csv_checks.text_encoding(path)
    with open(path, newline="", encoding=encoding) as handle:
        first = handle.readline()
    if not first.strip():
        raise RecordingError(f"{path}: line 1 is empty; the first line must be the header (e.g. t,a3,a2)")
    csv_checks.check_header_line(path, first)
    sep = delimiter or _sniff_delimiter(first)
    header = [name.strip() for name in next(csv.reader([first], delimiter=sep))]
    time_name, mapping = _resolve_columns(path, header, columns, time_column, recording_column)
    factors = {
        c: _unit_factor(
            path, mapping[c], c, column_units.get(c, units), f"column_units.{c}" if c in column_units else "units"
        )
        for c in CHANNELS
        if c in mapping
    }
    wanted = [time_name, *mapping.values()] + ([recording_column] if recording_column else [])
    csv_checks.check_header(path, header, wanted)
    size = path.stat().st_size

    # pass 1: time and recording ids only (and where the known load changes: its value kept at those rows only)
    times, row_parts = [], []
    load_name = mapping.get(KNOWN_MASS)
    load_at: list[int] = []  # data index where the known load takes a new value
    load_value: list[float] = []  # that value [kg]
    names: list[str] = []
    starts: list[int] = []
    seen: set[str] = set()
    count, last_id = 0, None
    with _progress(progress) as bar:
        task = bar.add_task(f"checking {path.name}", total=size)
        for block in _blocks(path, header, sep, wanted, encoding, _short_row(path, header, wanted)):
            times.append(_floats(path, time_name, block) * TIME_UNITS[time_unit])
            row_parts.append(block.rows)
            if load_name is not None:
                load = _floats(path, load_name, block)  # finite, or a one-line error naming the cell
                negative = np.flatnonzero(load < 0)
                if negative.size:
                    i = int(negative[0])
                    raise RecordingError(
                        f"{path}: column {load_name!r} (known_mass), {_where(int(block.rows[i]))}: "
                        f"{float(load[i])!r} kg is negative (the known load on the seat is >= 0 kg)"
                    )
                change = np.flatnonzero(load[1:] != load[:-1]) + 1
                firsts = ([0] if not load_value or load[0] != load_value[-1] else []) + change.tolist()
                load_at.extend(count + i for i in firsts)
                load_value.extend(float(load[i]) for i in firsts)
            if recording_column:
                block.explain(recording_column)  # an id is used as text: no parse failure would show a quote
                ids = np.asarray([c.strip() for c in csv_stream.strings(block.cells[recording_column])], dtype=object)
                empty = np.flatnonzero(ids == "")
                if empty.size:
                    raise RecordingError(
                        f"{path}: column {recording_column!r}, {_where(int(block.rows[empty[0]]))}: cell is empty"
                    )
                change = np.flatnonzero(ids[1:] != ids[:-1]) + 1
                firsts = ([0] if ids[0] != last_id else []) + change.tolist()
                for i in firsts:
                    name = str(ids[i])
                    if name in seen:
                        raise RecordingError(
                            f"{path}: column {recording_column!r}, {_where(int(block.rows[i]))}: recording {name!r} "
                            f"appears again after other recordings (keep each recording's rows together)"
                        )
                    seen.add(name)
                    names.append(name)
                    starts.append(count + i)
                last_id = ids[-1]
            count += block.rows.size
            bar.update(task, completed=block.bytes_read)
    if not count:
        raise RecordingError(f"{path}: column {time_name!r}: no data rows after the header")
    t_all = np.concatenate(times)
    rows = np.concatenate(row_parts)
    del times, row_parts
    if not recording_column:
        names, starts = [path.stem], [0]
    blocks = list(zip(starts, starts[1:] + [count]))

    hs = []
    for name, (a, b) in zip(names, blocks):
        label = f" (recording {name!r})" if recording_column else ""
        hs.append(_check_time(path, time_name, t_all[a:b], rows[a:b], label, gap_factor, rate_tolerance))
    h = float(np.mean(hs))
    csv_checks.check_rate(path, time_name, h, time_unit, TIME_UNITS, rate_range)
    for name, (a, _), h_i in zip(names, blocks, hs):
        if abs(h_i - h) > rate_tolerance * h:
            raise RecordingError(
                f"{path}: column {time_name!r} (recording {name!r}), {_where(int(rows[a]))}: step {h_i:.6g} s "
                f"differs from the file's mean step {h:.6g} s (one file holds one rate)"
            )

    lengths = [b - a for a, b in blocks]
    if window is None:
        if len(set(lengths)) > 1:
            raise RecordingError(
                f"{path}: column {recording_column!r}: recordings have different lengths "
                f"({dict(zip(names, lengths))}); cut them into equal samples with window=N"
            )
        cuts = [(r, a, lengths[0]) for r, (a, _) in enumerate(blocks)]
        n_steps = lengths[0]
    else:
        window = int(window)
        stride = int(stride) if stride is not None else window
        cuts = []
        for r, ((a, b), name) in enumerate(zip(blocks, names)):
            if b - a < window:
                label = f" (recording {name!r})" if recording_column else ""
                raise RecordingError(
                    f"{path}: column {time_name!r}{label}, {_where(int(rows[a]))}: {b - a} rows, "
                    f"fewer than window = {window} (the drive is shorter than one window)"
                )
            cuts.extend((r, start, window) for start in range(a, b - window + 1, stride))
        n_steps = window
    known_mass = None
    if load_name is not None:
        known_mass = _known_mass(path, load_name, cuts, names, rows, np.asarray(load_at), np.asarray(load_value))
    channels = tuple(c for c in CHANNELS if c in mapping)
    return RecordingLayout(
        path=path,
        header=header,
        sep=sep,
        encoding=encoding,
        time_name=time_name,
        mapping=mapping,
        factors=factors,
        cuts=cuts,
        t_start=np.asarray([t_all[start] for _, start, _ in cuts], dtype=np.float64),
        h=h,
        n_steps=n_steps,
        channels=channels,
        source_columns={"time": time_name, **mapping},
        source_units={c: str(column_units.get(c, units)).strip() for c in channels},
        recordings=list(names),
        rows=lengths,
        n_rows=int(count),
        window=window,
        stride=stride if window is not None else None,
        file_bytes=size,
        known_mass=known_mass,
    )


def _known_mass(
    path: Path, name: str, cuts, names: list[str], rows: np.ndarray, at: np.ndarray, value: np.ndarray
) -> np.ndarray:
    """Each sample's known load float64 [M] kg from the rows ``at`` [k] where the column takes a new ``value`` [k]
    (at[0] = 0); a load that changes inside a sample is an error naming the row where it changes."""
    out = np.empty(len(cuts), dtype=np.float64)
    for m, (r, start, length) in enumerate(cuts):
        k = int(np.searchsorted(at, start, side="right")) - 1
        if k + 1 < at.size and at[k + 1] < start + length:
            i = int(at[k + 1])
            raise RecordingError(
                f"{path}: column {name!r} (known_mass), {_where(int(rows[i]))}: the known load changes from "
                f"{float(value[k])!r} to {float(value[k + 1])!r} kg inside a sample of recording {names[r]!r} starting at "
                f"{_where(int(rows[start]))}; keep it constant within each recording or window"
            )
        out[m] = value[k]
    return out


def iter_windows(layout: RecordingLayout, progress: bool = False):
    """Second pass: (sample m, accel float32 [T, 3] in m/s² with NaN where not recorded, road float32 [T] or
    None) for every sample of ``layout`` in order, the file streamed again; memory holds one window and one
    block of rows."""
    path = layout.path
    keys = [k for k in (*CHANNELS, ROAD) if k in layout.mapping]
    wanted = [layout.mapping[k] for k in keys]
    buffer = np.empty((0, len(keys)), dtype=np.float64)
    buffer_start = 0  # data index of buffer[0]
    m = 0
    cuts = layout.cuts
    with _progress(progress) as bar:
        task = bar.add_task(f"cutting {path.name}", total=layout.file_bytes)
        for block in _blocks(path, layout.header, layout.sep, wanted, layout.encoding):
            columns = []
            for key, name in zip(keys, wanted):
                raw = _floats(path, name, block)
                factor = layout.factors.get(key, 1.0)
                csv_checks.check_float32(path, name, raw, factor, block.rows)  # else stored as inf
                columns.append(raw * factor)
            values = np.stack(columns, axis=1)
            buffer = np.concatenate([buffer, values]) if buffer.size else values
            end = buffer_start + buffer.shape[0]
            while m < len(cuts) and cuts[m][1] + cuts[m][2] <= end:
                _, start, length = cuts[m]
                piece = buffer[start - buffer_start : start - buffer_start + length]
                accel = np.full((length, 3), np.nan, dtype=np.float32)
                for j, key in enumerate(keys):
                    if key in CHANNELS:
                        accel[:, CHANNELS.index(key)] = piece[:, j]
                road = piece[:, keys.index(ROAD)].astype(np.float32) if ROAD in keys else None
                yield m, accel, road
                m += 1
            keep_from = min(cuts[m][1] if m < len(cuts) else end, end)  # rows not yet read cannot be dropped
            buffer = buffer[keep_from - buffer_start :]
            buffer_start = keep_from
            bar.update(task, completed=block.bytes_read)
    if m != len(cuts):
        raise RecordingError(f"{path}: the file changed while it was read ({m} of {len(cuts)} samples found)")


def read_recordings(
    path: str | os.PathLike,
    *,
    units: str = "m/s2",
    column_units: Mapping[str, str] | None = None,
    columns: Mapping[str, str | None] | None = None,
    time_column: str | None = None,
    time_unit: str = "s",
    recording_column: str | None = None,
    window: int | None = None,
    stride: int | None = None,
    rate_tolerance: float = 1e-3,
    gap_factor: float = 1.5,
    delimiter: str | None = None,
    rate_range: Sequence[float] = csv_checks.RATE_RANGE,
) -> ImportedRecordings:
    """Read a CSV recording into the dataset layout (module docstring) in memory; raises RecordingError.

    units: the accelerations' unit in the file, "m/s2" or "g" (1 g = 9.80665 m/s²);
    column_units: per-channel overrides, e.g. {"a2": "m/s2"}. columns: channel -> CSV column
    name (a channel not named there is taken from a column of its own name when present; None
    skips it). recording_column: several recordings, one id per row, each in one block of rows.
    window, stride: cut every recording into samples of `window` steps starting every `stride`
    (default: window) steps; without a window every recording is one sample and all must have
    the same length. rate_range: the sampling rates [Hz] accepted (csv_checks.check_rate). For a long
    recording write it with :func:`import_recordings` (streamed).
    """
    layout = scan_recordings(
        path,
        units=units,
        column_units=column_units,
        columns=columns,
        time_column=time_column,
        time_unit=time_unit,
        recording_column=recording_column,
        window=window,
        stride=stride,
        rate_tolerance=rate_tolerance,
        gap_factor=gap_factor,
        delimiter=delimiter,
        rate_range=rate_range,
    )
    accel = np.full((layout.n_samples, layout.n_steps, 3), np.nan, dtype=np.float32)
    road = np.empty((layout.n_samples, layout.n_steps), dtype=np.float32) if layout.has_road else None
    for m, a, r in iter_windows(layout):
        accel[m] = a
        if road is not None:
            road[m] = r
    return ImportedRecordings(
        accel=accel,
        road=road,
        known_mass=layout.known_mass,
        profile_id=layout.profile_id,
        t_start=layout.t_start,
        h=layout.h,
        channels=layout.channels,
        source_columns=layout.source_columns,
        source_units=layout.source_units,
        recordings=layout.recordings,
        rows=layout.rows,
        window=layout.window,
        stride=layout.stride,
    )


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
    fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent)
    os.close(fd)
    return Path(tmp)


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
    except BaseException:
        tmp.unlink(missing_ok=True)
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

    No `physics` attribute (module docstring). DatasetWriter is not used because it refuses
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
    except BaseException:
        tmp.unlink(missing_ok=True)
        if guard is not None:
            raise_if_failed(guard, output)  # a full disk is the cause of whatever HDF5 raised
        raise
    return output


# --------------------------------------------------------------------------------------------------
# A stand-alone three-axis logger (a phone app): its own clock, gravity included (data/two_loggers.py)
AXIS_PREFIXES = ("", "a", "acc", "accel", "acceleration", "linear acceleration", "accelerometer")


@dataclass
class LoggerRecording:
    """One three-axis logger's recording: t float64 [n] in its own clock [s] (irregular), xyz float64 [n, 3]
    in m/s² with gravity, the columns read and the file."""

    path: Path
    t: np.ndarray
    xyz: np.ndarray
    columns: dict[str, str]
    unit: str

    @property
    def rate_hz(self) -> float:
        """The mean rate from every sample's own time stamp: (n - 1) / (t_last - t_first)."""
        return float((self.t.size - 1) / (self.t[-1] - self.t[0]))


def _axis_columns(path: Path, header: Sequence[str], axes: Sequence[str] | None, key: str) -> list[str]:
    """The x, y, z columns: named (``axes``), else found by name: x/y/z alone or after a prefix such as
    "acc" or "Acceleration", units in brackets ignored (`Acceleration x (m/s^2)`, `accX`, `az`)."""
    if axes is not None:
        axes = [str(a) for a in axes]
        if len(axes) != 3:
            raise RecordingError(f"{path}: {key} = {axes}: give the three axis columns [x, y, z]")
        for a in axes:
            if a not in header:
                raise RecordingError(f"{path}: column {a!r} ({key}) is missing from the header (line 1) {list(header)}")
        return axes
    import re

    found: dict[str, str] = {}
    for name in header:
        plain = re.sub(r"\(.*?\)|\[.*?\]", "", name).strip().lower()
        plain = re.sub(r"[\s_:\-]+", " ", plain).strip()
        if plain and plain[-1] in "xyz" and plain[:-1].strip() in AXIS_PREFIXES:
            found.setdefault(plain[-1], name)
    if len(found) != 3:
        raise RecordingError(
            f"{path}: three acceleration axes (x, y, z) not found in the header (line 1) {list(header)}; "
            f"name them with {key}=[X,Y,Z]"
        )
    return [found["x"], found["y"], found["z"]]


def read_logger(
    path: str | os.PathLike,
    *,
    axes: Sequence[str] | None = None,
    axes_key: str = "axes",
    time_column: str | None = None,
    time_unit: str = "s",
    units: str = "m/s2",
    gap_factor: float = 1.5,
    delimiter: str | None = None,
    rate_range: Sequence[float] = csv_checks.RATE_RANGE,
    progress: bool = False,
) -> LoggerRecording:
    """A logger's CSV: a time column and three acceleration axes with gravity (a phone app's
    `Time (s),Acceleration x (m/s^2),...`). Sample times may be irregular (each row keeps its own stamp:
    the rate is not checked for constancy), but must increase, without gaps above gap_factor x the
    median step; the mean rate within rate_range [Hz]. Streamed in blocks; kept: 32 bytes a row. The text
    checks of data/csv_checks.py as for read_recordings. Raises RecordingError (one line)."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: input CSV does not exist")
    if time_unit not in TIME_UNITS:
        raise RecordingError(f"{path}: time_unit = {time_unit!r} is not supported; use one of {list(TIME_UNITS)}")
    encoding = csv_checks.text_encoding(path)
    with open(path, newline="", encoding=encoding) as handle:
        first = handle.readline()
    if not first.strip():
        raise RecordingError(f"{path}: line 1 is empty; the first line must be the header")
    csv_checks.check_header_line(path, first)
    sep = delimiter or _sniff_delimiter(first)
    header = [name.strip() for name in next(csv.reader([first], delimiter=sep))]
    if time_column is None:
        time_column = next((n for n in header if n.lower() in DEFAULT_TIME_COLUMNS), None)
        time_column = time_column or next((n for n in header if n.lower().startswith("time")), None)
        if time_column is None:
            raise RecordingError(
                f"{path}: no time column (t, time or Time (s)) in the header (line 1) {list(header)}; "
                f"name yours with time_column=NAME"
            )
    elif time_column not in header:
        raise RecordingError(f"{path}: column {time_column!r} (time_column) is missing from the header (line 1)")
    xyz_names = _axis_columns(path, header, axes, axes_key)
    factor = _unit_factor(path, xyz_names[0], "x, y, z", units, "units")
    wanted = [time_column, *xyz_names]
    csv_checks.check_header(path, header, wanted)
    times, parts, row_parts = [], [], []
    with _progress(progress) as bar:
        task = bar.add_task(f"reading {path.name}", total=path.stat().st_size)
        for block in _blocks(path, header, sep, wanted, encoding, _short_row(path, header, wanted)):
            times.append(_floats(path, time_column, block) * TIME_UNITS[time_unit])
            xyz = np.stack([_floats(path, n, block) for n in xyz_names], 1)
            for j, n in enumerate(xyz_names):
                csv_checks.check_float32(path, n, xyz[:, j], factor, block.rows)
            parts.append(xyz * factor)
            row_parts.append(block.rows)
            bar.update(task, completed=block.bytes_read)
    if not times:
        raise RecordingError(f"{path}: column {time_column!r}: no data rows after the header")
    t, rows = np.concatenate(times), np.concatenate(row_parts)
    _check_time(path, time_column, t, rows, "", gap_factor, math.inf)
    csv_checks.check_rate(path, time_column, float((t[-1] - t[0]) / (t.size - 1)), time_unit, TIME_UNITS, rate_range)
    return LoggerRecording(
        path=path,
        t=t,
        xyz=np.concatenate(parts),
        columns={"time": time_column, "x": xyz_names[0], "y": xyz_names[1], "z": xyz_names[2]},
        unit=str(units),
    )
