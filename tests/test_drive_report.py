"""qcm-estimate aggregate=drive: drives.csv / drive_progress.csv from per-window columns built here (known
truth, a change, a drive whose every window is rejected, overlapping windows), and end to end on drives
from the simulator that is not ours (bench/foreign_sim.py) through qcm-import."""

import csv
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from conftest import app_in_process
from hybridqcm.data.import_writer import write_recordings
from hybridqcm.data.importer import read_recordings
from hybridqcm.errors import DatasetError
from hybridqcm.estimation.drive_plan import DrivePlan, drive_plan
from hybridqcm.estimation.solver import SolverStatus
from hybridqcm.estimation.window_check import WindowStatus
from hybridqcm.reports.drive import aggregate_drives

REPO = Path(__file__).resolve().parents[1]
K3 = 98935.0
_spec = importlib.util.spec_from_file_location("foreign_sim", REPO / "bench" / "foreign_sim.py")
fs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fs)


def _rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _plan(profile_id, t_start, names, window_s=5.0, **settings):
    defaults = dict(
        statuses=("converged",),
        weights="reported",
        scale="birge",
        alpha=0.01,
        min_windows=2,
        outlier_alpha=0.001,
        neighbours=2,
        plots=1,
        per_window=("tau",),
    )
    defaults.update(settings)
    return DrivePlan(
        **defaults,
        profile_id=np.asarray(profile_id),
        t_start=np.asarray(t_start, dtype=float),
        names=tuple(names),
        window_s=window_s,
    )


def _columns(masses, rel_sd, rng, status=None):
    """Per-window columns as drive_columns writes them: θ = (p1, p2) drawn around the truth with the
    covariance the window reports (p1 = C3/m3 with C3 = 615, p2 = K3/m3)."""
    masses = np.asarray(masses, float)
    n = masses.size
    p = np.stack([615.0 / masses, K3 / masses], 1)
    sd = rel_sd * p
    cov = np.stack([np.diag(s**2) for s in sd])
    theta = p + rng.standard_normal((n, 2)) * sd
    status = np.full(n, int(SolverStatus.CONVERGED)) if status is None else np.asarray(status)
    p2_low, p2_high = theta[:, 1] - 1.96 * sd[:, 1], theta[:, 1] + 1.96 * sd[:, 1]
    return {
        "drive_cand_theta": torch.from_numpy(theta)[:, None],
        "drive_cand_cov": torch.from_numpy(cov)[:, None],
        "drive_cand_model_cov": torch.from_numpy(cov)[:, None],
        "drive_cand_status": torch.from_numpy(status).long()[:, None],
        "drive_cand_fits": torch.from_numpy(status != int(SolverStatus.MISFIT))[:, None],
        "drive_cand_logz": torch.zeros(n, 1, dtype=torch.float64),
        "drive_model": torch.zeros(n, dtype=torch.long),
        "status": torch.from_numpy(status).long(),
        "m3_low": torch.from_numpy(K3 / p2_high),
        "m3_high": torch.from_numpy(K3 / p2_low),
        "true": torch.from_numpy(np.concatenate([p, np.ones((n, 8))], 1)),
    }


def test_drives_csv_segments_rejections_and_progress(tmp_path, capsys):
    """Drive A: 80 kg, then 110 kg after window 6 (of 12); drive B: every window misfit; drive C: 60 kg with
    windows every 2.5 s of 5 s (overlapping: every other one used)."""
    rng = np.random.default_rng(0)
    mass = [80.0] * 6 + [110.0] * 6 + [70.0] * 4 + [60.0] * 8
    status = [int(SolverStatus.CONVERGED)] * 12 + [int(SolverStatus.MISFIT)] * 4 + [int(SolverStatus.CONVERGED)] * 8
    columns = _columns(mass, 0.01, rng, status)
    pid = [0] * 12 + [1] * 4 + [2] * 8
    t0 = [5.0 * k for k in range(12)] + [5.0 * k for k in range(4)] + [2.5 * k for k in range(8)]
    plan = _plan(pid, t0, ["A", "B", "C"])
    cfg = OmegaConf.create({"K3": K3, "plots": True, "tensorboard": True})
    summary = aggregate_drives(cfg, {}, plan, columns, tmp_path, ["rigid"])
    rows = _rows(tmp_path / "drives.csv")
    assert [(r["drive"], r["segment"]) for r in rows] == [("A", "0"), ("A", "1"), ("B", "0"), ("C", "0")]
    a0, a1, b, c = rows
    assert float(a1["start_s"]) == 30.0 and float(a0["end_s"]) == 30.0  # split at the change
    for r, truth in ((a0, 80.0), (a1, 110.0), (c, 60.0)):
        assert abs(float(r["m3"]) / truth - 1) < 0.02  # 6 windows of 1 %: well inside
        assert float(r["m3_low"]) < float(r["m3"]) < float(r["m3_high"])
        assert float(r["m3_true"]) == pytest.approx(truth)
        assert r["status"] == "ok" and r["model"] == "rigid"
    assert (a0["windows"], a0["windows_used"], a1["windows_used"]) == ("6", "6", "6")
    assert (b["status"], b["m3"], b["windows_rejected"], b["windows_used"]) == ("no_usable_window", "", "4", "0")
    assert (c["windows"], c["windows_used"], c["windows_overlapping"]) == ("8", "4", "4")
    assert (
        "drive B: every one of its 4 window(s) was rejected (rejected:misfit); no estimate" in capsys.readouterr().out
    )
    # 1 % windows: ±5 % after the first window (1.96 %), ±2 % once the interval narrowed below 2 %
    assert float(a0["t_to_5pct_s"]) == 5.0 and 5.0 < float(a0["t_to_2pct_s"]) <= 15.0
    progress = _rows(tmp_path / "drive_progress.csv")
    assert len(progress) == len(mass)
    first = [r for r in progress if r["drive"] == "A" and r["segment"] == "1"]
    assert [r["windows_used"] for r in first] == [str(k) for k in range(1, 7)]
    assert float(first[0]["t_s"]) == 5.0 and float(first[-1]["t_s"]) == 30.0
    last = first[-1]
    assert (last["m3"], last["m3_low"], last["m3_high"]) == (a1["m3"], a1["m3_low"], a1["m3_high"])
    assert [r["used"] for r in progress if r["drive"] == "C"] == ["used", "overlapping"] * 4
    assert summary["drives"] == 3 and summary["drives_split"] == 1 and summary["drives_without_estimate"] == 1
    assert (tmp_path / "plots" / "drive_A.png").exists()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0}).Reload()
    assert "drive/drive_A" in events.Tags()["images"]


def _selection_columns(rng, n=8, mass=75.0):
    """Windows of an occupant-model selection over rigid, body1, rigid+delay (θ = p1, p2, r1, k1, c1, tau):
    each candidate's estimate around the truth with its own covariance, evidences drawn so that the windows'
    own choices are mixed."""
    names = ["rigid", "body1", "rigid+delay"]
    p = np.array([615.0 / mass, K3 / mass, 0.5, 900.0, 30.0, 0.0])
    theta = np.full((n, 3, 6), np.nan)
    cov = np.full((n, 3, 6, 6), np.nan)
    for c, present in enumerate(([0, 1], [0, 1, 2, 3, 4], [0, 1, 5])):
        for w in range(n):
            a = rng.standard_normal((len(present), len(present)))
            block = a @ a.T + len(present) * np.eye(len(present))
            block *= np.outer(0.02 * np.abs(p[present]) + 1e-3, 0.02 * np.abs(p[present]) + 1e-3)
            theta[w, c, present] = p[present] + np.linalg.cholesky(block) @ rng.standard_normal(len(present))
            cov[w, c][np.ix_(present, present)] = block
    logz = rng.normal(0.0, 2.0, (n, 3))
    status = np.zeros((n, 3), dtype=np.int64)
    return names, {
        "drive_cand_theta": torch.from_numpy(theta),
        "drive_cand_cov": torch.from_numpy(cov),
        "drive_cand_model_cov": torch.from_numpy(cov),
        "drive_cand_status": torch.from_numpy(status),
        "drive_cand_fits": torch.ones(n, 3, dtype=torch.bool),
        "drive_cand_logz": torch.from_numpy(logz),
        "drive_model": torch.from_numpy(logz.argmax(1)),
        "status": torch.zeros(n, dtype=torch.long),
        "m3_low": torch.full((n,), mass * 0.9, dtype=torch.float64),
        "m3_high": torch.full((n,), mass * 1.1, dtype=torch.float64),
    }


def _information_mean(theta, cov):
    """Σ Λ_w θ_w / Σ Λ_w written out with numpy (the combination's definition)."""
    precision = [np.linalg.inv(c) for c in cov]
    return np.linalg.solve(sum(precision), sum(P @ t for P, t in zip(precision, theta)))


@pytest.mark.parametrize("rigid_wins", [True, False])
def test_a_drive_pools_its_windows_under_the_model_of_most_summed_evidence(tmp_path, rigid_wins):
    """The drive's model is the one with the most evidence summed over its windows (a model's delay variant
    counts for it: rigid+delay is rigid with the window's own delay), its prior counted once per drive; every
    window is then combined under that model, also those whose own choice was another. body1 leads or trails
    the better rigid variant by 1 nat in 6 windows and leads by 2 in the other 2, its prior 0.2 nats above
    rigid's: summed, body1 - rigid = ∓6 + 4 - 7 x 0.2."""
    rng = np.random.default_rng(5)
    names, columns = _selection_columns(rng)
    logz = columns["drive_cand_logz"]
    best_rigid = torch.maximum(logz[:, 0], logz[:, 2])
    logz[:, 1] = best_rigid + (-1.0 if rigid_wins else 1.0)
    logz[::4, 1] = best_rigid[::4] + 2.0  # two windows on their own prefer body1 either way
    columns["drive_model"] = logz.argmax(1)
    log_prior = {"rigid": -0.2, "body1": 0.0}
    # in θ (space="linear"), the windows summed as they are (prior="windows": these windows carry no prior columns,
    # which prior="once" would read as the body prior): the combination that this test computes independently
    plan = _plan([0] * 8, [5.0 * k for k in range(8)], ["D"], per_window=("tau",), space="linear", prior="windows")
    cfg = OmegaConf.create({"K3": K3, "plots": False, "tensorboard": False})
    params = ("p1", "p2", "r1", "k1", "c1", "tau")
    aggregate_drives(cfg, {}, plan, columns, tmp_path, names, params, log_prior)
    (row,) = _rows(tmp_path / "drives.csv")
    if rigid_wins:  # per window the rigid variant (with or without its delay) of the higher evidence
        pick, keep = [0 if logz[w, 0] >= logz[w, 2] else 2 for w in range(8)], [0, 1]  # τ: each window's own
    else:
        pick, keep = [1] * 8, [0, 1, 2, 3, 4]
    assert rigid_wins == (2 in pick or 0 in pick)
    theta = [columns["drive_cand_theta"][w, c, keep].numpy() for w, c in enumerate(pick)]
    cov = [columns["drive_cand_cov"][w, c][keep][:, keep].numpy() for w, c in enumerate(pick)]
    expected = K3 / _information_mean(theta, cov)[1]
    assert row["model"] == ("rigid" if rigid_wins else "body1")
    assert float(row["m3"]) == pytest.approx(expected, rel=1e-10)
    assert row["windows_used"] == "8" and "body1:" in row["windows_models"]
    assert float(row["model_margin"]) == pytest.approx(abs((-6.0 if rigid_wins else 6.0) + 4.0 - 7 * 0.2))


def test_drive_prior_once_takes_the_windows_priors_out_of_their_posteriors(tmp_path):
    """drive.prior=once on body1 windows that carry their prior (drive_cand_prior_*, a third of the smallest
    information on the body parameters): in θ (space="linear") the drive's mean is, written out with numpy,
    (Σ Λ_w − (n − 1) P)⁻¹ (Σ Λ_w θ_w − (n − 1) P μ): n posteriors, n − 1 of their priors taken out."""
    rng = np.random.default_rng(6)
    names, columns = _selection_columns(rng)
    columns["drive_cand_logz"][:, 1] += 50.0  # body1 carries the drive
    columns["drive_model"] = columns["drive_cand_logz"].argmax(1)
    keep, n = [0, 1, 2, 3, 4], 8
    theta = [columns["drive_cand_theta"][w, 1, keep].numpy() for w in range(n)]
    cov = [columns["drive_cand_cov"][w, 1][keep][:, keep].numpy() for w in range(n)]
    smallest = min(np.linalg.eigvalsh(np.linalg.inv(c)).min() for c in cov)
    lam = np.array([0.0, 0.0, 1.0, 1.0, 1.0, 0.0]) * smallest / 3
    mu = np.array([0.0, 0.0, 0.6, 950.0, 28.0, 0.0])
    columns["drive_cand_prior_precision"] = torch.from_numpy(np.broadcast_to(lam, (n, 3, 6)).copy())
    columns["drive_cand_prior_mean"] = torch.from_numpy(np.broadcast_to(mu, (n, 3, 6)).copy())
    cfg = OmegaConf.create({"K3": K3, "plots": False, "tensorboard": False})
    params = ("p1", "p2", "r1", "k1", "c1", "tau")
    precision = [np.linalg.inv(c) for c in cov]
    P, m = np.diag(lam[keep]), mu[keep]
    expected = np.linalg.solve(
        sum(precision) - (n - 1) * P, sum(L @ t for L, t in zip(precision, theta)) - (n - 1) * P @ m
    )
    for prior, mean in (("once", expected), ("windows", _information_mean(theta, cov))):
        plan = _plan([0] * n, [5.0 * k for k in range(n)], ["D"], space="linear", prior=prior)
        aggregate_drives(cfg, {}, plan, columns, tmp_path, names, params, None)
        (row,) = _rows(tmp_path / "drives.csv")
        assert row["model"] == "body1" and row["windows_used"] == "8"
        assert float(row["m3"]) == pytest.approx(K3 / mean[1], rel=1e-10)
    assert abs(expected[1] / _information_mean(theta, cov)[1] - 1) > 1e-5  # far beyond the 1e-10 checked above


def test_a_window_the_drives_model_did_not_fit_is_rejected(tmp_path):
    """A window where the drive's model ended misfit is not combined (counted as rejected, with the reason),
    even when another model fitted it and won there."""
    rng = np.random.default_rng(6)
    names, columns = _selection_columns(rng, n=6)
    columns["drive_cand_logz"][:, 1] = -50.0  # body1 loses everywhere: the drive is rigid
    columns["drive_cand_fits"][2, [0, 2]] = False  # window 2: neither rigid variant fits
    columns["drive_cand_status"][2, [0, 2]] = int(SolverStatus.MISFIT)
    columns["drive_cand_logz"][2, 1] = 10.0
    plan = _plan([0] * 6, [5.0 * k for k in range(6)], ["D"])
    cfg = OmegaConf.create({"K3": K3, "plots": False, "tensorboard": False})
    aggregate_drives(cfg, {}, plan, columns, tmp_path, names, ("p1", "p2", "r1", "k1", "c1", "tau"), None)
    (row,) = _rows(tmp_path / "drives.csv")
    assert (row["model"], row["windows_used"], row["windows_rejected"]) == ("rigid", "5", "1")
    used = [r["used"] for r in _rows(tmp_path / "drive_progress.csv")]
    assert used[2] == "rejected:misfit" and used.count("used") == 5


def test_windows_without_information_are_skipped_and_counted(tmp_path, capsys):
    """no_signal / clipped windows (kept from the fit: NaN estimates, estimation/window_check.py) are never
    combined and are counted apart from the rejected ones; a drive of nothing else has no estimate."""
    rng = np.random.default_rng(3)
    status = [0, int(WindowStatus.NO_SIGNAL), 0, 0, int(SolverStatus.MISFIT), 0]
    status += [int(WindowStatus.CLIPPED), int(WindowStatus.NO_SIGNAL)]
    columns = _columns([70.0] * 6 + [90.0] * 2, 0.01, rng, status)
    for key in ("drive_cand_theta", "drive_cand_cov", "drive_cand_model_cov", "m3_low", "m3_high"):
        columns[key][[1, 6, 7]] = math.nan  # as drive_skipped_columns / skipped_tables write them
    columns["drive_cand_fits"][[1, 6, 7]] = False
    columns["drive_cand_logz"][[1, 6, 7]] = -math.inf
    plan = _plan([0] * 6 + [1] * 2, [5.0 * k for k in range(6)] + [0.0, 5.0], ["A", "B"])
    cfg = OmegaConf.create({"K3": K3, "plots": False, "tensorboard": False})
    aggregate_drives(cfg, {}, plan, columns, tmp_path, ["rigid"])
    a, b = _rows(tmp_path / "drives.csv")
    assert (a["windows"], a["windows_used"], a["windows_skipped"], a["windows_rejected"]) == ("6", "4", "1", "1")
    assert abs(float(a["m3"]) / 70.0 - 1) < 0.02 and a["status"] == "ok"
    assert (b["status"], b["windows_skipped"], b["windows_rejected"]) == ("no_usable_window", "2", "0")
    assert "drive B: every one of its 2 window(s)" in capsys.readouterr().out
    used_column = [r["used"] for r in _rows(tmp_path / "drive_progress.csv")]
    assert used_column == ["used", "skipped:no_signal", "used", "used", "rejected:misfit", "used"] + [
        "skipped:clipped",
        "skipped:no_signal",
    ]


def test_drive_plan_needs_the_drives_layout(tmp_path):
    path = tmp_path / "no_t.h5"
    with h5py.File(path, "w") as f:
        f["test/accel"] = np.zeros((3, 10, 3), np.float32)
        f["test/profile_id"] = np.zeros(3, np.int32)
    cfg = OmegaConf.create({"aggregate": "drive", "drive": {}})
    with pytest.raises(DatasetError, match=r"no_t.h5: /test lacks \['t_start'\], which aggregate=drive needs"):
        drive_plan(cfg, {"path": path, "split": "test", "n_samples": 3, "h": 0.01})
    cfg = OmegaConf.create({"aggregate": "trip"})
    with pytest.raises(Exception, match="aggregate='trip': give drive"):
        drive_plan(cfg, {"path": path, "split": "test", "n_samples": 3, "h": 0.01})


def test_drive_plan_checks_the_joint_setting(tmp_path):
    path = tmp_path / "drives.h5"
    with h5py.File(path, "w") as f:
        f["test/accel"] = np.zeros((3, 10, 3), np.float32)
        f["test/profile_id"] = np.zeros(3, np.int32)
        f["test/t_start"] = np.arange(3, dtype=np.float64)
    settings = {"alpha": 0.01, "min_windows": 2, "outlier_alpha": 0.001, "neighbours": 2, "plots": 0}
    plan = {"path": path, "split": "test", "n_samples": 3, "h": 0.01}
    cfg = OmegaConf.create({"aggregate": "drive", "drive": {**settings, "joint": "progress"}})
    assert drive_plan(cfg, plan).joint == "progress"
    cfg = OmegaConf.create({"aggregate": "drive", "drive": {**settings, "joint": "always"}})
    with pytest.raises(Exception, match=r"drive.joint='always': choose one of \['none', 'final', 'progress'\]"):
        drive_plan(cfg, plan)
    # the combination's defaults (estimation/drive.py) and their one-line refusals
    default = drive_plan(OmegaConf.create({"aggregate": "drive", "drive": settings}), plan)
    assert (default.scale, default.split, default.space) == ("marginal", "pooled", "log")
    assert (default.prior, default.prior_from) == ("once", "model")
    for key, bad, choices in [
        ("scale", "robust", r"\['none', 'birge', 'marginal'\]"),
        ("split", "chow", r"\['wald', 'pooled'\]"),
        ("space", "sqrt", r"\['log', 'linear'\]"),
        ("prior", "twice", r"\['windows', 'once'\]"),
        ("prior_from", "both", r"\['model', 'reported'\]"),
    ]:
        cfg = OmegaConf.create({"aggregate": "drive", "drive": {**settings, key: bad}})
        with pytest.raises(Exception, match=rf"drive.{key}='{bad}': choose one of {choices}"):
            drive_plan(cfg, plan)


@pytest.mark.parametrize(
    "occupant",
    [
        pytest.param(["occupant.models=[rigid]", "delay=null"], id="rigid"),
        # each segment and its running estimate from joint fits of its windows read again from the file
        pytest.param(["occupant.models=[rigid]", "delay=null", "drive.joint=progress"], id="rigid-joint"),
        # occupant_roadfree's default: rigid, body1, body2 by evidence, delay auto (191 s on 2 shared cores)
        pytest.param([], id="default-models", marks=pytest.mark.slow),
    ],
)
def test_aggregate_drive_end_to_end_on_foreign_drives(tmp_path, occupant):
    """Two 32 s drives (2 % noise) with a 6 s stop half-way and another occupant after it: imported with
    4 s windows, estimated in blocks of at most 2 000 steps (no restarts: the stop's windows would only cost
    time), each split at the stop (± one window), each segment within 3 % of its occupant. One window of the
    first drive is all zeros (a logger standing still): skipped (no_signal), counted, not combined."""
    out = tmp_path / "drives"
    fs.main(["drives", "--out", str(out), "--n", "2", "--duration", "32", "--stop-s", "6", "--change"]
            + ["--noise", "0.02", "--seed", "4"])  # fmt: skip
    data = read_recordings(out / "drives.csv", recording_column="recording", window=400)
    data.accel[1, :, :2] = 0.0
    h5 = write_recordings(tmp_path / "drives.h5", data)
    run = tmp_path / "run"
    overrides = ["experiment=occupant_roadfree", f"data.path={h5}", *occupant]
    overrides += ["aggregate=drive", "restarts.count=0", "block_samples=2000", "progress=false"]
    if "drive.joint=progress" in occupant:  # qcm-estimate's run in-process; the rigid case runs it on the console
        app_in_process("estimate", run, *overrides)
    else:
        cmd = [sys.executable, "-m", "hybridqcm.apps.estimate", *overrides, f"hydra.run.dir={run}"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
    truth = json.loads((out / "truth.json").read_text())["drives"]
    rows = _rows(run / "drives.csv")
    assert sorted({r["drive"] for r in rows}) == sorted(truth)
    for name, record in truth.items():
        segs = [r for r in rows if r["drive"] == name]
        assert len(segs) == 2, segs
        stop = record["stop_s"]
        assert stop[0] - 4.0 <= float(segs[1]["start_s"]) <= stop[1] + 4.0
        for seg, m3 in zip(segs, (record["m3"], record["m3_after"])):
            assert abs(float(seg["m3"]) / m3 - 1) < 0.03
    assert {r["fit"] for r in rows} == {"joint" if "drive.joint=progress" in occupant else "combined"}
    summary = json.loads((run / "summary.json").read_text())
    assert summary["drive_aggregate"]["drives_split"] == 2
    assert summary["blocks"] == 4  # block_samples: 5 windows of 400 steps read per block at most, 18 windows
    progress = _rows(run / "drive_progress.csv")
    assert len(progress) == data.n_samples
    assert _rows(run / "estimates.csv")[1]["status"] == "no_signal" and data.profile_id[1] == 0
    assert [r["used"] for r in progress if r["index"] == "1"] == ["skipped:no_signal"]
    first = [r for r in rows if r["drive"] == data.recordings[0]]
    assert (first[0]["windows_skipped"], first[1]["windows_skipped"]) == ("1", "0")
    assert summary["skipped_windows"]["no_signal"] == 1


def test_foreign_drives_agree_with_dop853():
    """The drive simulator's convolution with each vehicle's impulse response (eigen-decomposed) against
    scipy's DOP853 on the same piecewise-linear road, from rest: a3 and a2 to 5e-7 of their range (DOP853 steps
    across the road's kinks; the hold is exact there)."""
    from scipy.integrate import solve_ivp

    n, dt, n_fine = 2, 1e-3, 1500
    v = fs.draw_vehicles(n, np.random.default_rng(2))
    v["C1"] = np.zeros(n)
    accel, cls = fs.drive_accelerations(v, dt, n_fine, np.random.default_rng(7), speed_mps=30 / 3.6, classes=[0, 1, 2])
    rng = np.random.default_rng(7)  # replay the simulator's stream: classes, then each road
    assert (rng.choice(np.asarray([0, 1, 2]), n) == cls).all()
    grid = np.arange(n_fine) * dt
    for i in range(n):
        u = fs.drive_road(n_fine, 30 / 3.6 * dt, int(cls[i]), rng)
        u = u - u[0]  # the car at rest on the road where it starts
        A, B = fs._state_space(v, i)
        sol = solve_ivp(
            lambda t, x, A=A, B=B, u=u: A @ x + B[:, 0] * np.interp(t, grid, u),
            (0, grid[-1]),
            np.zeros(6),
            method="DOP853",
            t_eval=grid[::10],
            rtol=1e-11,
            atol=1e-14,
            max_step=dt,
        )
        ref = (A[3:5] @ sol.y + np.outer(B[3:5, 0], u[::10])).T
        assert np.abs(ref - accel[i, ::10]).max() <= 5e-7 * np.abs(ref).max()


def test_windows_with_and_without_their_own_delay_combine_as_the_joint_fit(tmp_path):
    """A drive whose windows chose rigid and rigid+delay (τ each window's own) is one rigid drive: its m3 and
    σ equal the joint least-squares fit of all windows at once — (p1, p2) shared, each window its own initial
    state and, where it has one, its own delay column — solved directly as one problem (the independent fact;
    a linear model, so the Gaussian combination is exact)."""
    g = torch.Generator().manual_seed(11)
    truth = torch.tensor([615.0 / 80.0, K3 / 80.0], dtype=torch.float64)
    n_w, rows, n_state = 6, 60, 3
    windows = []
    for w in range(n_w):
        A = torch.randn(rows, 2, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.01], dtype=torch.float64)
        own = n_state + (1 if w >= 3 else 0)  # windows 3..5 carry their own delay column
        B = torch.randn(rows, own, generator=g, dtype=torch.float64)
        y = A @ truth + B @ torch.randn(own, generator=g, dtype=torch.float64)
        y = y + 0.05 * torch.randn(rows, generator=g, dtype=torch.float64)
        windows.append((A, B, y))
    theta = torch.full((n_w, 2, 3), math.nan, dtype=torch.float64)  # candidates rigid, rigid+delay; p1, p2, tau
    cov = torch.full((n_w, 2, 3, 3), math.nan, dtype=torch.float64)
    for w, (A, B, y) in enumerate(windows):
        J = torch.cat([A, B], 1)
        c = torch.linalg.inv(J.T @ J)  # unit noise variance: the weights are relative, as are the answers
        est = c @ J.T @ y
        if w < 3:
            theta[w, 0, :2], cov[w, 0, :2, :2] = est[:2], c[:2, :2]
        else:  # the delay: the last own column, kept with the parameters as the selection reports it
            keep = [0, 1, J.shape[1] - 1]
            theta[w, 1], cov[w, 1] = est[keep], c[keep][:, keep]
    logz = torch.tensor([[0.0, -math.inf]] * 3 + [[-5.0, 0.0]] * 3, dtype=torch.float64)
    columns = {
        "drive_cand_theta": theta,
        "drive_cand_cov": cov,
        "drive_cand_model_cov": cov.clone(),
        "drive_cand_status": torch.zeros(n_w, 2, dtype=torch.long),
        "drive_cand_fits": torch.isfinite(logz),
        "drive_cand_logz": logz,
        "drive_model": logz.argmax(1),
        "status": torch.zeros(n_w, dtype=torch.long),
        "m3_low": torch.full((n_w,), 70.0, dtype=torch.float64),
        "m3_high": torch.full((n_w,), 90.0, dtype=torch.float64),
    }
    plan = _plan([0] * n_w, [5.0 * k for k in range(n_w)], ["D"], scale="none", space="linear")  # the linear fit
    cfg = OmegaConf.create({"K3": K3, "plots": False, "tensorboard": False})
    aggregate_drives(cfg, {}, plan, columns, tmp_path, ["rigid", "rigid+delay"], ("p1", "p2", "tau"))
    (row,) = _rows(tmp_path / "drives.csv")
    # the joint problem: columns (p1, p2) shared, then each window's own block
    widths = [B.shape[1] for _, B, _ in windows]
    J = torch.zeros(n_w * rows, 2 + sum(widths), dtype=torch.float64)
    col = 2
    for w, (A, B, _) in enumerate(windows):
        J[w * rows : (w + 1) * rows, :2] = A
        J[w * rows : (w + 1) * rows, col : col + widths[w]] = B
        col += widths[w]
    y = torch.cat([w[2] for w in windows])
    cov_joint = torch.linalg.inv(J.T @ J)
    p2, sd_p2 = float((cov_joint @ J.T @ y)[1]), float(cov_joint[1, 1].sqrt())
    assert (row["model"], row["windows_used"], row["windows_models"]) == ("rigid", "6", "rigid:3;rigid+delay:3")
    assert float(row["m3"]) == pytest.approx(K3 / p2, rel=1e-9)
    assert float(row["m3_std"]) == pytest.approx(K3 / p2**2 * sd_p2, rel=1e-7)


def test_unsettled_fits_and_models_that_rarely_settle_do_not_choose_the_drives_model():
    """drive_model: rigid leads body2 by 1 nat in each of 6 windows; one body2 fit that ran out of iterations
    claims 100 nats more (a Laplace evidence away from an optimum): it does not weigh. Settled in 2 windows
    of 6 only, where it leads by 5, body2 is not in the race at all."""
    from hybridqcm.estimation.drive_model import drive_model

    names = ["rigid", "body2"]
    logz = torch.tensor([[0.0, -1.0]] * 6, dtype=torch.float64)
    fits = torch.ones(6, 2, dtype=torch.bool)
    settled = torch.ones(6, 2, dtype=torch.bool)
    chosen = torch.zeros(6, dtype=torch.long)
    logz[0, 1], settled[0, 1] = 100.0, False
    family, variant, margin, _ = drive_model(logz, fits, chosen, names, None, settled)
    assert family == "rigid" and margin == pytest.approx(5.0) and variant.tolist() == [0] * 6
    family, _, _, _ = drive_model(logz, fits, chosen, names, None, torch.ones_like(settled))
    assert family == "body2"  # the same numbers, the fit taken as settled
    logz[:, 1], settled[:, 1] = 5.0, False
    settled[[1, 2], 1] = True
    family, _, margin, _ = drive_model(logz, fits, chosen, names, None, settled)
    assert family == "rigid" and margin == math.inf
