"""qcm-import's known_mass column (issue 31): the known load of a calibration drive, one value per recording or
window, written as /<split>/known_mass [M] kg and read back by qcm-calibrate's loader
(estimation/calibration_run.known_loads, a different code path); a load that changes inside a window, a negative
or non-finite one: one line each."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from hybridqcm.data import csv_stream
from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.import_writer import import_recordings
from hybridqcm.data.importer import read_recordings
from hybridqcm.estimation.calibration_run import known_loads
from test_importer import qcm_import


def _drives(path: Path, loads: list[list[float]], n: int = 200, h: float = 0.01) -> Path:
    """One recording per entry of ``loads``, n rows each; the load column holds loads[r][k * n // len] on rows
    of the k-th part of recording r (so a recording may change its load at a known row)."""
    rng = np.random.default_rng(3)
    lines = ["t,a3,a2,load_kg,drive"]
    for r, parts in enumerate(loads):
        for k in range(n):
            load = parts[k * len(parts) // n]
            lines.append(f"{k * h:.4f},{rng.normal(0, 0.3):.6g},{rng.normal(0, 0.3):.6g},{load:g},d{r}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("block_bytes", [97, 1 << 22])
def test_known_mass_per_window_is_read_by_qcm_calibrate(tmp_path, monkeypatch, block_bytes):
    """Loads 0, 40, 80 kg on three drives, and a fourth that changes from 120 to 60 kg at its window boundary
    (row 100 of 200): constant within every window of 100 steps, so accepted; each window carries its own."""
    monkeypatch.setattr(csv_stream, "BLOCK_BYTES", block_bytes)
    csv = _drives(tmp_path / "cal.csv", [[0.0], [40.0], [80.0], [120.0, 60.0]])
    out = tmp_path / "cal.h5"
    options = dict(columns={"known_mass": "load_kg"}, recording_column="drive", window=100)
    layout = import_recordings(csv, out, **options)
    expected = [0, 0, 40, 40, 80, 80, 120, 60]
    assert layout.known_mass.tolist() == expected
    np.testing.assert_array_equal(known_loads(out, "test", None), expected)
    with h5py.File(out, "r") as f:
        assert f["test/known_mass"].dtype == np.float64 and f["test/accel"].shape == (8, 100, 3)
        assert '"known_mass": "kg"' in f.attrs["units"]
    assert read_recordings(csv, **options).known_mass.tolist() == expected  # the in-memory reader agrees


def test_app_takes_a_column_named_known_mass_and_without_one_writes_none(tmp_path):
    csv = _drives(tmp_path / "cal.csv", [[0.0], [75.5]])
    csv.write_text(csv.read_text().replace("load_kg", "known_mass", 1))
    out = tmp_path / "cal.h5"
    result = qcm_import(tmp_path, f"input={csv}", f"output={out}", "recording_column=drive", "progress=false")
    assert result.returncode == 0, result.stderr
    assert "known_mass (in kg)" in result.stdout
    np.testing.assert_array_equal(known_loads(out, "test", None), [0.0, 75.5])
    plain = tmp_path / "plain.h5"
    result = qcm_import(
        tmp_path, f"input={csv}", f"output={plain}", "recording_column=drive", "columns.known_mass=false"
    )
    assert result.returncode == 0, result.stderr
    with h5py.File(plain, "r") as f:
        assert "known_mass" not in f["test"]
    with pytest.raises(Exception, match="known_mass is missing"):
        known_loads(plain, "test", None)


@pytest.mark.parametrize(
    "loads, window, expected",
    [
        (
            [[0.0], [40.0, 80.0]],
            None,
            "row 301 (line 302): the known load changes from 40.0 to 80.0 kg inside a "
            "sample of recording 'd1' starting at row 201",
        ),  # fmt: skip
        ([[0.0, 40.0, 80.0, 120.0]], 100, "row 51 (line 52): the known load changes from 0.0 to 40.0 kg"),
        ([[0.0], [-5.0]], None, "row 201 (line 202): -5.0 kg is negative"),
        ([[0.0], [float("nan")]], None, "row 201 (line 202): cell = 'nan' (NaN or infinite"),
        ([[0.0], [float("inf")]], None, "row 201 (line 202): cell = 'inf' (NaN or infinite"),
    ],
)
def test_bad_known_mass_is_one_line_naming_the_column_and_row(tmp_path, monkeypatch, loads, window, expected):
    monkeypatch.setattr(csv_stream, "BLOCK_BYTES", 97)  # the change falls in a later block than the window start
    csv = _drives(tmp_path / "bad.csv", loads)
    out = tmp_path / "bad.h5"
    with pytest.raises(RecordingError) as error:
        import_recordings(csv, out, columns={"known_mass": "load_kg"}, recording_column="drive", window=window)
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"{csv}: column 'load_kg'") and expected in message, message
    assert not out.exists()
