"""qcm-estimate at scale: recordings per second on 1 and 2 processes (and a GPU), and peak memory vs file size.

    python bench/bench_estimate_scale.py throughput [--n 64] [--experiment exp10|occupant_roadfree] [OVERRIDE ...]
    python bench/bench_estimate_scale.py memory [--sizes 17000 170000] [--cheap]

throughput: the same recordings estimated by one process, by `trainer=ddp trainer.devices=2`
(4 blocks, so each rank solves 2) and, where CUDA is available, by one process with
`trainer.accelerator=gpu` (the networks on the GPU, GN on the CPU), one after the other; prints
recordings/s of the GN solve (the busiest process's time on its blocks), of the predict call (with
the ranks' start-up) and of the whole command, side by side, the ratios to one process, and how far
each run's estimates are from the one-process run's (they should agree: same blocks, same seeds).
exp10 needs the checkpoints of a physics CNN and a U-Net (default: the demo's, outputs/demo; or
--cnn/--unet); without them use --experiment occupant_roadfree (no networks). Further arguments are
Hydra overrides for every run (e.g. n_steps=max).

memory: a file of max(sizes) recordings made by tiling the test split of data/cont_small.h5 (a valid
schema file: the source's root attributes, accel/road/params) into data/bench_scale_N.h5, then one
qcm-estimate process per size n over its first n recordings; prints its peak RSS (getrusage of the waited-for child).
--cheap: one GN iteration per recording on the Euler model, p1 free (the memory path is the same: blocks
read, solved, written as shards, merged), so 170 000 recordings fit in minutes.
Results and commands: docs/measurements/scaling.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "data" / "cont_small.h5"
DEMO = ROOT / "outputs" / "demo"


def make_big_file(n: int, source: Path = SOURCE, split: str = "test") -> Path:
    """data/bench_scale_N.h5: the source's test split repeated to N recordings (written in pieces)."""
    path = ROOT / "data" / f"bench_scale_{n}.h5"
    if path.exists():
        return path
    path.parent.mkdir(exist_ok=True)
    tmp = path.with_suffix(".h5.partial")
    with h5py.File(source, "r") as src, h5py.File(tmp, "w") as dst:
        for key, value in src.attrs.items():
            if key != "summary":  # the source's per-split summary does not describe the copy
                dst.attrs[key] = value
        group = src[split]
        m = group["accel"].shape[0]
        for key in ("accel", "road", "params"):
            data = group[key]
            out = dst.create_dataset(
                f"{split}/{key}", shape=(n, *data.shape[1:]), dtype=data.dtype, chunks=(min(256, n), *data.shape[1:])
            )
            piece = data[()]
            for start in range(0, n, m):
                stop = min(n, start + m)
                out[start:stop] = piece[: stop - start]
    os.replace(tmp, path)
    return path


class RowTimeout(Exception):
    """A run ended by estimate's ``timeout`` (its process group killed); ``run_dir`` holds the finished blocks."""

    def __init__(self, run_dir: Path, seconds: float):
        super().__init__(f"stopped after {seconds:.0f} s")
        self.run_dir, self.seconds = run_dir, seconds


def estimate(
    overrides: list[str], run_dir: Path, threads: int | None = None, timeout: float | None = None
) -> tuple[float, dict, int]:
    """(wall seconds, summary.json, peak RSS in MiB of the command and its children). ``timeout`` [s]: the run
    and its children are killed after it and RowTimeout raised (shard_progress reads what it finished)."""
    probe = (
        "import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
        "print('MAXRSS', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(r.returncode)"
    )
    app = [sys.executable, "-m", "hybridqcm.apps.estimate"]  # also where the console scripts are not installed
    command = [sys.executable, "-c", probe, *app, *overrides, f"hydra.run.dir={run_dir}"]
    command += ["progress=false", "plots=false", "tensorboard=false", "overwrite=true"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")])))
    if threads:  # torch threads per process (Lightning gives spawned ranks cores / ranks unless set)
        env["OMP_NUM_THREADS"] = str(threads)
    t0 = time.perf_counter()
    # its own process group: a timeout stops the estimate under the probe too, not the probe alone
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True
    )
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise RowTimeout(run_dir, time.perf_counter() - t0) from None
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"qcm-estimate failed:\n{(stdout + stderr)[-3000:]}")
    rss = next(int(line.split()[1]) for line in stdout.splitlines() if line.startswith("MAXRSS"))
    return wall, json.loads((run_dir / "summary.json").read_text()), rss // 1024


def shard_progress(run_dir: Path) -> dict:
    """The finished blocks of a run (its shard markers, RUN/shards/*.done.json): blocks, rows, the blocks' GN
    seconds (sum, min, max), the largest device memory of a block [MiB] and the status counts."""
    markers = [json.loads(m.read_text()) for m in sorted((run_dir / "shards").glob("*.done.json"))]
    statuses: dict[str, int] = {}
    for m in sorted((run_dir / "shards").glob("*.status.csv")):
        if m.with_name(m.name.replace(".status.csv", ".done.json")).exists():
            for row in csv.DictReader(m.open()):
                statuses[row["status"]] = statuses.get(row["status"], 0) + 1
    seconds = [m["seconds"] for m in markers]
    memory = [m["device_memory_mib"] for m in markers if m.get("device_memory_mib") is not None]
    return {
        "blocks": len(markers),
        "rows": sum(m["rows"][1] - m["rows"][0] for m in markers),
        "seconds": sum(seconds),
        "seconds_min": min(seconds, default=float("nan")),
        "seconds_max": max(seconds, default=float("nan")),
        "device_memory_mib": max(memory, default=None),
        "status_counts": statuses,
    }


def experiment_overrides(name: str, cnn: Path | None = None, unet: Path | None = None) -> list[str]:
    if name == "exp10":
        cnn = cnn or DEMO / "exp2_physics/checkpoints/last.ckpt"
        unet = unet or DEMO / "exp9_unet/checkpoints/last.ckpt"
        if not (cnn.exists() and unet.exists()):
            sys.exit(f"exp10 needs {cnn} and {unet}; use --experiment occupant_roadfree")
        return ["experiment=exp10_hybrid", f"cnn_ckpt={cnn}", f"unet_ckpt={unet}"]
    return [f"experiment={name}"]


def read_estimates(path: Path) -> tuple[list[str], list[str], np.ndarray]:
    """(statuses, names of the numeric columns, the numeric columns) of an estimates.csv."""
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    status = [r.pop("status") for r in rows]
    return status, list(rows[0]) if rows else [], np.array([[float(v) for v in r.values()] for r in rows])


def throughput(args) -> None:
    source = args.data or SOURCE
    base = [*experiment_overrides(args.experiment, args.cnn, args.unet), f"data.path={source}", f"n_samples={args.n}"]
    base += [f"batch_size={args.batch_size or max(1, args.n // 4)}", *args.overrides]
    runs = {"1 process": [], "2 processes": ["trainer=ddp", "trainer.devices=2"]}
    if torch.cuda.is_available():  # a GPU column only where there is one
        runs[f"GPU ({torch.cuda.get_device_name(0)})"] = ["trainer.accelerator=gpu"]
    threads = f"{args.threads} torch thread(s) per process" if args.threads else "default torch threads"
    print(f"{args.experiment}, {args.n} recordings of {source.name}, {os.cpu_count()} cores, {threads}")
    labels = {name: f"ratio {name.split(' (')[0]}/1" for name in runs if name != "1 process"}
    width = max(map(len, [*runs, *labels.values()]))
    print(f"{'':{width}} {'rec/s (GN)':>11} {'rec/s (predict)':>16} {'rec/s (command)':>16}", flush=True)
    rows, cpu, estimates = {}, {}, {}
    for name, extra in runs.items():  # each row as soon as it is measured: a run cut short keeps the rest
        run_dir = ROOT / "outputs" / "bench_scale" / name.split(" (")[0].replace(" ", "_")
        wall, summary, _ = estimate([*base, *extra], run_dir, args.threads)
        busiest = max(summary["seconds_blocks_per_process"])  # the slowest rank's GN time
        rows[name] = (args.n / busiest, args.n / summary["seconds_solve"], args.n / wall)
        cpu[name] = summary["cpu_seconds_blocks"] / args.n
        estimates[name] = read_estimates(run_dir / "estimates.csv")
        print(f"{name:{width}} {rows[name][0]:11.3f} {rows[name][1]:16.3f} {rows[name][2]:16.3f}", flush=True)
    one = rows["1 process"]
    for name, label in labels.items():
        other = rows[name]
        print(f"{label:{width}} {other[0] / one[0]:11.2f} {other[1] / one[1]:16.2f} {other[2] / one[2]:16.2f}")
    status_one, columns, numbers_one = estimates["1 process"]
    # intervals (std_*, m3_low/high) apart: on noise-free data they sit at the rounding floor
    interval = np.array([c.startswith("std_") or c in ("m3_std", "m3_low", "m3_high") for c in columns], dtype=bool)
    for name, (status, _, numbers) in estimates.items():
        if name != "1 process" and numbers.size:  # the runs must estimate the same thing for their rates to compare
            # the same non-finite value in both runs (an unbounded interval, a NaN column) is agreement
            same = (numbers == numbers_one) | (np.isnan(numbers) & np.isnan(numbers_one))
            with np.errstate(invalid="ignore"):
                rel = np.abs(numbers - numbers_one) / np.maximum(np.abs(numbers_one), 1e-300)
            rel = np.where(same, 0.0, np.where(np.isnan(rel), np.inf, rel))
            changed = sum(a != b for a, b in zip(status, status_one))
            print(
                f"{name} vs 1 process: max relative difference of the estimates {np.nanmax(rel[:, ~interval]):.2e}, "
                f"of the intervals {np.nanmax(rel[:, interval], initial=0.0):.2e}; statuses differing {changed}"
            )
    # CPU seconds per recording in the GN blocks: equal for 1 and 2 processes means the ranks add no
    # work, i.e. 2 dedicated cores give ~2x GN throughput (what a shared machine cannot show in wall time).
    print("GN CPU s/recording: " + ", ".join(f"{k} {v:.4f}" for k, v in cpu.items()))


def memory(args) -> None:
    cheap = [
        "experiment=exp5_random_init",
        "dynamics=euler",
        "initial_state=rest",
        "known=[p2,p3,p4,p5,p6,p7,p8,p9,p10]",
        "stages=[{name: gn, channels: all, max_iterations: 1}]",
    ]
    overrides = cheap if args.cheap else experiment_overrides(args.experiment)
    print(f"{'recordings':>10} {'file MiB':>9} {'peak RSS MiB':>13} {'after solve':>12} {'wall s':>8}")
    path = make_big_file(max(args.file_size or 0, *args.sizes))  # one file; each run reads its first n
    for n in args.sizes:
        run_dir = ROOT / "outputs" / "bench_scale" / f"mem_{n}"
        wall, summary, rss = estimate([*overrides, f"data.path={path}", f"n_samples={n}"], run_dir)
        assert summary["n_samples"] == n
        solve = summary.get("max_rss_mib", {}).get("solve", float("nan"))  # the app's own, before the merge
        print(f"{n:10d} {path.stat().st_size / 2**20:9.0f} {rss:13d} {solve:12.0f} {wall:8.0f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    t = sub.add_parser("throughput")
    t.add_argument("--n", type=int, default=64)
    t.add_argument("--experiment", default="exp10")
    t.add_argument("--threads", type=int, default=None, help="OMP_NUM_THREADS for every run (e.g. 1)")
    t.add_argument("--data", type=Path, default=None, help=f"dataset (default {SOURCE})")
    t.add_argument("--cnn", type=Path, default=None, help="exp10: physics CNN checkpoint (default: the demo's)")
    t.add_argument("--unet", type=Path, default=None, help="exp10: U-Net checkpoint (default: the demo's)")
    t.add_argument("--batch-size", type=int, default=None, help="recordings per block (default n / 4)")
    t.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    m = sub.add_parser("memory")
    m.add_argument("--sizes", type=int, nargs="+", default=[17000, 170000])
    m.add_argument("--experiment", default="occupant_roadfree")
    m.add_argument("--cheap", action="store_true")
    m.add_argument("--file-size", type=int, default=None, help="recordings in the file (default: the largest size)")
    args = parser.parse_args()
    throughput(args) if args.what == "throughput" else memory(args)


if __name__ == "__main__":
    main()
