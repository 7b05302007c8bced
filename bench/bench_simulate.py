"""Benchmark of data generation: batched integrator vs per-sample loops, fast vs direct roads,
and writing the full reference dataset.

    .venv/bin/python bench/bench_simulate.py            # full scale (34 000 x 500 integrator, 51 000 x 512 file)
    .venv/bin/python bench/bench_simulate.py --quick    # reduced scale, ~1 min
    .venv/bin/python bench/bench_simulate.py --skip-write
    .venv/bin/python bench/bench_simulate.py --physics-only --scale 0.05   # euler vs continuous datasets only

Prints absolute figures and ratios side by side, plus the machine load (other processes may share
the CPU; the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from hybridqcm.data.hdf5 import dataset_info
from hybridqcm.data.simulate import kmh_to_mps, write_dataset
from hybridqcm.physics.integrators import simulate
from hybridqcm.physics.parameters import params_to_matrices, road_gain
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.road import RoadProfile

H = 0.01
SPEED = kmh_to_mps(30.0)


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} CPUs"


def inputs(n_samples: int, n_steps: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    params = build_prior("thesis", h=H).sample(n_samples, g).params
    n_profiles = max(1, n_samples // 100)
    roads = RoadProfile().sample(torch.randint(0, 3, (n_profiles,), generator=g), n_steps, H, SPEED, g)
    return params, roads[torch.arange(n_samples) % n_profiles]


def batched(params: torch.Tensor, road: torch.Tensor, batch: int) -> float:
    start = time.perf_counter()
    for first in range(0, params.shape[0], batch):
        simulate(params[first : first + batch], road[first : first + batch], H)
    return time.perf_counter() - start


def per_sample_torch(params: torch.Tensor, road: torch.Tensor) -> float:
    """The same `simulate`, called once per sample (batch of 1)."""
    start = time.perf_counter()
    for i in range(params.shape[0]):
        simulate(params[i : i + 1], road[i : i + 1], H)
    return time.perf_counter() - start


def per_sample_numpy(params: torch.Tensor, road: torch.Tensor) -> float:
    """A plain Python loop over samples and steps with numpy 3x3 algebra (the textbook way)."""
    D, S = (m.numpy() for m in params_to_matrices(params))
    force = (road_gain(params)[:, None] * road).numpy()
    n_steps = road.shape[1]
    start = time.perf_counter()
    for i in range(params.shape[0]):
        v, q = np.zeros(3), np.zeros(3)
        accel = np.empty((n_steps, 3))
        b = np.zeros(3)
        for k in range(n_steps):
            b[2] = force[i, k]
            a = D[i] @ v + S[i] @ q + b
            accel[k] = a
            v = v + H * a
            q = q + H * v
    return time.perf_counter() - start


def bench_integrator(n_samples: int, n_steps: int, batch: int, n_loop: int) -> None:
    print(f"\n== integrator: {n_samples} samples x {n_steps} steps (semi-explicit Euler, float64)")
    params, road = inputs(n_samples, n_steps)
    t_batched = batched(params, road, batch)
    rate = n_samples * n_steps / t_batched
    t_torch1 = per_sample_torch(params[:n_loop], road[:n_loop]) * n_samples / n_loop
    t_numpy = per_sample_numpy(params[:n_loop], road[:n_loop]) * n_samples / n_loop
    print(f"{'method':<48}{'seconds':>12}{'sample-steps/s':>16}{'slower than batched':>22}")
    print(f"{f'batched simulate (chunks of {batch})':<48}{t_batched:12.2f}{rate:16.3g}{1.0:21.1f}x")
    for name, t in (
        (f"simulate per sample (timed {n_loop}, extrapolated)", t_torch1),
        (f"numpy loop per sample (timed {n_loop}, extrapolated)", t_numpy),
    ):
        print(f"{name:<48}{t:12.1f}{n_samples * n_steps / t:16.3g}{t / t_batched:21.1f}x")


def bench_road(n_profiles: int, n_steps: int) -> None:
    print(f"\n== road profiles: {n_profiles} profiles x {n_steps} steps x 1000 waves (float64)")
    road = RoadProfile()
    classes = torch.randint(0, 3, (n_profiles,), generator=torch.Generator().manual_seed(0))
    start = time.perf_counter()
    fast = road.sample(classes, n_steps, H, SPEED, torch.Generator().manual_seed(1))
    t_fast = time.perf_counter() - start
    start = time.perf_counter()
    direct = road.sample_direct(classes, n_steps, H, SPEED, torch.Generator().manual_seed(1))
    t_direct = time.perf_counter() - start
    diff = float((fast - direct).abs().max() / direct.abs().max())
    print(f"{'method':<48}{'seconds':>12}{'ratio':>10}")
    print(f"{'matrix products (RoadProfile.sample)':<48}{t_fast:12.4f}{1.0:9.1f}x")
    print(f"{'direct sum of sines (RoadProfile.sample_direct)':<48}{t_direct:12.4f}{t_direct / t_fast:9.1f}x")
    print(f"speed-up {t_direct / t_fast:.0f}x (target >= 50x); max relative difference {diff:.1e}")


def _reference_protocol() -> tuple[dict, int]:
    """Profiles per class and draws per profile of configs/simulate.yaml (34 000 + 17 000 samples)."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "configs" / "simulate.yaml")
    return OmegaConf.to_container(cfg.splits), int(cfg.samples_per_profile)


def bench_write(scale: float, directory: Path) -> None:
    profiles, per_profile = _reference_protocol()
    splits = {
        s: {"profiles": {c: max(1, round(n * scale)) for c, n in p["profiles"].items()}} for s, p in profiles.items()
    }
    total = sum(sum(s["profiles"].values()) for s in splits.values()) * per_profile
    path = directory / "reference.h5"
    print(f"\n== write_dataset: {total} samples x 512 steps, both splits, gzip level 1, thesis prior, seed 0")
    start = time.perf_counter()
    summaries = write_dataset(
        path,
        splits,
        build_prior("thesis", h=H),
        RoadProfile(),
        n_steps=512,
        h=H,
        speed_mps=SPEED,
        samples_per_profile=per_profile,
        seed=0,
        progress=False,
    )
    seconds = time.perf_counter() - start
    info = dataset_info(path)
    size = path.stat().st_size / 2**20
    print(
        f"wall time {seconds:.1f} s (target < 60 s at full scale), {total / seconds:.0f} samples/s, file {size:.0f} MiB"
    )
    for split, summary in summaries.items():
        print(
            f"  {split}: {info['splits'][split]['n_samples']} samples, {summary.seconds:.1f} s, "
            f"prior acceptance {100 * summary.acceptance_rate:.2f} % ({summary.n_drawn} candidates)"
        )
    path.unlink()


def bench_physics(scale: float, directory: Path) -> None:
    """write_dataset with physics=euler (from rest) and physics=continuous (mid-drive, warm-up 2-20 s), side by side."""
    profiles, per_profile = _reference_protocol()
    splits = {
        s: {"profiles": {c: max(1, round(n * scale)) for c, n in p["profiles"].items()}} for s, p in profiles.items()
    }
    total = sum(sum(s["profiles"].values()) for s in splits.values()) * per_profile
    print(f"\n== physics: {total} samples x 512 steps, both splits, gzip level 1, thesis prior, seed 0")
    print(f"{'physics':<40}{'seconds':>10}{'samples/s':>12}{'ratio':>8}")
    times = {}
    for physics, warmup, prior_h in (("euler", (0.0, 0.0), H), ("continuous", (2.0, 20.0), None)):
        path = directory / f"{physics}.h5"
        start = time.perf_counter()
        write_dataset(
            path,
            splits,
            build_prior("thesis", h=prior_h),
            RoadProfile(),
            n_steps=512,
            h=H,
            speed_mps=SPEED,
            samples_per_profile=per_profile,
            seed=0,
            progress=False,
            physics=physics,
            warmup_s=warmup,
        )
        times[physics] = time.perf_counter() - start
        path.unlink()
        label = f"{physics} (warm-up {warmup[0]:g}-{warmup[1]:g} s)"
        print(f"{label:<40}{times[physics]:10.1f}{total / times[physics]:12.0f}{times[physics] / times['euler']:7.2f}x")
    print(f"continuous / euler = {times['continuous'] / times['euler']:.2f} (target <= 2)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="reduced scale (3 400 samples, 1/10 of the dataset)")
    parser.add_argument("--skip-write", action="store_true", help="skip the dataset-writing benchmark")
    parser.add_argument("--batch", type=int, default=3400, help="integrator batch size (samples per simulate call)")
    parser.add_argument("--write-only", action="store_true", help="only the dataset-writing benchmark")
    parser.add_argument("--physics-only", action="store_true", help="only the euler vs continuous dataset comparison")
    parser.add_argument(
        "--scale", type=float, default=None, help="fraction of the reference protocol for --physics-only"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: torch's choice); 1 gives steadier figures on a shared CPU",
    )
    parser.add_argument("--dir", type=Path, default=None, help="where to write the temporary dataset")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    print(
        f"hybridqcm bench_simulate {'(quick)' if args.quick else '(full scale)'}: torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, {platform.processor() or platform.machine()}"
    )
    print(f"before: {load()}")
    n = 3400 if args.quick else 34000
    if args.physics_only:
        with tempfile.TemporaryDirectory(dir=args.dir) as directory:
            bench_physics(args.scale or (0.1 if args.quick else 1.0), Path(directory))
        print(f"\nafter: {load()}")
        return 0
    if not args.write_only:
        bench_integrator(n, 500, min(args.batch, n), n_loop=100 if args.quick else 200)
        bench_road(34 if args.quick else 340, 512)
    if not args.skip_write:
        with tempfile.TemporaryDirectory(dir=args.dir) as directory:
            bench_write(0.1 if args.quick else 1.0, Path(directory))
            bench_physics(0.1 if args.quick else 1.0, Path(directory))
    print(f"\nafter: {load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
