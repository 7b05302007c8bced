"""Accuracy / time table of the integrators on the quarter-car model (SPEC §4).

    .venv/bin/python bench/bench_integrators.py            # 200 accuracy samples, 1000 x 500 timing
    .venv/bin/python bench/bench_integrators.py --quick

Accuracy: thesis-prior systems on ISO 8608 roads (class A-C, 30 km/h), 500 steps (5 s at h = 0.01),
compared with the exact solution of the same zero-order-hold-driven linear system (matrix
exponential per sample: x_{k+1} = e^{Ah} x_k + A^-1 (e^{Ah} - I) b_k), at the sample times.
Error = ||a_method - a_exact|| / ||a_exact|| over all steps and the three accelerations, per sample;
median and max over samples; likewise for the displacements.
Time: `simulate` on 1000 samples x 500 steps, best of `--repeat`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import scipy.linalg
import torch

from hybridqcm.physics.integrators import METHODS, simulate
from hybridqcm.physics.parameters import params_to_matrices, road_gain, system_matrix
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.road import RoadProfile

SPEED = 30 / 3.6


def exact_zoh(params: torch.Tensor, force: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact (accel, disp) [M, N, 3] of the continuous system with the wheel forcing held over each step."""
    A = system_matrix(params).numpy()  # [M, 6, 6]
    Phi = scipy.linalg.expm(A * h)
    Gamma = np.linalg.solve(A, Phi - np.eye(6))[:, :, 2]  # [M, 6]: response to a unit v1-forcing
    M, N = force.shape
    x = np.zeros((M, 6))
    states = np.empty((M, N, 6))
    for k in range(N):
        states[:, k] = x
        x = np.einsum("mij,mj->mi", Phi, x) + Gamma * force[:, k : k + 1]
    D, S = (m.numpy() for m in params_to_matrices(params))
    v, q = states[..., :3], states[..., 3:]
    accel = np.einsum("mij,mkj->mki", D, v) + np.einsum("mij,mkj->mki", S, q)
    accel[..., 2] += force
    return accel, q


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm((a - b).reshape(a.shape[0], -1), axis=1) / np.linalg.norm(b.reshape(b.shape[0], -1), axis=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--samples", type=int, default=200, help="samples for the accuracy columns")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    n_acc = 50 if args.quick else args.samples
    n_time = 200 if args.quick else 1000
    print(
        f"hybridqcm bench_integrators{' (quick)' if args.quick else ''}: torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads; load average before {' '.join(f'{x:.2f}' for x in os.getloadavg())}"
    )

    g = torch.Generator().manual_seed(0)
    params = build_prior("thesis", h=0.01).sample(max(n_acc, n_time), g).params
    road_class = torch.randint(0, 3, (params.shape[0],), generator=g)
    duration = 5.0
    errors: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = {}
    hs = (0.01, 0.005, 0.0025)
    for h in hs:
        n = int(round(duration / h))
        road = RoadProfile().sample(road_class[:n_acc], n, h, SPEED, torch.Generator().manual_seed(1))
        force = (road_gain(params[:n_acc])[:, None] * road).numpy()
        accel_exact, disp_exact = exact_zoh(params[:n_acc], force, h)
        for method in METHODS:
            traj = simulate(params[:n_acc], road, h, method)
            errors[method, h] = (relative(traj.accel.numpy(), accel_exact), relative(traj.disp.numpy(), disp_exact))

    road = RoadProfile().sample(road_class[:n_time], 500, 0.01, SPEED, torch.Generator().manual_seed(2))
    seconds = {}
    for method in METHODS:
        best = float("inf")
        for _ in range(args.repeat):
            start = time.perf_counter()
            simulate(params[:n_time], road, 0.01, method)
            best = min(best, time.perf_counter() - start)
        seconds[method] = best * 1000 / n_time  # per 1000 samples

    print(
        f"\naccuracy vs exact ZOH solution, {n_acc} thesis-prior samples, 5 s on class A-C roads; "
        f"relative L2 error of the accelerations (median / max over samples)"
    )
    header = (
        f"{'method':<22}" + "".join(f"{f'h = {h:g}':>22}" for h in hs) + f"{'disp err h=0.01 (med)':>24}"
        f"{'order':>8}{'s / 1000x500 (h=0.01)':>24}{'vs semi-expl.':>15}"
    )
    print(header)
    for method in METHODS:
        cells = "".join(
            f"{f'{np.median(errors[method, h][0]):.2e} / {errors[method, h][0].max():.1e}':>22}" for h in hs
        )
        order = np.log2(np.median(errors[method, hs[1]][0]) / np.median(errors[method, hs[2]][0]))
        print(
            f"{method:<22}{cells}{np.median(errors[method, 0.01][1]):24.2e}{order:8.2f}"
            f"{seconds[method]:24.3f}{seconds[method] / seconds['semi_explicit_euler']:14.1f}x"
        )
    print(f"\nload average after {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
