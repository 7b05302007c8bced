"""The checks of a CSV recording that no reader does for us, each a one-line RecordingError.

Kept apart from the reading (data/importer.py) so any reader — the csv module's rows or a
streaming one — calls the same checks on what it read:

* `text_encoding`: UTF-8 (with or without BOM) or UTF-16/32 with a BOM, read as such; a binary
  file or another encoding is named as what it is, not as a codec's complaint;
* `check_header_line`, `check_header`: an unmatched quote in the header, a column name the import
  uses that appears twice (which one would be read?);
* `check_fields` (`checked_rows` around a csv.reader): a field holding a line break, i.e. a stray
  double quote that swallowed lines; bytes not in the file's encoding, named by line;
* `check_float32`: a value beyond float32 (the file's dtype) would be stored as inf;
* `check_rate`: a rate no vehicle logger records at (time in ms read as s gives h = 10 s).

None of them copies a column: the range check uses two reductions.
"""

from __future__ import annotations

import codecs
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from hybridqcm.errors import DatasetError

FLOAT32_MAX = float(np.finfo(np.float32).max)
RATE_RANGE = (10.0, 100_000.0)  # Hz: the seat's dynamics (1-20 Hz) need >= 10 Hz; above 100 kHz is no accelerometer
_BOMS = (
    (codecs.BOM_UTF32_LE, "utf-32"),
    (codecs.BOM_UTF32_BE, "utf-32"),
    (codecs.BOM_UTF8, "utf-8-sig"),
    (codecs.BOM_UTF16_LE, "utf-16"),
    (codecs.BOM_UTF16_BE, "utf-16"),
)


class RecordingError(DatasetError):
    """A CSV recording that cannot be imported; the message names the file, column and row."""


def text_encoding(path: str | os.PathLike, probe: int = 1 << 16) -> str:
    """The encoding to read the CSV with: from its byte-order mark, else UTF-8 (checked on the first
    `probe` bytes). RecordingError for a binary file or text in another encoding."""
    path = Path(path)
    with open(path, "rb") as handle:
        head = handle.read(probe)
    for bom, name in _BOMS:  # UTF-32 LE starts like UTF-16 LE: the longer marks first
        if head.startswith(bom):
            return name
    if b"\0" in head:
        raise RecordingError(
            f"{path}: not a text CSV (it holds NUL bytes: a binary file, or UTF-16 without a byte-order mark); "
            f"export the recording as CSV text in UTF-8"
        )
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as error:
        if error.start < len(head) - 4:  # not just a character cut at the probe's end
            raise RecordingError(undecodable(path, head, error)) from None
    return "utf-8-sig"


def undecodable(path: Path, data: bytes, error: UnicodeDecodeError, first_line: int = 1) -> str:
    """The message for bytes that are not UTF-8: where, and what to do."""
    line = first_line + data[: error.start].count(b"\n")
    byte = data[error.start : error.start + 1].hex()
    return (
        f"{path}: line {line}: byte 0x{byte} is not UTF-8 text (a Latin-1 or Windows-1252 export?); "
        f"save the file as UTF-8 (or UTF-16 with a byte-order mark)"
    )


def check_header_line(path: Path, first_line: str) -> None:
    """An unmatched double quote in line 1 (the header would be split wrongly)."""
    if first_line.count('"') % 2:
        raise RecordingError(
            f"{path}: header (line 1) has an unmatched double quote: {first_line.strip()!r}; remove the stray quote"
        )


def check_header(path: Path, header: Sequence[str], used: Sequence[str]) -> None:
    """A column the import reads whose name appears more than once in the header."""
    for name in dict.fromkeys(used):
        places = [i + 1 for i, h in enumerate(header) if h == name]
        if len(places) > 1:
            raise RecordingError(
                f"{path}: header (line 1): column {name!r} appears {len(places)} times (fields "
                f"{', '.join(map(str, places))}), so which one to read is ambiguous; rename the others"
            )


def check_fields(path: Path, fields: Sequence[str], first_line: int, last_line: int) -> None:
    """A field with a line break in it: a stray double quote that made the reader swallow lines."""
    for field in fields:
        if "\n" in field or "\r" in field:
            span = "to the end of the file" if last_line <= first_line else f"over lines {first_line}-{last_line}"
            raise RecordingError(
                f'{path}: line {first_line}: a double quote (") opens a field that runs {span}: a stray quote? '
                f"(cell starts {field[:20]!r}); remove it"
            )


def checked_rows(path: Path, reader) -> Iterator[list[str]]:
    """The rows of a csv.reader over the data lines (the header already read), with `check_fields`
    on a row that spans several lines and text that is not in the file's encoding named by line."""
    previous = reader.line_num
    while True:
        try:
            fields = next(reader)
        except StopIteration:
            return
        except UnicodeDecodeError as error:
            raise RecordingError(
                f"{path}: line {reader.line_num + 2}: {error.reason} ({error.encoding}): not text in the "
                f"file's encoding; save the file as UTF-8"
            ) from None
        if reader.line_num - previous > 1:  # the line numbers are the file's with the header as line 1
            check_fields(path, fields, previous + 2, reader.line_num + 1)
        previous = reader.line_num
        yield fields


def check_float32(path: Path, name: str, values: np.ndarray, factor: float, rows: np.ndarray) -> None:
    """Every |value x factor| must fit float32 (the stored dtype), or it would be stored as inf."""
    if values.size == 0:
        return
    limit = FLOAT32_MAX / abs(float(factor))
    high, low = float(values.max()), float(values.min())
    if high <= limit and low >= -limit:
        return
    i = int(np.argmax(np.abs(values) > limit))
    raise RecordingError(
        f"{path}: column {name!r}, row {int(rows[i])} (line {int(rows[i]) + 1}): value {values[i]:.6g} is beyond "
        f"the float32 range (±{FLOAT32_MAX:.4g} in the stored unit); a logger does not record that"
    )


def check_rate(
    path: Path, time_name: str, h: float, time_unit: str, units: dict, rate_range: Sequence[float] = RATE_RANGE
) -> None:
    """A sampling rate 1/h outside ``rate_range`` Hz is refused, naming the time_unit that would fit."""
    low, high = float(rate_range[0]), float(rate_range[1])
    rate = 1.0 / h
    if low <= rate <= high:
        return
    raw = h / units[time_unit]  # the step in the file's own numbers
    fits = [u for u, f in units.items() if u != time_unit and low <= 1.0 / (raw * f) <= high]
    hint = f"if the time is in {fits[0]}, pass time_unit={fits[0]}" if fits else "check the time column"
    raise RecordingError(
        f"{path}: column {time_name!r}: sampling rate {rate:.6g} Hz (h = {h:.6g} s, read with time_unit={time_unit}) "
        f"is outside {low:g}-{high:g} Hz, no vehicle logger's rate; {hint} (rate_range=[LOW,HIGH] allows others)"
    )


__all__ = [
    "RecordingError",
    "FLOAT32_MAX",
    "RATE_RANGE",
    "text_encoding",
    "undecodable",
    "check_header_line",
    "check_header",
    "check_fields",
    "checked_rows",
    "check_float32",
    "check_rate",
]
