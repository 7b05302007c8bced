"""Seat calibration measured (issue 31): calibrate on ballast drives, estimate unknown occupants, score both.

    PYTHONPATH=src .venv/bin/python bench/calibration_table.py --out outputs/calibration_table [--cal 40 --unknown 40
        --noise 0 0.05 --loads 0 40 80 120 --exponent 0.5 --pan 12 --law auto --persons 40 --repeats 8]

Per noise level: bench/foreign_sim.py make writes the calibration file (--known-loads cycled over --cal drives)
and a file of --unknown rigid occupants (30-150 kg) on the same foam seat (other seeds); qcm-calibrate fits the
seat; qcm-estimate experiment=occupant_roadfree occupant.models=[rigid] delay=null seat_file=... estimates them.
Scored against the files' truth: occupant_mass (calibrated) against /test/truth_occupant_mass, and the
uncalibrated answer m3 = K3_ref / p2 (what a user without a calibration reads as the occupant) against it too;
mean / max relative error, share within 2 %, 95 % interval coverage. Prints a markdown table.
--persons N: at every noise level above 0 also N seated persons (foreign_sim --occupant body1: one body mode,
the pan set to --pan) on the same seat, estimated with occupant_roadfree's default models (rigid, body1, body2,
delay auto) and the same seat file.
--repeats R: R - 1 more calibrations per noise level on other ballast drives (other seeds), each by qcm-calibrate,
applied in process (estimation/calibration.SeatLaw.occupant_interval, what qcm-estimate seat_file= computes) to the
same unknown occupants' fits: a calibration's error is one bias shared by every occupant, so one draw says little
about a 0.1 % difference; printed per draw (the law chosen) and as mean ± standard deviation over the R. Beside
them the true law (foreign_sim's K3 98935 N/m, --exponent, --pan) on the same fits: no calibration error.
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
sys.path.insert(0, str(HERE.parent / "src"))
from hybridqcm.estimation.calibration import SeatLaw, load_seat  # noqa: E402

K3_SIM = 98935.0  # bench/foreign_sim.py's REF K3: qcm-estimate's reference K3 too (m3 = K3 / p2)


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


def _score_law(run_dir: Path, data: Path, seat: SeatLaw) -> dict:
    """The occupant's errors and coverage with ``seat`` applied in process to a run's m3 and interval."""
    with open(run_dir / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    with h5py.File(data, "r") as f:
        truth = f["test/truth_occupant_mass"][()][[int(r["index"]) for r in rows]]
    m3, low, high = (np.array([float(r[k]) for r in rows]) for k in ("m3", "m3_low", "m3_high"))
    p2_low = np.where(np.isfinite(high), K3_SIM / high, 0.0)
    occ, occ_low, occ_high = seat.occupant_interval(K3_SIM / m3, p2_low, K3_SIM / low)
    err = np.abs(occ / truth - 1)
    return {
        "mean": float(np.mean(err)),
        "max": float(np.max(err)),
        "within_2pct": float(np.mean(err <= 0.02)),
        "coverage": float(np.mean((occ_low <= truth) & (truth <= occ_high))),
    }


def _repeats(args, out: Path, tag: str, k: int, noise: float, sim: list, run_dir: Path, unknown: Path) -> dict:
    """--repeats: more calibrations (other seeds) applied in process to the same unknown fits (module docstring)."""
    py, draws = sys.executable, []
    for r in range(args.repeats):
        seat_file = out / f"{tag}_seat.json" if r == 0 else out / f"{tag}_r{r}_seat.json"
        if r:
            cal = out / f"{tag}_r{r}_cal.h5"
            seed = args.seed + 2 * k + 1000 + r
            loads = [str(x) for x in args.loads]
            _run([*sim, "--out", str(cal), "--n", str(args.cal), "--seed", str(seed), "--known-loads", *loads])
            _run([py, "-m", "hybridqcm.apps.calibrate", f"data.path={cal}", f"output={seat_file}",
                  f"hydra.run.dir={out / (tag + f'_r{r}_calibrate')}", "progress=false", "plots=false",
                  f"law={args.law}"])  # fmt: skip
        seat = load_seat(seat_file)
        draws.append({"law": seat.law, "K3_ref": seat.K3_ref, "exponent": seat.exponent, "pan_mass": seat.pan_mass}
                     | _score_law(run_dir, unknown, seat))  # fmt: skip
    true = SeatLaw(K3_SIM, args.exponent, args.pan, np.zeros((3, 3)), loads=[0.0])
    return {"draws": draws, "true_law": _score_law(run_dir, unknown, true)}


def _repeat_lines(results) -> list[str]:
    if not any("repeats" in r for r in results):
        return []
    lines = [
        "",
        "| noise | calibration draw | law chosen | K3_ref, e, pan | mean error | excess over uncalibrated | coverage |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        if "repeats" not in r:
            continue
        uncal = r["uncalibrated m3"]["mean"]
        draws = r["repeats"]["draws"]
        for j, d in enumerate(draws):
            fitted = f"{d['K3_ref']:.0f}, {d['exponent']:.3f}, {d['pan_mass']:.2f} kg"
            lines.append(f"| {r['noise']:g} | {j} | {d['law']} | {fitted} | {100 * d['mean']:.3f} % | "
                         f"{100 * (d['mean'] - uncal):+.3f} % | {100 * d['coverage']:.1f} % |")  # fmt: skip
        mean = np.array([d["mean"] for d in draws])
        cover = np.array([d["coverage"] for d in draws])
        sd = np.std(mean, ddof=1) if len(mean) > 1 else float("nan")
        lines.append(f"| {r['noise']:g} | mean ± sd of {len(draws)} | | | {100 * mean.mean():.3f} ± {100 * sd:.3f} % | "
                     f"{100 * (mean.mean() - uncal):+.3f} % | {100 * cover.mean():.1f} % |")  # fmt: skip
        t = r["repeats"]["true_law"]
        lines.append(f"| {r['noise']:g} | the true law | | | {100 * t['mean']:.3f} % | {100 * (t['mean'] - uncal):+.3f} % | "
                     f"{100 * t['coverage']:.1f} % |")  # fmt: skip
    return lines


def _report(args, results) -> list[str]:
    """The tables main prints (and --md writes)."""
    lines = [
        f"calibration: {args.cal} drives at loads {args.loads} kg; {args.unknown} unknown rigid occupants 30-150 kg;",
        f"foam seat K3, C3 ∝ (M/80)^{args.exponent}, pan {args.pan} kg (bench/foreign_sim.py)",
        "",
        "| noise | fitted K3_ref, e, pan | estimate | mean error | max error | within 2 % | 95 % coverage |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        law = r["law"]
        fitted = f"{law['law']}: {law['K3_ref']:.0f}, {law['exponent']:.3f}, {law['pan_mass']:.2f} kg"
        for label in ("calibrated", "uncalibrated m3", "persons (body1), default models"):
            if label not in r:
                continue
            s = r[label]
            lines.append(
                f"| {r['noise']:g} | {fitted} | {label} | {100 * s['mean']:.3g} % | {100 * s['max']:.3g} % | "
                f"{100 * s['within_2pct']:.0f} % | {100 * s['coverage']:.0f} % |"
            )
    lines += _repeat_lines(results)
    lines += ["", f"converged: {', '.join(str(r['converged']) + '/' + str(r['n']) for r in results)}"]
    if args.persons:
        lines.append(
            f"persons converged: {', '.join(r['persons_converged'] for r in results if 'persons_converged' in r)}"
        )
    return lines


def _markdown(args, argv, lines: list[str]) -> str:
    """--md's page: a title, the command that made it and the tables (bench-generated, RESULTS.md includes it)."""
    import datetime
    import shlex

    command = " ".join(shlex.quote(a) for a in ["bench/calibration_table.py", *argv])
    body = [line if line.startswith("|") or not line else line + "  " for line in lines]
    return "\n".join(
        [
            f"# {args.md_title}",
            "",
            f"Generated by `PYTHONPATH=src .venv/bin/python {command}` on {datetime.date.today()} (rigid occupants "
            "`qcm-estimate experiment=occupant_roadfree occupant.models=[rigid] delay=null seat_file=...`, persons "
            "the default models; each calibration by `qcm-calibrate`; the second simulator, bench/foreign_sim.py). "
            "Bounds and the other measurements: docs/measurements/calibration.md.",
            "",
            *body,
            "",
        ]
    )


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
    ap.add_argument("--law", default="auto", help="qcm-calibrate's law= (auto, power, linear, ...)")
    ap.add_argument("--repeats", type=int, default=1, help="calibration draws per noise level (module docstring)")
    ap.add_argument("--persons", type=int, default=0, help="seated persons (body1) per noise level above 0")
    ap.add_argument(
        "--md", type=Path, help="also write the tables as a markdown page (e.g. docs/results/calibration.md)"
    )
    ap.add_argument("--md-title", default="Seat calibration (issue 31): a foam seat calibrated on ballast drives")
    args = ap.parse_args(argv)
    if args.md is not None and not args.md.parent.is_dir():
        ap.error(f"--md {args.md}: its folder does not exist")
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
        score |= {"noise": noise, "law": {k: law[k] for k in ("law", "K3_ref", "exponent", "pan_mass")}}
        if args.repeats > 1:
            score["repeats"] = _repeats(args, out, tag, k, noise, sim, run_dir, unknown)
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
    lines = _report(args, results)
    print("\n".join(lines))
    if args.md:
        from hybridqcm.atomic import atomic_write_text

        atomic_write_text(args.md, _markdown(args, sys.argv[1:] if argv is None else list(argv), lines))
        print(f"wrote {args.md}")


if __name__ == "__main__":
    main()
