"""Seat calibration (issue 31): the law fit, its inverse, the seat file, and qcm-calibrate -> qcm-estimate
seat_file= end to end on the second simulator's foam seat (bench/foreign_sim.py --seat-law power)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import h5py
import numpy as np
import pytest
import scipy.optimize
import scipy.stats

from conftest import app_in_process, make_foreign
from hybridqcm.errors import DatasetError
from hybridqcm.estimation.calibration import (
    NESTED,
    PARAMETERS,
    CalibrationError,
    SeatFileError,
    SeatLaw,
    fit_seat_law,
    load_seat,
    seat_document,
)

K3, E, PAN, C3, EC = 1.07e5, 0.35, 9.3, 640.0, 0.6  # not the simulator's seat (0.5, 12 kg): nothing tuned to it
LOADS = np.repeat([0.0, 30.0, 70.0, 110.0], 3)


def _p(loads, k3=K3, e=E, pan=PAN):
    total = loads + pan
    return C3 * (total / 80) ** EC / total, k3 * (total / 80) ** e / total  # p1, p2


def test_the_law_fit_recovers_the_exponent_and_pan_mass_of_closed_form_p2():
    p1, p2 = _p(LOADS)
    result = fit_seat_law(LOADS, p2, np.full_like(p2, 1e-12), p1=p1)
    seat = result["law"]
    assert seat.K3_ref == pytest.approx(K3, rel=1e-8)
    assert seat.exponent == pytest.approx(E, abs=1e-8)
    assert seat.pan_mass == pytest.approx(PAN, abs=1e-6)
    assert seat.C3_ref == pytest.approx(C3, rel=1e-8) and seat.c3_exponent == pytest.approx(EC, abs=1e-8)
    assert np.abs(result["residual_kg"]).max() < 1e-6
    assert sorted(result["loo"]) == [0.0, 30.0, 70.0, 110.0]  # 3 loads left: the power law still determined
    assert max(np.abs(v).max() for v in result["loo"].values()) < 1e-5


def test_the_law_covariance_matches_the_scatter_of_repeated_calibrations():
    """The Gauss-Newton covariance against the spread of 300 fits to noisy p2 (1 % relative noise)."""
    _, p2 = _p(LOADS)
    rng = np.random.default_rng(3)
    fits, reported = [], []
    for _ in range(300):
        noisy = p2 * np.exp(0.01 * rng.standard_normal(p2.size))
        seat = fit_seat_law(LOADS, noisy, 0.01 * noisy)["law"]
        fits.append([seat.K3_ref, seat.exponent, seat.pan_mass])
        reported.append(np.sqrt(np.diag(seat.covariance)))
    spread, told = np.std(fits, axis=0), np.median(reported, axis=0)
    assert np.allclose(told, spread, rtol=0.25), (told, spread)
    assert np.allclose(np.mean(fits, axis=0), [K3, E, PAN], atol=0.5 * spread)  # unbiased within noise


def test_the_linear_law_needs_two_loads_and_the_power_law_three():
    loads = np.array([0.0, 0.0, 80.0, 80.0])
    _, p2 = _p(loads, e=0.0)
    seat = fit_seat_law(loads, p2, 1e-12 * p2, law="linear")["law"]
    assert seat.exponent == 0.0 and seat.K3_ref == pytest.approx(K3, rel=1e-8)
    assert seat.pan_mass == pytest.approx(PAN, abs=1e-6)
    with pytest.raises(CalibrationError, match="2 distinct loads"):
        fit_seat_law(loads, p2, 1e-12 * p2, law="power")


def test_auto_chooses_the_proportional_law_on_a_linear_seat_with_its_closed_form_k3():
    """A linear seat without a pan (p2 = K3 / L) at 1 % noise: law=auto keeps K3 alone in most draws, and then
    K3 is the weighted mean of ln(p2 L) (the closed-form least squares of the one-parameter law)."""
    loads = np.repeat([30.0, 60.0, 100.0, 150.0], 10)
    rng = np.random.default_rng(11)
    chosen = []
    for _ in range(40):
        rel = 0.01 * (1 + rng.random(loads.size))  # each recording its own stated σ
        p2 = K3 / loads * np.exp(rel * rng.standard_normal(loads.size))
        result = fit_seat_law(loads, p2, rel * p2)
        seat = result["law"]
        chosen.append(seat.law)
        if seat.law == "proportional":
            w2 = 1 / rel**2
            closed = math.exp(np.sum(w2 * np.log(p2 * loads)) / np.sum(w2))
            assert seat.K3_ref == pytest.approx(closed, rel=1e-9)
            assert seat.exponent == 0.0 and seat.pan_mass == 0.0 and seat.free == ["K3_ref"]
            assert np.all(seat.covariance[1:] == 0) and np.all(seat.covariance[:, 1:] == 0)
            # its variance: the one-parameter law's (Σ w²)⁻¹ K3², widened by the Birge factor
            chi2 = np.sum(w2 * (np.log(p2 * loads) - math.log(closed)) ** 2)
            birge = max(1.0, chi2 / (loads.size - 1))
            assert seat.covariance[0, 0] == pytest.approx(closed**2 / np.sum(w2) * birge, rel=1e-6)
        assert [row["law"] for row in result["selection"]] == list(NESTED)
    assert chosen.count("proportional") >= 30  # the F-test's level 5 %: ~2 draws in 40 pick a larger law


def test_auto_keeps_the_full_law_on_a_foam_seat_with_a_pan():
    p1, p2 = _p(LOADS)
    rng = np.random.default_rng(5)
    for _ in range(10):
        noisy = p2 * np.exp(0.01 * rng.standard_normal(p2.size))
        result = fit_seat_law(LOADS, noisy, 0.01 * noisy, p1=p1)
        assert result["law"].law == "power" and result["law"].free == list(PARAMETERS)
        assert [row["law"] for row in result["selection"]] == ["power", "linear"]  # driven empty: a pan
        assert result["selection"][1]["p_value"] < 1e-6


def test_a_law_without_a_pan_on_an_empty_seat_is_one_line():
    _, p2 = _p(LOADS)
    with pytest.raises(CalibrationError, match="driven empty") as error:
        fit_seat_law(LOADS, p2, 0.01 * p2, law="proportional")
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("stated", [0.5, 2.0])
def test_the_covariance_is_widened_where_the_stated_sigma_is_too_narrow_and_kept_where_too_wide(stated):
    """Recordings stating σ at half (twice) their true scatter: the Birge factor widens the covariance to the
    spread of repeated calibrations (keeps the stated one, twice the spread: never narrowed)."""
    _, p2 = _p(LOADS)
    rng = np.random.default_rng(8)
    fits, reported, dofs = [], [], []
    for _ in range(200):
        noisy = p2 * np.exp(0.01 * rng.standard_normal(p2.size))
        seat = fit_seat_law(LOADS, noisy, 0.01 * stated * noisy, law="power")["law"]
        fits.append([seat.K3_ref, seat.exponent, seat.pan_mass])
        reported.append(np.sqrt(np.diag(seat.covariance)))
        dofs.append(seat.dof)
    expected = np.std(fits, axis=0) * max(1.0, stated)
    assert np.allclose(np.median(reported, axis=0), expected, rtol=0.25)
    # Student-t only where the scale was estimated (χ²/dof > 1: at half the σ all but ~1 % of the draws)
    assert dofs.count(LOADS.size - 3) >= 190 if stated < 1 else set(dofs) == {None}


def test_the_occupant_bound_through_the_law_matches_finite_differences():
    """occupant_relative_sd: σ(ln p2) through occupant(p2) = M(p2) - pan against a central difference in ln p2,
    and with the calibration's covariance the two joined in quadrature."""
    cov = np.diag([300.0**2, 0.01**2, 0.5**2])
    seat = SeatLaw(K3, E, PAN, cov, loads=[0.0, 120.0])
    for M in (20.0, 61.0, 140.0):
        p2, sd = seat.k3(M) / M, 0.013
        step = 1e-6
        slope = (seat.occupant_mass(p2 * math.exp(step)) - seat.occupant_mass(p2 * math.exp(-step))) / (2 * step)
        occ = float(seat.occupant_mass(p2))
        data = abs(float(slope)) * sd / occ
        assert float(seat.occupant_relative_sd(p2, sd, calibration=False)) == pytest.approx(data, rel=1e-6)
        both = math.hypot(data, float(seat.calibration_std(p2)) / occ)
        assert float(seat.occupant_relative_sd(p2, sd)) == pytest.approx(both, rel=1e-6)


def test_the_calibrations_interval_uses_the_student_t_quantile_at_its_dof():
    seat = SeatLaw(K3, E, PAN, np.diag([300.0**2, 0.01**2, 0.5**2]), loads=[0.0, 120.0], dof=4)
    assert seat.calibration_quantile() == pytest.approx(scipy.stats.t.ppf(scipy.stats.norm.cdf(1.96), 4))
    occ, low, high = seat.occupant_interval(np.array([1000.0]), np.array([1000.0]), np.array([1000.0]))
    assert float((occ - low)[0]) == pytest.approx(seat.calibration_quantile() * float(seat.calibration_std(1000.0)))
    seat.dof = None
    assert seat.calibration_quantile() == 1.96


@pytest.mark.parametrize(
    "loads, message",
    [
        (np.full(4, 60.0), "all loads are equal"),
        (np.array([0.0, -5.0, 40.0, 80.0]), "known_mass[1] = -5.0 kg"),
        (np.array([0.0, np.nan, 40.0, 80.0]), "known_mass[1] = nan kg"),
    ],
)
def test_bad_loads_are_one_line(loads, message):
    p2 = np.full(4, 1000.0)
    with pytest.raises(CalibrationError) as error:
        fit_seat_law(loads, p2, 0.01 * p2)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_the_self_consistent_mass_inverts_the_law():
    """M from p2 in closed form against a numerical root of p2 M - K3(M) = 0, and the delta-method gradient
    against finite differences of the occupant mass in (K3_ref, e, pan)."""
    cov = np.diag([300.0**2, 0.01**2, 0.5**2])
    seat = SeatLaw(K3, E, PAN, cov, loads=[0.0, 120.0])
    for M in (15.0, 52.0, 93.0, 161.0):
        p2 = seat.k3(M) / M
        root = scipy.optimize.brentq(lambda m, p2=p2: p2 * m - seat.k3(m), 1.0, 1000.0, xtol=1e-12)
        assert float(seat.total_mass(p2)) == pytest.approx(root, rel=1e-10)
        assert float(seat.occupant_mass(p2)) == pytest.approx(root - PAN, rel=1e-10)
        grad = []
        for j, step in enumerate((1.0, 1e-6, 1e-6)):
            values = []
            for sign in (1, -1):
                theta = [K3, E, PAN]
                theta[j] += sign * step
                values.append(float(SeatLaw(*theta, cov).occupant_mass(p2)))
            grad.append((values[0] - values[1]) / (2 * step))
        grad = np.array(grad)
        assert float(seat.calibration_std(p2)) == pytest.approx(math.sqrt(grad @ cov @ grad), rel=1e-5)
    occ, low, high = seat.occupant_interval(np.array([1000.0]), np.array([990.0]), np.array([1010.0]))
    assert low < occ < high and seat.occupant_mass(1010.0) > low and seat.occupant_mass(990.0) < high


# ------------------------------------------------------------------------------------------------ seat file
def _document(tmp_path, name="seat.json", **changes):
    seat = SeatLaw(K3, E, PAN, np.diag([300.0**2, 0.01**2, 0.5**2]), loads=[0.0, 40.0, 80.0, 120.0])
    path = tmp_path / name
    path.write_text(seat_document(seat, {"fit": {"chi2": 1.0}}))
    return seat, path


def test_a_seat_file_round_trips(tmp_path):
    seat, path = _document(tmp_path)
    back = load_seat(path)
    assert (back.K3_ref, back.exponent, back.pan_mass, back.loads) == (seat.K3_ref, E, PAN, seat.loads)
    assert np.array_equal(back.covariance, seat.covariance)


def _resigned(payload):
    """A payload with a valid checksum (what a careful forger writes): the schema checks must stand alone."""
    from hybridqcm.estimation.calibration import _checksum

    payload.pop("sha256", None)
    payload["sha256"] = _checksum(payload)
    return json.dumps(payload)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda text, p: text.replace(f'"pan_mass": {PAN}', '"pan_mass": 4.0'), "sha256 does not match"),
        (lambda text, p: json.dumps({"K3": 98935.0, "pan": 12}), "not a seat file of qcm-calibrate"),
        (lambda text, p: "!!python/object/apply:os.system ['touch PWNED']", "not JSON"),
        (lambda text, p: text.replace('"exponent": 0.35', '"exponent": NaN'), "not JSON"),
        (lambda text, p: _resigned({**p, "exponent": 1.5}), "exponent=1.5 lies outside"),
        (lambda text, p: _resigned({**p, "covariance": [[1, 2, 0], [2, 1, 0], [0, 0, 1]]}), "positive semi-definite"),
        (lambda text, p: _resigned({**p, "K3_ref": "1e5"}), "K3_ref='1e5' is not a finite number"),
        (lambda text, p: _resigned({k: v for k, v in p.items() if k != "loads_kg"}), "loads_kg=None"),
    ],
)
def test_a_seat_file_not_ours_or_tampered_is_refused_in_one_line(tmp_path, edit, message):
    _, path = _document(tmp_path)
    text = path.read_text()
    path.write_text(edit(text, json.loads(text)))
    with pytest.raises(SeatFileError) as error:
        load_seat(path)
    assert message in str(error.value) and str(path) in str(error.value) and "\n" not in str(error.value)
    assert not (tmp_path / "PWNED").exists()


def test_known_loads_are_checked_before_any_fit(tmp_path):
    from hybridqcm.estimation.calibration_run import known_loads

    plain = tmp_path / "plain.h5"
    make_foreign(plain, n=2)
    with pytest.raises(DatasetError, match=r"/test/known_mass is missing"):
        known_loads(plain, "test", None)
    path = tmp_path / "equal.h5"
    make_foreign(path, n=2, known_loads=60, pan_mass=5)
    with pytest.raises(DatasetError, match="all 2 loads are 60.0 kg"):
        known_loads(path, "test", None)
    with h5py.File(path, "r+") as f:
        f["test/known_mass"][1] = -3.0
    with pytest.raises(DatasetError, match=r"known_mass\[1\] = -3.0 kg is negative"):
        known_loads(path, "test", None)


def test_a_seat_file_is_created_exclusively(tmp_path):
    from hybridqcm.atomic import atomic_create_text

    path = atomic_create_text(tmp_path / "seat.json", "first")
    with pytest.raises(FileExistsError):
        atomic_create_text(path, "second")
    assert path.read_text() == "first" and [p.name for p in tmp_path.iterdir()] == ["seat.json"]
    assert atomic_create_text(path, "second", overwrite=True).read_text() == "second"


def test_seat_file_is_read_by_the_quarter_cars_models_and_refused_by_the_half_car(tmp_path, tiny_dataset):
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.errors import ConfigError
    from hybridqcm.estimation.plan import validate
    from hybridqcm.estimation.plan_seat import seat_plan

    _, seat_file = _document(tmp_path)
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        road = compose(
            "estimate", overrides=["experiment=exp5_random_init", f"data.path={tiny_dataset}", f"seat_file={seat_file}"]
        )
        half = compose("estimate", overrides=["experiment=hcm_full_observation", f"seat_file={seat_file}"])
    assert seat_plan(road, validate(road)).exponent == pytest.approx(E)  # road-driven: p2 = K3 / M as well
    with pytest.raises(ConfigError, match="seat_file=.*read by the quarter car's models.*vehicle_model=half_car"):
        seat_plan(half, None)


# ------------------------------------------------------------------------------------------------ console
def _app(module, run_dir, *overrides):
    cmd = [sys.executable, "-m", f"hybridqcm.apps.{module}", *overrides, f"hydra.run.dir={run_dir}", "progress=false"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600)


def test_calibrate_then_estimate_unknown_occupants_on_a_foam_seat(tmp_path):
    """4 loads x 2 noise-free drives on a foam seat (K3, C3 ∝ (M/80)^0.5, 12 kg pan), then 4 unknown rigid
    occupants: occupant_mass within 1 % and inside its interval; m3 = K3/p2 (the reference seat) is not."""
    cal, unknown = tmp_path / "cal.h5", tmp_path / "unknown.h5"
    seat = {"seat_law": "power", "seat_exponent": 0.5, "pan_mass": 12}
    make_foreign(cal, n=8, known_loads=[0, 40, 80, 120], seed=11, **seat)
    make_foreign(unknown, n=4, seed=12, **seat)
    seat_file = tmp_path / "seat.json"
    proc = _app("calibrate", tmp_path / "cal", f"data.path={cal}", f"output={seat_file}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "pan mass" in proc.stdout and (tmp_path / "cal" / "plots" / "seat_k3.png").stat().st_size > 0
    law = load_seat(seat_file)
    assert law.exponent == pytest.approx(0.5, abs=0.01) and law.pan_mass == pytest.approx(12, abs=0.5)
    fit_summary = json.loads((tmp_path / "cal" / "fit" / "summary.json").read_text())  # a run without seat_file
    assert fit_summary["mass_scale"]["calibrated"] is False
    with open(tmp_path / "cal" / "fit" / "estimates.csv", newline="") as handle:
        assert "occupant_mass" not in next(csv.reader(handle))

    app_in_process(  # qcm-estimate's run in-process (qcm-calibrate above runs on the console)
        "estimate",
        tmp_path / "est",
        "experiment=occupant_roadfree",
        "occupant.models=[rigid]",
        "delay=null",
        f"data.path={unknown}",
        f"seat_file={seat_file}",
        "progress=false",
    )
    with open(tmp_path / "est" / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    with h5py.File(unknown, "r") as f:
        truth, on_spring = f["test/truth_occupant_mass"][()], f["test/truth_m3"][()]
    mass = np.array([float(r["occupant_mass"]) for r in rows])
    low, high = (np.array([float(r[f"occupant_mass_{k}"]) for r in rows]) for k in ("low", "high"))
    assert np.all(np.abs(mass / truth - 1) < 0.01), (mass, truth)
    assert np.all((low <= truth) & (truth <= high))
    m3 = np.array([float(r["m3"]) for r in rows])  # uncalibrated: the reference K3 on a foam seat
    assert np.mean(np.abs(m3 / on_spring - 1)) > 0.05
    summary = json.loads((tmp_path / "est" / "summary.json").read_text())
    assert summary["mass_scale"]["calibrated"] is True and summary["mass_scale"]["pan_mass"] == law.pan_mass


def test_calibrate_on_a_file_without_known_mass_is_one_line(tmp_path):
    data = tmp_path / "plain.h5"
    make_foreign(data, n=2)
    proc = _app("calibrate", tmp_path / "run", f"data.path={data}", f"output={tmp_path / 'seat.json'}")
    assert proc.returncode == 2 and "known_mass is missing" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "seat.json").exists()


def test_calibrate_refuses_an_existing_output_before_any_work(tmp_path):
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.errors import ConfigError
    from hybridqcm.estimation.calibration_run import run_calibration

    (tmp_path / "seat.json").write_text("the user's")
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("calibrate", overrides=[f"data.path={tmp_path / 'none.h5'}", f"output={tmp_path / 'seat.json'}"])
    with pytest.raises(ConfigError, match="exists; choose another name or pass overwrite=true"):
        run_calibration(cfg, fit=lambda *_: pytest.fail("fitted despite the refused output"))
    assert (tmp_path / "seat.json").read_text() == "the user's"


def test_known_p3_p5_from_the_reference_on_a_calibrated_seat_are_warned_with_the_k3_ratio(capsys):
    """exp7/8/10 hold p3 = C3/m2, p5 = K3/m2 at the reference vehicle's: on a seat whose K3 grows with the load
    the warning names how far K3(M) lies from the reference K3 over the occupants (the law at M = occ + pan)."""
    from omegaconf import OmegaConf

    from hybridqcm.reports.estimate import _held_seat_parameters

    seat = SeatLaw(K3, E, PAN, np.zeros((3, 3)), loads=[0.0, 120.0])
    occupant = np.array([30.0, 70.0, 140.0])
    cfg = OmegaConf.create({"known": ["p3", "p5"], "known_source": "reference", "K3": 98935.0})
    held = _held_seat_parameters(cfg, seat, occupant)
    ratio = K3 * ((occupant + PAN) / 80) ** E / 98935.0
    assert held["parameters"] == ["p3", "p5"]
    assert held["k3_ratio_min"] == pytest.approx(ratio.min()) and held["k3_ratio_max"] == pytest.approx(ratio.max())
    assert "warning: known ['p3', 'p5'] are held" in capsys.readouterr().out
    cfg.known_source = "file"
    assert _held_seat_parameters(cfg, seat, occupant) is None


def test_a_chosen_law_round_trips_and_a_file_whose_held_parameters_are_not_0_is_refused(tmp_path):
    cov = np.zeros((3, 3))
    cov[0, 0] = 300.0**2
    seat = SeatLaw(K3, 0.0, 0.0, cov, law="proportional", loads=[30.0, 150.0], dof=39)
    path = tmp_path / "seat.json"
    path.write_text(seat_document(seat, {}))
    back = load_seat(path)
    assert (back.law, back.free, back.dof, back.K3_ref) == ("proportional", ["K3_ref"], 39, K3)
    assert float(back.occupant_mass(K3 / 70.0)) == pytest.approx(70.0)
    bad = tmp_path / "bad.json"
    bad.write_text(seat_document(SeatLaw(K3, 0.0, 4.0, cov, law="proportional", loads=[30.0, 150.0]), {}))
    with pytest.raises(SeatFileError, match="holds \\['exponent', 'pan_mass'\\] at 0") as error:
        load_seat(bad)
    assert "\n" not in str(error.value)


def test_occupants_beyond_the_calibrations_loads_are_warned_with_the_extrapolation(tmp_path, capsys):
    """summary.json's mass_scale and one warning line: how many occupant masses lie outside the loads the seat
    was calibrated at, their range and the furthest extrapolation (NaN rows, not fitted, are not counted)."""
    from omegaconf import OmegaConf

    from hybridqcm.reports.estimate import _mass_scale

    seat = SeatLaw(K3, E, PAN, np.zeros((3, 3)), loads=[0.0, 40.0, 80.0, 120.0])
    (tmp_path / "estimates.csv").write_text("index,occupant_mass\n0,30.0\n1,131.5\n2,nan\n3,150.25\n4,120.0\n")
    cfg = OmegaConf.create({"seat_file": "seat.json", "K3": 98935.0})
    scale = _mass_scale(cfg, seat, tmp_path)
    assert (scale["extrapolated"], scale["extrapolated_kg"]) == (2, pytest.approx(30.25))
    out = capsys.readouterr().out.strip().splitlines()
    assert out == [
        "warning: 2 of 4 occupant masses lie outside the calibration's loads 0..120 kg (131.5..150.2 kg: the seat "
        "law extrapolated by up to 30.2 kg; calibrate with heavier or lighter loads)"
    ]
    seat.loads = [0.0, 160.0]
    assert _mass_scale(cfg, seat, tmp_path)["extrapolated"] == 0 and capsys.readouterr().out == ""


def test_estimate_with_a_seat_file_that_is_not_ours_is_one_line_and_runs_nothing(tmp_path):
    """qcm-estimate seat_file=<a YAML object tag> refuses before any fit: exit 2, one line naming the file, nothing
    executed, no estimates.csv."""
    data, seat_file = tmp_path / "plain.h5", tmp_path / "seat.json"
    make_foreign(data, n=2)
    seat_file.write_text(f"!!python/object/apply:os.system ['touch {tmp_path / 'PWNED'}']\n")
    proc = _app(
        "estimate", tmp_path / "est", "experiment=occupant_roadfree", f"data.path={data}", f"seat_file={seat_file}"
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and f"seat_file={seat_file}: not a seat file" in lines[0], lines
    assert not (tmp_path / "PWNED").exists() and not (tmp_path / "est" / "estimates.csv").exists()
