"""qcm-import: CSV recordings into the dataset layout, checked against the numbers the test wrote
(read back with h5py directly, not with the importer), and every bad input's one-line error."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.import_writer import write_recordings
from hybridqcm.data.importer import read_recordings

G = 9.80665  # standard gravity, m/s² per g (by definition)
REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "COLUMNS": "160", "PYTHONWARNINGS": "ignore", "PYTHONPATH": str(REPO / "src")}


def write_csv(path: Path, header: list[str], columns: list, fmt: str = "%.9g") -> Path:
    """A CSV with `header` and the given columns (arrays or lists of strings), one row per sample."""
    cells = [[c if isinstance(c, str) else fmt % c for c in column] for column in columns]
    lines = [",".join(header)] + [",".join(row) for row in zip(*cells)]
    path.write_text("\n".join(lines) + "\n")
    return path


def signals(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, 0.3, size=(3, n))


def qcm_import(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    script = Path(sys.executable).parent / "qcm-import"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hybridqcm.apps.importer"]
    return subprocess.run(
        command + [f"hydra.run.dir={tmp_path / 'run'}", *overrides],
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
        cwd=tmp_path,
    )


@pytest.mark.parametrize("units, factor", [("g", G), ("m/s2", 1.0)])
def test_round_trip_in_g_and_si_with_rate_detected(tmp_path, units, factor):
    n, h = 400, 1 / 250
    t = np.arange(n) * h
    a3, a2, a1 = signals(n)
    road = np.linspace(0.0, 0.02, n)
    csv = write_csv(tmp_path / "drive.csv", ["time", "seat_z", "floor_z", "a1", "road"], [t, a3, a2, a1, road])
    data = read_recordings(csv, units=units, columns={"a3": "seat_z", "a2": "floor_z"})
    out = write_recordings(tmp_path / "drive.h5", data, split="test", source=str(csv))
    with h5py.File(out, "r") as f:
        assert f.attrs["schema"] == "hybridqcm.dataset/2" and f.attrs["created_by"] == "qcm-import"
        assert "physics" not in f.attrs and f.attrs["source"] == str(csv)
        assert f.attrs["h"] == pytest.approx(h, rel=1e-9) and f.attrs["n_steps"] == n
        accel, stored_road = f["test/accel"][()], f["test/road"][()]
        assert "params" not in f["test"]
    assert accel.dtype == np.float32 and accel.shape == (1, n, 3)
    for c, expected in enumerate((a3, a2, a1)):
        np.testing.assert_allclose(accel[0, :, c], expected * factor, rtol=2e-7, atol=1e-7)
    np.testing.assert_allclose(stored_road[0], road, rtol=2e-7, atol=1e-9)  # metres, never scaled by units


def test_per_column_unit_override_and_unrecorded_channels_are_nan(tmp_path):
    n = 300
    t = np.arange(n) * 0.01
    a3, a2, _ = signals(n, seed=1)
    csv = write_csv(tmp_path / "two.csv", ["t", "a3", "a2"], [t, a3, a2])
    data = read_recordings(csv, units="g", column_units={"a2": "m/s2"})
    out = write_recordings(tmp_path / "two.h5", data)
    with h5py.File(out, "r") as f:
        accel = f["test/accel"][()]
        assert "road" not in f["test"]
    np.testing.assert_allclose(accel[0, :, 0], a3 * G, rtol=2e-7, atol=1e-7)
    np.testing.assert_allclose(accel[0, :, 1], a2, rtol=2e-7, atol=1e-7)
    assert np.isnan(accel[..., 2]).all() and np.isfinite(accel[..., :2]).all()
    assert data.channels == ("a3", "a2")


def test_rate_tolerance_separates_clock_jitter_from_a_non_constant_rate(tmp_path):
    n, h = 200, 0.005
    jitter = np.zeros(n)
    jitter[50] = 4e-4 * h  # both neighbouring steps off by 4e-4 h: inside the default 1e-3
    t = np.arange(n) * h + jitter
    a3 = signals(n)[0]
    assert read_recordings(
        write_csv(tmp_path / "ok.csv", ["t", "a3"], [t, a3], fmt="%.12g"), units="g"
    ).h == pytest.approx(h, rel=1e-9)
    jitter[50] = 3e-3 * h
    bad = write_csv(tmp_path / "bad.csv", ["t", "a3"], [np.arange(n) * h + jitter, a3], fmt="%.12g")
    with pytest.raises(RecordingError, match=r"column 't', row 51 \(line 52\): .*not constant"):
        read_recordings(bad, units="g")
    assert read_recordings(bad, units="g", rate_tolerance=1e-2).n_steps == n


def _bad(tmp_path: Path, mutate) -> Path:
    """A 60-row CSV (t, a3, a2 at 100 Hz) with `mutate(cells)` applied; cells[col][i] is data row i + 1."""
    n = 60
    a3, a2, _ = signals(n, seed=2)
    cells = {"t": [f"{0.01 * k:.6f}" for k in range(n)], "a3": [f"{x:.6f}" for x in a3], "a2": [f"{x:.6f}" for x in a2]}
    mutate(cells)
    return write_csv(tmp_path / "bad.csv", list(cells), list(cells.values()))


def _set(column: str, row: int, value: str):
    def mutate(cells):
        cells[column][row - 1] = value

    return mutate


def _drop_row(row: int):
    def mutate(cells):
        for column in cells.values():
            del column[row - 1]

    return mutate


BAD_CELLS = [
    # (mutation, column, data row, phrase)
    (_set("a2", 7, "1.2.3"), "a2", 7, "'1.2.3' is not a number"),
    (_set("a3", 5, ""), "a3", 5, "cell is empty"),
    (_set("a3", 9, "nan"), "a3", 9, "NaN or infinite"),
    (_set("a2", 60, "inf"), "a2", 60, "NaN or infinite"),
    (_set("t", 3, "x"), "t", 3, "is not a number"),
    (_set("t", 12, f"{0.095:.6f}"), "t", 12, "is not after"),  # earlier than row 11's 0.10
    (_set("t", 12, f"{0.10:.6f}"), "t", 12, "is not after"),  # equal to row 11's time
    (_drop_row(20), "t", 20, "gap of 0.02 s"),  # row 20 now holds t = 0.20 after 0.18
    (_set("t", 30, f"{0.2905:.6f}"), "t", 30, "not constant"),  # 5 % of h early
]


@pytest.mark.parametrize("mutate, column, row, phrase", BAD_CELLS)
def test_bad_cells_name_the_file_column_and_row(tmp_path, mutate, column, row, phrase):
    csv = _bad(tmp_path, mutate)
    with pytest.raises(RecordingError) as caught:
        read_recordings(csv, units="g")
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{csv}: column {column!r}, row {row} (line {row + 1})"), message
    assert phrase in message, message


HEADER_ERRORS = [
    # (header, options, expected message after "<file>: ")
    (["time_s", "a3"], {}, "column 't' or 'time' (the time column) is missing from the header (line 1)"),
    (["t", "a3"], {"time_column": "clock"}, "column 'clock' (time_column) is missing from the header (line 1)"),
    (["t", "x", "y"], {}, "no acceleration column: none of a3, a2, a1 in the header (line 1)"),
    (["t", "a3"], {"columns": {"a2": "floor_z"}}, "column 'floor_z' (columns.a2) is missing from the header (line 1)"),
    (["t", "a3"], {"units": "mg"}, "column 'a3' (a3), header line 1: unknown unit units = 'mg'"),
    (
        ["t", "a3", "a2"],
        {"units": "g", "column_units": {"a2": "ft/s2"}},
        "column 'a2' (a2), header line 1: unknown unit column_units.a2 = 'ft/s2'",
    ),
]


@pytest.mark.parametrize("header, options, expected", HEADER_ERRORS)
def test_header_and_unit_errors_name_the_file_and_column(tmp_path, header, options, expected):
    n = 20
    columns = [np.arange(n) * 0.01] + [signals(n)[0]] * (len(header) - 1)
    csv = write_csv(tmp_path / "h.csv", header, columns)
    with pytest.raises(RecordingError) as caught:
        read_recordings(csv, **options)
    assert str(caught.value).startswith(f"{csv}: {expected}"), str(caught.value)


def test_windows_cut_every_recording_with_stride(tmp_path):
    h = 0.01
    lengths = {"drive1": 1000, "drive2": 700}
    t = np.concatenate([np.arange(n) * h + 100.0 * r for r, n in enumerate(lengths.values())])
    ids = [name for name, n in lengths.items() for _ in range(n)]
    a3, a2, _ = signals(len(t), seed=3)
    csv = write_csv(tmp_path / "two_drives.csv", ["t", "a3", "a2", "recording"], [t, a3, a2, ids])
    data = read_recordings(csv, units="m/s2", recording_column="recording", window=300, stride=100)
    # (n - window) // stride + 1 windows per recording: 8 + 5
    assert data.n_samples == 13 and data.n_steps == 300 and data.recordings == ["drive1", "drive2"]
    out = write_recordings(tmp_path / "w.h5", data, split="train")
    with h5py.File(out, "r") as f:
        accel, profile, t0 = f["train/accel"][()], f["train/profile_id"][()], f["train/t_start"][()]
        assert f.attrs["n_steps"] == 300 and f.attrs["window"] == 300 and f.attrs["stride"] == 100
    assert profile.tolist() == [0] * 8 + [1] * 5
    np.testing.assert_allclose(t0, [k * 1.0 for k in range(8)] + [100.0 + k * 1.0 for k in range(5)], atol=1e-9)
    np.testing.assert_allclose(accel[9, :, 0], a3[1000 + 100 : 1000 + 400], rtol=2e-7, atol=1e-7)  # drive2's 2nd window
    assert data.window == 300 and len(read_recordings(csv, recording_column="recording", window=700).profile_id) == 2


def test_recordings_errors(tmp_path):
    h, n = 0.01, 50
    t = np.concatenate([np.arange(n) * h, np.arange(n) * h, np.arange(n) * h])
    a3 = signals(3 * n)[0]
    csv = write_csv(tmp_path / "r.csv", ["t", "a3", "recording"], [t, a3, ["A"] * n + ["B"] * n + ["A"] * n])
    with pytest.raises(
        RecordingError, match=rf"column 'recording', row {2 * n + 1} \(line {2 * n + 2}\): recording 'A' appears again"
    ):
        read_recordings(csv, recording_column="recording")
    csv = write_csv(tmp_path / "s.csv", ["t", "a3", "recording"], [t[:80], a3[:80], ["A"] * n + ["B"] * 30])
    with pytest.raises(RecordingError, match=r"column 'recording': recordings have different lengths"):
        read_recordings(csv, recording_column="recording")
    with pytest.raises(
        RecordingError,
        match=rf"column 't' \(recording 'B'\), row {n + 1} \(line {n + 2}\): 30 rows, fewer than window = 40",
    ):
        read_recordings(csv, recording_column="recording", window=40)


def test_failed_write_leaves_no_file_and_overwrite_is_refused(tmp_path, monkeypatch):
    n = 100
    csv = write_csv(tmp_path / "d.csv", ["t", "a3", "a2"], [np.arange(n) * 0.01, *signals(n)[:2]])
    data = read_recordings(csv)
    out_dir = tmp_path / "out"
    original = h5py.Group.create_dataset

    def fail_on_profile(self, name, *args, **kwargs):
        if name == "profile_id":
            raise OSError("disk full (simulated)")
        return original(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", fail_on_profile)
    with pytest.raises(OSError, match="disk full"):
        write_recordings(out_dir / "d.h5", data)
    assert list(out_dir.iterdir()) == []  # neither the target nor a .partial file
    monkeypatch.undo()

    out = write_recordings(out_dir / "d.h5", data)
    before = out.read_bytes()
    with pytest.raises(FileExistsError, match="exists; pass overwrite=true"):
        write_recordings(out, read_recordings(csv, units="g"))
    assert out.read_bytes() == before
    write_recordings(out, read_recordings(csv, units="g"), overwrite=True)
    with h5py.File(out, "r") as f:
        np.testing.assert_allclose(f["test/accel"][0, :, 0], signals(n)[0] * G, rtol=2e-7, atol=1e-7)


def test_app_writes_summary_and_fails_in_one_line_without_leaving_output(tmp_path):
    n = 1000
    t = np.arange(n) * 0.002  # 500 Hz
    a3, a2, _ = signals(n, seed=4)
    csv = write_csv(tmp_path / "drive.csv", ["t", "seat_z", "floor_z"], [t, a3 / G, a2 / G])
    out = tmp_path / "data" / "drive.h5"
    result = qcm_import(
        tmp_path,
        f"input={csv}",
        f"output={out}",
        "units=g",
        "columns.a3=seat_z",
        "columns.a2=floor_z",
        "window=400",
        "stride=200",
    )
    assert result.returncode == 0, result.stderr
    assert (
        "500 Hz" in result.stdout
        and "4 sample(s) x 400 steps" in result.stdout
        and "a3 (in g), a2 (in g)" in result.stdout
    )
    with h5py.File(out, "r") as f:
        np.testing.assert_allclose(f["test/accel"][1, :, 0], a3[200:600], rtol=2e-6, atol=1e-6)
        assert np.isnan(f["test/accel"][..., 2]).all()

    again = qcm_import(tmp_path, f"input={csv}", f"output={out}", "units=g", "columns.a3=seat_z")
    assert again.returncode == 2 and "exists; pass overwrite=true" in again.stderr

    lines = csv.read_text().splitlines()
    del lines[300]  # data row 300: a gap after t = 0.598
    gap = tmp_path / "gap.csv"
    gap.write_text("\n".join(lines) + "\n")
    bad_out = tmp_path / "bad" / "gap.h5"
    result = qcm_import(tmp_path, f"input={gap}", f"output={bad_out}", "units=g", "columns.a3=seat_z")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0, result.stderr
    assert f"{gap}: column 't', row 300 (line 301): gap of 0.004 s" in result.stderr
    assert not bad_out.exists() and not (bad_out.parent.exists() and any(bad_out.parent.iterdir()))


def test_help_documents_every_key(tmp_path):
    config = yaml.safe_load((REPO / "configs" / "import.yaml").read_text())
    keys = [k for k in config if k not in ("defaults", "hydra", "task_name")]
    result = qcm_import(tmp_path, "--help")
    assert result.returncode == 0, result.stderr
    for key in keys:
        assert f"  {key}" in result.stdout, key
    assert "qcm-import input=drive.csv" in result.stdout


def test_delimiters_time_units_and_short_rows(tmp_path):
    n = 50
    a3 = signals(n)[0]
    rows = [f"{k * 10};{x:.9g}" for k, x in enumerate(a3)]  # milliseconds, semicolons
    csv = tmp_path / "semi.csv"
    csv.write_text("t ; a3\n" + "\n".join(rows) + "\n")
    data = read_recordings(csv, time_unit="ms")
    assert data.h == pytest.approx(0.01, rel=1e-12)
    np.testing.assert_allclose(data.accel[0, :, 0], a3, rtol=2e-7, atol=1e-7)
    short = tmp_path / "short.csv"
    short.write_text(
        "t,a3,a2\n" + "\n".join(f"{0.01 * k:.2f},1,2" if k != 9 else f"{0.01 * k:.2f},1" for k in range(n)) + "\n"
    )
    with pytest.raises(RecordingError, match=r"short.csv: column 'a2', row 10 \(line 11\): cell is empty"):
        read_recordings(short)


# -- inputs that used to be taken silently or reported misleadingly (issue 29) ------------------------------
def _drive(tmp_path: Path, n: int = 300, name: str = "drive.csv") -> tuple[Path, list[str]]:
    t = np.arange(n) * 0.01
    lines = ["t,a3,a2"] + [f"{t[k]:.2f},{x:.9g},{y:.9g}" for k, (x, y) in enumerate(zip(*signals(n)[:2]))]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path, lines


def test_duplicate_columns_beyond_float32_and_rate_of_ms_read_as_s_are_refused(tmp_path):
    path, lines = _drive(tmp_path)
    dup = tmp_path / "dup.csv"  # before: the second a2 was read, silently
    dup.write_text("\n".join(["t,a3,a2,a2"] + [f"{line},0" for line in lines[1:]]) + "\n")
    with pytest.raises(
        RecordingError, match=r"dup.csv: header \(line 1\): column 'a2' appears 2 times \(fields 3, 4\)"
    ):
        read_recordings(dup)
    big = tmp_path / "big.csv"  # before: stored as inf
    big.write_text("\n".join(lines[:41] + [lines[41].rsplit(",", 1)[0] + ",1e40"] + lines[42:]) + "\n")
    with pytest.raises(
        RecordingError, match=r"big.csv: column 'a2', row 41 \(line 42\): value 1e\+40 is beyond the float32"
    ):
        read_recordings(big)
    g = tmp_path / "g.csv"  # in g the limit is 9.81 times lower
    g.write_text("\n".join(lines[:2] + [lines[2].rsplit(",", 1)[0] + ",1e38"] + lines[3:]) + "\n")
    read_recordings(g)  # 1e38 m/s² fits float32
    with pytest.raises(RecordingError, match=r"row 2 \(line 3\): value 1e\+38 is beyond"):
        read_recordings(g, units="g")
    ms = tmp_path / "ms.csv"  # time in milliseconds: before, h = 10 s silently
    ms.write_text(
        "\n".join(["t,a3,a2"] + [f"{10 * k},{line.split(',', 1)[1]}" for k, line in enumerate(lines[1:])]) + "\n"
    )
    with pytest.raises(
        RecordingError, match=r"ms.csv: column 't': sampling rate 0.1 Hz .* if the time is in ms, pass time_unit=ms"
    ):
        read_recordings(ms)
    assert read_recordings(ms, time_unit="ms").h == pytest.approx(0.01, rel=1e-12)
    assert read_recordings(ms, rate_range=(0.05, 1.0)).h == pytest.approx(10.0)  # the user says so


def test_encodings_and_stray_quotes_are_named_for_what_they_are(tmp_path):
    path, lines = _drive(tmp_path)
    reference = read_recordings(path).accel
    for encoding in ("utf-16", "utf-8-sig", "utf-32"):  # before: "'utf-8' codec can't decode byte 0xff"
        other = tmp_path / f"{encoding}.csv"
        other.write_text("\n".join(lines) + "\n", encoding=encoding)
        np.testing.assert_array_equal(read_recordings(other).accel, reference)
    latin = tmp_path / "latin.csv"
    latin.write_bytes(("\n".join(lines[:5]) + "\n").encode() + b"0.05,0.1\xb2,0.2\n")
    with pytest.raises(RecordingError, match=r"latin.csv: line 6: byte 0xb2 is not UTF-8 text"):
        read_recordings(latin)
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\x89HDF\r\n\x1a\n\0\0\0")
    with pytest.raises(RecordingError, match="binary.csv: not a text CSV"):
        read_recordings(binary)
    quote = tmp_path / "quote.csv"  # before: "column 'a2', row 300 (line 301): cell is empty"
    quote.write_text("\n".join(lines[:51] + ['0.50,"0.1,0.2'] + lines[52:]) + "\n")
    with pytest.raises(
        RecordingError, match=r"quote.csv: line 52: a double quote \(\"\) opens a field that runs over lines 52-301"
    ):
        read_recordings(quote)
    header = tmp_path / "header.csv"  # before: "no acceleration column ... ['t', 'a3,a2']"
    header.write_text('t,"a3,a2\n' + "\n".join(lines[1:]) + "\n")
    with pytest.raises(RecordingError, match="header.csv: header \\(line 1\\) has an unmatched double quote"):
        read_recordings(header)


def test_task_name_cannot_put_the_run_folder_outside_the_project(tmp_path):
    path, _ = _drive(tmp_path)
    script = Path(sys.executable).parent / "qcm-import"
    result = subprocess.run(
        [str(script), f"input={path}", f"output={tmp_path / 'o.h5'}", "task_name=../../../escaped"],
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
        cwd=tmp_path / "..",
    )
    assert result.returncode == 2
    assert (
        result.stderr.strip()
        == "error: task_name='../../../escaped' must be a plain folder name (no '/', '..' or empty)"
    )
    assert not (tmp_path / "o.h5").exists() and not list(tmp_path.parents[2].glob("escaped*"))


@pytest.mark.parametrize("signum", [15, 2])
def test_sigterm_and_ctrl_c_during_the_write_leave_no_partial_and_one_line(tmp_path, signum):
    n = 100_000
    t = np.arange(n) * 0.001
    a3, a2, _ = np.random.default_rng(0).normal(size=(3, n))
    big = tmp_path / "long.csv"
    np.savetxt(big, np.stack([t, a3, a2], 1), delimiter=",", header="t,a3,a2", comments="", fmt="%.6f")
    out = tmp_path / "out" / "long.h5"
    script = Path(sys.executable).parent / "qcm-import"
    # overlapping windows make the write the long part (40 MB through gzip)
    command = [
        str(script),
        f"input={big}",
        f"output={out}",
        "window=1000",
        "stride=10",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + 120
    while not list(out.parent.glob(".long.h5.*.partial")) if out.parent.exists() else True:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.005)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, stderr
    name = {15: "SIGTERM", 2: "SIGINT"}[signum]
    assert stderr.strip().splitlines() == [
        f"error: interrupted by {name}; temporary files removed, outputs left as they were"
    ]
    assert list(out.parent.iterdir()) == []  # neither the output nor a .partial
