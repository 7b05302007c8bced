"""Bias of the exact model's hold at the true parameters: how far from the truth a noise-free GN fit
of all 10 p and x0 lands when started at the truth, per hold / sub-steps / input margins.

    PYTHONPATH=src .venv/bin/python bench/bench_exact_bias.py data/cont_small.h5 --samples 200 \\
        --margins 0,0 4,8 --holds spline:4 spline:8 spline:16

The file must be a continuous-time dataset with params, vel and disp (qcm-simulate physics=continuous).
Prints the median relative model error of (a3, a2, a1) at the truth, the median relative error of
every fitted parameter and the fraction of p3, p5 within 5 % (the least identifiable ones).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from hybridqcm.data.hdf5 import read_split
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.response import ExactResponse
from hybridqcm.estimation.solver import GaussNewton, SolverConfig
from hybridqcm.physics.linear_models import QuarterCarRoad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path")
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--margins", nargs="+", default=["0,0", "4,8"])
    parser.add_argument("--holds", nargs="+", default=["spline:4", "spline:8", "spline:16"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    longest = max(sum(int(x) for x in m.split(",")) for m in args.margins)
    a = read_split(
        args.path,
        "test",
        ["accel", "road", "params", "vel", "disp"],
        n_steps=args.steps + longest,
        index=slice(0, args.samples),
    )
    accel = torch.tensor(np.asarray(a["accel"], dtype=np.float64))
    road = torch.tensor(np.asarray(a["road"], dtype=np.float64))
    p = torch.tensor(a["params"])
    for margin in args.margins:
        before, after = (int(x) for x in margin.split(","))
        x0 = torch.tensor(np.concatenate([a["vel"][:, before], a["disp"][:, before]], 1), dtype=torch.float64)
        targets = accel[:, before : before + args.steps]
        inputs = road[:, : before + args.steps + after]
        for spec in args.holds:
            hold, m = spec.split(":")
            model = ExactResponse(QuarterCarRoad(False), 0.01, hold, int(m), "unknown")
            theta = torch.cat([p, x0], 1)
            t0 = time.perf_counter()
            predicted = model.outputs(theta, inputs, before, args.steps)
            model_err = ((predicted - targets).square().sum(1) / targets.square().sum(1)).sqrt().median(0).values
            problem = LeastSquaresProblem(targets, inputs, 0.01, model=model, input_offset=before)
            result = GaussNewton(SolverConfig(max_iterations=10)).solve(problem, theta)
            err = (result.params[:, :10] - p).abs() / p
            print(
                f"margins {before},{after} {hold}:{m}: model error a3/a2/a1 "
                f"{' / '.join(f'{x:.1e}' for x in model_err.tolist())}; fit median error % "
                f"{' '.join(f'{x:.3f}' for x in (100 * err.median(0).values).tolist())}; "
                f"p3 within 5 %: {float((err[:, 2] < 0.05).double().mean()):.3f}, "
                f"p5: {float((err[:, 4] < 0.05).double().mean()):.3f} ({time.perf_counter() - t0:.1f} s)"
            )


if __name__ == "__main__":
    main()
