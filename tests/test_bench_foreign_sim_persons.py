"""Seated persons and two logger clocks in the simulator that is not ours (bench/foreign_sim.py), and the
Cramér–Rao bound of the occupant's static mass (bench/occupant_crb.py).

Each check against a fact found outside the code under test: the seat's closed-form transmissibility with a
one-mode body (SPEC § 10), the rigid seat's state space written out by hand, a shift of whole samples, and
the 1/sqrt(T) law of the bound's information on a stationary input.
"""

import csv
import importlib.util
import json
import re
from pathlib import Path

import numpy as np
from scipy import signal
from scipy.interpolate import CubicSpline


def _load(name):
    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


fs = _load("foreign_sim")
crb = _load("occupant_crb")


def test_body1_transmissibility_is_the_closed_form():
    """(a) A long noise-free body1 recording: a3/a2 by cross-spectra equals
    (C3 s + K3)/(s² (m_s + m_b T_b) + C3 s + K3), T_b = (c_b s + k_b)/(m_b s² + c_b s + k_b), near 2-8 Hz,
    and the rigid formula with the same static mass does not."""
    v = fs.draw_vehicles(2, np.random.default_rng(3))
    fs.draw_persons(v, "body1", np.random.default_rng(4))
    h = 0.01
    accel, *_ = fs.simulate(v, 6000, h, np.random.default_rng(5), warmup=(2.0, 3.0), sub=5)
    for i in range(2):
        f, P22 = signal.welch(accel[i, :, 1], fs=1 / h, nperseg=1000)
        _, P23 = signal.csd(accel[i, :, 1], accel[i, :, 0], fs=1 / h, nperseg=1000)
        s = 2j * np.pi * f
        C3, K3 = v["C3"][i], v["K3"][i]
        m_s, m_b, k_b, c_b = v["pan"][i] + v["m_r"][i], v["m_b"][i], v["k_b"][i], v["c_b"][i]
        T_b = (c_b * s + k_b) / (m_b * s**2 + c_b * s + k_b)
        H = (C3 * s + K3) / (s**2 * (m_s + m_b * T_b) + C3 * s + K3)
        rigid = (C3 * s + K3) / (s**2 * (m_s + m_b) + C3 * s + K3)
        err = np.abs(P23 / P22 / H - 1)
        for lo in range(2, 8):  # 1 Hz bands: the estimate's leakage, not the physics, is what is left
            assert err[(f >= lo) & (f < lo + 1)].mean() < 0.04, (i, lo)
        band = (f >= 2) & (f <= 8)
        assert np.median(err[band]) < 0.01
        assert np.abs(P23 / P22 / rigid - 1)[band].max() > 0.2
        assert abs(v["m3"][i] - (m_s + m_b)) < 1e-9  # truth_m3: pan + person, the static mass


def test_rigid_default_is_the_old_seat():
    """(b) The default rigid vehicle's matrices are the old formula written out; a person that is all rigid on
    a massless pan, run through the padded five-body model, records what the rigid vehicle records."""
    v = fs.draw_vehicles(3, np.random.default_rng(7), c1_max=300.0)
    for i in range(3):
        A, B = fs._state_space(v, i)
        m3, m2, m1 = v["m3"][i], v["m2"][i], v["m1"][i]
        C3, C2, C1, K3, K2, K1 = (v[k][i] for k in ("C3", "C2", "C1", "K3", "K2", "K1"))
        a3 = [-K3 / m3, K3 / m3, 0, -C3 / m3, C3 / m3, 0]
        a2 = [K3 / m2, -(K3 + K2) / m2, K2 / m2, C3 / m2, -(C3 + C2) / m2, C2 / m2]
        a1 = [0, K2 / m1, -(K2 + K1) / m1, 0, C2 / m1, -(C2 + C1) / m1]
        np.testing.assert_allclose(A[3:], [a3, a2, a1], rtol=1e-15)
        np.testing.assert_allclose(B[3:], [[0, 0], [0, 0], [K1 / m1, C1 / m1]], rtol=1e-15)
    p = {k: val.copy() for k, val in v.items()}
    fs.draw_persons(p, "mixed", np.random.default_rng(0))
    p["occupant"][:] = 0
    p["pan"][:] = 0.0
    p["m_s"] = p["m3"] = v["m3"].copy()
    old, road_old, *_ = fs.simulate(v, 120, 0.01, np.random.default_rng(2), warmup=(1.0, 2.0))
    new, road_new, *_ = fs.simulate(p, 120, 0.01, np.random.default_rng(2), warmup=(1.0, 2.0))
    np.testing.assert_array_equal(road_old, road_new)
    np.testing.assert_allclose(new, old, rtol=0, atol=1e-12 * np.abs(old).max())


def test_delay_shifts_a3_only():
    """(c) At h = 1 ms a3 5 ms late is the undelayed a3 five samples earlier; a2, a1 and the road are untouched.
    Delays between fine points (0.5 ms late, 0.3 ms early) agree with a cubic spline through the undelayed a3
    (to 1e-6 of its range; a spline's own error there is about 1e-8)."""
    v = fs.draw_vehicles(2, np.random.default_rng(1))
    fs.draw_persons(v, "body2", np.random.default_rng(2))
    kw = dict(warmup=(0.5, 0.6), sub=1)
    base, road, *_ = fs.simulate(v, 400, 0.001, np.random.default_rng(3), **kw)
    late, road_late, *_ = fs.simulate(v, 400, 0.001, np.random.default_rng(3), delay_s=np.full(2, 0.005), **kw)
    np.testing.assert_array_equal(late[:, :, 1:], base[:, :, 1:])
    np.testing.assert_array_equal(road_late, road)
    np.testing.assert_allclose(late[:, 5:, 0], base[:, :-5, 0], rtol=0, atol=1e-12 * np.abs(base).max())
    t = np.arange(400) * 0.001
    for d in (0.0005, -0.0003):  # late, early
        part, *_ = fs.simulate(v, 400, 0.001, np.random.default_rng(3), delay_s=np.full(2, d), **kw)
        for i in range(2):
            spline = CubicSpline(t, base[i, :, 0])(t[5:-5] - d)
            scale = np.abs(base[i, :, 0]).max()
            assert np.abs(part[i, 5:-5, 0] - spline).max() < 1e-6 * scale
            assert np.abs(base[i, 5:-5, 0] - spline).max() > 2e-3 * scale  # the part of a step is visible


def test_body2_apparent_mass_peaks_in_their_bands():
    """The series chain's |apparent mass| has two maxima, at 4-6 and 8-12 Hz; the static mass is pan + M."""
    v = fs.draw_vehicles(30, np.random.default_rng(0))
    fs.draw_persons(v, "body2", np.random.default_rng(1))
    f = np.linspace(0.5, 20, 3901)
    for i in range(30):
        body = {k: v[k][i] for k in fs.PERSON_COLUMNS}
        app = np.abs(fs.apparent_mass(v["m_r"][i], body, 2j * np.pi * f, kind=2))
        top = np.flatnonzero((app[1:-1] > app[:-2]) & (app[1:-1] > app[2:])) + 1
        assert len(top) == 2 and 4 <= f[top[0]] <= 6 and 8 <= f[top[1]] <= 12
        # the CRB script's own chain formula (K3 = 1, C3 = 0, no pan: H = 1/(s² M_app + 1)) agrees
        s = 2j * np.pi * f
        H = crb.person_transfer(0.0, 1.0, 0.0, 2, body, s)
        np.testing.assert_allclose(np.abs((1 / H - 1) / s**2), app, rtol=1e-9)
        assert abs(body["m_r"] + body["m_a"] + body["m_b"] - body["M"]) < 1e-9
    np.testing.assert_allclose(v["m3"], v["pan"] + v["M"])


def test_crb_rigid_bound_falls_as_one_over_sqrt_t():
    """(d) On a stationary input (white a2, a3 = H a2) at a fixed noise level the rigid bound of M falls
    as 1/sqrt(T): the information 1/sd² of a window, averaged over the disjoint windows of one long record,
    grows 4 and 16 times for windows 4 and 16 times longer; an unknown delay only adds to the bound."""
    rng = np.random.default_rng(0)
    n, h = 8192 * 4, 0.01
    theta = np.array([615.0 / 80, 98935.0 / 80])
    a2 = rng.standard_normal(n)
    s = 2j * np.pi * np.fft.rfftfreq(n, h)
    a3 = np.fft.irfft(crb.transfer("rigid", theta, s).ravel() * np.fft.rfft(a2), n)
    rms3, rms2 = np.sqrt(np.mean(a3**2)), np.sqrt(np.mean(a2**2))
    info = {}
    for m in (512, 2048, 8192):
        sd = [crb.relative_sd("rigid", theta, a2[j : j + m], rms3, rms2, h, False) for j in range(0, n, m)]
        info[m] = np.mean(np.asarray(sd) ** -2.0)
    assert abs(info[2048] / info[512] / 4 - 1) < 0.1
    assert abs(info[8192] / info[512] / 16 - 1) < 0.1
    assert crb.relative_sd("rigid", theta, a2[:512], rms3, rms2, h, True) >= crb.relative_sd(
        "rigid", theta, a2[:512], rms3, rms2, h, False
    )


def test_crb_is_the_spread_of_a_fit_at_the_bound():
    """The Fisher information is right: with noise on a3 only (a2 exact) the least-squares fit of (p1, p2) is
    the maximum-likelihood one, and its spread over 300 noise draws matches the bound within 15 %."""
    import scipy.optimize

    rng = np.random.default_rng(1)
    n, h, sigma = 512, 0.01, 0.05
    theta = np.array([615.0 / 100, 98935.0 / 100])
    a2 = np.convolve(rng.standard_normal(n + 50), np.ones(5) / 5, "same")[:n]
    bins = np.arange(1, (n - 1) // 2 + 1)
    s = 2j * np.pi * bins / (n * h)
    A2 = np.fft.rfft(a2)[bins]
    H = crb.transfer("rigid", theta, s).ravel()
    rms3 = np.sqrt(
        np.mean(
            np.fft.irfft(np.fft.rfft(a2) * crb.transfer("rigid", theta, 2j * np.pi * np.fft.rfftfreq(n, h)).ravel(), n)
            ** 2
        )
    )
    bound = sigma * crb.relative_sd("rigid", theta, a2, rms3, 0.0, h, False)
    est = []
    for _ in range(300):
        A3 = H * A2 + np.fft.rfft(sigma * rms3 * rng.standard_normal(n))[bins]

        def resid(lt, A3=A3):
            e = A3 - crb.transfer("rigid", np.exp(lt), s).ravel() * A2
            return np.concatenate([e.real, e.imag])

        est.append(np.exp(scipy.optimize.least_squares(resid, np.log(theta), method="lm").x[1]) / theta[1] - 1)
    assert abs(np.std(est) / bound - 1) < 0.15


def test_score_counts_the_wrong_converged_answers(tmp_path):
    """score --json: coverage, within 2/5/10 %, the chosen models and the converged-but-wrong-and-excluded count."""
    import h5py

    data = tmp_path / "d.h5"
    truth_m3 = np.array([100.0, 100.0, 100.0, 100.0])
    with h5py.File(data, "w") as f:
        f["test/params"] = np.tile([6.15, 989.35, 0, 0, 0, 0, 0, 0, 0, 0], (4, 1))
        f["test/truth_m3"] = truth_m3
        f["test/truth_occupant"] = np.array([0, 1, 2, 1], np.int8)
    rows = [  # m3, low, high, status, model
        (101.0, 95.0, 105.0, "converged", "rigid"),
        (120.0, 110.0, 130.0, "converged", "body1"),  # 20 % off, truth outside: the one to count
        (120.0, 90.0, 130.0, "converged", "body1"),  # 20 % off, truth inside: honest
        (130.0, 125.0, 135.0, "misfit", "body2"),  # outside, but not called converged
    ]
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"data": {"path": str(data)}}))
    with open(run / "estimates.csv", "w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["index", "m3", "m3_low", "m3_high", "status", "occupant_model", "tau", "p1", "p2"])
        for i, (m, lo, hi, st, model) in enumerate(rows):
            w.writerow([i, m, lo, hi, st, model, 0.0004 * 2**i if i else 0.0, 6.15, 98935 / m])
    fs.main(["score", str(run), "--json", str(tmp_path / "s.json")])
    out = json.loads((tmp_path / "s.json").read_text())
    assert out["converged_wrong_excluded"] == 1
    assert out["coverage_95"] == 0.5
    assert out["within"] == {"2": 0.25, "5": 0.25, "10": 0.25}
    assert out["occupant_model"] == {"body1": 2, "body2": 1, "rigid": 1}
    assert out["by_true_occupant"]["body1"]["n"] == 2
    assert abs(out["delay"]["mean_abs_ms"] - 1.4) < 1e-9 and out["delay"]["within_1ms"] == 0.5  # 0, 0.8, 1.6, 3.2 ms


def test_honesty_bound_is_the_monte_carlo_count():
    """The honesty bound (occupant_crb.dishonest_at_bound) against errors drawn at each recording's sd and
    counted as bench/foreign_sim.py's score counts them (more than 10 % off, truth outside est ± z sd); and
    its limits: all of the 5 % misses when every sd exceeds 0.1/1.96, none when every sd is tiny."""
    rng = np.random.default_rng(11)
    x = rng.uniform(0.01, 0.09, 400)  # relative sd of the static mass per recording
    draws = rng.standard_normal((4000, x.size)) * x
    for coverage, z in ((0.95, 1.959963984540054), (0.98, 2.3263478740408408)):
        counted = np.mean((np.abs(draws) > 0.10) & (np.abs(draws) > z * x))
        bound = crb.dishonest_at_bound(x, coverage)
        assert abs(counted - bound) < 4 * np.sqrt(bound / draws.size) + 1e-4, (coverage, counted, bound)
    assert abs(crb.dishonest_at_bound(np.full(10, 0.2), 0.95) - 0.05) < 1e-12
    assert crb.dishonest_at_bound(np.full(10, 0.005), 0.95) < 1e-80
    needed = crb.coverage_for_honesty(x, 0.01)
    assert 0.95 < needed < 1.0
    assert crb.dishonest_at_bound(x, needed) <= 0.01 < crb.dishonest_at_bound(x, needed - 1e-4)


def test_the_persons_table_shows_the_honesty_bound_of_each_row(tmp_path, monkeypatch):
    """bench/persons_table.py's dishonest cell carries the honesty bound at the row's coverage: each recording at
    its own occupant's bound (the model the file's JSON has a number for), scaled to the file's noise, the
    run's first n recordings only; noise-free rows have none."""
    table = _load("persons_table")
    monkeypatch.setattr(table, "DATA", tmp_path)
    rel = {
        "rigid_unknown": [0.2, None, None, 3.0],
        "body1_unknown": [None, 1.2, 0.9, None],
        "body2_unknown": [None] * 4,
    }
    (tmp_path / "crb_mixed_n5.json").write_text(json.dumps({"per_recording_rel_sd_at_unit_noise": rel}))
    x = np.array([0.2, 1.2, 0.9]) * 0.05  # the first three recordings, each its own occupant's
    assert table._honesty_bound("mixed_n5", 3, 0.97) == crb.dishonest_at_bound(x, 0.97)
    cell = table._dishonest("mixed_n5", {"n": 3, "coverage": 0.97, "dishonest": 0.01})
    assert cell == f"1.00 % ({100 * crb.dishonest_at_bound(x, 0.97):.2f} %)"
    (tmp_path / "crb_mixed_n0.json").write_text(json.dumps({"per_recording_rel_sd_at_unit_noise": rel}))
    assert table._honesty_bound("mixed_n0", 3, 0.97) is None


def test_the_speed_table_puts_each_phase_beside_the_rigid_fit(capsys):
    """bench/persons_table.py speed's phase table: the default's CPU seconds by phase (summary.json's
    seconds_phases), the median over the runs, and each over the rigid model's median solve CPU; a tree whose
    summaries have no phases (a tree before the phase clock) has no row."""
    from hybridqcm.estimation.occupant import PHASES

    table = _load("persons_table")
    phases = [
        {p: 1.0 + i for i, p in enumerate((*PHASES, "total"))},
        {p: 3.0 + i for i, p in enumerate((*PHASES, "total"))},
    ]
    times = {
        (0, "rigid_n5", "rigid"): [{"cpu": 2.0, "phases": None}, {"cpu": 2.0, "phases": None}],
        (0, "rigid_n5", "persons"): [{"cpu": 40.0, "phases": phases[0]}, {"cpu": 44.0, "phases": phases[1]}],
        (1, "rigid_n5", "rigid"): [{"cpu": 2.0, "phases": None}],
        (1, "rigid_n5", "persons"): [{"cpu": 40.0, "phases": None}],
    }
    table._phase_table(times, ["old", "new"], ["rigid_n5"])
    rows = [line for line in capsys.readouterr().out.splitlines() if re.match(r"\| tree\d", line)]
    assert len(rows) == 1 and rows[0].startswith("| tree0 | rigid_n5 |")
    cells = rows[0].strip("|").split("|")[2:]
    assert cells[0].strip() == "2.00 (1.0×)"  # fits: median(1, 3) = 2 over the rigid fit's 2 s
    assert cells[-1].strip() == f"{8.0:.2f} ({8.0 / 2:.1f}×)"  # total: median(7, 9)


def test_the_floor_fits_every_candidate_within_the_rigid_fits_budget(tmp_path, capsys):
    """bench/persons_table.py floor: its runs compose, as qcm-estimate composes them, to the default's stages capped
    at the budget with no restarts (the uncapped rigid run keeps the default's stages); the candidates' run fits
    rigid, body1 and body2 once each within the cap (summary.json's iterations by stage) and records each one's own CPU
    seconds (seconds_phases.fit_cpu); the table divides each fit by the capped rigid model and the three together
    by both rigid runs, and the results page's floor line reads the runs' summaries."""
    from hydra import compose, initialize_config_dir

    from conftest import app_in_process, make_foreign
    from hybridqcm.config import CONFIG_DIR

    table = _load("persons_table")
    runs = table._floor_runs((3, 2))
    assert tuple(runs) == table.FLOOR_RUNS  # the folders the results page reads
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        composed = {kind: compose("estimate", overrides=overrides) for kind, overrides in runs.items()}
    assert [s.max_iterations for s in composed["rigid"].stages] == [10, 30]  # the default's, as `speed` runs it
    for kind in ("rigid_capped", "candidates"):
        assert [s.max_iterations for s in composed[kind].stages] == [3, 2] and composed[kind].restarts.count == 0
    assert list(composed["candidates"].occupant.models) == ["rigid", "body1", "body2"]
    assert composed["candidates"].delay is None and composed["candidates"].occupant.workers == 1

    make_foreign(tmp_path / "two.h5", n=2, seed=3, occupant="body1", noise=0.05)
    summary = app_in_process(
        "estimate", tmp_path / "run", *runs["candidates"], f"data.path={tmp_path / 'two.h5'}",
        "plots=false", "tensorboard=false", "progress=false",
    )  # fmt: skip
    fit_cpu = summary["seconds_phases"]["fit_cpu"]
    assert set(fit_cpu) == {"rigid", "body1", "body2"} and all(v > 0 for v in fit_cpu.values())
    for candidate in fit_cpu:  # each stage's mean iterations per recording, within its cap
        stages = summary["stages"]
        assert (
            0 < stages[f"{candidate}/seat_w30_iterations_mean"] <= 3
            and 0 < stages[f"{candidate}/seat_iterations_mean"] <= 2
        )

    runs = tmp_path / "floor"  # the table's line from the runs as `floor` leaves them
    for kind, summary_of in (("candidates", summary), ("rigid", {"cpu_seconds_blocks": 0.5}), ("rigid_capped", {})):
        (runs / f"two__{kind}").mkdir(parents=True)
        (runs / f"two__{kind}" / "summary.json").write_text(
            json.dumps({"n_samples": 2, "cpu_seconds_blocks": 0.25, **summary_of})
        )
    line = table._floor_lines(runs, ["two", "absent"])[-1]
    total = sum(fit_cpu.values())
    assert (
        line.startswith("- two, 2 recordings:")
        and f"= {total:.1f} CPU s, {total / 0.5:.1f}× the rigid model's 0.50" in line
    )
    assert f"({total / 0.25:.1f}× the rigid model at the same budget)" in line
    assert table._floor_lines(tmp_path / "nothing", ["two"]) == []

    times = {
        ("rigid_n5", "rigid"): [{"wall": 2.0, "cpu": 2.0}, {"wall": 2.2, "cpu": 2.4}],
        ("rigid_n5", "rigid_capped"): [{"cpu": 1.0}, {"cpu": 1.0}],
        ("rigid_n5", "candidates"): [{"fits": {"rigid": 1.0, "body1": 2.0, "body2": 5.0}}] * 2,
    }
    row = table._floor_table(times, ["rigid_n5"], 400, (3, 2))[-1]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3:6] == ["1.00 (1.0×)", "2.00 (2.0×)", "5.00 (5.0×)"]
    assert cells[6:] == ["8.00", "8.0×", f"{8.0 / 2.2:.1f}×"]  # over median(2.0, 2.4) CPU s of the rigid model


def test_persons_outside_the_literatures_ranges_are_drawn_where_asked():
    """draw_persons(body1=...): the same random draws scaled to other ranges (the default ranges give today's
    persons bit for bit); the mode's frequency, damping ratio and rigid share recomputed from the stored masses,
    springs and dampers fall inside the asked ranges and outside the literature's."""
    base = fs.draw_vehicles(50, np.random.default_rng(7))
    same = fs.draw_persons({k: v.copy() for k, v in base.items()}, "body1", np.random.default_rng(8))
    explicit = fs.draw_persons(
        {k: v.copy() for k, v in base.items()}, "body1", np.random.default_rng(8), dict(fs.BODY1_RANGES)
    )
    assert all(np.array_equal(same[k], explicit[k]) for k in fs.PERSON_COLUMNS)
    ranges = {"f_hz": (6.0, 8.0), "zeta": (0.15, 0.3), "rigid_share": (0.05, 0.2)}
    v = fs.draw_persons({k: v.copy() for k, v in base.items()}, "body1", np.random.default_rng(8), ranges)
    f = np.sqrt(v["k_b"] / v["m_b"]) / (2 * np.pi)
    zeta = v["c_b"] / (2 * np.sqrt(v["k_b"] * v["m_b"]))
    share = v["m_r"] / v["M"]
    for value, (lo, hi) in ((f, ranges["f_hz"]), (zeta, ranges["zeta"]), (share, ranges["rigid_share"])):
        assert np.all((value >= lo) & (value <= hi))
    assert np.all(f > 6.0) and np.all(zeta < 0.3) and np.all(share < 0.2)
    assert np.allclose(v["M"], base["m3"]) and np.allclose(v["m3"], v["pan"] + v["M"])


def test_bounds_of_a_persons_range_that_are_not_lo_below_hi_are_refused(tmp_path):
    import pytest

    for flag, bounds in (("--body-zeta", ["0.5", "0.3"]), ("--body-rigid-share", ["0.5", "1.2"])):
        with pytest.raises(SystemExit, match=f"{flag} .*two bounds 0 < LO < HI"):
            fs.main(["make", "--out", str(tmp_path / "x.h5"), "--n", "2", "--occupant", "body1", flag, *bounds])
    assert not (tmp_path / "x.h5").exists()
