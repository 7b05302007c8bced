"""Cramér–Rao bound of the occupant mass on a calibrated seat (issue 31): p2's bound through the seat law.

    PYTHONPATH=src .venv/bin/python bench/calibration_crb.py FILE.h5 [--file-noise 0.05 --noise 0.05
        --exponent 0.5 --pan 12 --seat-file SEAT.json --first N --json OUT.json]

bench/occupant_crb.py gives per recording the bound σ(ln p2) of one window (`--domain time`, the default: the
finite window's Fisher information, bench/window_fisher.py; `dft`: the window taken as periodic, too small; of
the road-free seat model, a3 and a2 both noisy; for a rigid occupant the rigid model, for a
body1 person the body1 model at its true constants; τ known and unknown). On the reference seat that is the
relative bound of the static mass M = K3 / p2. On a seat with the law K3(M) = K3_ref (M / 80)^e and a pan,
the occupant = M(p2) - pan with ∂occupant/∂ln p2 = -M / (1 - e) (estimation/calibration.SeatLaw
.occupant_relative_sd), so its relative bound is σ(ln p2) M / ((1 - e) occupant): 1/(1-e) = 2 at e = 0.5, and
more for light occupants (M / occupant). Reported as the mean over recordings of E|error| = sqrt(2/π) σ (the
number to set beside a table's mean error), the median |error| of the recordings' normal errors together (beside
a measured median: a few light occupants' large σ, where the linearisation is poor, weigh on the mean) and the share an estimator at the bound would have within 2 %:
* the reference seat's bound (M = K3 / p2, K3 known: what the issue's one-window bounds are),
* the true law without calibration error (the seat known exactly),
* with --seat-file also the calibration's covariance (delta method, joined in quadrature): the law as fitted;
* with --cal-file (the calibration drives, /test/known_mass) the calibration's own bound: each drive's σ(ln p2)
  bound (rigid ballast, τ known as qcm-calibrate fits) weighs ln p2 = ln K3_ref - e ln 80 + (e - 1) ln(L + pan)
  (estimation/calibration._model) at the true law; its Fisher information's inverse over (K3_ref, e, pan), or
  over the parameters of --cal-law (proportional: K3 alone), is the calibration covariance at the bound.
Truth (the static mass on the spring, K3 at it, the pan, the occupant) from the file (bench/foreign_sim.py).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import h5py
import numpy as np
from scipy.special import erf

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "src"))
from hybridqcm.estimation.calibration import NESTED, SeatLaw, _model, load_seat  # noqa: E402

K3_SIM = 98935.0  # bench/foreign_sim.py's reference K3 at 80 kg


def _occupant_crb():
    spec = importlib.util.spec_from_file_location("occupant_crb", HERE / "occupant_crb.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _mixture_median(rel_sd: np.ndarray) -> float:
    """The median |error| over recordings at the bound: t with mean_i P(|N(0, σ_i)| ≤ t) = 1/2 (bisection)."""
    low, high = 0.0, 10 * float(rel_sd.max())
    for _ in range(100):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if np.mean(erf(mid / (np.sqrt(2) * rel_sd))) < 0.5 else (low, mid)
    return 0.5 * (low + high)


def summary(rel_sd: np.ndarray) -> dict:
    """Mean E|error| = sqrt(2/π) σ and the expected share within 2 % over recordings' relative σ [n]."""
    rel_sd = rel_sd[np.isfinite(rel_sd)]
    return {
        "n": int(rel_sd.size),
        "mean_abs_error": float(np.sqrt(2 / np.pi) * rel_sd.mean()),
        "median_abs_error": float(_mixture_median(rel_sd)),
        "within_2pct": float(np.mean(erf(0.02 / (np.sqrt(2) * rel_sd)))),
    }


def occupant_bounds(sd_ln_p2: np.ndarray, p2: np.ndarray, true: SeatLaw, fitted: SeatLaw | None) -> dict:
    """Per recording relative σ of the occupant: the reference seat's (σ ln p2), the true law's, the fitted
    law's with its calibration covariance (None without one)."""
    out = {"reference seat (M = K3 / p2)": sd_ln_p2, "true law": true.occupant_relative_sd(p2, sd_ln_p2, False)}
    if fitted is not None:
        out["fitted law + calibration covariance"] = fitted.occupant_relative_sd(p2, sd_ln_p2, True)
    return out


def calibration_bound(
    crb, path: str, noise: float, file_noise: float, true: SeatLaw, law: str, domain: str = "dft"
) -> SeatLaw:
    """The true law with the covariance of its Cramér–Rao bound from the calibration drives in ``path``."""
    accel, h, truth = crb.read_file(Path(path))
    with h5py.File(path, "r") as f:
        loads = f["test/known_mass"][()][: len(accel)]
    sd = noise * crb.bounds(accel, h, truth, file_noise, domain)["rigid_known"]
    theta = np.array([np.log(true.K3_ref), true.exponent, true.pan_mass])
    _, J = _model(theta, loads)
    free = np.array(NESTED[law])
    Jw = J[:, free] / sd[:, None]
    cov = np.zeros((3, 3))
    cov[np.ix_(free, free)] = np.linalg.inv(Jw.T @ Jw)
    T = np.diag([true.K3_ref, 1.0, 1.0])
    return SeatLaw(true.K3_ref, true.exponent, true.pan_mass, T @ cov @ T, law=law, loads=sorted(set(loads)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("file", help="a foreign_sim .h5 file (rigid occupants or body1 persons)")
    ap.add_argument("--noise", type=float, default=0.05, help="the noise fraction of the bound")
    ap.add_argument("--file-noise", type=float, default=0.0, help="the file's foreign_sim --noise")
    ap.add_argument("--exponent", type=float, default=0.5, help="the true law's exponent")
    ap.add_argument("--pan", type=float, default=12.0, help="the true law's pan mass [kg]")
    ap.add_argument("--seat-file", help="a qcm-calibrate seat file: the fitted law and its covariance")
    ap.add_argument("--cal-file", help="the calibration drives (foreign_sim --known-loads): the calibration's bound")
    ap.add_argument("--cal-law", default="power", choices=list(NESTED), help="the law whose parameters it fits")
    ap.add_argument("--first", type=int, help="the file's first N recordings only")
    ap.add_argument("--json", help="write the summary here")
    ap.add_argument(
        "--domain",
        choices=("time", "dft"),
        default="time",
        help="one window's bound: time, the finite window (bench/window_fisher.py); dft, taken as periodic (too small)",
    )
    ap.add_argument(
        "--body-prior",
        action="store_true",
        help="--domain time: body1 persons' bound with the default's literature body prior as information (at --noise)",
    )
    args = ap.parse_args(argv)
    if args.body_prior and args.domain != "time":
        sys.exit("calibration_crb: --body-prior is for --domain time")
    crb = _occupant_crb()
    accel, h, truth = crb.read_file(Path(args.file))
    if args.first is not None:
        accel, truth = accel[: args.first], crb._first(truth, args.first)
    per = crb.bounds(accel, h, truth, args.file_noise, args.domain, body_prior=args.body_prior, level=args.noise)
    with h5py.File(args.file, "r") as f:
        n = len(accel)
        occupant = f["test/truth_occupant_mass"][()][:n]
    p2 = truth["K3"] / truth["m3"]
    true = SeatLaw(K3_SIM, args.exponent, args.pan, np.zeros((3, 3)), loads=[0.0])
    check = np.abs(true.occupant_mass(p2) / occupant - 1).max()
    if check > 1e-6:
        sys.exit(f"calibration_crb: --exponent {args.exponent} --pan {args.pan} is not {args.file}'s law ({check:.2g})")
    fitted = load_seat(args.seat_file) if args.seat_file else None
    at_bound = None
    if args.cal_file:
        at_bound = calibration_bound(crb, args.cal_file, args.noise, args.file_noise, true, args.cal_law, args.domain)
    kinds = np.asarray(truth["occupant"])
    result = {"file": args.file, "noise": args.noise, "n": int(n), "rows": []}
    for model, kind in (("rigid", 0), ("body1", 1)):
        sel = kinds == kind
        if not sel.any():
            continue
        for delay in ("known", "unknown"):
            sd = args.noise * per[f"{model}_{delay}"][sel]
            bounds = occupant_bounds(sd, p2[sel], true, fitted)
            if at_bound is not None:
                label = f"true law + the calibration's bound ({args.cal_law})"
                bounds[label] = at_bound.occupant_relative_sd(p2[sel], sd, True)
            for label, rel in bounds.items():
                result["rows"].append({"model": model, "delay": delay, "bound": label} | summary(rel))
    print(f"{args.file}: {n} recordings, noise {args.noise:g} (one window each)\n")
    print("| occupant model | τ | bound of | mean E|error| at the bound | median | within 2 % at the bound |")
    print("|---|---|---|---|---|---|")
    for r in result["rows"]:
        print(f"| {r['model']} ({r['n']}) | {r['delay']} | {r['bound']} | {100 * r['mean_abs_error']:.2f} % | "
              f"{100 * r['median_abs_error']:.2f} % | "
              f"{100 * r['within_2pct']:.0f} % |")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
