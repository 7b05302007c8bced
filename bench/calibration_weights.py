"""How a seat calibration weighs its drives (issue 31): the same calibration drives' road-free fits, the law
fitted with other weights, applied to the same unknown occupants' fits.

    PYTHONPATH=src .venv/bin/python bench/calibration_weights.py OUT [--draws 6] [--model-runs DIR]

OUT: a bench/calibration_table.py --repeats folder (noise0.05_calibrate/fit, noise0.05_r{r}_calibrate/fit: each
calibration's per-drive estimates.csv; noise0.05_estimate: the unknown occupants' fits; the files' truth).
Weights of ln p2 (estimation/calibration.fit_seat_law's 1/σ_rel):
* reported: each drive's own std_p2 (what qcm-calibrate uses: the run's interval, a jackknife for the road-free
  model, which scatters from drive to drive with few degrees of freedom);
* per load: the median σ_rel of the drives at the same load (the load's precision without the scatter);
* equal: one weight for every drive;
* model (with --model-runs DIR: DIR/r{r}/fit/estimates.csv of qcm-calibrate fit='[intervals.covariance=model]'
  on the same files): the model-based σ of each drive.
Per weighting, over the draws: the occupant's mean relative error, the calibration's own error (the fitted law
against the true one at each unknown's true p2: what the calibration adds), and the 95 % coverage.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import h5py
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "src"))
from hybridqcm.estimation.calibration import SeatLaw, fit_seat_law  # noqa: E402

K3_SIM = 98935.0


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _drives(fit_dir: Path, cal_file: Path):
    rows = [r for r in _rows(fit_dir / "estimates.csv") if r["status"] == "converged"]
    with h5py.File(cal_file, "r") as f:
        loads = f["test/known_mass"][()][[int(r["index"]) for r in rows]]
    p2, std = (np.array([float(r[k]) for r in rows]) for k in ("p2", "std_p2"))
    return loads, p2, std


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--draws", type=int, default=6)
    ap.add_argument("--model-runs", type=Path, default=None)
    ap.add_argument("--exponent", type=float, default=0.5)
    ap.add_argument("--pan", type=float, default=12.0)
    args = ap.parse_args(argv)
    out = args.out
    unknown_rows = _rows(out / "noise0.05_estimate" / "estimates.csv")
    idx = np.array([int(r["index"]) for r in unknown_rows])
    with h5py.File(out / "noise0.05_unknown.h5", "r") as f:
        truth, p2_true = f["test/truth_occupant_mass"][()][idx], f["test/params"][()][idx, 1]
    m3, low, high = (np.array([float(r[k]) for r in unknown_rows]) for k in ("m3", "m3_low", "m3_high"))
    p2 = K3_SIM / m3
    p2_low, p2_high = np.where(np.isfinite(high), K3_SIM / high, 0.0), K3_SIM / low
    true = SeatLaw(K3_SIM, args.exponent, args.pan, np.zeros((3, 3)), loads=[0.0])
    table: dict[str, list] = {}
    for r in range(args.draws):
        tag = "noise0.05" if r == 0 else f"noise0.05_r{r}"
        loads, p2_cal, std = _drives(out / f"{tag}_calibrate" / "fit", out / f"{tag}_cal.h5")
        rel = std / p2_cal
        per_load = np.array([np.median(rel[loads == load]) for load in loads])
        sigmas = {"reported": std, "per load": per_load * p2_cal, "equal": np.full_like(p2_cal, np.median(std))}
        if args.model_runs is not None:
            m_loads, m_p2, m_std = _drives(args.model_runs / f"r{r}" / "fit", out / f"{tag}_cal.h5")
            if np.array_equal(m_loads, loads) and np.allclose(m_p2, p2_cal, rtol=1e-9):
                sigmas["model"] = m_std
            else:
                sigmas["model (own fits)"] = None
                p2_cal_model, loads_model, std_model = m_p2, m_loads, m_std
        for name, sigma in sigmas.items():
            if sigma is None:
                fit = fit_seat_law(loads_model, p2_cal_model, std_model, law="power")
            else:
                fit = fit_seat_law(loads, p2_cal, sigma, law="power")
            seat = fit["law"]
            occ, occ_low, occ_high = seat.occupant_interval(p2, p2_low, p2_high)
            err = np.abs(occ / truth - 1)
            cal_err = np.abs(seat.occupant_mass(p2_true) / true.occupant_mass(p2_true) - 1)
            cover = np.mean((occ_low <= truth) & (truth <= occ_high))
            table.setdefault(name, []).append((err.mean(), cal_err.mean(), cover, seat.exponent, seat.pan_mass))
    print(f"{out}: {len(unknown_rows)} unknown occupants, {args.draws} calibration draws (law=power)\n")
    print(
        "| weights | occupant mean error (± sd over draws) | the calibration's own error (mean) | coverage | e, pan (sd) |"
    )
    print("|---|---|---|---|---|")
    for name, rows in table.items():
        a = np.array(rows)
        print(
            f"| {name} | {100 * a[:, 0].mean():.3f} ± {100 * a[:, 0].std(ddof=1):.3f} % | {100 * a[:, 1].mean():.3f} % | "
            f"{100 * a[:, 2].mean():.1f} % | {a[:, 3].mean():.3f} ({a[:, 3].std(ddof=1):.3f}), "
            f"{a[:, 4].mean():.2f} ({a[:, 4].std(ddof=1):.2f}) kg |"
        )
    t_err = np.abs(true.occupant_mass(p2) / truth - 1).mean()
    print(f"| the true law | {100 * t_err:.3f} % | 0 | | |")


if __name__ == "__main__":
    main()
