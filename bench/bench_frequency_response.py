"""The noise model's frequency response, the eigendecomposition against an LU solve per frequency, side by side.

    PYTHONPATH=src .venv/bin/python bench/bench_frequency_response.py [--n 400] [--steps 500] [--repeat 5]

H [b, K, o, m] (and dH/dp) of `estimation/noise.frequency_response` for persons on the seat (one and two body
modes) and in the road-driven quarter car, at the K = steps // 2 + 1 frequencies of a window, one thread: the
library's modal form against `noise._response_lu` (the per-frequency LU solve it replaced, kept for the
recordings whose eigenvectors are ill conditioned) on the same tensors, best of ``--repeat``, with the largest
relative difference of H and of dH (dH relative to its largest entry per recording).
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from hybridqcm.estimation import noise
from hybridqcm.physics.linear_models import QuarterCarOccupantRoad, SeatOccupantBaseExcitation
from hybridqcm.physics.occupant import body_start
from hybridqcm.physics.parameters import PhysicalConstants


def _cases(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    for n_modes in (1, 2):
        seat = torch.cat([torch.tensor([615.0 / 80.0, 98935.0 / 80.0]), body_start(n_modes)]).double()
        jitter = torch.exp(0.2 * torch.randn(n, seat.numel(), generator=g, dtype=torch.float64))
        p = seat[None] * jitter
        yield f"seat, body{n_modes}", SeatOccupantBaseExcitation(n_modes), p
    car = PhysicalConstants(C1=300.0).to_params()[None].expand(n, -1)
    yield "quarter car, body1", QuarterCarOccupantRoad(1), torch.cat([p[:, :2], car[:, 2:], p[:, 2:5]], 1)


def _best(fn, args: tuple, repeat: int) -> float:
    fn(*args)
    best = math.inf
    for _ in range(repeat):
        start = time.perf_counter()
        fn(*args)
        best = min(best, time.perf_counter() - start)
    return best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=400, help="recordings")
    ap.add_argument("--steps", type=int, default=500, help="window length (K = steps // 2 + 1 frequencies)")
    ap.add_argument("--h", type=float, default=0.01)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    omega = 2 * math.pi * torch.fft.rfftfreq(args.steps, d=args.h, dtype=torch.float64)
    jw = (1j * omega).to(torch.complex128)
    print(f"{args.n} recordings, {omega.numel()} frequencies, one thread, best of {args.repeat} (ms)\n")
    print("| model | derivatives | LU | modal | modal / LU | max rel. diff H | max rel. diff dH |")
    print("|---|---|---|---|---|---|---|")
    for name, model, p in _cases(args.n, args.seed):
        matrices = model.matrices(p)
        for derivatives in (False, True):
            lu = _best(noise._response_lu, (model, p, matrices, jw, derivatives), args.repeat)
            modal = _best(noise.frequency_response, (model, p, omega, derivatives), args.repeat)
            H_lu, dH_lu = noise._response_lu(model, p, matrices, jw, derivatives)
            H, dH = noise.frequency_response(model, p, omega, derivatives)
            scale = H_lu.abs().amax((1, 2, 3), keepdim=True)
            diff_h = float(((H - H_lu).abs() / scale).max())
            diff_dh = "–"
            if derivatives:
                diff_dh = f"{float(((dH - dH_lu).abs() / dH_lu.abs().amax((1, 2, 3, 4), keepdim=True)).max()):.1e}"
            print(
                f"| {name} | {'yes' if derivatives else 'no'} | {1e3 * lu:.1f} | {1e3 * modal:.1f} | "
                f"{modal / lu:.2f} | {diff_h:.1e} | {diff_dh} |"
            )


if __name__ == "__main__":
    main()
