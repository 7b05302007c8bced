"""How much calibration is enough (issue 31 item 3): occupant-mass error against the number of calibration loads,
the drive time per load, and the drive time per unknown occupant (aggregate=drive), on a foam seat.

    PYTHONPATH=src .venv/bin/python bench/calibration_drives.py --out outputs/cal_drives [--unknown 40 --repeats 10
        --noise 0.05 --exponent 0.5 --pan 12 --windows 1 3 6]

Data (bench/foreign_sim.py make, the simulator that is not ours; 5.12 s windows at 100 Hz, a3 + a2, additive
white noise of --noise of each channel's RMS; foam seat K3, C3 ∝ (M/80)^e with a pan on the spring):
  * a calibration pool: ballast 0, 40, 80, 120 kg cycled over 4 x repeats x max(windows) recordings (each
    recording one window of a calibration drive: its own vehicle draw and road, the same seat);
  * --unknown rigid occupants ~ U(30, 150) kg, each with max(windows) windows (recording i carries occupant
    i % unknown), written as drives here: /test/profile_id = i % unknown, /test/t_start = (i // unknown) 5.12 s.
Runs (the console scripts): qcm-estimate experiment=occupant_roadfree occupant.models=[rigid] delay=null on the
pool (the per-recording fit qcm-calibrate makes), and the same with aggregate=drive n_samples=unknown x W for
each W in --windows (drives of W windows). Then per calibration (loads, windows per load, repeat r: disjoint
recordings of the pool) the seat law is fitted in process by estimation/calibration.fit_seat_law (qcm-calibrate's
call, law=power with 3-4 loads, linear with 2; 1 load cannot be calibrated) and applied to every drive's
(m3, m3_low, m3_high) as reports/drive.py does; scored against /test/truth_occupant_mass: mean relative error,
coverage of the 95 % interval, averaged over the repeats. One console check: qcm-calibrate n_samples=4 W (4 loads,
W windows, repeat 0) and qcm-estimate aggregate=drive seat_file=... give the same drives' occupant_mass as the
in-process path.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "src"))

from hybridqcm.estimation.calibration import CalibrationError, SeatLaw, fit_seat_law  # noqa: E402

POOL_LOADS = [0.0, 40.0, 80.0, 120.0]
SUBSETS = {1: [80.0], 2: [0.0, 120.0], 3: [0.0, 40.0, 120.0], 4: POOL_LOADS}
WINDOW_S = 5.12


def _run(cmd: list[str]) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)}\n{proc.stderr[-2000:]}")


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _estimate(py, data: Path, run_dir: Path, *extra: str) -> None:
    _run([py, "-m", "hybridqcm.apps.estimate", "experiment=occupant_roadfree", "occupant.models=[rigid]",
          "delay=null", f"data.path={data}", f"hydra.run.dir={run_dir}", "progress=false", "plots=false",
          "tensorboard=false", *extra])  # fmt: skip


def _occupant(seat: SeatLaw, K3: float, m3, low, high):
    """reports/drive.py's transform, vectorised: p2 = K3/m3 and its interval mapped, through the law."""
    p2, p2_low, p2_high = K3 / m3, np.where(np.isfinite(high), K3 / high, 0.0), K3 / low
    return seat.occupant_interval(p2, p2_low, p2_high)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="a new folder")
    ap.add_argument("--unknown", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--exponent", type=float, default=0.5)
    ap.add_argument("--pan", type=float, default=12.0)
    ap.add_argument("--windows", type=int, nargs="+", default=[1, 3, 6])
    ap.add_argument("--seed", type=int, default=300)
    ap.add_argument("--K3", type=float, default=98935.0, help="qcm-estimate's K3 (drives.csv's m3 = K3 / p2)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=False)
    py, t0 = sys.executable, time.perf_counter()
    w_max = max(args.windows)
    sim = [py, str(HERE / "foreign_sim.py"), "make", "--noise", str(args.noise), "--seat-law", "power",
           "--seat-exponent", str(args.exponent), "--pan-mass", str(args.pan)]  # fmt: skip
    pool, unknown = out / "pool.h5", out / "unknown.h5"
    n_pool = len(POOL_LOADS) * args.repeats * w_max
    _run([*sim, "--out", str(pool), "--n", str(n_pool), "--seed", str(args.seed),
          "--known-loads", *map(str, POOL_LOADS)])  # fmt: skip
    masses = np.random.default_rng(args.seed + 1).uniform(30.0, 150.0, args.unknown).round(3)
    _run([*sim, "--out", str(unknown), "--n", str(args.unknown * w_max), "--seed", str(args.seed + 2),
          "--known-loads", *map(str, masses)])  # fmt: skip
    with h5py.File(unknown, "r+") as f:
        n = f["test/accel"].shape[0]
        f["test/profile_id"] = (np.arange(n) % args.unknown).astype(np.int32)
        f["test/t_start"] = (np.arange(n) // args.unknown) * WINDOW_S
        truth = f["test/truth_occupant_mass"][: args.unknown]
    _estimate(py, pool, out / "pool_fit")
    fits = _rows(out / "pool_fit" / "estimates.csv")
    with h5py.File(pool, "r") as f:
        loads = f["test/known_mass"][()]
    index = np.array([int(r["index"]) for r in fits])
    value = {k: np.array([float(r[k]) for r in fits]) for k in ("p1", "p2", "std_p1", "std_p2")}
    ok = np.array([r["status"] == "converged" for r in fits]) & (value["p2"] > 0)
    load, window = loads[index], index // len(POOL_LOADS)  # window w of load L: recording 4 w + position of L

    drives = {}
    for w in args.windows:
        run = out / f"drives_w{w}"
        _estimate(py, unknown, run, "aggregate=drive", f"n_samples={args.unknown * w}")
        rows = _rows(run / "drives.csv")
        assert [int(r["drive"]) for r in rows] == list(range(args.unknown)), "a drive was split or lost"
        drives[w] = {k: np.array([float(r[k] or "nan") for r in rows]) for k in ("m3", "m3_low", "m3_high")}

    def score(seat: SeatLaw, w: int) -> tuple[float, float]:
        d = drives[w]
        occ, low, high = _occupant(seat, args.K3, d["m3"], d["m3_low"], d["m3_high"])
        return float(np.nanmean(np.abs(occ / truth - 1))), float(np.mean((low <= truth) & (truth <= high)))

    table = []
    for n_loads, subset in SUBSETS.items():
        for w_cal in args.windows:
            cell = {"loads": n_loads, "windows_per_load": w_cal, "scores": {w: [] for w in args.windows}, "laws": []}
            law = "power" if n_loads >= 3 else "linear"
            for r in range(args.repeats):
                use = ok & np.isin(load, subset) & (window >= r * w_max) & (window < r * w_max + w_cal)
                try:
                    fit = fit_seat_law(load[use], value["p2"][use], value["std_p2"][use], law=law)
                except CalibrationError as error:  # qcm-calibrate's one-line refusal (e.g. a load's only fit failed)
                    cell.setdefault("refused", []).append(str(error))
                    continue
                seat = fit["law"]
                cell["laws"].append([seat.K3_ref, seat.exponent, seat.pan_mass])
                for w in args.windows:
                    cell["scores"][w].append(score(seat, w))
            cell["law"] = law
            table.append(cell)
    true_law = SeatLaw(args.K3, args.exponent, args.pan, np.zeros((3, 3)), loads=POOL_LOADS)
    reference = {w: score(true_law, w) for w in args.windows}
    uncalibrated = {w: float(np.nanmean(np.abs(drives[w]["m3"] / truth - 1))) for w in args.windows}

    # the console path for one cell: qcm-calibrate (4 loads, w_max windows each, repeat 0) -> seat file ->
    # qcm-estimate aggregate=drive seat_file=... ; its occupant_mass against the in-process one
    seat_file = out / "seat_check.json"
    _run([py, "-m", "hybridqcm.apps.calibrate", f"data.path={pool}", f"output={seat_file}",
          f"n_samples={len(POOL_LOADS) * w_max}", f"hydra.run.dir={out / 'calibrate_check'}", "progress=false",
          "plots=false"])  # fmt: skip
    _estimate(py, unknown, out / "drives_check", "aggregate=drive", f"seat_file={seat_file}")
    console = np.array([float(r["occupant_mass"]) for r in _rows(out / "drives_check" / "drives.csv")])
    use = ok & (window < w_max)
    seat = fit_seat_law(load[use], value["p2"][use], value["std_p2"][use])["law"]
    d = drives[w_max]
    in_process = _occupant(seat, args.K3, d["m3"], d["m3_low"], d["m3_high"])[0]
    check = float(np.nanmax(np.abs(console / in_process - 1)))

    result = {"args": vars(args), "table": table, "true_law": reference, "uncalibrated": uncalibrated,
              "console_check_max_rel_diff": check, "seconds": time.perf_counter() - t0}  # fmt: skip
    (out / "table.json").write_text(json.dumps(result, indent=1, default=str))
    _print(args, table, reference, uncalibrated, check, result["seconds"])


def _print(args, table, reference, uncalibrated, check, seconds) -> None:
    ws = args.windows
    print(f"foam seat e = {args.exponent}, pan {args.pan} kg; noise {args.noise:g}; {args.unknown} unknown occupants; ")
    print(f"{args.repeats} calibrations per row (disjoint drives); drive time per load = windows x {WINDOW_S} s\n")
    head = " | ".join(f"{w} window{'s' if w > 1 else ''} ({w * WINDOW_S:g} s): mean error, coverage" for w in ws)
    print(f"| loads | law | windows per load (s) | {head} |")
    print("|---" * (3 + len(ws)) + "|")
    for cell in table:
        label = f"| {cell['loads']} | {cell['law']} | {cell['windows_per_load']} ({cell['windows_per_load'] * WINDOW_S:g} s) |"
        refused = len(cell.get("refused", []))
        if refused == args.repeats:
            print(f"{label} " + " | ".join(["cannot be calibrated"] * len(ws)) + " |")
            continue
        cells = []
        for w in ws:
            s = np.array(cell["scores"][w])
            cells.append(f"{100 * s[:, 0].mean():.2f} % (± {100 * s[:, 0].std():.2f}), {100 * s[:, 1].mean():.0f} %")
        if refused:
            cells[-1] += f" ({refused} of {args.repeats} calibrations refused)"
        print(f"{label} " + " | ".join(cells) + " |")
    print(
        "| — | true law | — | "
        + " | ".join(f"{100 * reference[w][0]:.2f} %, {100 * reference[w][1]:.0f} %" for w in ws)
        + " |"
    )
    print("| — | uncalibrated m3 | — | " + " | ".join(f"{100 * uncalibrated[w]:.1f} %" for w in ws) + " |")
    for cell in table:
        for message in sorted(set(cell.get("refused", []))):
            print(f"\n{cell['loads']} load(s), {cell['windows_per_load']} window(s) per load: refused: {message}")
    print(
        f"\nconsole check (qcm-calibrate + qcm-estimate aggregate=drive seat_file=): max relative difference {check:.2e}"
    )
    print(f"{seconds:.0f} s")


if __name__ == "__main__":
    main()
