"""qcm-estimate's report: the run's metrics, summary and console table (the per-block rows of
estimates.csv and status.csv: estimation/tables.py).

A block's rows are written as soon as its GN solve ends (estimation/shards.py); the metrics
(error distribution, calibration, occupant mass m3 = K3/p2, status counts) are computed once
from the merged per-sample columns [M, P] of parameters, std, truth and status, never from the
recordings: memory holds a few numbers per recording, not the time series.

estimates.csv: index, p (P), status, std_p (P), m3, m3_std, m3_low, m3_high, x0 (S), std_x0 (S).
The 95 % interval of m3 is the image of p2's (m3 = K3/p2 is monotone): skewed, unlike m3 ± 1.96σ.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch.utils.tensorboard import SummaryWriter

from hybridqcm import runfolder
from hybridqcm.atomic import atomic_write_csv, atomic_write_text
from hybridqcm.console import print_table
from hybridqcm.estimation import compiled_loops
from hybridqcm.estimation.solver import STATUS_LABELS, SolverStatus
from hybridqcm.estimation.tables import ALL_STATUS_LABELS, merge_stage_stats
from hybridqcm.estimation.window_check import WINDOW_STATUS_LABELS, is_skipped
from hybridqcm.metrics import coverage_95, error_distribution_rows, m3_interval, write_error_distribution
from hybridqcm.physics.parameters import PARAM_NAMES


def noise_label(noise_sigma: float, sensor) -> str:
    """The noise the estimator saw, in words: the sensor model and/or the source's multiplicative
    `noise_sigma` (SPEC §5); 'none' when neither is set."""
    parts = [f"source multiplicative σ = {float(noise_sigma):g}"] if float(noise_sigma) > 0 else []
    if sensor is not None and sensor.active:
        parts.append(sensor.describe())
    return "; ".join(parts) or "none"


def failed_and_errors(params, true, status_codes, free, summary: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """(failed [M] bool, relative errors [M, len(free)] of the free parameters, inf where failed), and the
    summary's failed_samples / all_within_1pct / all_within_10pct. A diverged or non-finite sample counts
    as failed (and, in the callers, as not covered), never as a success."""
    failed = ~torch.isfinite(params).all(1) | (status_codes == int(SolverStatus.DIVERGED))
    err = ((params - true).abs() / true.abs())[:, free]
    err = torch.where(failed[:, None] | ~torch.isfinite(err), torch.full_like(err, math.inf), err)
    summary["failed_samples"] = int(failed.sum())
    summary["all_within_1pct"] = float((err <= 0.01).all(1).double().mean())
    summary["all_within_10pct"] = float((err <= 0.10).all(1).double().mean())
    return failed, err


def write_metrics(
    cfg,
    columns: Mapping[str, torch.Tensor],
    true: torch.Tensor | None,
    known: Sequence[int],
    run_dir: Path,
    n_steps: int | None = None,
    noise: str = "none",
) -> tuple[dict, list | None]:
    """`noise` describes the noise on the data for the table's title (`noise_label`). Status counts, and with the truth [M, 10]: error distribution, calibration.csv, m3 metrics,
    sorted plots and the TensorBoard table. Returns (summary entries, error-table rows or None)."""
    status_codes = columns["status"]
    status = [ALL_STATUS_LABELS[int(s)] for s in status_codes]
    # windows kept from the fit (a car standing still, a clipped channel): no estimate, not in the metrics
    skipped = {k: int(sum(1 for s in status if s == k)) for k in WINDOW_STATUS_LABELS.values()}
    summary: dict = {
        "status_counts": {k: int(sum(1 for s in status if s == k)) for k in STATUS_LABELS.values()}
        | {k: v for k, v in skipped.items() if v},
        "skipped_windows": skipped,
    }
    fitted = ~is_skipped(status_codes)
    if not bool(fitted.all()):
        columns = {k: v[fitted] if isinstance(v, torch.Tensor) else v for k, v in columns.items()}
        true = None if true is None else true[fitted]
        status_codes = columns["status"]
    params, std = columns["params"], columns["std"]
    n, n_params = params.shape
    summary["iterations_mean"] = float(columns["iterations"].double().mean()) if n else math.nan
    summary["restarted_samples"] = int((columns["restarts"] > 0).sum())
    if true is None or n == 0:
        return summary, None
    K3 = float(cfg.K3)
    free = [j for j in range(n_params) if j not in known]
    free_names = [PARAM_NAMES[j] for j in free]
    true = true[:, :n_params]
    m3, m3_std, m3_low, m3_high = m3_interval(params, std, K3)
    if "m3_low" in columns:  # the interval the estimates report (a model selection's may be wider)
        m3_low, m3_high = columns["m3_low"], columns["m3_high"]
    table_rows = error_distribution_rows(params[:, free], true[:, free], free_names)
    window = cfg.n_steps if n_steps is None else n_steps
    title = f"{cfg.experiment_name}: {n} samples, N = {window}, sensor noise: {noise}"
    write_error_distribution(table_rows, run_dir, title=title)
    failed, err = failed_and_errors(params, true, status_codes, free, summary)
    # calibration: fraction of true values inside the 95 % interval; a failed sample or an infinite
    # interval (diverged, not identifiable) covers nothing: it is a failure, not a success.
    cal_rows = []
    for j, name in zip(free, free_names):
        ok = ~failed & torch.isfinite(std[:, j]) & torch.isfinite(params[:, j])
        cal_rows.append(
            [
                name,
                n,
                coverage_95(params[:, j], true[:, j], std[:, j], failed),
                float(std[:, j][ok].median() / true[:, j][ok].median()) if bool(ok.any()) else math.inf,
            ]
        )
    true_m3 = K3 / true[:, 1]
    m3_ok = ~failed & torch.isfinite(m3_high) & torch.isfinite(m3_low)
    inside = ((true_m3 >= m3_low) & (true_m3 <= m3_high) & m3_ok).double()
    m3_width = (m3_high - m3_low) / true_m3
    cal_rows.append(
        [
            "m3",
            n,
            float(inside.mean()),
            float(m3_std[m3_ok].median() / true_m3[m3_ok].median()) if bool(m3_ok.any()) else math.inf,
        ]
    )
    atomic_write_csv(run_dir / "calibration.csv", ["param", "n", "coverage_95", "median_rel_std"], cal_rows)
    m3_err = (m3 - true_m3).abs() / true_m3.abs()
    m3_err = torch.where(torch.isfinite(m3_err), m3_err, torch.full_like(m3_err, math.inf))
    summary["m3_mean_rel_err"] = float(m3_err.mean())
    summary["m3_p95_rel_err"] = float(m3_err.quantile(0.95))
    summary["m3_within_0.5pct"] = float((m3_err <= 0.005).double().mean())
    summary["m3_within_1pct"] = float((m3_err <= 0.01).double().mean())
    summary["m3_within_5pct"] = float((m3_err <= 0.05).double().mean())
    summary["m3_coverage_95"] = float(inside.mean())
    # What the statuses promise: an answer called `converged` is right. Its mean and worst error, beside
    # the mean over every recording (which a single flagged wrong basin can dominate); None: none converged.
    done = m3_err[status_codes == int(SolverStatus.CONVERGED)]
    summary["m3_mean_rel_err_converged"] = float(done.mean()) if done.numel() else None
    summary["m3_max_rel_err_converged"] = float(done.max()) if done.numel() else None
    summary["m3_interval_median_rel_width"] = float(m3_width[m3_ok].median()) if bool(m3_ok.any()) else math.inf
    pictures = []  # this run's plots only: a figure of the user's in plots/ is not ours to log
    if cfg.plots:
        from hybridqcm.plots import close, plot_sorted_predictions  # matplotlib: only when plotting

        for j, name in zip(free, free_names):
            pictures.append(run_dir / "plots" / f"sorted_{name}.png")
            close(
                plot_sorted_predictions(
                    params[:, j].numpy(), true[:, j].numpy(), name, pictures[-1], title=f"{cfg.experiment_name}: {name}"
                )
            )
        pictures.append(run_dir / "plots" / "sorted_m3.png")
        close(
            plot_sorted_predictions(
                m3.numpy(), true_m3.numpy(), "m3 [kg]", pictures[-1], title=f"{cfg.experiment_name}: occupant mass"
            )
        )
    if cfg.tensorboard:  # the table and the plots beside the GN losses, in one TensorBoard run
        from hybridqcm.tracking import log_estimation_to_tensorboard

        log_estimation_to_tensorboard(run_dir / "tb", table_rows, sorted(pictures), title=title)
    return summary, table_rows


def log_stage_losses(log_dir: Path, stage_loss: Mapping[str, Sequence[float]]) -> None:
    """gn/<stage>/mean_loss per iteration, as GaussNewtonRefinement logs it in a single process."""
    writer = SummaryWriter(log_dir=str(log_dir))
    try:
        for name, losses in stage_loss.items():
            for iteration, value in enumerate(losses):
                writer.add_scalar(f"gn/{name}/mean_loss", value, iteration)
    finally:
        writer.close()


def print_report(cfg, summary: Mapping, table_rows: list | None, run_dir: Path) -> None:
    n = summary["n_samples"]
    print_table(
        f"{cfg.experiment_name}: status", ["status", "samples"], [[k, v] for k, v in summary["status_counts"].items()]
    )
    skipped = summary.get("skipped_windows") or {}
    if sum(skipped.values()):
        n -= sum(skipped.values())
        print(
            f"skipped {sum(skipped.values())} window(s) without information, no estimate: "
            + ", ".join(f"{k} {v}" for k, v in skipped.items())
            + " (estimates.csv status; skip_windows.* in the config)"
        )
    if table_rows is None:
        why = "every window was skipped" if n == 0 else "no params in the file"
        print(f"estimates of {n} samples ({why}: no error table) -> {run_dir}")
        return
    print_table(
        f"{cfg.experiment_name}: relative error, {n} samples",
        ["param", "max", "mean", "≤1 %", "≤5 %", "≤10 %", "≤25 %", ">25 %"],
        [
            [
                r["param"],
                f"{100 * r['max_err']:.3g} %",
                f"{100 * r['mean_err']:.3g} %",
                f"{100 * r['within_1pct']:.2f} %",
                f"{100 * r['within_5pct']:.2f} %",
                f"{100 * r['within_10pct']:.2f} %",
                f"{100 * r['within_25pct']:.2f} %",
                f"{100 * r['over_25pct']:.2f} %",
            ]
            for r in table_rows
        ],
    )
    print(
        f"all estimated parameters within 1 %: {100 * summary['all_within_1pct']:.2f} % of samples; "
        f"GN {summary['seconds_solve']:.1f} s, total {summary['seconds_total']:.1f} s -> {run_dir}"
    )


def plot_first_recordings(run_dir, plan, estimates_csv, count: int = 4) -> list:
    """plots/apparent_mass_<index>.png for the first ``count`` recordings: measured and fitted a3/a2 and
    the fitted apparent mass over 0.5-15 Hz (plots.plot_apparent_mass). Returns the PNG paths."""
    import csv

    import numpy as np
    import scipy.signal

    from hybridqcm.data.hdf5 import read_split
    from hybridqcm.estimation.window_check import WINDOW_STATUS_LABELS
    from hybridqcm.physics.occupant import normalised_apparent_mass
    from hybridqcm.plots import close, plot_apparent_mass

    with open(estimates_csv, newline="") as handle:
        fitted = (r for r in csv.DictReader(handle) if r["status"] not in WINDOW_STATUS_LABELS.values())
        rows = [row for _, row in zip(range(count), fitted)]
    if not rows:
        return []
    index = np.array([int(r["index"]) for r in rows])
    if plan.get("seat") is not None:  # a seat of a half / full car, in the quarter car's layout (a3, a2, a1)
        from hybridqcm.data.vehicle_files import read_seat_split

        accel = read_seat_split(plan["path"], plan["split"], plan["seat"], ("accel",), index=index, check_finite=False)
        accel = accel["accel"]
    else:
        accel = read_split(plan["path"], plan["split"], ("accel",), index=index, check_finite=False)["accel"]
    h = plan["h"]
    modes = max((int(k[1:]) for k in rows[0] if k[:1] == "r" and k[1:].isdigit()), default=0)
    names = ["p1", "p2"] + [f"{k}{i}" for i in range(1, modes + 1) for k in ("r", "k", "c")]
    paths = []
    for row, (a3, a2) in zip(rows, accel[:, :, :2].transpose(0, 2, 1)):
        params = torch.tensor([[float(row[n]) for n in names]], dtype=torch.float64).nan_to_num(0.0)
        nper = min(256, a2.shape[0])
        f_measured, s22 = scipy.signal.welch(a2, fs=1 / h, nperseg=nper)
        _, s23 = scipy.signal.csd(a2, a3, fs=1 / h, nperseg=nper)
        band = (f_measured >= 0.5) & (f_measured <= 15)
        freq = np.linspace(0.5, min(15.0, 0.5 / h), 300)
        omega = torch.tensor(2 * np.pi * freq)
        am = normalised_apparent_mass(params, omega)[0]
        s = 1j * omega
        p1, p2 = params[0, 0], params[0, 1]
        fitted = (p1 * s + p2) / (s * s * am + p1 * s + p2)
        tau = float(row.get("tau") or 0.0)
        fitted = fitted * torch.exp(-s * tau)
        title = (
            f"recording {row['index']}: {row.get('occupant_model', 'rigid')}, static mass {float(row['m3']):.1f} kg "
            f"[{float(row['m3_low']):.1f}, {float(row['m3_high']):.1f}], status {row['status']}"
        )
        path = run_dir / "plots" / f"apparent_mass_{int(row['index']):06d}.png"
        measured = (s23 / s22)[band]
        close(plot_apparent_mass(f_measured[band], measured, freq, fitted.numpy(), am.numpy(), path, title))
        paths.append(path)
    return paths


def finish_run(cfg, plan, solved, run_dir: Path, seat, inputs_used, t_start: float, aggregate=None) -> dict:
    """After the merge (rank 0): the occupant plots, the stage losses, the metrics files, summary.json,
    the completion marker and the console report; returns the summary. ``solved``: estimation.runner.Solved;
    ``seat``: the seat file's law or None; ``aggregate(columns) -> dict``: the drives' aggregate (aggregate=drive)."""
    from hybridqcm.estimation.runner import max_rss_mib

    columns = solved.columns
    # a person at a glance: fitted apparent mass vs the measured a3/a2
    if plan.get("occupant") is not None and cfg.plots and {"a3", "a2"} <= set(plan["observed"]):
        pictures = plot_first_recordings(run_dir, plan, run_dir / "estimates.csv")
        if cfg.tensorboard and pictures:
            from hybridqcm.tracking import log_estimation_to_tensorboard

            log_estimation_to_tensorboard(run_dir / "tb", [], pictures, prefix="occupant")
    summary = run_summary(cfg, plan, solved, run_dir)
    noise = noise_label(cfg.noise_sigma, plan["sensor"])
    metrics, table_rows = write_metrics(
        cfg, columns, columns.get("true"), plan["known"], run_dir, plan["n_steps"], noise=noise
    )
    summary.update(metrics)
    if aggregate is not None:
        summary["drive_aggregate"] = aggregate(columns)
    summary["noise"] = noise
    summary["mass_scale"] = _mass_scale(cfg, seat, run_dir)
    summary["seconds_total"] = time.perf_counter() - t_start
    # This process's peak resident memory after the solve and at the end (spawned ranks excluded).
    summary["max_rss_mib"] = {"solve": solved.rss_solve_mib, "total": max_rss_mib(), "ranks": max_rss_mib(True)}
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    runfolder.write_completion_marker(run_dir, "qcm-estimate", runfolder.task_overrides(), inputs_used)
    print_report(cfg, summary, table_rows, run_dir)
    return summary


def _phase_seconds(markers: list[dict]) -> dict | None:
    """{"wall" | "cpu" | "fit_wall" | "fit_cpu": {phase or candidate: seconds}} summed over the blocks' markers
    that have them (an occupant selection's), None where none has."""
    timed = [m["phase_seconds"] for m in markers if m.get("phase_seconds")]
    if not timed:
        return None
    total: dict[str, dict[str, float]] = {}
    for phases in timed:
        for kind, seconds in phases.items():
            into = total.setdefault(kind, {})
            for name, value in seconds.items():
                into[name] = into.get(name, 0.0) + float(value)
    return total


def run_summary(cfg, plan, solved, run_dir: Path) -> dict:
    """summary.json's account of the run before its metrics: data, settings resolved by the plan, the
    stages' losses and statuses (logged to TensorBoard with tensorboard=true), blocks, processes, seconds."""
    markers = solved.markers
    stage_names = [s["name"] for s in plan["stages"]]
    stage_names += [k for k in dict.fromkeys(k for m in markers for k in m["stages"]) if k not in stage_names]
    stage_loss, stage_status = merge_stage_stats([m["stages"] for m in markers], stage_names)
    if cfg.tensorboard:
        log_stage_losses(run_dir / "tb", stage_loss)
    return {
        "experiment": cfg.experiment_name,
        "data": str(plan["path"]),
        "split": plan["split"],
        "n_samples": int(plan["n_samples"]),
        "n_steps": plan["n_steps"],
        "noise_sigma": float(cfg.noise_sigma),
        "seed": int(cfg.seed),
        "observed": plan["observed"],
        "known": [PARAM_NAMES[j] for j in plan["known"]],
        "model": plan["model"],
        "initial_state": plan["initial_state"],
        "x0_start": plan["x0_start"],
        "base_excitation": plan["base_excitation"],
        "hold": str(cfg.hold) if plan["model"] == "exact" else None,
        "sensor": {k: v for k, v in vars(plan["sensor"]).items() if not k.startswith("_")},
        "input_margin": list(plan["input_margin"]),
        "interval_covariance": plan["stages"][-1]["settings"].get("covariance", "model"),  # auto resolved
        "stages": stage_status,
        "stage_mean_loss": stage_loss,
        "seconds_solve": solved.seconds_solve,
        "processes": solved.processes,
        "blocks": solved.blocks,
        "blocks_resumed": solved.resumed,
        # per process: seconds spent solving blocks (the rest of seconds_solve is start-up and reading)
        "seconds_blocks_per_process": _per_process_seconds(markers),
        "cpu_seconds_blocks": sum(float(m.get("cpu_seconds", math.nan)) for m in markers),
        # an occupant selection's seconds by phase, summed over the blocks (estimation/occupant.PhaseClock)
        "seconds_phases": _phase_seconds(markers),
        "predict_devices": sorted({m["device"] for m in markers if m.get("device")}),  # the networks' device(s)
        "gn_device": str(cfg.get("gn_device", "cpu")),
        # the CPU solves' step recursions compiled (estimation/_kernels.py) or in torch (HYBRIDQCM_KERNELS=torch)
        "compiled_loops": compiled_loops(),
        # peak memory of one block's GN on the device (gn_device=accelerator on a GPU), else null
        "device_memory_mib": max((m["device_memory_mib"] for m in markers if m.get("device_memory_mib")), default=None),
    }


def _mass_scale(cfg, seat, run_dir: Path) -> dict:
    """summary.json's word on the mass scale: uncalibrated (m3 = K3 / p2 with the reference K3) or the seat
    file's law, and how many occupant masses lie outside the calibration's loads (extrapolated, warned)."""
    if seat is None:
        return {"calibrated": False, "K3": float(cfg.K3), "note": "m3 = K3 / p2 with the reference seat's K3"}
    import csv

    import numpy as np

    with open(run_dir / "estimates.csv", newline="") as handle:
        occupant = np.array([float(r["occupant_mass"]) for r in csv.DictReader(handle)])
    fitted = np.isfinite(occupant)
    beyond = fitted & ~seat.covers(occupant)
    outside = int(beyond.sum())
    lo, hi, far = min(seat.loads), max(seat.loads), occupant[beyond]
    reach = float(np.max(np.maximum(lo - far, far - hi))) if outside else 0.0  # the furthest extrapolation [kg]
    if outside:
        print(
            f"warning: {outside} of {int(fitted.sum())} occupant masses lie outside the calibration's loads "
            f"{lo:g}..{hi:g} kg ({far.min():.1f}..{far.max():.1f} kg: the seat law extrapolated by up to "
            f"{reach:.1f} kg; calibrate with heavier or lighter loads)"
        )
    held = _held_seat_parameters(cfg, seat, occupant[fitted])
    return {
        "calibrated": True,
        "held_at_reference": held,
        "seat_file": str(cfg.seat_file),
        "law": seat.law,
        "K3_ref": seat.K3_ref,
        "exponent": seat.exponent,
        "pan_mass": seat.pan_mass,
        "loads_kg": seat.loads,
        "extrapolated": outside,
        "extrapolated_kg": reach,
    }


def _held_seat_parameters(cfg, seat, occupant) -> dict | None:
    """p3 = C3/m2 and p5 = K3/m2 held known from the reference vehicle (known_source=reference, exp7/8/10) on a
    calibrated seat: the seat's K3 at the occupant's load is K3(M) = K3_ref (M/80)^e, not the vehicle config's K3,
    and the fit does not correct them; warned in one line with how far off K3 is over the occupants
    (docs/design/calibration.md)."""
    names = [name for name in ("p3", "p5") if name in list(cfg.get("known") or [])]
    if not names or cfg.get("known_source") != "reference" or occupant.size == 0:
        return None
    ratio = seat.k3(occupant + seat.pan_mass) / float(cfg.K3)
    low, high = float(ratio.min()), float(ratio.max())
    if max(abs(low - 1), abs(high - 1)) > 0.01:
        print(
            f"warning: known {names} are held at the reference vehicle's (known_source=reference), but the seat file's "
            f"K3 at these occupants' loads is {low:.3g}..{high:.3g} x the reference K3 = {float(cfg.K3):g} N/m: p3, p5 "
            "are off by that factor (hold none of them, or give known_source=file)"
        )
    return {"parameters": names, "k3_ratio_min": low, "k3_ratio_max": high}


def _per_process_seconds(markers) -> list[float]:
    busy: dict = {}
    for marker in markers:
        busy[marker.get("pid")] = busy.get(marker.get("pid"), 0.0) + float(marker.get("seconds", math.nan))
    return sorted(busy.values(), reverse=True)


__all__ = [
    "finish_run",
    "noise_label",
    "run_summary",
    "plot_first_recordings",
    "write_metrics",
    "log_stage_losses",
    "print_report",
]
