"""Windows without information (a car standing still, a clipped logger) are found before any fit,
skipped with a status and counted; the others are estimated as if they were alone."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from hybridqcm.estimation.window_check import WindowCheck, WindowStatus, is_skipped, window_status

T = 500


def _signal(amplitude: float = 1.0, offset: float = 0.0, seed: int = 0) -> torch.Tensor:
    """[T] a sum of sines at 100 Hz (a continuous signal: its extremes are met once)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64) * 0.01
    f = torch.rand(6, generator=g, dtype=torch.float64) * 10 + 0.5
    phase = torch.rand(6, generator=g, dtype=torch.float64) * 2 * math.pi
    return offset + amplitude * torch.sin(2 * math.pi * f[:, None] * t + phase[:, None]).sum(0) / 3


def _windows(*channels_per_window) -> torch.Tensor:
    return torch.stack([torch.stack(list(chs), -1) for chs in channels_per_window])


def test_constant_and_clipped_windows_are_told_from_quiet_and_quantised_ones():
    good = _signal()
    parked = torch.zeros(T)
    gravity = torch.full((T,), 9.80665).float().double() + torch.randint(-2, 3, (T,)) * 2**-20  # float32 jitter
    quiet = _signal(amplitude=1e-4)  # the quietest simulated windows: 1.7e-4 m/s² std, estimated fine
    limit = 0.6 * float(good.abs().max())
    clipped = good.clamp(-limit, limit)  # the logger's full scale at 60 % of the peak
    quantised = torch.round(good / 0.01) * 0.01  # a 0.01 m/s² logger: an extreme may repeat at a flat peak
    signals = _windows(
        (good, good), (good, parked), (gravity, good), (quiet, good), (good, clipped), (quantised, good)
    ).float()
    expected = [0, WindowStatus.NO_SIGNAL, WindowStatus.NO_SIGNAL, 0, WindowStatus.CLIPPED, 0]
    assert window_status(signals).tolist() == [int(e) for e in expected]
    assert (clipped == limit).sum() >= 5 and int(
        max((quantised == quantised.max()).sum(), (quantised == quantised.min()).sum())
    ) < 5
    # a stop with a noisy sensor: no_signal once min_std is the sensor's noise floor
    noisy_stop = 0.005 * torch.randn(T, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    pair = _windows((good, good), (noisy_stop, good))
    assert window_status(pair).tolist() == [0, 0]
    assert window_status(pair, WindowCheck(min_std=0.01)).tolist() == [0, int(WindowStatus.NO_SIGNAL)]
    assert window_status(signals, WindowCheck(clip_samples=None))[4] == 0
    assert is_skipped(window_status(signals)).tolist() == [False, True, True, False, True, False]


@pytest.mark.parametrize("bad", [{"min_std": -1.0}, {"min_std": math.nan}, {"clip_samples": 1}, {"clip_samples": 2.5}])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError):
        WindowCheck(**bad)


# -- qcm-estimate -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """Six noise-free recordings (a3, a2) of the second simulator, and a copy with window 2 parked (a3
    and a2 all zero) and window 4's a2 clipped at 60 % of its peak."""
    root = tmp_path_factory.mktemp("drives")
    clean = root / "clean.h5"
    subprocess.run(
        [sys.executable, str(Path(__file__).parents[1] / "bench" / "foreign_sim.py"), "make", "--out", str(clean)]
        + ["--n", "6", "--steps", "160"],
        check=True,
        capture_output=True,
    )
    damaged = root / "damaged.h5"
    damaged.write_bytes(clean.read_bytes())
    with h5py.File(damaged, "r+") as f:
        accel = f["test/accel"][:]
        accel[2, :, :2] = 0.0
        limit = 0.6 * np.abs(accel[4, :, 1]).max()
        accel[4, :, 1] = np.clip(accel[4, :, 1], -limit, limit)
        f["test/accel"][...] = accel
    return {"clean": clean, "damaged": damaged}


def _estimate(run_dir: Path, data: Path, monkeypatch, *extra) -> dict:
    """qcm-estimate experiment=occupant_roadfree in this process (its run folder: the working directory)."""
    from hydra import compose, initialize_config_dir

    from hybridqcm.apps.estimate import run
    from hybridqcm.config import CONFIG_DIR

    overrides = ["experiment=occupant_roadfree", f"data.path={data}", "n_steps=100", "progress=false"]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("estimate", overrides=[*overrides, "tensorboard=false", "plots=false", *extra])
    run_dir.mkdir(parents=True)
    monkeypatch.chdir(run_dir)
    return run(cfg)


def _rows(run_dir, name="estimates.csv"):
    with open(run_dir / name, newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow  # a faster check of the same behaviour stays in the default suite
def test_a_window_without_information_gets_its_status_and_the_others_their_estimates(
    drives, tmp_path, monkeypatch, capsys
):
    """Before: a parked window ended the whole run in a traceback ('output noise variances must be finite
    and > 0'), no estimates; a clipped one was fitted (p1 8.6 % off, called misfit)."""
    _estimate(tmp_path / "clean", drives["clean"], monkeypatch)
    summary = _estimate(tmp_path / "damaged", drives["damaged"], monkeypatch)
    expected, rows = _rows(tmp_path / "clean"), _rows(tmp_path / "damaged")
    skipped = {2: "no_signal", 4: "clipped"}
    assert [r["index"] for r in rows] == [str(i) for i in range(6)]
    assert [r["status"] for r in _rows(tmp_path / "damaged", "status.csv")] == [
        skipped.get(i, r["status"]) for i, r in enumerate(expected)
    ]
    for i, (row, reference) in enumerate(zip(rows, expected)):
        if i in skipped:
            assert row["status"] == skipped[i] and math.isnan(float(row["m3"])) and math.isnan(float(row["p2"]))
        else:  # every other window: the clean file's estimate, as if the skipped ones were not there
            assert row["status"] == reference["status"]
            assert float(row["m3"]) == pytest.approx(float(reference["m3"]), rel=1e-9)
    assert summary == json.loads((tmp_path / "damaged" / "summary.json").read_text())
    assert summary["skipped_windows"] == {"no_signal": 1, "clipped": 1}
    assert summary["status_counts"]["no_signal"] == summary["status_counts"]["clipped"] == 1
    assert summary["n_samples"] == 6
    truth = h5py.File(drives["clean"], "r")["test/truth_m3"][:]
    errors = [abs(float(r["m3"]) / truth[i] - 1) for i, r in enumerate(rows) if i not in skipped]
    assert summary["m3_mean_rel_err"] == pytest.approx(np.mean(errors), rel=1e-6)  # over the fitted four
    assert "skipped 2 window(s) without information, no estimate: no_signal 1, clipped 1" in capsys.readouterr().out


def test_every_window_skipped_is_a_result_not_a_crash(drives, tmp_path, monkeypatch, capsys):
    data = tmp_path / "all_parked.h5"
    data.write_bytes(drives["clean"].read_bytes())
    with h5py.File(data, "r+") as f:
        f["test/accel"][:, :, :2] = 0.0
    summary = _estimate(tmp_path / "run", data, monkeypatch, "batch_size=2")  # blocks with nothing to fit
    assert summary["skipped_windows"] == {"no_signal": 6, "clipped": 0} and summary["status_counts"]["no_signal"] == 6
    assert {r["status"] for r in _rows(tmp_path / "run")} == {"no_signal"}
    assert "every window was skipped" in capsys.readouterr().out
