"""Seat calibration measured (issue 31): calibrate on ballast drives, estimate unknown occupants, score both.

    PYTHONPATH=src .venv/bin/python bench/calibration_table.py --out outputs/calibration_table [--cal 40 --unknown 40
        --noise 0 0.05 --loads 0 40 80 120 --exponent 0.5 --pan 12 --law power --persons 40]

Per noise level: bench/foreign_sim.py make writes the calibration file (--known-loads cycled over --cal drives)
and a file of --unknown rigid occupants (30-150 kg) on the same foam seat (other seeds); qcm-calibrate fits the
seat; qcm-estimate experiment=occupant_roadfree occupant.models=[rigid] delay=null seat_file=... estimates them.
Scored against the files' truth: occupant_mass (calibrated) against /test/truth_occupant_mass, and the
uncalibrated answer m3 = K3_ref / p2 (what a user without a calibration reads as the occupant) against it too;
mean / max relative error, share within 2 %, 95 % interval coverage. Prints a markdown table.
--persons N: at every noise level above 0 also N seated persons (foreign_sim --occupant body1: one body mode,
the pan set to --pan) on the same seat, estimated with occupant_roadfree's default models (rigid, body1, body2,
delay auto) and the same seat file.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

HERE = Path(__file__).resolve().parent


def _run(cmd: list[str]) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)}\n{proc.stderr[-2000:]}")


def _score(run_dir: Path, data: Path, labels=(("calibrated", "occupant_mass"), ("uncalibrated m3", "m3"))) -> dict:
    with open(run_dir / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    with h5py.File(data, "r") as f:
        truth = f["test/truth_occupant_mass"][()][[int(r["index"]) for r in rows]]

    def columns(name):
        return (np.array([float(r[f"{name}{k}"]) for r in rows]) for k in ("", "_low", "_high"))

    out = {}
    for label, name in labels:
        value, low, high = columns(name)
        err = np.abs(value / truth - 1)
        out[label] = {
            "mean": float(np.mean(err)),
            "max": float(np.max(err)),
            "within_2pct": float(np.mean(err <= 0.02)),
            "coverage": float(np.mean((low <= truth) & (truth <= high))),
        }
    out["converged"] = sum(r["status"] == "converged" for r in rows)
    out["n"] = len(rows)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="a new folder")
    ap.add_argument("--cal", type=int, default=40)
    ap.add_argument("--unknown", type=int, default=40)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.05])
    ap.add_argument("--loads", type=float, nargs="+", default=[0.0, 40.0, 80.0, 120.0])
    ap.add_argument("--exponent", type=float, default=0.5)
    ap.add_argument("--pan", type=float, default=12.0)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--law", default="power", help="qcm-calibrate's law= (power or linear)")
    ap.add_argument("--persons", type=int, default=0, help="seated persons (body1) per noise level above 0")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=False)
    py = sys.executable
    seat = ["--seat-law", "power", "--seat-exponent", str(args.exponent), "--pan-mass", str(args.pan)]
    results = []
    for k, noise in enumerate(args.noise):
        tag = f"noise{noise:g}"
        cal, unknown, seat_file = out / f"{tag}_cal.h5", out / f"{tag}_unknown.h5", out / f"{tag}_seat.json"
        sim = [py, str(HERE / "foreign_sim.py"), "make", "--noise", str(noise), *seat]
        loads = [str(x) for x in args.loads]
        _run([*sim, "--out", str(cal), "--n", str(args.cal), "--seed", str(args.seed + 2 * k), "--known-loads", *loads])
        _run([*sim, "--out", str(unknown), "--n", str(args.unknown), "--seed", str(args.seed + 2 * k + 1)])
        common = ["progress=false", "plots=false"]
        _run([py, "-m", "hybridqcm.apps.calibrate", f"data.path={cal}", f"output={seat_file}",
              f"hydra.run.dir={out / (tag + '_calibrate')}", "progress=false", f"law={args.law}"])  # fmt: skip
        run_dir = out / f"{tag}_estimate"
        _run([py, "-m", "hybridqcm.apps.estimate", "experiment=occupant_roadfree", "occupant.models=[rigid]",
              "delay=null", f"data.path={unknown}", f"seat_file={seat_file}", f"hydra.run.dir={run_dir}", *common])  # fmt: skip
        law = json.loads(seat_file.read_text())
        score = _score(run_dir, unknown)
        score |= {"noise": noise, "law": {k: law[k] for k in ("K3_ref", "exponent", "pan_mass")}}
        if args.persons and noise > 0:
            persons, person_dir = out / f"{tag}_persons.h5", out / f"{tag}_persons_estimate"
            _run([*sim, "--out", str(persons), "--n", str(args.persons), "--seed", str(args.seed + 50 + k),
                  "--occupant", "body1"])  # fmt: skip
            _run([py, "-m", "hybridqcm.apps.estimate", "experiment=occupant_roadfree", f"data.path={persons}",
                  f"seat_file={seat_file}", f"hydra.run.dir={person_dir}", *common])  # fmt: skip
            person = _score(person_dir, persons, (("persons (body1), default models", "occupant_mass"),))
            score["persons (body1), default models"] = person["persons (body1), default models"]
            score["persons_converged"] = f"{person['converged']}/{person['n']}"
        results.append(score)
    (out / "table.json").write_text(json.dumps(results, indent=1))
    print(f"calibration: {args.cal} drives at loads {args.loads} kg; {args.unknown} unknown rigid occupants 30-150 kg;")
    print(f"foam seat K3, C3 ∝ (M/80)^{args.exponent}, pan {args.pan} kg (bench/foreign_sim.py)\n")
    print("| noise | fitted K3_ref, e, pan | estimate | mean error | max error | within 2 % | 95 % coverage |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        law = r["law"]
        fitted = f"{law['K3_ref']:.0f}, {law['exponent']:.3f}, {law['pan_mass']:.2f} kg"
        for label in ("calibrated", "uncalibrated m3", "persons (body1), default models"):
            if label not in r:
                continue
            s = r[label]
            print(
                f"| {r['noise']:g} | {fitted} | {label} | {100 * s['mean']:.3g} % | {100 * s['max']:.3g} % | "
                f"{100 * s['within_2pct']:.0f} % | {100 * s['coverage']:.0f} % |"
            )
    print(f"\nconverged: {', '.join(str(r['converged']) + '/' + str(r['n']) for r in results)}")
    if args.persons:
        print(f"persons converged: {', '.join(r['persons_converged'] for r in results if 'persons_converged' in r)}")


if __name__ == "__main__":
    main()
