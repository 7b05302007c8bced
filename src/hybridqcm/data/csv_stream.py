"""A CSV recording read in blocks of rows, never whole: pyarrow's streaming CSV reader (issue 32).

An hour at 1 kHz is 3.6 million rows: a Python row loop holding every cell as a string took 11x the
file's size in memory. Here the file streams through pyarrow's C++ reader in blocks of ``block_bytes``;
each block comes back as the wanted columns' cells (Arrow strings: converting is the caller's, so that a
bad cell gets the importer's own one-line error) with the data row number of every row.

Rows are numbered as the importer always has: data row r is line r + 1 of the file (the header is line
1) and every physical line counts, blank ones included. A line of blanks and delimiters only, or a row
whose wanted cells are all blank, is a blank line and is skipped (pyarrow is told not to drop empty lines,
and lines it cannot split are counted where they are, so that the count stays physical).
A row with another number of fields than the first data row is an error naming its row and line: the
first data row may have more fields than the header (a trailing delimiter on every row, as some loggers
write), which then counts as the row's width.

pyarrow, like the csv module, lets a stray double quote swallow the lines up to the next quote; it does not
say so. A cell that does not parse and holds a line break (Block.explain), a short row holding a quote, a
quoted field across a block's end, or (UTF-8 files) fewer rows than the file has lines at the end of a pass
(a quote in a column not read) is therefore diagnosed by the csv module with data/csv_checks.py's checks, on
the error path only, so the message is the one the csv-module reader gave. Bytes that are not
UTF-8 in a column read are named by line likewise (in a column not read they are not looked at).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridqcm.data import csv_checks
from hybridqcm.errors import DatasetError

BLOCK_BYTES = 1 << 20  # 1 MiB of text per block: ~30 000 rows of t, a3, a2 (4 MiB: no faster, 80 MB more peak memory)


class CsvStreamError(DatasetError):
    """A row the reader cannot split into the header's fields (the message names the file, row and line)."""


@dataclass
class Block:
    """One block of rows: rows int64 [n] (data row numbers, 1-based), cells {column: pyarrow string array [n]},
    bytes_read (of the file so far: for a progress bar), source (path, delimiter, encoding)."""

    rows: np.ndarray
    cells: dict
    bytes_read: int
    source: tuple = ()

    def explain(self, name: str) -> None:
        """For a column whose cells did not parse (or whose text is used as is): a cell holding a line break
        is a stray quote's doing, raised as csv_checks' one-line error at the line where the quote opens."""
        if self.source and _has_line_break(self.cells[name]):
            _diagnose(*self.source)


class _Counting(io.RawIOBase):
    """A binary file that counts the bytes and the line breaks (\\n, \\r\\n or \\r) read through it."""

    def __init__(self, handle):
        self.handle, self.count, self.breaks, self.last = handle, 0, 0, b""

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        n = self.handle.readinto(buffer) or 0
        if n:
            data = bytes(memoryview(buffer)[:n])
            joined = data.count(b"\r\n") + (self.last == b"\r" and data[:1] == b"\n")
            self.breaks += data.count(b"\n") + data.count(b"\r") - joined
            self.last = data[-1:]
        self.count += n
        return n

    def data_lines(self) -> int:
        """Lines after the header (line 1) in what was read: every line break, and a last line without one."""
        lines = self.breaks + (1 if self.last not in (b"", b"\n", b"\r") else 0)
        return max(0, lines - 1)


def _first_data_fields(path: Path, sep: str, encoding: str) -> int | None:
    """Number of fields of the first non-blank data row (None: no data row)."""
    with open(path, newline="", encoding=encoding) as handle:
        handle.readline()
        for fields in csv.reader(handle, delimiter=sep):
            if fields and any(f.strip() for f in fields):
                return len(fields)
    return None


def iter_blocks(
    path: str | os.PathLike,
    header: Sequence[str],
    sep: str,
    columns: Sequence[str],
    block_bytes: int | None = None,
    encoding: str = "utf-8-sig",
    on_short_row: Callable[[int, int], Exception] | None = None,
) -> Iterator[Block]:
    """The wanted ``columns`` of ``path`` (header already read: its names are ``header``) block after block.

    on_short_row(row, n_fields) -> the exception to raise for a row with fewer fields than the first data
    row (the importer names the first missing column); None: a generic one-line error. block_bytes: None is
    the module's BLOCK_BYTES (read at the call)."""
    import pyarrow as pa
    import pyarrow.csv as pcsv

    path = Path(path)
    names = list(header)
    width = _first_data_fields(path, sep, encoding)
    if width is None:
        return
    if width > len(names):  # a trailing delimiter (or more): columns without a name are not imported
        names += [f"\x00extra{k}" for k in range(width - len(names))]
    invalid: list[tuple[int, int, str]] = []
    skipped: list[int] = []  # data rows of lines with only blanks and delimiters (skipped, still counted)
    blank_line = set(" \t\r\n" + sep)

    def handler(row) -> str:
        number = int(row.number) - 1 if row.number is not None else -1
        if set(row.text) <= blank_line:
            skipped.append(number)
        else:
            invalid.append((number, int(row.actual_columns), row.text))
        return "skip"

    wanted = list(dict.fromkeys(columns))
    utf8 = encoding in ("utf-8-sig", "utf-8", "utf8")
    raw = open(path, "rb", buffering=0)
    counting = _Counting(raw)
    try:
        stream = io.BufferedReader(counting, buffer_size=1 << 20)
        # the header line is skipped by count; a BOM needs no more
        arrow_encoding = "utf8" if encoding == "utf-8-sig" else encoding
        reader = pcsv.open_csv(
            stream,
            read_options=pcsv.ReadOptions(
                use_threads=False,
                block_size=int(block_bytes or BLOCK_BYTES),
                column_names=names,
                skip_rows=1,
                encoding=arrow_encoding,
            ),
            parse_options=pcsv.ParseOptions(delimiter=sep, ignore_empty_lines=False, invalid_row_handler=handler),
            convert_options=pcsv.ConvertOptions(
                include_columns=wanted,
                column_types={name: pa.string() for name in wanted},
                strings_can_be_null=False,
                quoted_strings_can_be_null=False,
            ),
        )
        seen = 0  # rows delivered so far (every physical data line; an invalid one stops the read)
        for batch in _batches(reader, path, sep, encoding):
            if invalid:
                raise _invalid(path, sep, encoding, invalid[0], width, on_short_row)
            n = batch.num_rows
            rows = np.arange(seen + 1, seen + n + 1, dtype=np.int64)
            while skipped and skipped[0] <= rows[-1]:  # a skipped line before these rows shifts them by one
                gap = int(np.searchsorted(rows, skipped.pop(0)))
                rows[gap:] += 1
            seen = int(rows[-1]) if n else seen
            cells = {name: batch.column(name) for name in wanted}
            blank = None
            for name in wanted:
                empty = np.asarray(_blank(cells[name]))
                blank = empty if blank is None else blank & empty
            if blank is not None and blank.any():
                keep = np.flatnonzero(~blank)
                rows = rows[keep]
                index = pa.array(keep)
                cells = {name: cells[name].take(index) for name in wanted}
            if rows.size:
                yield Block(rows=rows, cells=cells, bytes_read=counting.count, source=(path, sep, encoding))
        if invalid:
            raise _invalid(path, sep, encoding, invalid[0], width, on_short_row)
        if utf8 and seen + len(skipped) != counting.data_lines():  # lines swallowed in a column not read
            _diagnose(path, sep, encoding)
            raise CsvStreamError(
                f"{path}: {seen + len(skipped)} rows read where the file has {counting.data_lines()} lines after "
                f"the header (a quoted field spanning lines?)"
            )
    finally:
        raw.close()


def _batches(reader, path: Path, sep: str, encoding: str):
    """The reader's record batches; bytes not in the file's encoding are named by line (one line)."""
    import pyarrow as pa

    while True:
        try:
            batch = reader.read_next_batch()
        except StopIteration:
            return
        except UnicodeDecodeError:
            _diagnose_encoding(path, encoding)
            raise
        except pa.ArrowInvalid as error:
            if "UTF8" in str(error):
                _diagnose_encoding(path, encoding)
            else:  # e.g. "parser got out of sync with chunker": a quoted field across a block's end
                _diagnose(path, sep, encoding)
            raise CsvStreamError(f"{path}: {str(error).splitlines()[0]}") from None
        yield batch


def _has_line_break(cells) -> bool:
    import pyarrow.compute as pc

    return bool(pc.any(pc.match_substring_regex(cells, "[\\r\\n]")).as_py())


def _diagnose(path: Path, sep: str, encoding: str) -> None:
    """The error path: the file read again by the csv module through csv_checks.checked_rows, which raises
    the one-line RecordingError for a stray quote (or undecodable text) at the line where it starts."""
    with open(path, newline="", encoding=encoding) as handle:
        handle.readline()
        for _ in csv_checks.checked_rows(path, csv.reader(handle, delimiter=sep)):
            pass


def _diagnose_encoding(path: Path, encoding: str) -> None:
    """Raises csv_checks' one-line message for the first line of ``path`` that is not UTF-8 (UTF-8 files)."""
    if encoding not in ("utf-8-sig", "utf-8", "utf8"):
        return
    with open(path, "rb") as handle:
        for number, line in enumerate(handle, start=1):
            try:
                line.decode("utf-8")
            except UnicodeDecodeError as error:
                raise csv_checks.RecordingError(csv_checks.undecodable(path, line, error, number)) from None


def _blank(cells):
    import pyarrow.compute as pc

    return pc.equal(pc.utf8_length(pc.utf8_trim_whitespace(cells)), 0).to_numpy(zero_copy_only=False)


def _invalid(path: Path, sep: str, encoding: str, bad: tuple[int, int, str], width: int, on_short_row) -> Exception:
    row, fields, text = bad
    if '"' in text or "\n" in text or "\r" in text:  # a quote that swallowed lines: named where it opens
        _diagnose(path, sep, encoding)
    if fields < width and on_short_row is not None:
        return on_short_row(row, fields)
    return CsvStreamError(
        f"{path}: row {row} (line {row + 1}) has {fields} fields where the first data row has {width}"
    )


def strings(cells) -> list[str]:
    """A pyarrow string array as Python strings (for the slow, exact path of a bad block)."""
    return cells.to_pylist()


def to_float64(cells) -> np.ndarray | None:
    """Cells as float64 by pyarrow's parser (surrounding whitespace ignored), or None when a cell is not a
    number to it: the caller then takes the exact path that names the cell."""
    import pyarrow as pa
    import pyarrow.compute as pc

    try:
        return pc.cast(pc.utf8_trim_whitespace(cells), pa.float64()).to_numpy(zero_copy_only=False)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None


__all__ = ["BLOCK_BYTES", "Block", "CsvStreamError", "iter_blocks", "strings", "to_float64"]
