"""The Cramér–Rao bound beside a drive's numbers (issue 32): the static mass's E|error| over whole drives and
the driving time after which an estimator at the bound has its 95 % interval within ±5 % and ±2 %.

    .venv/bin/python bench/foreign_sim.py drives --out data/drives --n 300 --whole
    .venv/bin/python bench/drive_crb.py data/drives/whole.h5 [--noise 0.05] [--delay-unknown]

Per drive (whole.h5 holds each drive's clean a3, a2 on one clock) bench/occupant_crb.py's bound σ_M/M of the
whole drive (white noise of `noise` times each channel's RMS on both, errors in variables) under the model an
estimator has to fit: rigid for a rigid occupant, body1 at the true constants for a one-mode person (`drives
--occupant body1 --whole` stores the persons' truth), body1 fitted to a two-mode person.
The information of a stationary drive grows in proportion to its duration D, so the bound after T seconds
is σ_M/M (D/T)^½ and an estimator at the bound has its 95 % interval within ±x after T_x = D (1.96 σ_M/M / x)²
(the bound of a short stretch computed directly from its periodogram scatters from second to second: too few
frequencies for the bound's large-sample form). Printed: the mean E|error| = sqrt(2/π) σ_M/M of whole drives
and the median T_5, T_2. `--domain time` takes the drive as the finite stretch it is (bench/window_fisher.py; the
periodic bound is 1-9 % too small on 60 s drives), `--window 500` the summed information of its 5 s windows, each
with its own initial state (the bound of the per-window estimate combined by information: 1-2 % above the whole's).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
from pathlib import Path

import numpy as np


def _crb():
    spec = importlib.util.spec_from_file_location("occupant_crb", Path(__file__).with_name("occupant_crb.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _windowed(crb, accel: np.ndarray, h: float, truth: dict, window: int) -> dict:
    """occupant_crb.bounds' per-drive σ_M/M (unit noise) from the summed information of the drive's consecutive
    windows of ``window`` samples (the remainder dropped), each window's bound in the time domain."""
    n_rec, steps = accel.shape[:2]
    k = steps // window
    if k < 1:
        raise SystemExit(f"drive_crb: --window {window}: longer than the drives ({steps} samples)")
    pieces = accel[:, : k * window].reshape(n_rec * k, window, accel.shape[2])
    # the noise is a fraction of the whole drive's RMS, not of each window's
    rms = np.repeat(np.sqrt(np.mean(accel[:, :, :2] ** 2, axis=1)), k, axis=0)
    per = crb.bounds(pieces, h, _repeat(truth, k), domain="time", rms=rms)
    out = {}
    for key, values in per.items():
        v = np.asarray(values, dtype=float).reshape(n_rec, k)
        if key == "fit_error":
            out[key] = v[:, 0]
            continue
        with np.errstate(divide="ignore"):
            info = np.nansum(v**-2.0, axis=1)
        with np.errstate(divide="ignore"):
            out[key] = np.where(np.isnan(v).all(axis=1), np.nan, info**-0.5)
    return out


def _repeat(truth: dict, k: int) -> dict:
    """The truth of each drive repeated for its k windows (arrays per recording, nested dicts of them)."""
    return {key: _repeat(v, k) if isinstance(v, dict) else np.repeat(np.asarray(v), k) for key, v in truth.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("whole", help="foreign_sim drives --whole output (whole.h5)")
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--delay-unknown", action="store_true", help="the channel delay estimated too")
    ap.add_argument("--n", type=int, help="the first n drives only (those a run estimated)")
    ap.add_argument("--json")
    ap.add_argument(
        "--domain",
        choices=("dft", "time"),
        default="dft",
        help="dft: the drive taken as periodic; time: its finite stretch with an unknown initial state "
        "(bench/window_fisher.py; the whole drive at once is slow: about 20 s a 60 s drive)",
    )
    ap.add_argument(
        "--window",
        type=int,
        default=0,
        help="--domain time: the information of consecutive windows of this many samples, each with its own "
        "initial state, summed (what a per-window estimate combined by information can reach; 0: the whole drive)",
    )
    args = ap.parse_args(argv)
    if args.window and args.domain != "time":
        raise SystemExit("drive_crb: --window is for --domain time")
    if args.window < 0:
        raise SystemExit(f"drive_crb: --window {args.window}: a number of samples >= 0")
    crb = _crb()
    accel, h, truth = crb.read_file(Path(args.whole))
    if args.n:
        accel, truth = accel[: args.n], crb._first(truth, args.n)
    n_rec, steps = accel.shape[:2]
    # each drive's bound under the model an estimator has to fit (occupant_crb.bounds: rigid for a rigid
    # occupant, body1 at the true constants for a body1 person, body1 fitted to a body2 person)
    if args.window:
        per = _windowed(crb, accel, h, truth, args.window)
    else:
        per = crb.bounds(accel, h, truth, domain=args.domain)
    which = "unknown" if args.delay_unknown else "known"
    kinds = np.asarray(truth["occupant"]).astype(int)
    columns = np.stack([per[f"{m}_{which}"] for m in ("rigid", "body1", "body1fit")], 1)
    whole = args.noise * columns[np.arange(n_rec), np.minimum(kinds, 2)]
    duration = steps * h
    t5, t2 = (duration * (1.959963984540054 * whole / level) ** 2 for level in (0.05, 0.02))
    occupants = ", ".join(f"{k} {int(np.sum(kinds == j))}" for j, k in enumerate(crb.KINDS) if np.any(kinds == j))
    numbers = {
        "drives": n_rec,
        "occupants": occupants,
        "duration_s": steps * h,
        "noise": args.noise,
        "delay_unknown": bool(args.delay_unknown),
        "domain": args.domain,
        "window": args.window,
        "mean_abs_error_bound": float(np.sqrt(2 / np.pi) * whole.mean()),
        "median_t_to_5pct_s": float(np.median(t5)),
        "median_t_to_2pct_s": float(np.median(t2)),
        "reached_2pct_in_drive": float(np.mean(t2 <= duration)),
    }
    print(
        f"{args.whole}: {n_rec} drives of {steps * h:g} s at {100 * args.noise:g} % noise ({occupants}), delay "
        f"{'estimated' if args.delay_unknown else 'known'}: bound E|error| {100 * numbers['mean_abs_error_bound']:.3g} %, "
        f"median time to ±5 % {numbers['median_t_to_5pct_s']:.3g} s, to ±2 % {numbers['median_t_to_2pct_s']:.3g} s "
        f"(±2 % within the drive for {100 * numbers['reached_2pct_in_drive']:.3g} %)"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(numbers, indent=1))


if __name__ == "__main__":
    main()
