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
one; data/import_writer.py writes them to the file as they come, and :func:`read_recordings` collects
them in memory (small files, tests). The columns (units, names, cells, time): data/csv_columns.py. Two
loggers with their own clocks (a seat and a floor recording): data/logger_csv.py, data/two_loggers.py.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hybridqcm.data import csv_checks, csv_stream
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.csv_columns import (
    KNOWN_MASS,
    ROAD,
    TIME_UNITS,
    check_time,
    column_floats,
    progress_bar,
    read_blocks,
    resolve_columns,
    row_label,
    short_row_error,
    sniff_delimiter,
    unit_factor,
)
from hybridqcm.physics.parameters import CHANNELS


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


def _check_options(path, time_unit, rate_tolerance, gap_factor, window, stride, column_units) -> dict[str, str]:
    """The options that need no file; returns column_units without its null entries."""
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
    return column_units


@dataclass
class _Header:
    """The header line read and checked: which column is which, the unit factors and the columns to read."""

    encoding: str
    sep: str
    header: list[str]
    time_name: str
    mapping: dict[str, str]
    factors: dict[str, float]
    wanted: list[str]


def _read_header(path, delimiter, columns, time_column, recording_column, units, column_units) -> _Header:
    encoding = csv_checks.text_encoding(path)
    with open(path, newline="", encoding=encoding) as handle:
        first = handle.readline()
    if not first.strip():
        raise RecordingError(f"{path}: line 1 is empty; the first line must be the header (e.g. t,a3,a2)")
    csv_checks.check_header_line(path, first)
    sep = delimiter or sniff_delimiter(first)
    header = [name.strip() for name in next(csv.reader([first], delimiter=sep))]
    time_name, mapping = resolve_columns(path, header, columns, time_column, recording_column)
    factors = {
        c: unit_factor(
            path, mapping[c], c, column_units.get(c, units), f"column_units.{c}" if c in column_units else "units"
        )
        for c in CHANNELS
        if c in mapping
    }
    wanted = [time_name, *mapping.values()] + ([recording_column] if recording_column else [])
    csv_checks.check_header(path, header, wanted)
    return _Header(encoding, sep, header, time_name, mapping, factors, wanted)


@dataclass
class _FirstPass:
    """Pass 1 over the rows: time [n] s and data row numbers [n], recordings (names, first data index), and
    where the known load takes a new value (data index, kg)."""

    t: np.ndarray
    rows: np.ndarray
    count: int
    names: list[str] = field(default_factory=list)
    starts: list[int] = field(default_factory=list)
    load_at: list[int] = field(default_factory=list)
    load_value: list[float] = field(default_factory=list)


def _load_changes(path: Path, name: str, block, count: int, found: _FirstPass) -> None:
    """Where a block's known load changes, appended to found.load_at / load_value (its value kept there only)."""
    load = column_floats(path, name, block)  # finite, or a one-line error naming the cell
    negative = np.flatnonzero(load < 0)
    if negative.size:
        i = int(negative[0])
        raise RecordingError(
            f"{path}: column {name!r} (known_mass), {row_label(int(block.rows[i]))}: "
            f"{float(load[i])!r} kg is negative (the known load on the seat is >= 0 kg)"
        )
    change = np.flatnonzero(load[1:] != load[:-1]) + 1
    firsts = ([0] if not found.load_value or load[0] != found.load_value[-1] else []) + change.tolist()
    found.load_at.extend(count + i for i in firsts)
    found.load_value.extend(float(load[i]) for i in firsts)


def _recording_starts(path: Path, column: str, block, count: int, last_id, seen: set[str], found: _FirstPass):
    """The recordings that start in a block, appended to found.names / starts; returns the block's last id."""
    block.explain(column)  # an id is used as text: no parse failure would show a quote
    ids = np.asarray([c.strip() for c in csv_stream.strings(block.cells[column])], dtype=object)
    empty = np.flatnonzero(ids == "")
    if empty.size:
        raise RecordingError(f"{path}: column {column!r}, {row_label(int(block.rows[empty[0]]))}: cell is empty")
    change = np.flatnonzero(ids[1:] != ids[:-1]) + 1
    firsts = ([0] if ids[0] != last_id else []) + change.tolist()
    for i in firsts:
        name = str(ids[i])
        if name in seen:
            raise RecordingError(
                f"{path}: column {column!r}, {row_label(int(block.rows[i]))}: recording {name!r} "
                f"appears again after other recordings (keep each recording's rows together)"
            )
        seen.add(name)
        found.names.append(name)
        found.starts.append(count + i)
    return ids[-1]


def _first_pass(path: Path, head: _Header, time_unit: str, recording_column: str | None, progress: bool) -> _FirstPass:
    """Time and recording ids only, streamed (and where the known load changes)."""
    times, row_parts = [], []
    found = _FirstPass(np.empty(0), np.empty(0, dtype=np.int64), 0)
    load_name = head.mapping.get(KNOWN_MASS)
    seen: set[str] = set()
    count, last_id = 0, None
    wanted = head.wanted
    with progress_bar(progress) as bar:
        task = bar.add_task(f"checking {path.name}", total=path.stat().st_size)
        blocks = read_blocks(
            path, head.header, head.sep, wanted, head.encoding, short_row_error(path, head.header, wanted)
        )
        for block in blocks:
            times.append(column_floats(path, head.time_name, block) * TIME_UNITS[time_unit])
            row_parts.append(block.rows)
            if load_name is not None:
                _load_changes(path, load_name, block, count, found)
            if recording_column:
                last_id = _recording_starts(path, recording_column, block, count, last_id, seen, found)
            count += block.rows.size
            bar.update(task, completed=block.bytes_read)
    if not count:
        raise RecordingError(f"{path}: column {head.time_name!r}: no data rows after the header")
    found.t, found.rows, found.count = np.concatenate(times), np.concatenate(row_parts), count
    if not recording_column:
        found.names, found.starts = [path.stem], [0]
    return found


def _common_step(path, time_name, found: _FirstPass, blocks, recording_column, time_unit, tolerances, rate_range):
    """Every recording's time checked (gaps, constant rate) and one step h [s] for the file."""
    gap_factor, rate_tolerance = tolerances
    hs = []
    for name, (a, b) in zip(found.names, blocks):
        label = f" (recording {name!r})" if recording_column else ""
        hs.append(check_time(path, time_name, found.t[a:b], found.rows[a:b], label, gap_factor, rate_tolerance))
    h = float(np.mean(hs))
    csv_checks.check_rate(path, time_name, h, time_unit, TIME_UNITS, rate_range)
    for name, (a, _), h_i in zip(found.names, blocks, hs):
        if abs(h_i - h) > rate_tolerance * h:
            raise RecordingError(
                f"{path}: column {time_name!r} (recording {name!r}), {row_label(int(found.rows[a]))}: step {h_i:.6g} s "
                f"differs from the file's mean step {h:.6g} s (one file holds one rate)"
            )
    return h


def _cut(path, time_name, found: _FirstPass, blocks, recording_column, window, stride):
    """The samples (recording, first data index, length), and n_steps: whole recordings or windows."""
    lengths = [b - a for a, b in blocks]
    if window is None:
        if len(set(lengths)) > 1:
            raise RecordingError(
                f"{path}: column {recording_column!r}: recordings have different lengths "
                f"({dict(zip(found.names, lengths))}); cut them into equal samples with window=N"
            )
        return [(r, a, lengths[0]) for r, (a, _) in enumerate(blocks)], lengths[0]
    cuts = []
    for r, ((a, b), name) in enumerate(zip(blocks, found.names)):
        if b - a < window:
            label = f" (recording {name!r})" if recording_column else ""
            raise RecordingError(
                f"{path}: column {time_name!r}{label}, {row_label(int(found.rows[a]))}: {b - a} rows, "
                f"fewer than window = {window} (the drive is shorter than one window)"
            )
        cuts.extend((r, start, window) for start in range(a, b - window + 1, stride))
    return cuts, window


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
    column_units = _check_options(path, time_unit, rate_tolerance, gap_factor, window, stride, column_units)
    head = _read_header(path, delimiter, columns, time_column, recording_column, units, column_units)
    found = _first_pass(path, head, time_unit, recording_column, progress)
    blocks = list(zip(found.starts, found.starts[1:] + [found.count]))
    tolerances = (gap_factor, rate_tolerance)
    h = _common_step(path, head.time_name, found, blocks, recording_column, time_unit, tolerances, rate_range)
    if window is not None:
        window = int(window)
        stride = int(stride) if stride is not None else window
    cuts, n_steps = _cut(path, head.time_name, found, blocks, recording_column, window, stride)
    known_mass = None
    if (load_name := head.mapping.get(KNOWN_MASS)) is not None:
        at, value = np.asarray(found.load_at), np.asarray(found.load_value)
        known_mass = _known_mass(path, load_name, cuts, found.names, found.rows, at, value)
    channels = tuple(c for c in CHANNELS if c in head.mapping)
    return RecordingLayout(
        path=path,
        header=head.header,
        sep=head.sep,
        encoding=head.encoding,
        time_name=head.time_name,
        mapping=head.mapping,
        factors=head.factors,
        cuts=cuts,
        t_start=np.asarray([found.t[start] for _, start, _ in cuts], dtype=np.float64),
        h=h,
        n_steps=n_steps,
        channels=channels,
        source_columns={"time": head.time_name, **head.mapping},
        source_units={c: str(column_units.get(c, units)).strip() for c in channels},
        recordings=list(found.names),
        rows=[b - a for a, b in blocks],
        n_rows=int(found.count),
        window=window,
        stride=stride if window is not None else None,
        file_bytes=path.stat().st_size,
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
                f"{path}: column {name!r} (known_mass), {row_label(int(rows[i]))}: the known load changes from "
                f"{float(value[k])!r} to {float(value[k + 1])!r} kg inside a sample of recording {names[r]!r} starting at "
                f"{row_label(int(rows[start]))}; keep it constant within each recording or window"
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
    with progress_bar(progress) as bar:
        task = bar.add_task(f"cutting {path.name}", total=layout.file_bytes)
        for block in read_blocks(path, layout.header, layout.sep, wanted, layout.encoding):
            columns = []
            for key, name in zip(keys, wanted):
                raw = column_floats(path, name, block)
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
