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
and the median T_5, T_2.
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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("whole", help="foreign_sim drives --whole output (whole.h5)")
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--delay-unknown", action="store_true", help="the channel delay estimated too")
    ap.add_argument("--n", type=int, help="the first n drives only (those a run estimated)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    crb = _crb()
    accel, h, truth = crb.read_file(Path(args.whole))
    if args.n:
        accel, truth = accel[: args.n], crb._first(truth, args.n)
    n_rec, steps = accel.shape[:2]
    # each drive's bound under the model an estimator has to fit (occupant_crb.bounds: rigid for a rigid
    # occupant, body1 at the true constants for a body1 person, body1 fitted to a body2 person)
    per = crb.bounds(accel, h, truth)
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
