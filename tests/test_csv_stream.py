"""qcm-import's streaming reader (data/csv_stream.py, importer.scan_recordings / iter_windows /
import_recordings): the windows written block by block against numpy's own cutting of the numbers the test
wrote, row numbering across blocks and blank lines, and the checks issue 32 added (a clock that restarts,
a drive shorter than one window), and main's text checks (data/csv_checks.py) where only a stream reaches:
past the encoding probe, in a later block, in a column the import does not read."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from hybridqcm.data import csv_stream
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.import_writer import import_recordings
from hybridqcm.data.importer import read_recordings


def _csv(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


def _drive(n: int, h: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    return np.arange(n) * h, rng.normal(0, 0.3, n), rng.normal(0, 0.3, n)


@pytest.mark.parametrize("block_bytes", [97, 4096, 1 << 22])
def test_streamed_windows_equal_numpys_cutting_at_any_block_size(tmp_path, monkeypatch, block_bytes):
    """Two recordings, overlapping windows (stride < window), blocks from a few rows to the whole file:
    every written window equals the CSV's numbers cut by numpy (float32 of the printed value)."""
    monkeypatch.setattr(csv_stream, "BLOCK_BYTES", block_bytes)
    t, a3, a2 = _drive(900, 0.01)
    rows = [
        f"{t[k] + (0 if k < 500 else 50.0):.6f},{a3[k]:.9g},{a2[k]:.9g},{'A' if k < 500 else 'B'}" for k in range(900)
    ]
    csv = _csv(tmp_path / "d.csv", "t,a3,a2,recording", rows)
    out = tmp_path / "d.h5"
    layout = import_recordings(csv, out, recording_column="recording", window=120, stride=50)
    starts = [s for s in range(0, 500 - 120 + 1, 50)] + [500 + s for s in range(0, 400 - 120 + 1, 50)]
    with h5py.File(out) as f:
        accel, pid, t0 = f["test/accel"][()], f["test/profile_id"][()], f["test/t_start"][()]
        assert f.attrs["n_steps"] == 120 and f.attrs["window"] == 120 and f.attrs["stride"] == 50
        assert f["test/accel"].chunks is not None and f["test/accel"].compression == "gzip"
    assert accel.shape == (len(starts), 120, 3) and layout.n_rows == 900
    a3, a2 = (np.array([float(f"{x:.9g}") for x in a]) for a in (a3, a2))  # as printed, parsed by Python
    for m, s in enumerate(starts):
        np.testing.assert_array_equal(accel[m, :, 0], a3[s : s + 120].astype(np.float32))
        np.testing.assert_array_equal(accel[m, :, 1], a2[s : s + 120].astype(np.float32))
        assert np.isnan(accel[m, :, 2]).all()
    assert pid.tolist() == [0 if s < 500 else 1 for s in starts]
    np.testing.assert_allclose(t0, [t[s] + (0 if s < 500 else 50.0) for s in starts], atol=1e-9)
    # the in-memory reader gives the same numbers
    data = read_recordings(csv, recording_column="recording", window=120, stride=50)
    np.testing.assert_array_equal(data.accel, accel)


def test_row_numbers_count_blank_lines_across_blocks(tmp_path, monkeypatch):
    """Blank lines are skipped but counted (row r is line r + 1, as the csv-module reader counted): a bad
    cell after them, in a later block, is named by its physical line."""
    monkeypatch.setattr(csv_stream, "BLOCK_BYTES", 64)
    t, a3, _ = _drive(40, 0.01)
    rows = [f"{t[k]:.2f},{a3[k]:.6f}" for k in range(40)]
    rows.insert(10, "")
    rows.insert(20, "   ")
    rows[30] = rows[30].split(",")[0] + ",oops"
    csv = _csv(tmp_path / "b.csv", "t,a3", rows)
    with pytest.raises(RecordingError, match=r"b.csv: column 'a3', row 31 \(line 32\): cell = 'oops' is not a number"):
        read_recordings(csv)
    rows[30] = rows[30].split(",")[0] + f",{a3[28]:.6f}"
    assert read_recordings(_csv(tmp_path / "ok.csv", "t,a3", rows)).n_steps == 40


def test_trailing_delimiters_and_wide_rows(tmp_path):
    t, a3, a2 = _drive(30, 0.01)
    rows = [f"{t[k]:.2f},{a3[k]:.6f},{a2[k]:.6f}," for k in range(30)]  # a logger that ends every row with ','
    data = read_recordings(_csv(tmp_path / "trail.csv", "t,a3,a2", rows))
    printed = np.array([float(f"{x:.6f}") for x in a2])
    np.testing.assert_array_equal(data.accel[0, :, 1], printed.astype(np.float32))
    rows = [f"{t[k]:.2f},{a3[k]:.6f},{a2[k]:.6f}" for k in range(30)]
    rows[12] += ",7"
    with pytest.raises(RecordingError) as caught:
        read_recordings(_csv(tmp_path / "wide.csv", "t,a3,a2", rows))
    assert str(caught.value) == f"{tmp_path / 'wide.csv'}: row 13 (line 14) has 4 fields where the first data row has 3"


def test_a_clock_that_restarts_is_named_as_such(tmp_path):
    t, a3, _ = _drive(200, 0.01)
    t[120:] -= t[120]  # a second recording appended without an id: the clock starts again at 0
    csv = _csv(tmp_path / "r.csv", "t,a3", [f"{t[k]:.2f},{a3[k]:.6f}" for k in range(200)])
    with pytest.raises(RecordingError) as caught:
        read_recordings(csv)
    message = str(caught.value)
    assert message.startswith(f"{csv}: column 't', row 121 (line 122): time 0 s is not after the previous row's 1.19 s")
    assert "the clock restarted here" in message and "recording_column=NAME" in message and "\n" not in message
    t, a3, _ = _drive(200, 0.01)
    t[50] = t[49]  # one repeated stamp: not a restart
    csv = _csv(tmp_path / "s.csv", "t,a3", [f"{t[k]:.2f},{a3[k]:.6f}" for k in range(200)])
    with pytest.raises(
        RecordingError, match=r"is not after the previous row's 0.49 s \(time must be strictly increasing\)$"
    ):
        read_recordings(csv)


def test_a_drive_shorter_than_one_window(tmp_path):
    t, a3, a2 = _drive(80, 0.01)
    csv = _csv(tmp_path / "short.csv", "t,a3,a2", [f"{t[k]:.2f},{a3[k]:.6f},{a2[k]:.6f}" for k in range(80)])
    with pytest.raises(RecordingError) as caught:
        import_recordings(csv, tmp_path / "short.h5", window=100)
    assert str(caught.value) == (
        f"{csv}: column 't', row 1 (line 2): 80 rows, fewer than window = 100 (the drive is shorter than one window)"
    )
    assert not list(tmp_path.glob("*.h5")) and not list(tmp_path.glob(".*partial"))


def test_an_error_in_the_second_pass_leaves_no_file(tmp_path):
    """The time column passes (pass 1), a channel cell fails while windows are being written (pass 2):
    the partial file is removed, nothing looks like a dataset."""
    t, a3, a2 = _drive(300, 0.01)
    rows = [f"{t[k]:.2f},{a3[k]:.6f},{a2[k]:.6f}" for k in range(300)]
    rows[250] = f"{t[250]:.2f},{a3[250]:.6f},nan"
    csv = _csv(tmp_path / "late.csv", "t,a3,a2", rows)
    with pytest.raises(RecordingError, match=r"column 'a2', row 251 \(line 252\): cell = 'nan' \(NaN or infinite"):
        import_recordings(csv, tmp_path / "out" / "late.h5", window=100)
    assert list((tmp_path / "out").iterdir()) == []


def test_stray_quotes_and_foreign_bytes_past_the_first_block_are_named_by_line(tmp_path, monkeypatch):
    """pyarrow, like the csv module, lets a stray quote swallow lines, silently: in a column read, in a column
    not read (rows lost, the drive cut short), or in a later block; and bytes that are not UTF-8 beyond the
    encoding probe's 64 KiB. Each is one line naming where it starts, as the csv-module reader named it."""
    monkeypatch.setattr(csv_stream, "BLOCK_BYTES", 4096)
    t, a3, a2 = _drive(3000, 0.01)
    rows = [f"{t[k]:.2f},{a3[k]:.6f},{a2[k]:.6f},note" for k in range(3000)]
    read = {"columns": {"a1": False}, "time_column": "t"}
    clean = _csv(tmp_path / "clean.csv", "t,a3,a2,comment", rows)
    assert read_recordings(clean, **read).n_steps == 3000
    for k in (999, 2995):  # a quote in the comment column, not imported: across blocks, or within the last
        unread = list(rows)
        unread[k] = unread[k].replace("note", '"note')
        csv = _csv(tmp_path / "unread.csv", "t,a3,a2,comment", unread)
        with pytest.raises(RecordingError) as caught:
            read_recordings(csv, **read)
        assert str(caught.value).startswith(
            f'{csv}: line {k + 2}: a double quote (") opens a field that runs over lines {k + 2}-3001: a stray quote?'
        )
    late = list(rows)  # in a column read, blocks after the first
    late[2000] = late[2000].replace(",", ',"', 2).replace(',"', ",", 1)
    csv = _csv(tmp_path / "late.csv", "t,a3,a2,comment", late)
    with pytest.raises(RecordingError, match=r"late.csv: line 2002: a double quote \(\"\) opens a field that runs"):
        read_recordings(csv, **read)
    latin = tmp_path / "latin.csv"  # 0xb2 (Latin-1 '²') in a2 at line 2 502: past the probe of the first 64 KiB
    text = ("t,a3,a2,comment\n" + "\n".join(rows) + "\n").encode()
    assert text.index(rows[2500].encode()) > 1 << 16
    bad = rows[2500].rsplit(",", 1)[0].encode() + b"\xb2,note"  # a2 with a unit glued on, in Latin-1
    latin.write_bytes(text.replace(rows[2500].encode(), bad))
    with pytest.raises(RecordingError) as caught:
        read_recordings(latin, **read)
    assert str(caught.value).startswith(f"{latin}: line 2502: byte 0xb2 is not UTF-8 text")
