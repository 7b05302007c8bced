"""Two loggers, two clocks (data/two_loggers.py): gravity's vertical, resampling from each sample's own
time stamp, and the clocks' offset and drift, against signals known in closed form at any instant (sums of
sines) recorded the way two phone apps would; and qcm-import input= base_input= end to end."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from hybridqcm.data.csv_checks import RecordingError
from hybridqcm.data.logger_csv import LoggerRecording, read_logger
from hybridqcm.data.resample import lowpass_resample, resample
from hybridqcm.data.two_loggers import align, vertical

REPO = Path(__file__).resolve().parents[1]
HEADER = "Time (s),Acceleration x (m/s^2),Acceleration y (m/s^2),Acceleration z (m/s^2)"


class Sines:
    """A random broadband acceleration a(t) = Σ A_j sin(2π f_j t + φ_j), f uniform in [0.2, 15] Hz: exact at any
    t (many components, so that two such signals share no lag by chance and one has no second alignment)."""

    def __init__(self, seed: int, n: int = 600, rms: float = 0.5):
        rng = np.random.default_rng(seed)
        self.f = rng.uniform(0.2, 15.0, n)
        self.phase = rng.uniform(0, 2 * np.pi, n)
        self.amp = np.full(n, rms * math.sqrt(2.0 / n))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        out = np.empty(t.shape)
        for a in range(0, t.size, 4000):
            block = t[a : a + 4000, None]
            out[a : a + 4000] = np.sin(2 * np.pi * self.f * block + self.phase) @ self.amp
        return out


def _rotation(tilt_deg: float, yaw: float) -> np.ndarray:
    t = math.radians(tilt_deg)
    tilt = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ tilt


def _logger(path, signal, start, seconds, rate, clock_ppm, tilt_deg, rng, noise=0.0, jitter=0.01):
    """A logger switched on at true time `start`: its own stamps from 0 (steps 1/rate (1 + jitter ξ)), its
    clock running (1 + clock_ppm 1e-6) fast, tilted, gravity on its axes; written as a phone app's CSV."""
    n = int(seconds * rate)
    stamps = np.concatenate([[0.0], np.cumsum((1 + jitter * np.clip(rng.standard_normal(n - 1), -3, 3)) / rate)])
    true = start + stamps / (1 + clock_ppm * 1e-6)
    world = np.column_stack([np.zeros(n), np.zeros(n), signal(true) + 9.80665])
    xyz = world @ _rotation(tilt_deg, rng.uniform(0, 2 * np.pi)) + noise * rng.standard_normal((n, 3))
    np.savetxt(path, np.column_stack([stamps, xyz]), delimiter=",", header=HEADER, comments="", fmt="%.7f")
    return path


def test_vertical_from_gravity_whatever_the_tilt():
    rng = np.random.default_rng(0)
    up = 0.3 * rng.standard_normal(5000)
    up -= up.mean()
    world = np.column_stack([np.zeros(5000), np.zeros(5000), up + 9.80665])
    for tilt in (0.0, 7.5, 19.0, 170.0):  # 170: upside down
        v = vertical(world @ _rotation(tilt, 1.1))
        np.testing.assert_allclose(v.values, up, atol=1e-12)
        assert v.tilt_deg == pytest.approx(min(tilt, 180 - tilt), abs=1e-9)


@pytest.mark.parametrize("rate, tolerance", [(100.0, 4e-3), (200.0, 1e-3)])
def test_resampling_from_jittered_stamps_is_exact_below_the_cutoff(rate, tolerance):
    """Irregular samples (1 % jitter) of a band-limited signal, resampled to a 100 Hz grid: the signal's own
    values there (the quadrature alone is off by 5 %), a constant stays constant, and resampled white
    noise keeps its variance (white noise at 100 Hz) or halves it (at 200 Hz: the half above 50 Hz removed)."""
    rng = np.random.default_rng(1)
    signal = Sines(3)
    n = int(60 * rate)
    stamps = np.concatenate([[0.0], np.cumsum((1 + 0.01 * np.clip(rng.standard_normal(n - 1), -3, 3)) / rate)])
    grid = 2.0 + np.arange(5000) / 100.0
    err = resample(stamps, signal(stamps), grid) - signal(grid)
    assert np.abs(err[700:-700]).max() <= tolerance * signal(grid).std()
    assert (
        np.abs(lowpass_resample(stamps, signal(stamps), grid, 50.0, 0.64) - signal(grid)).max()
        > 5 * tolerance * signal(grid).std()
    )
    # a constant: the windowed sinc's ripple is 1e-5 of it (the verticals are resampled with gravity removed)
    np.testing.assert_allclose(resample(stamps, np.full(stamps.size, 9.81), grid), 9.81, rtol=3e-5)
    noise = resample(stamps, rng.standard_normal(stamps.size), grid)
    assert noise.var() == pytest.approx(100.0 / rate, rel=0.08)


def test_offset_and_drift_of_two_clocks(tmp_path):
    """Seat and floor see the same motion (a seat that moves with the floor: no dynamics to confuse the
    clocks), 5 minutes, loggers 23.4 s apart at 100 and 200 Hz with 1 % jitter, tilted 12 and 18 degrees,
    clocks 80 ppm apart: the delay left between the channels within 0.5 ms mid-way (1.5 ms at the ends), the
    drift within 3 of its standard errors and 4 ppm (1.2 ms
    over the 5 minutes), the grid at 100 Hz."""
    rng = np.random.default_rng(2)
    signal = Sines(4)
    seat = read_logger(_logger(tmp_path / "seat.csv", signal, 30.0, 300, 200.0, 50.0, 12.0, rng, noise=0.02))
    floor = read_logger(_logger(tmp_path / "floor.csv", signal, 6.6, 330, 100.0, -30.0, 18.0, rng, noise=0.02))
    aligned = align(seat, floor)
    rep = aligned.report
    true_offset = (30.0 - 6.6) * (1 - 30e-6)  # the floor clock at the seat clock's zero
    true_drift = (1 - 30e-6) / (1 + 50e-6) - 1
    miss = abs(rep["drift_ppm"] - true_drift * 1e6)
    assert rep["drift_applied"] and miss <= 3 * rep["drift_sd_ppm"] and miss <= 4.0, (miss, rep["drift_sd_ppm"])
    # the delay left between the channels (true t_floor - t_seat less the mapping applied) over the grid
    ends = aligned.t0 + np.array([0.0, 0.5, 1.0]) * (aligned.a2.size - 1) * aligned.h
    t_seat = (ends - rep["offset_s"]) / (1 + rep["drift_ppm"] * 1e-6)
    left = true_offset + true_drift * t_seat - (rep["offset_s"] + rep["drift_ppm"] * 1e-6 * t_seat)
    assert abs(left[1]) <= 5e-4 and np.abs(left).max() <= 1.5e-3, left
    assert rep["rate_hz"] == 100.0 and aligned.h == 0.01
    assert rep["seat"]["tilt_deg"] == pytest.approx(12.0, abs=0.05) and rep["floor"]["tilt_deg"] == pytest.approx(
        18.0, abs=0.05
    )
    assert rep["seat"]["rate_hz"] == pytest.approx(200.0, rel=3e-4) and rep["floor"]["rate_hz"] == pytest.approx(
        100.0, rel=3e-4
    )
    # on the grid: the floor's motion at the floor clock's instants, the seat's at the seat clock's instants
    # the mapping assigns them, within the sensor noise (0.02 m/s² per axis; the 200 Hz seat's halved above 50 Hz)
    grid = aligned.t0 + np.arange(aligned.a2.size) * aligned.h
    seat_clock = (grid - rep["offset_s"]) / (1 + rep["drift_ppm"] * 1e-6 * rep["drift_applied"])
    assert np.sqrt(np.mean((aligned.a2 - signal(grid / (1 - 30e-6) + 6.6)) ** 2)) <= 1.2 * 0.02
    assert np.sqrt(np.mean((aligned.a3 - signal(seat_clock / (1 + 50e-6) + 30.0)) ** 2)) <= 1.2 * 0.02 * math.sqrt(0.5)


def test_files_that_share_no_time_are_refused(tmp_path):
    rng = np.random.default_rng(5)
    seat = read_logger(_logger(tmp_path / "seat.csv", Sines(6), 0.0, 120, 100.0, 0.0, 5.0, rng))
    floor = read_logger(_logger(tmp_path / "floor.csv", Sines(7), 500.0, 120, 100.0, 0.0, 5.0, rng))
    with pytest.raises(RecordingError) as caught:
        align(seat, floor)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 'seat.csv'} and {tmp_path / 'floor.csv'}: no common motion")
    assert "do not overlap in time" in message and "\n" not in message


def test_logger_checks_name_the_file_and_row(tmp_path):
    rng = np.random.default_rng(8)
    path = _logger(tmp_path / "l.csv", Sines(9), 0.0, 10, 100.0, 0.0, 0.0, rng)
    lines = path.read_text().splitlines()
    lines[500] = "0.001," + lines[500].split(",", 1)[1]  # the clock restarts at data row 500
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(RecordingError, match=r"column 'Time \(s\)', row 500 \(line 501\): .*the clock restarted here"):
        read_logger(path)
    bad = tmp_path / "axes.csv"
    bad.write_text("t,ax,ay\n0,1,2\n0.01,1,2\n")
    with pytest.raises(RecordingError, match=r"axes.csv: three acceleration axes \(x, y, z\) not found"):
        read_logger(bad)
    flat = LoggerRecording(
        path=tmp_path / "g.csv", t=np.arange(100) * 0.01, xyz=np.ones((100, 3)), columns={}, unit="g"
    )
    with pytest.raises(RecordingError, match=r"g.csv: the mean acceleration is 1.732 m/s², not gravity"):
        align(flat, flat)


def _qcm_import(tmp_path, *overrides):
    script = Path(sys.executable).parent / "qcm-import"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hybridqcm.apps.importer"]
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "COLUMNS": "200"}
    return subprocess.run(
        command + [f"hydra.run.dir={tmp_path / 'run'}", "progress=false", *overrides],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )


def test_qcm_import_two_loggers(tmp_path):
    rng = np.random.default_rng(10)
    signal = Sines(11)
    seat = _logger(tmp_path / "seat.csv", signal, 12.0, 90, 200.0, 20.0, 9.0, rng, noise=0.02)
    floor = _logger(tmp_path / "floor.csv", signal, 2.0, 95, 100.0, -20.0, 15.0, rng, noise=0.02)
    out = tmp_path / "drive.h5"
    proc = _qcm_import(tmp_path, f"input={seat}", f"base_input={floor}", f"output={out}", "window=500")
    assert proc.returncode == 0, proc.stderr
    printed = float(re.search(r"t_floor - t_seat = ([-\d.]+) s", proc.stdout).group(1))
    assert abs(printed - 10.0 * (1 - 20e-6)) < 2e-3 and "tilt 9.00" in proc.stdout and "tilt 15.00" in proc.stdout
    with h5py.File(out) as f:
        report = json.loads(f.attrs["two_loggers"])
        accel, t0 = f["test/accel"][()], f["test/t_start"][()]
        assert f.attrs["h"] == 0.01 and f.attrs["n_steps"] == 500 and f["test/profile_id"][()].tolist() == [0] * len(t0)
    assert abs(report["offset_s"] - 10.0 * (1 - 20e-6)) < 2e-3
    assert accel.shape[0] == 16 and np.isnan(accel[..., 2]).all()  # 80 s in common: 16 windows of 5 s
    np.testing.assert_allclose(np.diff(t0), 5.0, atol=1e-9)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["two_loggers"]["seat"]["rate_hz"] == pytest.approx(200.0, rel=5e-4)
    # shorter than one window: one line, no file
    short = _qcm_import(tmp_path, f"input={seat}", f"base_input={floor}", f"output={tmp_path / 's.h5'}", "window=9000")
    assert short.returncode == 2 and short.stderr.strip().count("\n") == 0
    assert "fewer than window = 9000 (the drive is shorter than one window)" in short.stderr
    assert not (tmp_path / "s.h5").exists()
