"""qcm-simulate's loaded seat (issue 31, physics/seat_law.py): the law applied to the prior's vehicles, the
config's checks, and a simulated foam-seat file calibrated by qcm-calibrate recovering the law it was made
with (the law's parameters given to qcm-simulate are the independent fact)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import h5py
import numpy as np
import pytest
import torch

from conftest import app_in_process
from hybridqcm.physics.parameters import REFERENCE_VEHICLE, is_stable
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.seat_law import LoadedSeat, SeatLawPrior

# not the foreign simulator's seat (0.5, 12 kg) and not the calibration tests' (0.35, 9.3 kg)
E, EC, PAN, LOADS = 0.3, 0.6, 7.5, [0.0, 35.0, 75.0, 115.0]


def test_the_prior_puts_its_vehicles_on_the_loaded_seat():
    """p1, p2 from the law at M = occupant + pan (written out here, not through LoadedSeat), p3 / p5 scaled
    by the law (the physical prior's vehicles: p5 / p3 = K3 / C3); every draw stable; known loads cycled."""
    seat = LoadedSeat("power", E, EC, PAN)
    prior = SeatLawPrior(build_prior("physical", h=None), seat)
    draw = prior.sample(64, torch.Generator().manual_seed(3))
    p, occ = draw.params.numpy(), draw.occupant.numpy()
    M = occ + PAN
    assert np.all((occ >= 30) & (occ <= 150))
    np.testing.assert_allclose(p[:, 1], REFERENCE_VEHICLE.K3 * (M / 80) ** E / M, rtol=1e-13)
    np.testing.assert_allclose(p[:, 0], REFERENCE_VEHICLE.C3 * (M / 80) ** EC / M, rtol=1e-13)
    # p5 / p3 = K3(M) / C3(M): the chassis mass cancels
    np.testing.assert_allclose(p[:, 4] / p[:, 2], p[:, 1] / p[:, 0], rtol=1e-12)
    assert bool(is_stable(draw.params, None).all())

    calibration = SeatLawPrior(build_prior("thesis", h=None), seat, known_loads=LOADS)
    first, second = (calibration.sample(n, torch.Generator().manual_seed(4)).occupant.tolist() for n in (6, 3))
    assert first + second == (LOADS * 3)[:9]  # the cycle goes on across calls
    calibration.reset()
    assert calibration.sample(2, torch.Generator().manual_seed(4)).occupant.tolist() == LOADS[:2]


@pytest.mark.parametrize(
    "seat,message",
    [
        ({"law": "foam"}, "seat.law='foam': choose one of ['reference', 'power']"),
        ({"law": "power"}, "seat.law=power needs seat.exponent"),
        ({"law": "power", "exponent": 1.2}, "seat.exponent=1.2: below 1"),
        ({"law": "power", "exponent": "abc"}, "seat.exponent='abc': a finite number"),
        ({"exponent": 0.5}, "seat.exponent=0.5 with seat.law=reference"),
        ({"pan_mass": -2}, "seat.pan_mass=-2: a mass >= 0 kg"),
        ({"known_loads": [0, -5], "pan_mass": 10}, "seat.known_loads=[0.0, -5.0]: loads >= 0 kg"),
        ({"known_loads": [0, 40]}, "an empty seat without a pan has no mass on its spring"),
        ({"known_loads": "heavy"}, "seat.known_loads='heavy': a list of loads in kg"),
        ({"pan_mass": 5, "occupant": "body1"}, "rigid occupants only, not occupant=body1"),
        ({"pan_mass": 5, "vehicle": "half_car"}, "the quarter car's seat only, not vehicle=half_car"),
        ({"spring": 3}, "seat.spring: not a seat key"),
    ],
)
def test_bad_seat_settings_are_one_line_naming_key_and_value(seat, message):
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.data.simulate_run import check_seat

    seat = dict(seat)
    occupant, vehicle = seat.pop("occupant", "rigid"), seat.pop("vehicle", "quarter_car")
    overrides = [f"{'+' if k == 'spring' else ''}seat.{k}={json.dumps(v)}" for k, v in seat.items()]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("simulate", overrides=overrides)
    with pytest.raises(ValueError) as error:
        check_seat(cfg, occupant, vehicle)
    assert message in str(error.value) and "\n" not in str(error.value)


def _app(module, run_dir, *overrides):
    cmd = [sys.executable, "-m", f"hybridqcm.apps.{module}", *overrides, f"hydra.run.dir={run_dir}", "progress=false"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600)


def _simulate(tmp_path, name, *overrides):
    """qcm-simulate's run in-process (conftest.app_in_process; qcm-calibrate below runs on the console)."""
    path = tmp_path / f"{name}.h5"
    seat = ["seat.law=power", f"seat.exponent={E}", f"seat.c3_exponent={EC}", f"seat.pan_mass={PAN}"]
    app_in_process(
        "simulate", tmp_path / f"sim_{name}", "preset=tiny", f"output={path}", "~splits.train",
        "splits.test.profiles={A: 2, B: 1, C: 1}", *seat, *overrides, "progress=false",
    )  # fmt: skip
    return path


def test_a_simulated_foam_seat_calibrated_by_qcm_calibrate_recovers_its_law(tmp_path):
    """qcm-simulate seat.law=power (e 0.3, C3's 0.6, pan 7.5 kg) with known loads -> qcm-calibrate -> the law
    given to qcm-simulate; then unknown occupants of another qcm-simulate file estimated with the seat file
    within 1 % of the file's truth_occupant_mass (noise-free)."""
    loads = "[" + ",".join(f"{x:g}" for x in LOADS) + "]"
    cal = _simulate(tmp_path, "cal", "samples_per_profile=2", f"seat.known_loads={loads}")
    with h5py.File(cal, "r") as f:
        known, truth = f["test/known_mass"][()], f["test/truth_occupant_mass"][()]
        assert known.tolist() == (LOADS * 2) and np.array_equal(known, truth)
        assert json.loads(f.attrs["seat"])["exponent"] == E
    seat_file = tmp_path / "seat.json"
    proc = _app("calibrate", tmp_path / "cal_run", f"data.path={cal}", f"output={seat_file}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    law = json.loads(seat_file.read_text())
    assert law["exponent"] == pytest.approx(E, abs=0.005) and law["pan_mass"] == pytest.approx(PAN, abs=0.1)
    assert law["K3_ref"] == pytest.approx(REFERENCE_VEHICLE.K3, rel=2e-3)
    assert law["c3_exponent"] == pytest.approx(EC, abs=0.01) and law["C3_ref"] == pytest.approx(615.0, rel=5e-3)

    unknown = _simulate(tmp_path, "unknown", "samples_per_profile=1", "seed=5")
    app_in_process(
        "estimate", tmp_path / "est", "experiment=occupant_roadfree", "occupant.models=[rigid]", "delay=null",
        f"data.path={unknown}", f"seat_file={seat_file}", "plots=false", "progress=false",
    )  # fmt: skip
    with open(tmp_path / "est" / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    with h5py.File(unknown, "r") as f:
        truth_all = f["test/truth_occupant_mass"][()]
        assert "known_mass" not in f["test"]
    truth = truth_all[[int(r["index"]) for r in rows]]
    mass = np.array([float(r["occupant_mass"]) for r in rows])
    assert np.all(np.abs(mass / truth - 1) < 0.01), (mass, truth)

    # the road-driven quarter car (exp5: all ten parameters from a3, a2, a1 and the road) reads it too
    app_in_process(
        "estimate", tmp_path / "road", "experiment=exp5_random_init", "n_samples=3", f"data.path={unknown}",
        f"seat_file={seat_file}", "plots=false", "progress=false",
    )  # fmt: skip
    with open(tmp_path / "road" / "estimates.csv", newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if r["status"] == "converged"]
    assert rows
    for r in rows:
        truth_i = truth_all[int(r["index"])]
        low, mass, high = (float(r[f"occupant_mass{k}"]) for k in ("_low", "", "_high"))
        assert abs(mass / truth_i - 1) < 0.01 and low <= truth_i <= high, (r["index"], mass, truth_i)
    assert json.loads((tmp_path / "road" / "summary.json").read_text())["mass_scale"]["calibrated"] is True
