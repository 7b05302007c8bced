"""One Gauss-Newton iteration over 17 000 samples x N = 100: ours vs reverse-mode autograd vs scipy.

    .venv/bin/python bench/bench_gauss_newton.py [--samples 17000] [--steps 100] [--threads 1]

Each method runs in its own child process (so its peak RSS is its own) on the same synthetic
data (thesis prior, ISO 8608 roads, simulated on the fly). Printed side by side:

* ours      forward-mode tangents (primal + 10 tangents per state), chunked, F = JᵀJ by bmm,
            Armijo trials forward-only; one full iteration of the batched solver, timed.
* autograd  the same iteration's Jacobian by reverse mode: torch.func.jacrev of the plain
            differentiable integrator (physics.integrators.simulate), vmapped over a subset,
            extrapolated to all samples (the Jacobian alone; the rest of the iteration excluded).
* scipy     scipy.optimize.least_squares (trf, 2-point Jacobian) solving samples one at a time
            from the same start, on a few samples; time per iteration (njev) extrapolated.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def _data(n: int, steps: int, seed: int = 0):
    import torch

    from hybridqcm.physics import reference_params
    from hybridqcm.testing import synthetic_samples

    s = synthetic_samples(n, n_steps=steps, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    init = reference_params().expand(n, 10) * (1 + 0.1 * torch.randn(n, 10, generator=g, dtype=torch.float64))
    return s, init


def run_ours(n, steps, threads):
    from hybridqcm.estimation.problems import LeastSquaresProblem
    from hybridqcm.estimation.solver import GaussNewton, SolverConfig

    s, init = _data(n, steps)
    problem = LeastSquaresProblem(s["accel"], s["road"], 0.01)
    solver = GaussNewton(SolverConfig(max_iterations=3, num_threads=threads))
    solver.solve(LeastSquaresProblem(s["accel"][:64], s["road"][:64], 0.01), init[:64])  # warm-up
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # peak of data generation
    t0 = time.perf_counter()
    result = solver.solve(problem, init)
    total = time.perf_counter() - t0
    # seconds[0]: the first iteration, all samples active (later ones only the unconverged)
    return {
        "iteration_s": result.seconds[0],
        "iterations_s": result.seconds,
        "solve_3_iterations_s": total,
        "peak_rss_before_solve_mb": rss_before,
    }


def run_autograd(n, steps, threads, subset=256):
    import torch
    from torch.func import jacrev, vmap

    from hybridqcm.physics.integrators import simulate

    torch.set_num_threads(threads)
    s, init = _data(subset, steps)

    def accel(p, road):  # one sample: p [10], road [N] -> [N, 3]
        return simulate(p[None], road[None], 0.01).accel[0]

    jac = vmap(jacrev(accel), in_dims=(0, 0))
    jac(init[:4], s["road"][:4])  # warm-up
    t0 = time.perf_counter()
    J = jac(init, s["road"])  # [subset, N, 3, 10]
    dt = time.perf_counter() - t0
    return {"jacobian_subset_s": dt, "subset": subset, "iteration_s": dt * n / subset, "shape": list(J.shape)}


def run_scipy(n, steps, threads, subset=8):
    import numpy as np
    from scipy.optimize import least_squares

    s, init = _data(subset, steps)
    accel = s["accel"].numpy()
    road = s["road"].numpy()

    def model(p, u):  # the same Euler recursion in numpy, one sample
        p1, p2, p3, p4, p5, p6, p7, p8, p9, p10 = p
        D = np.array([[-p1, p1, 0], [p3, -(p3 + p4), p4], [0, p7, -p8]])
        S = np.array([[-p2, p2, 0], [p5, -(p5 + p6), p6], [0, p9, -p10]])
        v, q = np.zeros(3), np.zeros(3)
        out = np.empty((u.shape[0], 3))
        for k in range(u.shape[0]):
            a = D @ v + S @ q
            a[2] += (p10 - p9) * u[k]
            out[k] = a
            v = v + 0.01 * a
            q = q + 0.01 * v
        return out

    t0 = time.perf_counter()
    njev = nfev = 0
    for i in range(subset):
        res = least_squares(
            lambda p, i=i: (model(p, road[i]) - accel[i]).ravel(),
            init[i].numpy(),
            method="trf",
            x_scale="jac",
            max_nfev=200,
        )
        njev += res.njev
        nfev += res.nfev
    dt = time.perf_counter() - t0
    per_iteration = dt / max(njev, 1)  # one iteration (Jacobian + step) of one sample
    return {
        "solve_subset_s": dt,
        "subset": subset,
        "njev": njev,
        "nfev": nfev,
        "iteration_s": per_iteration * n,
        "solve_all_s": dt / subset * n,
    }


def child(mode, n, steps, threads):
    fn = {"ours": run_ours, "autograd": run_autograd, "scipy": run_scipy}[mode]
    out = fn(n, steps, threads)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(out))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=17000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--child", choices=["ours", "autograd", "scipy"])
    args = ap.parse_args()
    if args.child:
        child(args.child, args.samples, args.steps, args.threads)
        return
    results = {}
    for mode in ("ours", "autograd", "scipy"):
        proc = subprocess.run(
            [
                sys.executable,
                __file__,
                "--child",
                mode,
                "--samples",
                str(args.samples),
                "--steps",
                str(args.steps),
                "--threads",
                str(args.threads),
            ],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            print(proc.stderr[-2000:])
            raise SystemExit(f"{mode} failed")
        results[mode] = json.loads(proc.stdout.strip().splitlines()[-1])
    ours = results["ours"]["iteration_s"]
    print(f"One Gauss-Newton iteration, {args.samples} samples x N = {args.steps}, torch threads = {args.threads}")
    print(f"{'method':<44} {'s / iteration':>14} {'x ours':>8} {'peak RSS MB':>12}")
    rows = [
        ("ours (forward-mode tangents, batched)", results["ours"]),
        (f"reverse-mode jacrev+vmap (Jacobian only, {results['autograd']['subset']} extrap.)", results["autograd"]),
        (f"scipy least_squares per sample ({results['scipy']['subset']} extrap.)", results["scipy"]),
    ]
    for name, r in rows:
        print(f"{name:<44} {r['iteration_s']:>14.3f} {r['iteration_s'] / ours:>8.1f} {r['peak_rss_mb']:>12.0f}")
    print(
        f"ours: iterations 1-3 took {[round(x, 3) for x in results['ours']['iterations_s']]} s "
        f"(later ones only on unconverged samples)"
    )
    print(
        f"ours: peak RSS {results['ours']['peak_rss_before_solve_mb']:.0f} MB already before the solve (data "
        f"generation), {results['ours']['peak_rss_mb']:.0f} MB after"
    )
    print(
        f"scipy: {results['scipy']['njev']} Jacobians for {results['scipy']['subset']} samples; "
        f"solving all {args.samples} one at a time would take {results['scipy']['solve_all_s']:.0f} s"
    )
    print("source study (V100 GPU): 29.6 s per iteration over 17 000 samples")


if __name__ == "__main__":
    main()
