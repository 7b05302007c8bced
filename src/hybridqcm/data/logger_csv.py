"""One logger's CSV: a time column and three axes with gravity (a phone app, a stand-alone logger).

    read_logger(path, ...) -> LoggerRecording (t [N] s, xyz [N, 3] m/s², the column names)

Two such recordings, a seat's and a floor's, are aligned onto one grid by data/two_loggers.py; the checks
and the block reader are those of qcm-import's own CSV (data/csv_columns.py, data/csv_checks.py).
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridqcm.data import csv_checks
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.csv_columns import (
    DEFAULT_TIME_COLUMNS,
    TIME_UNITS,
    check_time,
    column_floats,
    progress_bar,
    read_blocks,
    short_row_error,
    sniff_delimiter,
    unit_factor,
)

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
    sep = delimiter or sniff_delimiter(first)
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
    factor = unit_factor(path, xyz_names[0], "x, y, z", units, "units")
    wanted = [time_column, *xyz_names]
    csv_checks.check_header(path, header, wanted)
    times, parts, row_parts = [], [], []
    with progress_bar(progress) as bar:
        task = bar.add_task(f"reading {path.name}", total=path.stat().st_size)
        for block in read_blocks(path, header, sep, wanted, encoding, short_row_error(path, header, wanted)):
            times.append(column_floats(path, time_column, block) * TIME_UNITS[time_unit])
            xyz = np.stack([column_floats(path, n, block) for n in xyz_names], 1)
            for j, n in enumerate(xyz_names):
                csv_checks.check_float32(path, n, xyz[:, j], factor, block.rows)
            parts.append(xyz * factor)
            row_parts.append(block.rows)
            bar.update(task, completed=block.bytes_read)
    if not times:
        raise RecordingError(f"{path}: column {time_column!r}: no data rows after the header")
    t, rows = np.concatenate(times), np.concatenate(row_parts)
    check_time(path, time_column, t, rows, "", gap_factor, math.inf)
    csv_checks.check_rate(path, time_column, float((t[-1] - t[0]) / (t.size - 1)), time_unit, TIME_UNITS, rate_range)
    return LoggerRecording(
        path=path,
        t=t,
        xyz=np.concatenate(parts),
        columns={"time": time_column, "x": xyz_names[0], "y": xyz_names[1], "z": xyz_names[2]},
        unit=str(units),
    )
