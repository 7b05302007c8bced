"""Is the road-free estimator at its Cramér–Rao bound? Repeated noise on the same clean recordings, the spread of
the estimates beside both bounds of bench/occupant_crb.py (the finite window's and the periodic one).

    PYTHONPATH=src .venv/bin/python bench/bound_check.py --clean data/persons/rigid_n0.h5 --n 100 --repeats 4 \
        --noise 0.05 --channels both a3 --out outputs/bound_check [--extra occupant.models=[rigid] delay=null]

For each `--channels` case (both: white noise of `--noise` x each clean channel's RMS on a3 and a2; a3: on the
seat pad only; a2: on the chassis only) the first `--n` rigid recordings of the noise-free file are written
`--repeats` times with independent noise (seed `--seed`), estimated by
`qcm-estimate experiment=occupant_roadfree` with `--extra` (default: the rigid one-clock fit, so the bound's
model is the fitted one), and scored: the mean |error| of m3 against the bounds' E|error| = sqrt(2/π) σ_M/M
over the same windows (the estimator's 500 samples: the input margins of the spline hold, 6 each side), and
the rms of the errors in units of each recording's bound (1 at the bound). The a2-only case has no finite-window
bound here (its covariance T Tᵀ is singular without output noise) and prints the periodic one alone.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CASES = {"both": (1.0, 1.0), "a3": (1.0, 0.0), "a2": (0.0, 1.0)}
MARGIN = 6  # the estimator's input margins at each end (n_steps: max on 512 stored samples -> 500)


def _module(name: str):
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write_noisy(clean: Path, out: Path, n: int, repeats: int, noise: float, case: str, seed: int) -> None:
    """out: the first n recordings of clean, each repeated `repeats` times (recording i -> rows i*repeats + r)
    with white noise on the case's channels (a1 gets the same noise as a2: it is not read)."""
    s3, s2 = CASES[case]
    with h5py.File(clean, "r") as f:
        attrs = dict(f.attrs)
        data = {k: f["test"][k][:n] for k in f["test"].keys()}
    if "truth_occupant" in data and np.any(data["truth_occupant"] != 0):
        sys.exit(f"bound_check: {clean}: the first {n} recordings are not all rigid occupants")
    rows = {k: np.repeat(v, repeats, axis=0) for k, v in data.items()}
    accel = rows["accel"]
    rms = np.sqrt(np.mean(accel**2, axis=1, keepdims=True))
    scale = np.zeros_like(rms)
    scale[..., 0], scale[..., 1:] = noise * s3, noise * s2
    rows["accel"] = accel + scale * rms * np.random.default_rng(seed).standard_normal(accel.shape)
    tmp = out.with_suffix(".tmp.h5")
    with h5py.File(tmp, "w") as g:
        g.attrs.update(attrs)
        for k, v in rows.items():
            g.create_dataset(f"test/{k}", data=v)
    tmp.replace(out)


def bounds(clean: Path, n: int, noise: float, case: str) -> tuple[np.ndarray, np.ndarray]:
    """(finite window, periodic) σ_M/M [n] of the rigid model, τ known, on the estimator's 500 samples."""
    crb, wf = _module("occupant_crb"), _module("window_fisher")
    accel, h, truth = crb.read_file(clean)
    s3, s2 = CASES[case]
    finite, periodic = np.full(n, np.nan), np.full(n, np.nan)
    for i in range(n):
        a3, a2 = accel[i, :, 0], accel[i, :, 1]
        r3, r2 = noise * s3 * np.sqrt(np.mean(a3**2)), noise * s2 * np.sqrt(np.mean(a2**2))
        theta = [truth["C3"][i] / truth["m3"][i], truth["K3"][i] / truth["m3"][i]]
        w = slice(MARGIN, accel.shape[1] - MARGIN)
        periodic[i] = crb.relative_sd("rigid", theta, a2[w], r3, r2, h, False)
        if r3 > 0:
            finite[i] = wf.relative_sd("rigid", theta, a2[w], a3[w], r3, r2, h, False)
    return finite, periodic


def score(run: Path, truth_m3: np.ndarray, repeats: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(relative error [n * repeats], the recording of each row, statuses) from run/estimates.csv."""
    with open(run / "estimates.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    index = np.array([int(r["index"]) for r in rows])
    m3 = np.array([float(r["m3"]) for r in rows])
    recording = index // repeats
    return m3 / truth_m3[recording] - 1, recording, [r["status"] for r in rows]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clean", type=Path, required=True, help="a noise-free foreign_sim file of rigid occupants")
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--channels", nargs="+", choices=list(CASES), default=["both", "a3"])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "bound_check")
    ap.add_argument("--extra", nargs="*", default=["occupant.models=[rigid]", "delay=null"])
    args = ap.parse_args(argv)
    if not args.clean.is_file():
        sys.exit(f"bound_check: --clean {args.clean}: no such file")
    if args.n < 1 or args.repeats < 2 or not args.noise > 0:
        sys.exit(
            f"bound_check: --n {args.n} --repeats {args.repeats} --noise {args.noise}: n >= 1, repeats >= 2, noise > 0"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    with h5py.File(args.clean, "r") as f:
        truth_m3 = f["test/truth_m3"][: args.n]
    total = args.n * args.repeats
    print(
        "| noise on | recordings | m3 mean error | finite-window bound | / bound | rms error / bound "
        "| periodic bound | / bound | rms error / bound | converged |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for case in args.channels:
        data = args.out / f"{case}.h5"
        run = args.out / f"run_{case}"
        write_noisy(args.clean, data, args.n, args.repeats, args.noise, case, args.seed)
        command = [
            sys.executable, "-m", "hybridqcm.apps.estimate", "experiment=occupant_roadfree", f"data.path={data}",
            f"n_samples={total}", f"batch_size={total}", "progress=false", "plots=false", "tensorboard=false",
            "overwrite=true", f"hydra.run.dir={run}", *args.extra,
        ]  # fmt: skip
        subprocess.run(command, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        err, rec, status = score(run, truth_m3, args.repeats)
        finite, periodic = bounds(args.clean, args.n, args.noise, case)
        k = np.sqrt(2 / np.pi)
        cells = []
        for b in (finite, periodic):
            if np.isnan(b).any():
                cells += ["—", "—", "—"]
                continue
            cells += [f"{100 * k * b[rec].mean():.3f} %", f"{np.mean(np.abs(err)) / (k * b[rec].mean()):.3f}",
                      f"{np.sqrt(np.mean((err / b[rec]) ** 2)):.3f}"]  # fmt: skip
        converged = np.mean(np.array(status) == "converged")
        print(
            f"| {case} | {total} ({args.n} x {args.repeats}) | {100 * np.mean(np.abs(err)):.3f} % | {cells[0]} | "
            f"{cells[1]} | {cells[2]} | {cells[3]} | {cells[4]} | {cells[5]} | {100 * converged:.1f} % |"
        )


if __name__ == "__main__":
    main()
