"""The half car's and full car's tables: estimates.csv rows per block and the run's metrics.

estimates.csv: index, the vehicle's parameters (its physical names: m1<w>, m2, I_pitch, ..., m3 or
m3_<seat>, ...), status, std_<parameter>, then per seat the occupant mass's 95 % interval
(m3_low, m3_high or m3_<seat>_low, m3_<seat>_high: m3 ± 1.96 std, m3 being a parameter of the
model itself), the initial state x0_* and its std. Metrics (with the file's truth): the error
distribution of every estimated parameter, calibration.csv (95 % coverage per parameter), and per
seat the occupant mass's errors and coverage in summary.json (m3[_<seat>]_...).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from hybridqcm.apps.estimate_report import coverage_95
from hybridqcm.atomic import atomic_write_csv
from hybridqcm.console import print_table
from hybridqcm.estimation.solver import STATUS_LABELS, SolverStatus
from hybridqcm.metrics import error_distribution_rows, write_error_distribution
from hybridqcm.physics.vehicle_geometry import VehicleLayout


def vehicle_estimates_header(theta_names: Sequence[str], n_params: int, layout: VehicleLayout) -> list[str]:
    params, states = list(theta_names[:n_params]), list(theta_names[n_params:])
    intervals = [f"{m}_{end}" for m in layout.seat_mass_names() for end in ("low", "high")]
    return [
        "index",
        *params,
        "status",
        *[f"std_{n}" for n in params],
        *intervals,
        *states,
        *[f"std_{n}" for n in states],
    ]


def vehicle_block_tables(record: Mapping, n_params: int, names: Sequence[str], layout: VehicleLayout):
    """One refined block -> (estimate rows, status rows, columns for the metrics)."""
    result = record["final"]
    theta, theta_std = record["params"], result.std
    params, std = theta[:, :n_params], theta_std[:, :n_params]
    x0, x0_std = theta[:, n_params:], theta_std[:, n_params:]
    status = [STATUS_LABELS[int(s)] for s in result.status]
    masses = [list(names).index(m) for m in layout.seat_mass_names()]
    low = params[:, masses] - 1.96 * std[:, masses]
    high = params[:, masses] + 1.96 * std[:, masses]
    index = record["index"]
    rows, status_rows = [], []
    condition = result.condition_number
    for i in range(params.shape[0]):
        bounds = [repr(float(v)) for pair in zip(low[i], high[i]) for v in pair]
        rows.append(
            [
                int(index[i]),
                *[repr(float(x)) for x in params[i]],
                status[i],
                *[repr(float(x)) for x in std[i]],
                *bounds,
                *[repr(float(x)) for x in x0[i]],
                *[repr(float(x)) for x in x0_std[i]],
            ]
        )
        status_rows.append(
            [
                int(index[i]),
                status[i],
                int(result.iterations[i]),
                repr(float(result.loss[i])),
                repr(float(record["relative_loss"][i])),
                int(record["restarts"][i]),
                repr(float(condition[i])),
                repr(float(result.relative_residual[i])),
                repr(float(result.whiteness[i])),
            ]
        )
    columns = {
        "index": index.long(),
        "params": params.double(),
        "std": std.double(),
        "status": result.status.long(),
        "iterations": result.iterations.long(),
        "restarts": record["restarts"].long(),
    }
    return rows, status_rows, columns


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
    failed = ~torch.isfinite(params).all(1) | (status_codes == int(SolverStatus.DIVERGED))
    err = ((params - true).abs() / true.abs())[:, free]
    err = torch.where(failed[:, None] | ~torch.isfinite(err), torch.full_like(err, math.inf), err)
    summary["failed_samples"] = int(failed.sum())
    summary["all_within_1pct"] = float((err <= 0.01).all(1).double().mean())
    summary["all_within_10pct"] = float((err <= 0.10).all(1).double().mean())
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


__all__ = ["vehicle_estimates_header", "vehicle_block_tables", "write_vehicle_metrics", "vehicle_print_report"]
