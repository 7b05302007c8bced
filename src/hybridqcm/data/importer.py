"""Recordings from a user's logger (CSV) into the dataset layout (SPEC §5, § 9).

A CSV recording has a header line and one row per sample:

    t,a3,a2[,a1][,road][,recording]        time in seconds, accelerations in m/s² or g, road in metres

Any subset of the acceleration channels a3 (seat / occupant), a2 (chassis / seat base) and
a1 (wheel) may be present, under the user's own names (`columns={"a3": "seat_z"}`). The rate
may be anything, but it must be constant: the estimator's model is a discretisation with one
step h (SPEC § 9), so a gap or a jittery clock would silently become a different vehicle.

The result is in the layout of hdf5.py with the leading sample axis M:

    accel      float32 [M, T, 3]  (a3, a2, a1) in m/s², NaN in channels that were not recorded
    road       float32 [M, T]     u in metres, only when the CSV has a road column
    profile_id int32   [M]        index of the recording a sample was cut from (windows of one drive share a road)
    t_start    float64 [M]        the CSV time of each sample's first step [s]

M is the number of recordings (`recording_column`), or of windows of `window` steps taken every
`stride` steps from each recording. No params: a real recording has none. Files carry no
`physics` attribute: a recording is continuous-time physics with an unknown initial state,
which is what readers assume for files without one.

Every error is one line naming the file, the column and the row: the row is the 1-based data
row, and the line number in the file (the header is line 1) is given beside it.
"""

from __future__ import annotations

import csv
import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridqcm.data import csv_checks
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.h5file import raise_if_failed, writing
from hybridqcm.data.hdf5 import DatasetError  # noqa: F401 - importable here

SCHEMA_V2 = "hybridqcm.dataset/2"
STANDARD_GRAVITY = 9.80665  # m/s² per g (CGPM 1901, exact by definition)
CHANNELS = ("a3", "a2", "a1")  # column order of accel
ROAD = "road"
UNITS = {"m/s2": 1.0, "m/s^2": 1.0, "m/s²": 1.0, "g": STANDARD_GRAVITY}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
DEFAULT_TIME_COLUMNS = ("t", "time")
DELIMITERS = (",", ";", "\t")


@dataclass
class ImportedRecordings:
    """Arrays in the dataset layout plus what the summary and the file attributes need."""

    accel: np.ndarray  # float32 [M, T, 3], m/s², NaN where not recorded
    road: np.ndarray | None  # float32 [M, T] metres, or None
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
    unknown = sorted(set(columns) - set(CHANNELS) - {ROAD})
    if unknown:
        raise RecordingError(f"{path}: columns.{unknown[0]} is not a channel; map a3, a2, a1 or road to a CSV column")
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
    for key in (*CHANNELS, ROAD):
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
            f"{path}: column {duplicated[0]!r} is mapped to more than one role (time, a3, a2, a1, road, recording)"
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
        raise RecordingError(
            f"{path}: column {name!r}{label}, {_where(int(rows[k + 1]))}: time {t[k + 1]:.9g} s is not after "
            f"the previous row's {t[k]:.9g} s (time must be strictly increasing)"
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
    """Read a CSV recording into the dataset layout (module docstring); raises RecordingError.

    units: the accelerations' unit in the file, "m/s2" or "g" (1 g = 9.80665 m/s²);
    column_units: per-channel overrides, e.g. {"a2": "m/s2"}. columns: channel -> CSV column
    name (a channel not named there is taken from a column of its own name when present; None
    skips it). recording_column: several recordings, one id per row, each in one block of rows.
    window, stride: cut every recording into samples of `window` steps starting every `stride`
    (default: window) steps; without a window every recording is one sample and all must have
    the same length. rate_range: the sampling rates [Hz] accepted (csv_checks.check_rate).
    """
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

    with open(path, newline="", encoding=csv_checks.text_encoding(path)) as handle:
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
        index = {name: header.index(name) for name in wanted}
        cells: dict[str, list[str]] = {name: [] for name in wanted}
        data_rows: list[int] = []
        reader = csv.reader(handle, delimiter=sep)
        row = 0
        for fields in csv_checks.checked_rows(path, reader):
            if not fields or all(not f.strip() for f in fields):
                continue  # blank line
            row = reader.line_num  # lines read after the header: the data row; the line is row + 1
            if len(fields) < len(header):
                missing = header[len(fields)]
                if missing in index:
                    raise RecordingError(
                        f"{path}: column {missing!r}, {_where(row)}: cell is empty "
                        f"(the row has {len(fields)} of {len(header)} fields)"
                    )
                fields = fields + [""] * (len(header) - len(fields))
            for name, i in index.items():
                cells[name].append(fields[i])
            data_rows.append(row)
    if not data_rows:
        raise RecordingError(f"{path}: column {time_name!r}: no data rows after the header")
    rows = np.asarray(data_rows, dtype=np.int64)
    t_all = _to_float(path, time_name, cells[time_name], rows) * TIME_UNITS[time_unit]
    values = {key: _to_float(path, name, cells[name], rows) for key, name in mapping.items()}
    for key, name in mapping.items():
        csv_checks.check_float32(path, name, values[key], factors.get(key, 1.0), rows)

    # recordings: contiguous blocks of one id each
    if recording_column:
        ids = [c.strip() for c in cells[recording_column]]
        for i, value in enumerate(ids):
            if value == "":
                raise RecordingError(f"{path}: column {recording_column!r}, {_where(int(rows[i]))}: cell is empty")
        starts = [0] + [i for i in range(1, len(ids)) if ids[i] != ids[i - 1]]
        names = [ids[i] for i in starts]
        seen: set[str] = set()
        for i, name in zip(starts, names):
            if name in seen:
                raise RecordingError(
                    f"{path}: column {recording_column!r}, {_where(int(rows[i]))}: recording {name!r} "
                    f"appears again after other recordings (keep each recording's rows together)"
                )
            seen.add(name)
        blocks = list(zip(starts, starts[1:] + [len(ids)]))
    else:
        names, blocks = [path.stem], [(0, len(data_rows))]

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
                    f"fewer than window = {window}"
                )
            cuts.extend((r, start, window) for start in range(a, b - window + 1, stride))
        n_steps = window

    accel = np.full((len(cuts), n_steps, 3), np.nan, dtype=np.float32)
    road = np.empty((len(cuts), n_steps), dtype=np.float32) if ROAD in mapping else None
    for m, (_, start, length) in enumerate(cuts):
        for c, channel in enumerate(CHANNELS):
            if channel in values:
                accel[m, :, c] = values[channel][start : start + length] * factors[channel]
        if road is not None:
            road[m] = values[ROAD][start : start + length]
    channels = tuple(c for c in CHANNELS if c in mapping)
    return ImportedRecordings(
        accel=accel,
        road=road,
        profile_id=np.asarray([r for r, _, _ in cuts], dtype=np.int32),
        t_start=np.asarray([t_all[start] for _, start, _ in cuts], dtype=np.float64),
        h=h,
        channels=channels,
        source_columns={"time": time_name, **mapping},
        source_units={c: str(column_units.get(c, units)).strip() for c in channels},
        recordings=list(names),
        rows=lengths,
        window=window,
        stride=stride if window is not None else None,
    )


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
    if output.is_dir():
        raise RecordingError(f"{output} is a directory, not a file path")
    if output.exists() and not overwrite:
        raise FileExistsError(f"output={output} exists; pass overwrite=true to replace it")
    if not split or "/" in split:
        raise RecordingError(f"{output}: split = {split!r} is not a valid group name")
    output.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent)
    os.close(fd)
    tmp = Path(tmp)
    guard = None
    try:
        # a full disk: one DatasetError, not HDF5's segfault; Ctrl-C / SIGTERM after h5py's calls (data/h5file.py)
        with writing(tmp) as (handle, guard):
            attrs = {
                "schema": SCHEMA_V2,
                "h": float(data.h),
                "n_steps": int(data.n_steps),
                "created_by": created_by,
                "source": str(source),
                "units": json.dumps({"accel": "m/s2", "road": "m", "time": "s"}),
                "source_units": json.dumps(data.source_units),
                "source_columns": json.dumps(data.source_columns),
                "channels": json.dumps(list(data.channels)),
                "recordings": json.dumps(data.recordings),
            }
            if data.window is not None:
                attrs.update(window=int(data.window), stride=int(data.stride))
            handle.attrs.update(attrs)
            group = handle.create_group(split)
            arrays = {"accel": data.accel, "profile_id": data.profile_id, "t_start": data.t_start}
            if data.road is not None:
                arrays["road"] = data.road
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
