"""bench/calibration_crb.py: the occupant's bound on a calibrated seat, against independent formulas on the
second simulator's foam seat (bench/foreign_sim.py --seat-law power)."""

from __future__ import annotations

import importlib.util

import h5py
import numpy as np
import pytest

from conftest import REPO_ROOT, make_foreign
from hybridqcm.estimation.calibration import SeatLaw

E, PAN = 0.4, 9.0  # not the seat (0.5, 12 kg)


def _module(name):
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_occupant_bound_is_p2s_bound_times_m_over_1_minus_e_occupant(tmp_path):
    bench = _module("calibration_crb")
    path = tmp_path / "foam.h5"
    make_foreign(path, n=4, noise=0.05, seat_law="power", seat_exponent=E, pan_mass=PAN)
    crb = bench._occupant_crb()
    accel, h, truth = crb.read_file(path)
    sd = 0.05 * crb.bounds(accel, h, truth, 0.05)["rigid_known"]
    with h5py.File(path, "r") as f:
        occupant = f["test/truth_occupant_mass"][()]
    total = truth["m3"]  # pan + occupant on the spring
    p2 = truth["K3"] / total
    true = SeatLaw(bench.K3_SIM, E, PAN, np.zeros((3, 3)), loads=[0.0])
    rows = bench.occupant_bounds(sd, p2, true, None)
    assert np.allclose(rows["reference seat (M = K3 / p2)"], sd)
    assert np.allclose(rows["true law"], sd * total / ((1 - E) * occupant), rtol=1e-9)
    assert np.all(rows["true law"] > 1.6 * sd)  # 1/(1-e) = 1.67, more for M / occupant > 1


def test_the_calibrations_bound_is_the_inverse_fisher_information_of_its_drives(tmp_path):
    """calibration_bound's covariance against (Jᵀ Σ⁻¹ J)⁻¹ with J from central differences of
    ln p2 = ln(K3_ref (M/80)^e / M), M = load + pan, and the drives' own p2 bounds."""
    bench = _module("calibration_crb")
    path = tmp_path / "ballast.h5"
    loads = [0.0, 40.0, 80.0, 120.0]
    make_foreign(path, n=8, noise=0.05, seat_law="power", seat_exponent=E, pan_mass=PAN, known_loads=loads)
    crb = bench._occupant_crb()
    true = SeatLaw(bench.K3_SIM, E, PAN, np.zeros((3, 3)), loads=[0.0])
    seat = bench.calibration_bound(crb, str(path), 0.05, 0.05, true, "power")
    accel, h, truth = crb.read_file(path)
    sd = 0.05 * crb.bounds(accel, h, truth, 0.05)["rigid_known"]
    load = np.resize(np.array(loads), 8)

    def ln_p2(theta):
        K, e, pan = theta
        M = load + pan
        return np.log(K * (M / 80) ** e / M)

    theta = np.array([bench.K3_SIM, E, PAN])
    steps = np.array([1.0, 1e-6, 1e-6])
    J = np.stack([(ln_p2(theta + d) - ln_p2(theta - d)) / (2 * d[j]) for j, d in enumerate(np.diag(steps))], 1)
    expected = np.linalg.inv(J.T @ (J / sd[:, None] ** 2))
    assert np.allclose(seat.covariance, expected, rtol=1e-4)
    assert seat.K3_ref == pytest.approx(bench.K3_SIM) and seat.exponent == E and seat.pan_mass == PAN


def test_the_body_prior_is_refused_for_the_periodic_bound(tmp_path):
    bench = _module("calibration_crb")
    path = tmp_path / "foam.h5"
    make_foreign(path, n=2, noise=0.05, seat_law="power", seat_exponent=E, pan_mass=PAN)
    with pytest.raises(SystemExit, match="--body-prior is for --domain time"):
        bench.main(
            [
                str(path),
                "--file-noise",
                "0.05",
                "--exponent",
                str(E),
                "--pan",
                str(PAN),
                "--body-prior",
                "--domain",
                "dft",
            ]
        )
