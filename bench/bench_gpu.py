"""Gauss-Newton on a GPU against the CPU: qcm-estimate's time and memory on the same recordings (issue 33, item 3).

    python bench/bench_gpu.py [--data FILE] [--gpu-sizes 4096 17000 170000] [--cpu-size 4096] [--cpu-processes 16]
        [--row-timeout S]

Every run is one `qcm-estimate experiment=E` process (bench_estimate_scale.estimate: wall time, summary.json,
peak RSS of the process and its children) on the first n recordings of one file, made by repeating the test
split of --data (bench_estimate_scale.make_big_file). Rows, each printed as soon as it is measured:

- `cpu x1`: one process (the solver's one torch thread), --cpu-single recordings;
- `cpu xP`: P forked CPU ranks (`trainer=ddp trainer.devices=P`), --cpu-size recordings: all the host's cores;
- `gpu`: one process, `trainer.accelerator=gpu gn_device=accelerator` (GN on the GPU, float64), blocks of
  --batch recordings and solver chunks of --chunk (one Jacobian pass a block: a GPU wants few large kernels),
  for each of --gpu-sizes while the --budget-s allows (a size whose predicted time does not fit is skipped).

A 16-recording CPU run first fills numba's cache (a fresh machine's first process compiles the solver's loops, ~10 s,
not a row's time). ``--row-timeout``: a run still going after S seconds is stopped with its children and reported
by the blocks it finished (their own seconds, recordings, GPU memory, statuses; its first block compared with the
CPU's rows), so a row cut by the lease still says how fast it went.

Columns: recordings, wall seconds of the command, seconds_solve (summary.json: the predict call, GN included),
recordings per second of seconds_solve, the ratio of that rate to the one-process CPU rate, peak RSS (MiB) and
the GPU's peak memory of one block's GN (summary.json device_memory_mib). Then how far the GPU's estimates
are from the CPU's on the recordings both solved (the estimates, the intervals apart, and the statuses), and
the float64 GEMM rates of both devices measured in the same run. Results: docs/measurements/scaling.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_estimate_scale import ROOT, RowTimeout, estimate, make_big_file, read_estimates, shard_progress  # noqa: E402


def gemm_gflops(device: str, n: int) -> float:
    """float64 GEMM n x n x n on ``device`` [GFLOP/s], best of 3 after a warm-up."""
    a = torch.randn(n, n, dtype=torch.float64, device=device)
    b = torch.randn(n, n, dtype=torch.float64, device=device)
    a @ b
    best = float("inf")
    for _ in range(3):
        if device != "cpu":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        a @ b
        if device != "cpu":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return 2 * n**3 / best / 1e9


def compare(gpu_csv: Path, cpu_csv: Path) -> str:
    """The GPU run's estimates against the CPU run's on the rows both have."""
    status_g, columns, numbers_g = read_estimates(gpu_csv)
    status_c, _, numbers_c = read_estimates(cpu_csv)
    n = min(len(status_g), len(status_c))
    numbers_g, numbers_c = numbers_g[:n], numbers_c[:n]
    interval = np.array([c.startswith("std_") or c in ("m3_std", "m3_low", "m3_high") for c in columns], dtype=bool)
    same = (numbers_g == numbers_c) | (np.isnan(numbers_g) & np.isnan(numbers_c))
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(numbers_g - numbers_c) / np.maximum(np.abs(numbers_c), 1e-300)
    rel = np.where(same, 0.0, np.where(np.isnan(rel), np.inf, rel))
    changed = sum(a != b for a, b in zip(status_g[:n], status_c[:n]))
    return (
        f"GPU vs CPU on {n} recordings: max relative difference of the estimates {np.max(rel[:, ~interval]):.2e} "
        f"(median {np.median(rel[:, ~interval]):.1e}), of the intervals {np.max(rel[:, interval], initial=0.0):.2e}; "
        f"statuses differing {changed}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "gpu_src.h5", help="recordings to repeat (test split)")
    ap.add_argument("--experiment", default="exp5_random_init")
    ap.add_argument("--gpu-sizes", type=int, nargs="+", default=[4096, 17000, 170000])
    ap.add_argument("--cpu-size", type=int, default=4096, help="recordings of the P-process CPU run")
    ap.add_argument("--cpu-single", type=int, default=512, help="recordings of the one-process CPU run")
    ap.add_argument("--cpu-processes", type=int, default=os.cpu_count())
    ap.add_argument("--batch", type=int, default=17000, help="GPU: recordings per block")
    ap.add_argument("--chunk", type=int, default=17000, help="GPU: solver.chunk_size")
    ap.add_argument("--budget-s", type=float, default=420.0, help="skip the GPU sizes predicted to end later")
    ap.add_argument(
        "--row-timeout",
        type=float,
        default=None,
        help="stop a run after this many seconds; its finished blocks are reported",
    )
    ap.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = ap.parse_args()
    t_start = time.perf_counter()
    cuda = torch.cuda.is_available()
    name = torch.cuda.get_device_name(0) if cuda else "none"
    print(f"{args.experiment}; host {os.cpu_count()} cores, torch {torch.__version__}; GPU: {name}", flush=True)
    big = make_big_file(max([*args.gpu_sizes, args.cpu_size, args.cpu_single]), args.data)
    base = [f"experiment={args.experiment}", f"data.path={big}", "block_samples=null", *args.overrides]
    out = ROOT / "outputs" / "bench_gpu"
    rates: dict[str, float] = {}

    def row(label: str, n: int, extra: list[str]) -> Path | None:
        run_dir = out / f"{label.replace(' ', '')}_{n}"
        try:
            wall, summary, rss = estimate([*base, f"n_samples={n}", *extra], run_dir, timeout=args.row_timeout)
        except SystemExit as failed:  # a failed run is reported and the others still run
            print(f"{label} {n}: {failed}", flush=True)
            return None
        except RowTimeout as stopped:  # what it finished: its blocks' own seconds (no start-up, no merge)
            done = shard_progress(run_dir)
            rate = done["rows"] / done["seconds"] if done["seconds"] else float("nan")
            print(
                f"{label} {n}: {stopped}, {done['blocks']} blocks ({done['rows']} recordings) done at {rate:.1f} "
                f"rec/s of their GN seconds ({done['seconds_min']:.1f}-{done['seconds_max']:.1f} s a block), "
                f"GPU MiB {done['device_memory_mib']}   {done['status_counts']}",
                flush=True,
            )
            first = run_dir / "shards" / "block-000000.csv"
            return first if done["blocks"] else None
        rate = n / summary["seconds_solve"]
        rates[label] = rate
        ratio = rate / rates["cpu x1"] if "cpu x1" in rates else float("nan")
        memory = summary.get("device_memory_mib")
        print(
            f"{label:<10} {n:7d} {wall:8.1f} {summary['seconds_solve']:8.1f} {rate:9.1f} {ratio:7.2f} {rss:8d} "
            f"{'-' if memory is None else f'{memory:8.0f}':>8}   {summary['status_counts']}",
            flush=True,
        )
        return run_dir / "estimates.csv"

    # a fresh machine's first process compiles the solver's loops into numba's cache (~10 s): not a row's time
    t0 = time.perf_counter()
    estimate([*base, "n_samples=16", "trainer=cpu", "batch_size=16"], out / "warmup")
    print(f"warm-up (numba's cache): {time.perf_counter() - t0:.1f} s", flush=True)
    head = f"{'run':<10} {'n':>7} {'wall s':>8} {'solve s':>8} {'rec/s':>9} {'x cpu1':>7} {'RSS MiB':>8} {'GPU MiB':>8}"
    print(head, flush=True)

    row("cpu x1", args.cpu_single, ["trainer=cpu", f"batch_size={args.cpu_single}"])
    p = args.cpu_processes
    cpu_csv = row(
        f"cpu x{p}", args.cpu_size, ["trainer=ddp", f"trainer.devices={p}", f"batch_size={args.cpu_size // p}"]
    )
    if not cuda:
        print("no CUDA device: the GPU rows are left out")
        return
    gpu = ["trainer=gpu", "gn_device=accelerator", f"solver.chunk_size={args.chunk}"]
    per_recording = None
    for n in args.gpu_sizes:
        left = args.budget_s - (time.perf_counter() - t_start)
        if per_recording is not None and n * per_recording + 30 > left:
            print(f"gpu {n}: skipped, predicted {n * per_recording:.0f} s, {left:.0f} s of the budget left", flush=True)
            continue
        t0 = time.perf_counter()
        gpu_csv = row("gpu", n, [*gpu, f"batch_size={min(args.batch, n)}"])
        if gpu_csv is None:
            break
        per_recording = (time.perf_counter() - t0) / n
        if n >= args.cpu_size and cpu_csv is not None:
            print(compare(gpu_csv, cpu_csv), flush=True)
    print(
        f"float64 GEMM: CPU 2048² {gemm_gflops('cpu', 2048):.0f} GFLOP/s, GPU 8192² {gemm_gflops('cuda', 8192):.0f} GFLOP/s"
    )


if __name__ == "__main__":
    main()
