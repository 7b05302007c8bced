"""Two loggers per drive (issue 32): every seat/floor pair of a foreign_sim `drives --two-files` folder
through qcm-import's alignment (data/two_loggers.py) into ONE dataset (a drive per profile_id), for one
qcm-estimate aggregate=drive run, with the alignment scored against the simulator's truth.

    .venv/bin/python bench/foreign_sim.py drives --out data/two --n 100 --two-files
    .venv/bin/python bench/two_loggers.py data/two --out data/two/windows.h5 [--window 500]
    qcm-estimate experiment=occupant_roadfree delay=estimate aggregate=drive data.path=data/two/windows.h5 \\
        hydra.run.dir=outputs/two
    .venv/bin/python bench/foreign_sim.py score-drives outputs/two --truth data/two/truth.json --window-s 5

Printed per drive and in summary: the residual delay the alignment leaves between a3 and a2 (true
t_floor - t_seat minus the mapping applied, at mid-overlap and its largest size over the overlap; the
estimator's delay takes it), the drift found (and whether applied) against the truth, each logger's
tilt error and the rates found (from the time stamps; the simulator's nominal rates are 100 / 200 Hz,
its clocks off by up to ±50 ppm each).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py
import numpy as np

from hybridqcm.data.logger_csv import read_logger
from hybridqcm.data.two_loggers import align


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", help="foreign_sim drives --two-files output")
    ap.add_argument("--out", required=True)
    ap.add_argument("--window", type=int, default=500)
    ap.add_argument("--json", help="write the alignment numbers here")
    args = ap.parse_args(argv)
    folder = Path(args.folder)
    truth = json.loads((folder / "truth.json").read_text())["drives"]
    accel, pid, t0s, names, rows = [], [], [], [], []
    started = time.perf_counter()
    h = None
    for number, (name, record) in enumerate(truth.items()):
        seat = read_logger(folder / f"{name}_seat.csv")
        floor = read_logger(folder / f"{name}_floor.csv")
        aligned = align(seat, floor)
        rep = aligned.report
        h = aligned.h if h is None else h
        if abs(aligned.h - h) > 1e-12:
            raise SystemExit(f"{name}: grid rate {1 / aligned.h} differs from the first drive's {1 / h}")
        drift_applied = rep["drift_ppm"] * 1e-6 if rep["drift_applied"] else 0.0
        # residual t_floor - t_seat the estimator sees: truth minus the mapping applied, over the grid
        grid_floor = aligned.t0 + np.linspace(0.0, (aligned.a3.size - 1) * aligned.h, 5)
        grid_seat = (grid_floor - rep["offset_s"]) / (1 + drift_applied)
        mid = grid_seat[2]

        def residual(ts, rep=rep, record=record, drift_applied=drift_applied):
            true = record["offset_s"] + record["drift_ppm"] * 1e-6 * ts
            return 1000 * (true - (rep["offset_s"] + drift_applied * ts))

        rows.append(
            {
                "drive": name,
                "residual_delay_mid_ms": float(residual(mid)),
                "residual_delay_max_ms": float(np.max(np.abs(residual(grid_seat)))),
                "drift_ppm": rep["drift_ppm"],
                "drift_sd_ppm": rep["drift_sd_ppm"],
                "drift_applied": rep["drift_applied"],
                "drift_true_ppm": record["drift_ppm"],
                "tilt_err_deg": [
                    rep["seat"]["tilt_deg"] - record["seat_tilt_deg"],
                    rep["floor"]["tilt_deg"] - record["floor_tilt_deg"],
                ],
                "rate_rel_err": [
                    rep[r]["rate_hz"] / (record[f"{r}_rate_hz"] * (1 + record[f"{r}_clock_ppm"] * 1e-6)) - 1
                    for r in ("seat", "floor")
                ],
                "overlap_s": rep["overlap_s"],
            }
        )
        n = aligned.a3.size
        for start in range(0, n - args.window + 1, args.window):
            window = np.full((args.window, 3), np.nan, dtype=np.float32)
            window[:, 0] = aligned.a3[start : start + args.window]
            window[:, 1] = aligned.a2[start : start + args.window]
            accel.append(window)
            pid.append(number)
            t0s.append(aligned.t0 + start * aligned.h)
        names.append(name)
        r = rows[-1]
        print(
            f"{name}: residual delay {r['residual_delay_mid_ms']:+.2f} ms at mid (|max| {r['residual_delay_max_ms']:.2f}), "
            f"drift {r['drift_ppm']:+.0f} ± {r['drift_sd_ppm']:.0f} ppm (true {r['drift_true_ppm']:+.0f}, "
            f"{'applied' if r['drift_applied'] else 'not applied'}), tilt errors {r['tilt_err_deg'][0]:+.2f} / "
            f"{r['tilt_err_deg'][1]:+.2f} deg, rate errors {r['rate_rel_err'][0]:+.1e} / {r['rate_rel_err'][1]:+.1e}"
        )
    seconds = time.perf_counter() - started
    out = Path(args.out)
    tmp = out.with_name(out.name + ".partial")
    with h5py.File(tmp, "w") as f:
        f.attrs.update(schema="hybridqcm.dataset/2", h=h, n_steps=args.window, created_by="bench/two_loggers.py")
        f.attrs["recordings"] = json.dumps(names)
        f.attrs.update(window=args.window, stride=args.window)
        f["test/accel"] = np.stack(accel)
        f["test/profile_id"] = np.asarray(pid, dtype=np.int32)
        f["test/t_start"] = np.asarray(t0s)
    tmp.rename(out)
    mid = np.abs([r["residual_delay_mid_ms"] for r in rows])
    worst = np.array([r["residual_delay_max_ms"] for r in rows])
    tilt = np.abs([r["tilt_err_deg"] for r in rows])
    rate = np.abs([r["rate_rel_err"] for r in rows])
    summary = {
        "drives": len(rows),
        "seconds": seconds,
        "residual_delay_mid_ms_median": float(np.median(mid)),
        "residual_delay_mid_ms_max": float(mid.max()),
        "residual_delay_over_overlap_ms_max": float(worst.max()),
        "within_one_sample": float(np.mean(mid <= 1000 * h)),
        "tilt_err_deg_max": float(tilt.max()),
        "rate_rel_err_max": float(rate.max()),
        "drift_applied": int(sum(r["drift_applied"] for r in rows)),
    }
    print(
        f"{len(rows)} drives aligned in {seconds:.1f} s -> {out} ({len(accel)} windows of {args.window}); residual delay "
        f"at mid-overlap: median {summary['residual_delay_mid_ms_median']:.2f} ms, max {summary['residual_delay_mid_ms_max']:.2f} ms "
        f"(within one sample of {1000 * h:g} ms: {100 * summary['within_one_sample']:.0f} %), largest over an overlap "
        f"{summary['residual_delay_over_overlap_ms_max']:.2f} ms; tilt error <= {summary['tilt_err_deg_max']:.3f} deg; "
        f"rate error <= {summary['rate_rel_err_max']:.1e}; drift applied in {summary['drift_applied']}"
    )
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "drives": rows}, indent=1))


if __name__ == "__main__":
    main()
