"""Is Gauss-Newton efficient? Each recording's error against the error its own Fisher information allows.

For a regular, unbiased and efficient estimator, a recording's error is N(0, s_i²) with s_i² the
Cramér-Rao bound, which the model-based Laplace covariance σ̂² (Jᵀ W J)⁻¹ estimates. Then
z_i = e_i / s_i has std 1, and the mean |error| over recordings equals sqrt(2/π) mean(s_i) ("efficient
mean"). Where GN meets that, no estimator reading the same window (a network, a fusion of a network with
GN) can do better per recording except through prior information: with a Gaussian prior whose
information is r times the data's, the best posterior std is s_i / sqrt(1 + r), so a 0.8x error needs
r = 1/0.8² − 1 = 0.5625, a prior only 1.33 s_i wide. The "prior info" column is r for the occupant-mass
prior of the data (uniform 30-150 kg, std 34.6 kg) at each recording's mass: the median of s_i² / prior².

    PYTHONPATH=src .venv/bin/python bench/efficiency.py outputs/noise/exp10_noise0.01 outputs/noise/exp10_noise0.05 ...

Reads each run's estimates.csv and summary.json (data file, split) and the file's true parameters; only
the recordings called `converged` count (a flagged wrong basin's standard deviation is not a bound).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import h5py
import numpy as np

from hybridqcm.physics.parameters import REFERENCE_VEHICLE

PRIOR_STD_KG = 120.0 / math.sqrt(12.0)  # m3 ~ U(30, 150) kg (SPEC § 2)


def _run(run: Path) -> None:
    summary = json.loads((run / "summary.json").read_text())
    rows = list(csv.DictReader(open(run / "estimates.csv", newline="")))
    index = np.array([int(r["index"]) for r in rows])
    with h5py.File(summary["data"], "r") as handle:
        truth = handle[f"{summary['split']}/params"][()][index]
        m3 = handle[f"{summary['split']}/truth_m3"][()][index] if "truth_m3" in handle[summary["split"]] else None
    if m3 is None:
        m3 = REFERENCE_VEHICLE.K3 / truth[:, 1]
    converged = np.array([r["status"] == "converged" for r in rows])
    print(
        f"{run}: {converged.sum()} of {len(rows)} recordings converged, covariance {summary.get('interval_covariance')}"
    )
    columns = {"p1": (truth[:, 0], "p1", "std_p1"), "p2": (truth[:, 1], "p2", "std_p2"), "m3": (m3, "m3", "m3_std")}
    print("  quantity | mean |error| | efficient mean | ratio | std z | mean z | 0.8 x GN | prior info r (median)")
    for name, (true, key, std_key) in columns.items():
        est = np.array([float(r[key]) for r in rows])
        std = np.array([float(r[std_key]) for r in rows])
        keep = converged & np.isfinite(est) & np.isfinite(std) & (std > 0)
        err, rel_std = (est[keep] - true[keep]) / true[keep], std[keep] / true[keep]
        z = err / rel_std
        mean_err, efficient = np.mean(np.abs(err)), math.sqrt(2 / math.pi) * np.mean(rel_std)
        prior = f"{np.median((rel_std * true[keep]) ** 2 / PRIOR_STD_KG**2):.2g}" if name == "m3" else "-"
        print(
            f"  {name:8s} | {100 * mean_err:.3g} % | {100 * efficient:.3g} % | {mean_err / efficient:.3f} | "
            f"{np.std(z):.3f} | {np.mean(z):+.3f} | {80 * mean_err:.3g} % | {prior}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="qcm-estimate run directories")
    for run in parser.parse_args().runs:
        _run(run)


if __name__ == "__main__":
    main()
