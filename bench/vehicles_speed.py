"""Issue 30's speed target: the full car's full observation against the quarter car's exp 5, side by side.

    python bench/vehicles_speed.py [--n 64] [--rounds 2] [--vehicle full_car|half_car] [OVERRIDE ...]

Writes (once, into data/) a continuous mid-drive quarter-car file and a full-car file with the same
roads' classes, n recordings each in their test split, then runs `qcm-estimate experiment=exp5_random_init`
on the quarter car and `experiment=fcm_full_observation` (or hcm_) on the vehicle, alternately, `rounds`
times, one process each, the same settings otherwise. Prints per run the GN CPU seconds of its blocks
(the busiest process's CPU time: steadier than wall time on a shared machine) and the wall seconds of the
solve, the median ratio vehicle / quarter car of each, and what 17 000 recordings would take at these
rates (the blocks are independent, so time grows linearly with the count). Further arguments are Hydra
overrides for both runs. Results and commands: docs/measurements/vehicles.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "PYTHONWARNINGS": "ignore"}


def _simulate(path: Path, n: int, *overrides: str) -> None:
    if path.exists():
        return
    per_profile = 8
    profiles = max(1, -(-n // per_profile))
    command = [
        str(BIN / "qcm-simulate"),
        f"output={path}",
        f"samples_per_profile={per_profile}",
        f"splits.test.profiles={{A: {profiles}, B: 0, C: 0}}",
        "~splits.train",
        "progress=false",
        f"hydra.run.dir={ROOT / 'outputs' / 'bench_vehicles' / ('sim_' + path.stem)}",
        *overrides,
    ]
    subprocess.run(command, check=True, env=ENV, capture_output=True, text=True)


def _estimate(experiment: str, path: Path, n: int, run: str, overrides) -> dict:
    folder = ROOT / "outputs" / "bench_vehicles" / run
    command = [
        str(BIN / "qcm-estimate"),
        f"experiment={experiment}",
        f"data.path={path}",
        f"n_samples={n}",
        f"hydra.run.dir={folder}",
        "overwrite=true",
        "progress=false",
        "plots=false",
        "tensorboard=false",
        *overrides,
    ]
    proc = subprocess.run(command, env=ENV, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{experiment} failed: {proc.stderr[-2000:]}")
    summary = json.loads((folder / "summary.json").read_text())
    return {"cpu": float(summary["cpu_seconds_blocks"]), "wall": float(summary["seconds_solve"]), "summary": summary}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=64, help="recordings per run")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--vehicle", choices=("full_car", "half_car"), default="full_car")
    args, overrides = parser.parse_known_args()
    quarter = ROOT / "data" / f"bench_quarter_{args.n}.h5"
    vehicle = ROOT / "data" / f"bench_{args.vehicle}_{args.n}.h5"
    _simulate(quarter, args.n)
    _simulate(vehicle, args.n, f"vehicle={args.vehicle}")
    experiment = "fcm_full_observation" if args.vehicle == "full_car" else "hcm_full_observation"
    rows = []
    for r in range(args.rounds):
        q = _estimate("exp5_random_init", quarter, args.n, f"quarter_{r}", overrides)
        v = _estimate(experiment, vehicle, args.n, f"{args.vehicle}_{r}", overrides)
        rows.append((q, v))
        print(
            f"round {r}: quarter car {q['cpu']:.1f} s CPU / {q['wall']:.1f} s wall, "
            f"{args.vehicle} {v['cpu']:.1f} s CPU / {v['wall']:.1f} s wall -> ratio {v['cpu'] / q['cpu']:.2f} (CPU), "
            f"{v['wall'] / q['wall']:.2f} (wall)",
            flush=True,
        )
    cpu = statistics.median(v["cpu"] / q["cpu"] for q, v in rows)
    wall = statistics.median(v["wall"] / q["wall"] for q, v in rows)
    q_rate = statistics.median(q["cpu"] for q, _ in rows) / args.n
    v_rate = statistics.median(v["cpu"] for _, v in rows) / args.n
    print(
        f"\n{args.n} recordings, {args.rounds} rounds: {args.vehicle} / quarter car = {cpu:.2f} (CPU), {wall:.2f} (wall)"
    )
    print(
        f"17 000 recordings at these rates, one process: quarter car {q_rate * 17000 / 3600:.2f} h, "
        f"{args.vehicle} {v_rate * 17000 / 3600:.2f} h (CPU); target ratio <= 10"
    )
    last_q, last_v = rows[-1]
    print(
        "last stage's GN iterations per recording (mean): quarter car "
        f"{last_q['summary']['iterations_mean']:.1f}, {args.vehicle} {last_v['summary']['iterations_mean']:.1f}; "
        f"restarted: {last_q['summary']['restarted_samples']} / {last_v['summary']['restarted_samples']}"
    )


if __name__ == "__main__":
    main()
