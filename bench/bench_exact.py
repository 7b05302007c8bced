"""Exact-discretisation layer vs the Euler layer on the same batch (the Gauss-Newton model cost).

    PYTHONPATH=src .venv/bin/python bench/bench_exact.py [--samples 17000] [--steps 100] [--chunk 512]
        [--threads 1] [--hold spline] [--substeps 4] [--degree 5] [--margin 0] [--repeats 3]
        [--model quarter|seat|sprung]

Synthetic samples (thesis prior, ISO 8608 roads; the seat and sprung models take p1, p2 / p1..p6
of the same draws and the road as their driving acceleration); every layer runs over the whole
batch in chunks of --chunk samples with torch.set_num_threads(--threads), as the solver does.
Printed side by side (best of --repeats, the methods alternating within each repeat): seconds
per full pass of exact_sensitivities with x0 columns by the step recursion (method="recursion",
the old path) and in modal coordinates (method="modal", the default), their largest difference
relative to each column's largest value, exact_outputs and, for the quarter car,
euler_sensitivities ([b, T, 3, 11]) / euler_accelerations and the ratios.

    ... bench/bench_exact.py --gn [--substeps 16] [--margin 8]

times instead one Gauss-Newton iteration of the solver (all samples active, x0 unknown, inputs
with --margin samples on each side of the window) with the Euler model and the exact model by
each method of the Jacobian pass (the line search's exact_outputs runs its default, method="auto",
in both).

    ... bench/bench_exact.py --gn --substeps 16 --margin 8 --baseline /tmp/old [--threads 1 2]

times the same iteration with this tree's code and with the tree at --baseline (a checkout of main:
`git worktree add /tmp/old main`, or `mkdir /tmp/old && git archive main src | tar -x -C /tmp/old`),
imported side by side in this process (bench/_baseline.py), alternating within each repeat, at each
--threads count (SolverConfig.num_threads): seconds old and new, new / old, the largest relative
difference of the estimates after the iteration, and for more than one thread the speed-up of this
tree's code over its own 1-thread time (the first --threads value).

    ... bench/bench_exact.py --accuracy

prints instead the relative L2 error of each hold against the continuous-time response
(scipy solve_ivp, DOP853, rtol 1e-12) of the reference vehicle and one thesis-prior draw to a
road of three low-frequency sines, T = 100, h = 0.01, from rest.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch


def _best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def accuracy() -> None:
    import math

    import numpy as np
    from scipy.integrate import solve_ivp

    from hybridqcm.estimation.exact import exact_outputs
    from hybridqcm.physics import reference_params, road_gain, system_matrix
    from hybridqcm.physics.linear_models import QuarterCarRoad
    from hybridqcm.testing import synthetic_samples

    sines = ((0.010, 0.7, 0.3), (0.006, 1.9, 1.1), (0.003, 3.1, 2.0))  # metres, Hz, phase

    def road(t):
        lib = torch if isinstance(t, torch.Tensor) else np
        return sum(a * lib.sin(2 * math.pi * f * t + ph) for a, f, ph in sines)

    h, T = 0.01, 100
    t = np.arange(T) * h
    params = torch.stack([reference_params(), synthetic_samples(1, n_steps=2, seed=7)["params"][0]])
    reference = []
    for p in params:
        A = system_matrix(p).numpy()
        b = np.zeros(6)
        b[2] = float(road_gain(p))
        sol = solve_ivp(
            lambda s, x, A=A, b=b: A @ x + b * road(s),
            (0.0, t[-1]),
            np.zeros(6),
            method="DOP853",
            t_eval=t,
            rtol=1e-12,
            atol=1e-15,
        )
        reference.append(sol.y.T @ A[:3].T + np.outer(road(t), b[:3]))
    reference = torch.tensor(np.stack(reference))
    w = road(torch.tensor(t))[None, :, None].expand(2, T, 1)
    print("relative L2 error vs continuous time (all / a3 / a2 / a1):")
    cases = [("zoh", 1, 5), ("foh", 1, 5)] + [("spline", m, k) for k in (3, 5) for m in (1, 2, 4, 8)]
    for hold, m, k in cases:
        err = exact_outputs(QuarterCarRoad(), params, None, w, h, hold, m, spline_degree=k) - reference
        parts = [float(err[..., c].norm() / reference[..., c].norm()) for c in range(3)]
        label = f"{hold} k={k}" if hold == "spline" else hold
        print(
            f"  {label:10s} substeps={m}: {float(err.norm() / reference.norm()):.2e}  "
            + " / ".join(f"{x:.2e}" for x in parts)
        )


def _model(name: str):
    from hybridqcm.physics.linear_models import QuarterCarRoad, SeatBaseExcitation, SprungBaseExcitation

    return {"quarter": QuarterCarRoad, "seat": SeatBaseExcitation, "sprung": SprungBaseExcitation}[name]()


def gn_cases(args, package: str = "hybridqcm") -> dict:
    """The --gn setup (also bench/roofline.py's): {name: (problem, θ0)} for one GN iteration over
    args.samples x args.steps, inputs with args.margin samples on each side; "euler" from rest,
    "exact recursion" and "exact modal" with x0 unknown (one ExactResponse shared by both).
    ``package``: the name the code is imported under (hybridqcm_baseline for --baseline)."""
    import importlib

    response = importlib.import_module(f"{package}.estimation.response")
    LeastSquaresProblem = importlib.import_module(f"{package}.estimation.problems").LeastSquaresProblem
    reference_params = importlib.import_module(f"{package}.physics").reference_params
    QuarterCarRoad = importlib.import_module(f"{package}.physics.linear_models").QuarterCarRoad
    synthetic_samples = importlib.import_module(f"{package}.testing").synthetic_samples

    n, N, margin = args.samples, args.steps, args.margin
    data = synthetic_samples(n, n_steps=N + 2 * margin, seed=0)
    g = torch.Generator().manual_seed(1)
    init = reference_params().expand(n, 10) * (1 + 0.1 * torch.randn(n, 10, generator=g, dtype=torch.float64))
    accel, road = data["accel"][:, margin : margin + N].to(torch.float64), data["road"].to(torch.float64)
    exact = response.ExactResponse(QuarterCarRoad(), 0.01, args.hold, args.substeps, initial_state="unknown")
    theta0 = torch.cat([init, torch.zeros(n, 6, dtype=torch.float64)], 1)
    return {
        "euler": (LeastSquaresProblem(accel, road[:, margin : margin + N], 0.01), init),
        "exact recursion": (LeastSquaresProblem(accel, road, 0.01, model=exact, input_offset=margin), theta0),
        "exact modal": (LeastSquaresProblem(accel, road, 0.01, model=exact, input_offset=margin), theta0),
    }


def gauss_newton(args) -> None:
    """One GN iteration over all samples: Euler vs exact (recursion) vs exact (modal)."""
    import functools

    import hybridqcm.estimation.response as response
    from hybridqcm.estimation.exact import exact_sensitivities
    from hybridqcm.estimation.solver import GaussNewton, SolverConfig

    n, N, margin = args.samples, args.steps, args.margin
    solver = GaussNewton(SolverConfig(max_iterations=1, num_threads=args.threads, chunk_size=args.chunk))
    cases = gn_cases(args)
    original = response.exact_sensitivities
    best: dict[str, float] = {}
    try:
        for _ in range(args.repeats):
            for name, (problem, start) in cases.items():
                method = "recursion" if "recursion" in name else "modal"
                response.exact_sensitivities = functools.partial(exact_sensitivities, method=method)
                result = solver.solve(problem, start)
                best[name] = min(best.get(name, math.inf), result.seconds[0])
    finally:
        response.exact_sensitivities = original
    print(
        f"one GN iteration, {n} samples x N = {N} (margin {margin}), chunk {args.chunk}, {args.threads} thread(s), "
        f"hold={args.hold} substeps={args.substeps}, x0 unknown (best of {args.repeats})"
    )
    for name, seconds in best.items():
        print(f"  {name:16s} {seconds:7.3f} s   x Euler {seconds / best['euler']:5.2f}")
    print(f"  modal / recursion {best['exact modal'] / best['exact recursion']:.2f}")


def gauss_newton_against(args) -> None:
    """One GN iteration with this tree's code and the --baseline tree's, side by side (module docstring)."""
    import functools
    import importlib

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _baseline import NAME, load_baseline

    load_baseline(args.baseline)
    packages = {"old": NAME, "new": "hybridqcm"}
    modules = {
        tag: {part: importlib.import_module(f"{pkg}.estimation.{part}") for part in ("response", "exact", "solver")}
        for tag, pkg in packages.items()
    }
    cases = {tag: gn_cases(args, pkg) for tag, pkg in packages.items()}
    names = [name for name in cases["new"] if args.cases is None or name in args.cases]
    best: dict = {}
    estimates: dict = {}
    for threads in args.threads:
        for _ in range(args.repeats):
            for name in names:
                for tag in ("old", "new"):  # alternate, so that a change of machine load hits both alike
                    response, exact, solver = (modules[tag][part] for part in ("response", "exact", "solver"))
                    method = "recursion" if "recursion" in name else "modal"
                    original = response.exact_sensitivities
                    response.exact_sensitivities = functools.partial(exact.exact_sensitivities, method=method)
                    try:
                        config = solver.SolverConfig(max_iterations=1, num_threads=threads, chunk_size=args.chunk)
                        result = solver.GaussNewton(config).solve(*cases[tag][name])
                    finally:
                        response.exact_sensitivities = original
                    key = (name, threads, tag)
                    best[key] = min(best.get(key, math.inf), result.seconds[0])
                    estimates[key] = result.params
    print(
        f"one GN iteration, {args.samples} samples x N = {args.steps} (margin {args.margin}), chunk {args.chunk}, "
        f"hold={args.hold} substeps={args.substeps}, x0 unknown (exact), best of {args.repeats}; "
        f"old = {args.baseline}, new = this tree"
    )
    print("| case | threads | old s | new s | new / old | new speed-up over 1 thread | max rel. diff of estimates |")
    print("|---|---|---|---|---|---|---|")
    for name in names:
        for threads in args.threads:
            old, new = best[(name, threads, "old")], best[(name, threads, "new")]
            a, b = estimates[(name, threads, "old")], estimates[(name, threads, "new")]
            diff = float(((a - b).abs() / a.abs().clamp_min(1e-300)).max())
            speedup = best[(name, args.threads[0], "new")] / new if threads != args.threads[0] else 1.0
            print(f"| {name} | {threads} | {old:.3f} | {new:.3f} | {new / old:.2f} | {speedup:.2f} | {diff:.1e} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=17000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--chunk", type=int, default=512)
    parser.add_argument("--threads", type=int, nargs="+", default=[1], help="torch threads; several with --baseline")
    parser.add_argument("--hold", default="spline")
    parser.add_argument("--substeps", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--degree", type=int, default=5, help="spline degree (3 or 5)")
    parser.add_argument(
        "--margin", type=int, default=0, help="input samples on each side of the --steps window (start=margin)"
    )
    parser.add_argument("--model", choices=["quarter", "seat", "sprung"], default="quarter")
    parser.add_argument("--accuracy", action="store_true", help="print hold errors vs continuous time instead")
    parser.add_argument("--gn", action="store_true", help="time one Gauss-Newton iteration instead")
    parser.add_argument(
        "--baseline",
        default=None,
        help="with --gn: a tree (checkout of main) whose code is timed side by side with this tree's (docstring)",
    )
    parser.add_argument("--cases", nargs="+", default=None, help="with --baseline: which cases (default all)")
    args = parser.parse_args()
    if args.gn and args.baseline:
        gauss_newton_against(args)
        return
    args.threads = args.threads[0]
    torch.set_num_threads(args.threads)
    if args.accuracy:
        accuracy()
        return
    if args.gn:
        gauss_newton(args)
        return

    from hybridqcm.estimation.exact import exact_outputs, exact_sensitivities
    from hybridqcm.estimation.sensitivity import euler_accelerations, euler_sensitivities
    from hybridqcm.testing import synthetic_samples

    data = synthetic_samples(args.samples, n_steps=args.steps + 2 * args.margin, seed=0)
    model = _model(args.model)
    params = data["params"].to(torch.float64)[:, : model.n_params]
    road = data["road"].to(torch.float64)
    x0 = 1e-3 * torch.randn(
        args.samples, model.n_state, generator=torch.Generator().manual_seed(2), dtype=torch.float64
    )
    chunks = [
        (params[i : i + args.chunk], road[i : i + args.chunk], x0[i : i + args.chunk])
        for i in range(0, args.samples, args.chunk)
    ]
    h = 0.01
    window = dict(start=args.margin, n_steps=args.steps, spline_degree=args.degree)
    worst = [0.0]

    def run(kind: str):
        def go():
            for p, u, x in chunks:
                if kind == "recursion" or kind == "modal":
                    exact_sensitivities(model, p, x, u[..., None], h, args.hold, args.substeps, method=kind, **window)
                elif kind == "exact_out":
                    exact_outputs(model, p, x, u[..., None], h, args.hold, args.substeps, **window)
                elif kind == "euler_sens":
                    euler_sensitivities(p, u[:, args.margin : args.margin + args.steps], h)
                else:
                    euler_accelerations(p, u[:, args.margin : args.margin + args.steps], h)

        return go

    for p, u, x in chunks:  # warm-up (spline matrix cache, allocator) and agreement of the two methods
        old, new = (
            exact_sensitivities(model, p, x, u[..., None], h, args.hold, args.substeps, method=m, **window)
            for m in ("recursion", "modal")
        )
        scale = old.abs().amax((0, 1)).clamp_min(1e-300)
        worst[0] = max(worst[0], float(((old - new).abs().amax((0, 1)) / scale).max()))
    kinds = ["recursion", "modal", "exact_out"] + (["euler_sens", "euler_acc"] if args.model == "quarter" else [])
    t = {kind: math.inf for kind in kinds}
    for _ in range(args.repeats):  # alternate, so that a change of machine load hits all alike
        for kind in kinds:
            t[kind] = min(t[kind], _best(run(kind), 1))
    cols = model.n_output * (1 + model.n_params + model.n_state)
    print(
        f"{args.model}: {args.samples} samples x {args.steps} steps, chunk {args.chunk}, {args.threads} thread(s), "
        f"hold={args.hold} substeps={args.substeps} degree={args.degree} margin={args.margin}"
    )
    print(
        f"  exact_sensitivities [b,T,{cols}]  recursion {t['recursion']:.3f} s   modal {t['modal']:.3f} s   "
        f"modal/recursion {t['modal'] / t['recursion']:.2f}   max rel. difference {worst[0]:.1e}"
    )
    if args.model == "quarter":
        print(
            f"  euler_sensitivities [b,T,3,11] {t['euler_sens']:.3f} s   recursion/Euler "
            f"{t['recursion'] / t['euler_sens']:.2f}   modal/Euler {t['modal'] / t['euler_sens']:.2f}"
        )
        print(
            f"  exact_outputs       [b,T,3]    {t['exact_out']:.3f} s   "
            f"euler_accelerations [b,T,3]    {t['euler_acc']:.3f} s   ratio {t['exact_out'] / t['euler_acc']:.2f}"
        )
    else:
        print(f"  exact_outputs {t['exact_out']:.3f} s")


if __name__ == "__main__":
    main()
