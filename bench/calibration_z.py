"""Where a calibrated occupant interval's width comes from (issue 31): z-scores split into the recording's part
and the calibration's part.

    PYTHONPATH=src .venv/bin/python bench/calibration_z.py RUN_DIR [RUN_DIR ...] --data FILE [--seat SEAT.json]

RUN_DIR: a qcm-estimate run (estimates.csv) of FILE's recordings (bench/foreign_sim.py's truth). Per run:

- p2 (the data's part): z = (p2 - truth) / σ with σ the half-width of the run's p2 interval (the image of
  [m3_low, m3_high] under p2 = K3 / m3, the side the error lies on) over 1.96; also z against the column std_p2.
- with --seat (and truth_occupant_mass in FILE): the occupant's error split as
  occ(p2_hat) - occ(p2_true) (the recording's, through the fitted law) and occ(p2_true) - truth (the calibration's
  error at the true p2), each over its own σ (the data's half-width / 1.96 on that side; the law's delta-method σ
  times the t quantile over z where the file has a dof), and the total over the interval's half-width / 1.96.

Prints sd(z), mean(z), median |z| (0.674 for a standard normal), and the 50 / 90 / 95 % coverage the σ give.
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
from hybridqcm.estimation.calibration import load_seat  # noqa: E402

K3_REF = 98935.0  # the reference K3 of qcm-estimate (m3 = K3 / p2)
Z = {50: 0.6745, 90: 1.6449, 95: 1.96}


def _line(name: str, z: np.ndarray) -> str:
    z = z[np.isfinite(z)]
    cover = " / ".join(f"{100 * np.mean(np.abs(z) <= q):.1f}" for q in Z.values())
    return (
        f"  {name:<44s} n {z.size:4d}  sd {np.std(z):.3f}  mean {np.mean(z):+.3f}  median|z| {np.median(np.abs(z)):.3f}"
        f"  cover 50/90/95 % {cover}"
    )


def _side(err, low_width, high_width):
    """The σ on the side the error lies: err > 0 -> the estimate above the truth -> the lower half-width."""
    return np.where(err > 0, low_width, high_width) / 1.96


def report(run: Path, data: Path, seat_path: Path | None) -> None:
    with open(run / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    idx = np.array([int(r["index"]) for r in rows])

    def number(text):
        try:
            return float(text)
        except (TypeError, ValueError):
            return np.nan

    col = {k: np.array([number(r.get(k)) for r in rows]) for k in rows[0]}
    with h5py.File(data, "r") as f:
        p2_true = f["test/params"][()][idx, 1]
        occ_true = f["test/truth_occupant_mass"][()][idx] if "truth_occupant_mass" in f["test"] else None
    p2 = col["p2"]
    p2_low = np.where(np.isfinite(col["m3_high"]), K3_REF / col["m3_high"], 0.0)
    p2_high = K3_REF / col["m3_low"]
    err = p2 - p2_true
    print(f"{run}: {len(rows)} recordings")
    print(_line("p2, the run's interval", err / _side(err, p2 - p2_low, p2_high - p2)))
    print(_line("p2, column std_p2", err / col["std_p2"]))
    if seat_path is None or occ_true is None:
        return
    seat = load_seat(seat_path)
    occ = seat.occupant_mass(p2)
    occ_at_truth = seat.occupant_mass(p2_true)
    data_low, data_high = occ - seat.occupant_mass(p2_high), seat.occupant_mass(np.maximum(p2_low, 1e-300)) - occ
    cal_sd = seat.calibration_quantile() / 1.96 * seat.calibration_std(p2)
    e_data, e_cal, e_all = occ - occ_at_truth, occ_at_truth - occ_true, occ - occ_true
    print(_line("occupant: the recording's part (fitted law)", e_data / _side(e_data, data_low, data_high)))
    print(_line("occupant: the calibration's part", e_cal / cal_sd))
    low, high = np.hypot(data_low, 1.96 * cal_sd), np.hypot(data_high, 1.96 * cal_sd)
    print(_line("occupant: total", e_all / _side(e_all, low, high)))
    if "occupant_mass" in col:
        same = np.nanmax(np.abs(col["occupant_mass"] / occ - 1))
        lo_w, hi_w = col["occupant_mass"] - col["occupant_mass_low"], col["occupant_mass_high"] - col["occupant_mass"]
        print(_line("occupant: the run's own interval", e_all / _side(e_all, lo_w, hi_w)))
        print(f"  (the run's occupant_mass against this law at its p2: largest relative difference {same:.1e})")
    share = np.median(cal_sd**2 / (cal_sd**2 + (0.5 * (data_low + data_high) / 1.96) ** 2))
    print(f"  the calibration's share of the occupant's variance: median {100 * share:.1f} %")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--seat", type=Path, default=None)
    args = ap.parse_args(argv)
    for run in args.runs:
        report(run, args.data, args.seat)


if __name__ == "__main__":
    main()
