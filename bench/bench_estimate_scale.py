"""qcm-estimate at scale: recordings per second on 1 and 2 processes, and peak memory vs file size.

    python bench/bench_estimate_scale.py throughput [--n 64] [--experiment exp10|occupant_roadfree]
    python bench/bench_estimate_scale.py memory [--sizes 17000 170000] [--cheap]

throughput: the same recordings estimated by one process and by `trainer=ddp trainer.devices=2`
(4 blocks, so each rank solves 2), one after the other; prints recordings/s of the GN solve
(the busiest process's time on its blocks), of the predict call (with the ranks' start-up) and
of the whole command, side by side, and the ratios.
exp10 needs the demo's checkpoints (the physics CNN and the U-Net, /work/main/outputs/demo);
without them use --experiment occupant_roadfree (no networks).

memory: a file of max(sizes) recordings made by tiling the test split of data/cont_small.h5 (a valid
schema file: the source's root attributes, accel/road/params) into data/bench_scale_N.h5, then one
qcm-estimate process per size n over its first n recordings; prints its peak RSS (getrusage of the waited-for child).
--cheap: one GN iteration per recording on the Euler model, p1 free (the memory path is the same: blocks
read, solved, written as shards, merged), so 170 000 recordings fit in minutes.
Results and commands: docs/notes/scaling.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py

ROOT = Path(__file__).resolve().parents[1]
SOURCE = Path("/work/main/data/cont_small.h5")
DEMO = Path("/work/main/outputs/demo")
BIN = Path(sys.executable).parent


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
                f"{split}/{key}", shape=(n, *data.shape[1:]), dtype=data.dtype, chunks=(256, *data.shape[1:])
            )
            piece = data[()]
            for start in range(0, n, m):
                stop = min(n, start + m)
                out[start:stop] = piece[: stop - start]
    os.replace(tmp, path)
    return path


def estimate(overrides: list[str], run_dir: Path, threads: int | None = None) -> tuple[float, dict, int]:
    """(wall seconds, summary.json, peak RSS in MiB of the command and its children)."""
    probe = (
        "import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
        "print('MAXRSS', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(r.returncode)"
    )
    command = [sys.executable, "-c", probe, str(BIN / "qcm-estimate"), *overrides, f"hydra.run.dir={run_dir}"]
    command += ["progress=false", "plots=false", "tensorboard=false", "overwrite=true"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    if threads:  # torch threads per process (Lightning gives spawned ranks cores / ranks unless set)
        env["OMP_NUM_THREADS"] = str(threads)
    t0 = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if result.returncode != 0:
        sys.exit(f"qcm-estimate failed:\n{(result.stdout + result.stderr)[-3000:]}")
    rss = next(int(line.split()[1]) for line in result.stdout.splitlines() if line.startswith("MAXRSS"))
    return wall, json.loads((run_dir / "summary.json").read_text()), rss // 1024


def experiment_overrides(name: str) -> list[str]:
    if name == "exp10":
        cnn, unet = DEMO / "exp2_physics/checkpoints/last.ckpt", DEMO / "exp9_unet/checkpoints/last.ckpt"
        if not (cnn.exists() and unet.exists()):
            sys.exit(f"exp10 needs {cnn} and {unet}; use --experiment occupant_roadfree")
        return ["experiment=exp10_hybrid", f"cnn_ckpt={cnn}", f"unet_ckpt={unet}"]
    return [f"experiment={name}"]


def throughput(args) -> None:
    base = [*experiment_overrides(args.experiment), f"data.path={SOURCE}", f"n_samples={args.n}"]
    base.append(f"batch_size={max(1, args.n // 4)}")
    rows, cpu = {}, {}
    for name, extra in (("1 process", []), ("2 processes", ["trainer=ddp", "trainer.devices=2"])):
        wall, summary, _ = estimate(
            [*base, *extra], ROOT / "outputs" / "bench_scale" / name.replace(" ", "_"), args.threads
        )
        busiest = max(summary["seconds_blocks_per_process"])  # the slowest rank's GN time
        rows[name] = (args.n / busiest, args.n / summary["seconds_solve"], args.n / wall)
        cpu[name] = summary["cpu_seconds_blocks"] / args.n
    threads = f"{args.threads} torch thread(s) per process" if args.threads else "default torch threads"
    print(f"{args.experiment}, {args.n} recordings of {SOURCE.name}, {os.cpu_count()} cores, {threads}")
    print(f"{'':12} {'rec/s (GN)':>11} {'rec/s (predict)':>16} {'rec/s (command)':>16}")
    for name, (gn, solve, total) in rows.items():
        print(f"{name:12} {gn:11.3f} {solve:16.3f} {total:16.3f}")
    one, two = rows["1 process"], rows["2 processes"]
    print(f"{'ratio 2/1':12} {two[0] / one[0]:11.2f} {two[1] / one[1]:16.2f} {two[2] / one[2]:16.2f}")
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
    t.add_argument("--threads", type=int, default=None, help="OMP_NUM_THREADS for both runs (e.g. 1)")
    m = sub.add_parser("memory")
    m.add_argument("--sizes", type=int, nargs="+", default=[17000, 170000])
    m.add_argument("--experiment", default="occupant_roadfree")
    m.add_argument("--cheap", action="store_true")
    m.add_argument("--file-size", type=int, default=None, help="recordings in the file (default: the largest size)")
    args = parser.parse_args()
    throughput(args) if args.what == "throughput" else memory(args)


if __name__ == "__main__":
    main()
