"""aggregate=drive with a seat file (issues 31, 32): drives.csv's occupant_mass, occupant_mass_low,
occupant_mass_high, from per-window columns built here on a foam seat and end to end on a qcm-simulate
foam-seat file cut into drives."""

from __future__ import annotations

import csv
import json
import math

import h5py
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from conftest import app_in_process
from hybridqcm.estimation.calibration import SeatLaw, seat_document
from hybridqcm.estimation.solver import SolverStatus
from hybridqcm.reports.drive import aggregate_drives
from test_drive_report import _plan  # the drive settings of the drive tests

K3 = 98935.0  # the reference seat's: drives.csv's m3 = K3 / p2
K3_REF, E, PAN = 1.04e5, 0.4, 8.0  # the foam seat's law (not the simulators' defaults)


def _closed_form_occupant(p2, k3_ref=K3_REF, e=E, pan=PAN):
    """The occupant on the law K3(M) = k3_ref (M/80)^e at p2 = K3(M)/M, M = occupant + pan, solved here by
    bisection (not SeatLaw's closed form)."""
    lo, hi = 1e-3, 1e4
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if k3_ref * (mid / 80) ** e / mid > p2 else (lo, mid)
    return math.sqrt(lo * hi) - pan


def test_drives_csv_carries_the_occupant_through_the_seat_law(tmp_path):
    """Drive A: 6 windows of a 70 kg occupant (1 % p2 noise); drive B: every window misfit. occupant_mass is
    the law's occupant at the drive's p2 = K3 / m3 (bisection here), its interval wider than the data's image
    and than the calibration's alone."""
    rng = np.random.default_rng(5)
    occupant, n = 70.0, 6
    M = occupant + PAN
    p = np.array([620.0 / M, K3_REF * (M / 80) ** E / M])
    sd = 0.01 * p
    theta = np.concatenate([p + rng.standard_normal((n, 2)) * sd, np.tile(p, (4, 1))])
    cov = np.stack([np.diag(sd**2)] * (n + 4))
    p2_low, p2_high = theta[:, 1] - 1.96 * sd[1], theta[:, 1] + 1.96 * sd[1]
    status = [int(SolverStatus.CONVERGED)] * n + [int(SolverStatus.MISFIT)] * 4
    fits = np.array(status) != int(SolverStatus.MISFIT)
    columns = {  # one candidate (rigid) per window, as drive_plan writes drive_cand_*
        "drive_cand_theta": torch.from_numpy(theta)[:, None],
        "drive_cand_cov": torch.from_numpy(cov)[:, None],
        "drive_cand_model_cov": torch.from_numpy(cov)[:, None],
        "drive_cand_status": torch.tensor(status).long()[:, None],
        "drive_cand_fits": torch.from_numpy(fits)[:, None],
        "drive_cand_logz": torch.zeros(n + 4, 1, dtype=torch.float64),
        "drive_model": torch.zeros(n + 4, dtype=torch.long),
        "status": torch.tensor(status),
        "m3_low": torch.from_numpy(K3 / p2_high),
        "m3_high": torch.from_numpy(K3 / p2_low),
    }
    cal_sd = np.array([800.0, 0.02, 1.0])
    seat = SeatLaw(K3_REF, E, PAN, np.diag(cal_sd**2), loads=[0.0, 40.0, 80.0, 120.0])
    plan = _plan([0] * n + [1] * 4, [5.0 * k for k in range(n)] + [5.0 * k for k in range(4)], ("A", "B"), plots=0)
    cfg = OmegaConf.create({"K3": K3, "plots": False, "tensorboard": False})
    aggregate_drives(cfg, {}, plan, columns, tmp_path, ["rigid"], seat=seat)
    with open(tmp_path / "drives.csv", newline="") as handle:
        reader = csv.DictReader(handle)
        assert reader.fieldnames[-3:] == ["occupant_mass", "occupant_mass_low", "occupant_mass_high"]
        a, b = list(reader)
    m3, m3_low, m3_high = (float(a[k]) for k in ("m3", "m3_low", "m3_high"))
    mass, low, high = (float(a[k]) for k in ("occupant_mass", "occupant_mass_low", "occupant_mass_high"))
    assert mass == pytest.approx(_closed_form_occupant(K3 / m3), rel=1e-9)
    assert abs(mass / occupant - 1) < 0.02  # six windows of 1 % in p2, doubled at most by the law
    data_low, data_high = _closed_form_occupant(K3 / m3_low), _closed_form_occupant(K3 / m3_high)
    # the calibration's delta-method std by central differences of the bisection, parameter by parameter
    grad = []
    for i, h in enumerate((1.0, 1e-5, 1e-4)):
        up, down = [K3_REF, E, PAN], [K3_REF, E, PAN]
        up[i] += h
        down[i] -= h
        grad.append((_closed_form_occupant(K3 / m3, *up) - _closed_form_occupant(K3 / m3, *down)) / (2 * h))
    cal = 1.96 * math.sqrt(sum((g * s) ** 2 for g, s in zip(grad, cal_sd)))
    assert mass - low == pytest.approx(math.hypot(mass - data_low, cal), rel=1e-4)
    assert high - mass == pytest.approx(math.hypot(data_high - mass, cal), rel=1e-4)
    assert low <= occupant <= high
    assert b["status"] == "no_usable_window" and b["occupant_mass"] == b["occupant_mass_low"] == ""


def test_aggregate_drive_with_a_seat_file_end_to_end(tmp_path):
    """qcm-simulate foam seat (the law below), two occupants (55, 105 kg) as known loads cycled over 8 windows,
    cut here into two drives of 4 windows each (profile_id, t_start); the seat file holds the simulator's law.
    drives.csv's occupant_mass is within 0.5 % of each drive's truth (noise-free) and its interval covers it."""
    data = tmp_path / "drives.h5"
    # qcm-simulate's and qcm-estimate's runs in-process (their console: test_app_simulate, test_drive_report)
    app_in_process(
        "simulate", tmp_path / "sim", "preset=tiny", f"output={data}", "~splits.train", "splits.test.profiles={A: 6}",
        "samples_per_profile=1", "seat.law=power", f"seat.exponent={E}", f"seat.pan_mass={PAN}",
        "seat.known_loads=[55,105]", "progress=false",
    )  # fmt: skip
    with h5py.File(data, "r+") as f:
        truth = f["test/truth_occupant_mass"][()]
        n = truth.size
        del f["test/profile_id"]
        f["test/profile_id"] = (np.arange(n) % 2).astype(np.int32)
        f["test/t_start"] = (np.arange(n) // 2) * 5.12
    seat = SeatLaw(98935.0, E, PAN, np.diag([50.0**2, 1e-3**2, 0.05**2]), loads=[0.0, 60.0, 120.0])
    seat_file = tmp_path / "seat.json"
    seat_file.write_text(seat_document(seat, {"fit": {}}))
    app_in_process(
        "estimate", tmp_path / "est", "experiment=occupant_roadfree", "occupant.models=[rigid]", "delay=null",
        f"data.path={data}", f"seat_file={seat_file}", "aggregate=drive", "plots=false", "progress=false",
    )  # fmt: skip
    with open(tmp_path / "est" / "drives.csv", newline="") as handle:
        drives = list(csv.DictReader(handle))
    assert [r["drive"] for r in drives] == ["0", "1"]
    for r in drives:
        true = truth[int(r["drive"])]
        assert np.all(truth[int(r["drive"]) :: 2] == true) and r["windows_used"] == str(n // 2)
        mass, low, high = (float(r[k]) for k in ("occupant_mass", "occupant_mass_low", "occupant_mass_high"))
        assert abs(mass / true - 1) < 0.005 and low <= true <= high, (r, true)
    summary = json.loads((tmp_path / "est" / "summary.json").read_text())
    assert summary["mass_scale"]["calibrated"] is True
