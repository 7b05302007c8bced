"""The half car's and full car's tables: estimates.csv rows per block and the run's metrics.

estimates.csv: index, the vehicle's parameters (its physical names: m1<w>, m2, I_pitch, ..., m3 or
m3_<seat>, ...), status, std_<parameter>, then per seat the occupant mass's 95 % interval
(m3_low, m3_high or m3_<seat>_low, m3_<seat>_high: m3 ± 1.96 std, m3 being a parameter of the
model itself), the initial state x0_* and its std. Metrics (with the file's truth): the error
distribution of every estimated parameter, calibration.csv (95 % coverage per parameter), and per
seat the occupant mass's errors and coverage in summary.json (m3[_<seat>]_...).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from pathlib import Path

import torch

from hybridqcm import runfolder
from hybridqcm.atomic import atomic_write_csv, atomic_write_text
from hybridqcm.console import print_table
from hybridqcm.estimation.solver import STATUS_LABELS, SolverStatus
from hybridqcm.metrics import coverage_95, error_distribution_rows, write_error_distribution
from hybridqcm.physics.vehicle_geometry import VehicleLayout
from hybridqcm.reports.estimate import failed_and_errors, log_stage_losses


def write_vehicle_metrics(cfg, columns: Mapping[str, torch.Tensor], plan: Mapping, run_dir: Path, noise: str):
    """Status counts; with the file's truth the error table, calibration.csv, per-seat occupant-mass metrics,
    sorted plots and the TensorBoard table. Returns (summary entries, error-table rows or None)."""
    params, std, status_codes = columns["params"], columns["std"], columns["status"]
    names = list(plan["model"].param_names)
    layout: VehicleLayout = plan["layout"]
    n = params.shape[0]
    summary: dict = {
        "status_counts": {k: int((status_codes == v).sum()) for v, k in STATUS_LABELS.items()},
        "iterations_mean": float(columns["iterations"].double().mean()),
        "restarted_samples": int((columns["restarts"] > 0).sum()),
    }
    true = columns.get("true")
    if true is None:
        return summary, None
    free = [j for j, name in enumerate(names) if name not in plan["known"]]
    free_names = [names[j] for j in free]
    title = f"{cfg.experiment_name}: {n} samples, N = {plan['n_steps']}, sensor noise: {noise}"
    table_rows = error_distribution_rows(params[:, free], true[:, free], free_names)
    write_error_distribution(table_rows, run_dir, title=title)
    failed, err = failed_and_errors(params, true, status_codes, free, summary)
    summary["worst_parameter_within_1pct"] = min(
        ((name, float((err[:, k] <= 0.01).double().mean())) for k, name in enumerate(free_names)), key=lambda x: x[1]
    )
    calibration = []
    for j, name in zip(free, free_names):
        ok = ~failed & torch.isfinite(std[:, j])
        calibration.append(
            [
                name,
                n,
                coverage_95(params[:, j], true[:, j], std[:, j], failed),
                float(std[:, j][ok].median() / true[:, j][ok].abs().median()) if bool(ok.any()) else math.inf,
            ]
        )
    atomic_write_csv(run_dir / "calibration.csv", ["param", "n", "coverage_95", "median_rel_std"], calibration)
    plots = []
    for mass in layout.seat_mass_names():
        j = names.index(mass)
        e = (params[:, j] - true[:, j]).abs() / true[:, j]
        e = torch.where(failed | ~torch.isfinite(e), torch.full_like(e, math.inf), e)
        summary[f"{mass}_mean_rel_err"] = float(e.mean())
        summary[f"{mass}_p95_rel_err"] = float(e.quantile(0.95))
        summary[f"{mass}_max_rel_err"] = float(e.max())
        summary[f"{mass}_within_0.5pct"] = float((e <= 0.005).double().mean())
        summary[f"{mass}_within_1pct"] = float((e <= 0.01).double().mean())
        summary[f"{mass}_coverage_95"] = coverage_95(params[:, j], true[:, j], std[:, j], failed)
        ok = ~failed & torch.isfinite(std[:, j])
        summary[f"{mass}_interval_median_rel_width"] = (
            float((2 * 1.96 * std[:, j][ok] / true[:, j][ok]).median()) if bool(ok.any()) else math.inf
        )
        done = e[status_codes == int(SolverStatus.CONVERGED)]
        summary[f"{mass}_max_rel_err_converged"] = float(done.max()) if done.numel() else None
    if cfg.plots:
        from hybridqcm.plots import close, plot_sorted_predictions

        for j, name in zip(free, free_names):
            path = run_dir / "plots" / f"sorted_{name}.png"
            close(
                plot_sorted_predictions(
                    params[:, j].numpy(), true[:, j].numpy(), name, path, title=f"{cfg.experiment_name}: {name}"
                )
            )
            plots.append(path)
    if cfg.tensorboard:
        from hybridqcm.tracking import log_estimation_to_tensorboard

        log_estimation_to_tensorboard(run_dir / "tb", table_rows, plots, title=title)
    return summary, table_rows


def vehicle_print_report(cfg, summary: Mapping, table_rows: list | None, run_dir: Path) -> None:
    n = summary["n_samples"]
    print_table(
        f"{cfg.experiment_name}: status", ["status", "samples"], [[k, v] for k, v in summary["status_counts"].items()]
    )
    if table_rows is None:
        print(f"estimates of {n} recordings (no physical parameters in the file: no error table) -> {run_dir}")
        return
    print_table(
        f"{cfg.experiment_name}: relative error, {n} recordings",
        ["param", "max", "mean", "≤1 %", "≤5 %", "≤10 %", ">25 %"],
        [
            [
                r["param"],
                f"{100 * r['max_err']:.3g} %",
                f"{100 * r['mean_err']:.3g} %",
                f"{100 * r['within_1pct']:.2f} %",
                f"{100 * r['within_5pct']:.2f} %",
                f"{100 * r['within_10pct']:.2f} %",
                f"{100 * r['over_25pct']:.2f} %",
            ]
            for r in table_rows
        ],
    )
    masses = [k[: -len("_mean_rel_err")] for k in summary if k.endswith("_mean_rel_err")]
    print_table(
        f"{cfg.experiment_name}: occupant masses",
        ["seat mass", "mean error", "within 0.5 %", "95 % coverage", "median interval width"],
        [
            [
                m,
                f"{100 * summary[f'{m}_mean_rel_err']:.3g} %",
                f"{100 * summary[f'{m}_within_0.5pct']:.2f} %",
                f"{100 * summary[f'{m}_coverage_95']:.1f} %",
                f"{100 * summary[f'{m}_interval_median_rel_width']:.3g} %",
            ]
            for m in masses
        ],
    )
    print(
        f"all estimated parameters within 1 %: {100 * summary['all_within_1pct']:.2f} % of recordings; "
        f"GN {summary['seconds_solve']:.1f} s, total {summary['seconds_total']:.1f} s -> {run_dir}"
    )


def _summary(cfg, plan: dict, stage_status, stage_loss, markers: list, counts: dict) -> dict:
    """summary.json's entries of the run itself (the metrics are added by write_vehicle_metrics)."""
    layout: VehicleLayout = plan["layout"]
    return {
        "experiment": cfg.experiment_name,
        "vehicle": layout.kind,
        "seats": list(layout.seat_names),
        "tyre_damping": layout.tyre_damping,
        "data": str(plan["path"]),
        "split": plan["split"],
        "n_samples": int(plan["n_samples"]),
        "n_steps": plan["n_steps"],
        "seed": int(cfg.seed),
        "known": plan["known"],
        "model": "exact",
        "initial_state": plan["initial_state"],
        "hold": str(cfg.hold),
        "substeps": int(cfg.substeps),
        "spline_degree": plan["spline_degree"],
        "sensor": {k: v for k, v in vars(plan["sensor"]).items() if not k.startswith("_")},
        "input_margin": list(plan["input_margin"]),
        "stages": stage_status,
        "stage_mean_loss": stage_loss,
        "seconds_solve": counts["seconds_solve"],
        "processes": counts["processes"],
        "blocks": counts["blocks"],
        "blocks_resumed": counts["blocks_resumed"],
        "cpu_seconds_blocks": sum(float(m.get("cpu_seconds", math.nan)) for m in markers),
    }


def finish_vehicle_run(cfg, solved, run_dir: Path) -> dict:
    """The half / full car's reports from a solved run (estimation/vehicle_runner.solve_vehicle): stage losses
    in TensorBoard, the metrics files, summary.json, the completion marker and the console report."""
    plan = solved.plan
    if cfg.tensorboard:
        log_stage_losses(run_dir / "tb", solved.stage_loss)
    summary = _summary(cfg, plan, solved.stage_status, solved.stage_loss, solved.markers, solved.counts)
    noise = plan["sensor"].describe()
    metrics, table_rows = write_vehicle_metrics(cfg, solved.columns, plan, run_dir, noise)
    summary.update(metrics)
    summary["noise"] = noise
    summary["seconds_total"] = time.perf_counter() - solved.t_start
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    runfolder.write_completion_marker(run_dir, "qcm-estimate", runfolder.task_overrides(), [plan["path"]])
    if not cfg.get("keep_shards", False):
        solved.store.remove()
    vehicle_print_report(cfg, summary, table_rows, run_dir)
    return summary


__all__ = ["write_vehicle_metrics", "vehicle_print_report", "finish_vehicle_run"]
