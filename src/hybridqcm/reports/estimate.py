"""qcm-estimate's tables: per-block rows (estimates.csv, status.csv) and the run's metrics.

A block's rows are written as soon as its GN solve ends (estimation/shards.py); the metrics
(error distribution, calibration, occupant mass m3 = K3/p2, status counts) are computed once
from the merged per-sample columns [M, P] of parameters, std, truth and status, never from the
recordings: memory holds a few numbers per recording, not the time series.

estimates.csv: index, p (P), status, std_p (P), m3, m3_std, m3_low, m3_high, x0 (S), std_x0 (S).
The 95 % interval of m3 is the image of p2's (m3 = K3/p2 is monotone): skewed, unlike m3 ± 1.96σ.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch.utils.tensorboard import SummaryWriter

from hybridqcm.estimation.plan import PARAM_NAMES
from hybridqcm.atomic import atomic_write_csv
from hybridqcm.console import print_table
from hybridqcm.estimation.solver import STATUS_LABELS, SolverStatus
from hybridqcm.estimation.window_check import WINDOW_STATUS_LABELS, is_skipped
from hybridqcm.metrics import error_distribution_rows, write_error_distribution

# the status column: the solver's outcome, or why a window was not fitted
ALL_STATUS_LABELS = {**STATUS_LABELS, **WINDOW_STATUS_LABELS}

STATUS_HEADER = [
    "index",
    "status",
    "iterations",
    "loss",
    "relative_loss",
    "restarts",
    "condition_number",
    "relative_residual",
    "whiteness",
]


def estimates_header(theta_names: Sequence[str], n_params: int, extra: Sequence[str] = ()) -> list[str]:
    """θ = (p1..pP, x0...): the model's parameters first, then the estimated initial state (if any), then
    ``extra`` diagnostics (the occupant model chosen, its body modes: estimation/occupant.py)."""
    params, states = list(theta_names[:n_params]), list(theta_names[n_params:])
    return [
        "index",
        *params,
        "status",
        *[f"std_{n}" for n in params],
        "m3",
        "m3_std",
        "m3_low",
        "m3_high",
        *states,
        *[f"std_{n}" for n in states],
        *extra,
    ]


def m3_interval(params: torch.Tensor, std: torch.Tensor, K3: float) -> tuple[torch.Tensor, ...]:
    """(m3, m3_std, m3_low, m3_high) [b] from p [b, P] and its std [b, P] (delta method; interval mapped)."""
    m3 = K3 / params[:, 1]
    m3_std = K3 / params[:, 1].square() * std[:, 1]
    p2_low, p2_high = params[:, 1] - 1.96 * std[:, 1], params[:, 1] + 1.96 * std[:, 1]
    m3_low = K3 / p2_high
    m3_high = torch.where(p2_low > 0, K3 / p2_low.clamp_min(1e-300), torch.full_like(p2_low, math.inf))
    return m3, m3_std, m3_low, m3_high


# With a seat file (qcm-estimate seat_file=...; estimation/calibration.py): the occupant alone from the seat's law
SEAT_COLUMNS = ("occupant_mass", "occupant_mass_low", "occupant_mass_high")


def block_tables(
    record: Mapping,
    n_params: int,
    K3: float,
    n_scored: int | None = None,
    extra: Sequence[str] = (),
    seat=None,
) -> tuple[list, list, dict]:
    """One refined block (GaussNewtonRefinement.refine's record) -> (estimate rows, status rows, columns).

    columns: index [b], params [b, n_scored], std [b, n_scored] (the first n_scored parameters, those
    the file's truth holds; default all), status [b], iterations [b], restarts [b], m3_low, m3_high [b]
    (what the run's metrics need), as tensors. A record may carry its own m3 interval (``m3_low``,
    ``m3_high``: an occupant-model selection's, wider where models disagree) and ``extra`` columns.
    ``seat`` (a calibration.SeatLaw): SEAT_COLUMNS last, from p2 and its interval (the image of m3's under
    m3 = K3 / p2) and the seat's covariance."""
    result = record["final"]
    theta, theta_std = record["params"], result.std
    params, std = theta[:, :n_params], theta_std[:, :n_params]
    x0, x0_std = theta[:, n_params:], theta_std[:, n_params:]
    status = [STATUS_LABELS[int(s)] for s in result.status]
    m3, m3_std, m3_low, m3_high = m3_interval(params, std, K3)
    if "m3_low" in record:
        m3_low, m3_high = record["m3_low"].double(), record["m3_high"].double()
    extra_values = [record["extra"][name] for name in extra]
    if seat is not None:
        p2 = params[:, 1].double().numpy()
        p2_low = torch.where(m3_high.isfinite(), K3 / m3_high.double(), torch.zeros_like(m3_high.double())).numpy()
        p2_high = (K3 / m3_low.double()).numpy()
        extra_values += [torch.as_tensor(c) for c in seat.occupant_interval(p2, p2_low, p2_high)]
    index = record["index"]
    rows, status_rows = [], []
    condition = result.condition_number
    for i in range(params.shape[0]):
        rows.append(
            [
                int(index[i]),
                *[repr(float(x)) for x in params[i]],
                status[i],
                *[repr(float(x)) for x in std[i]],
                repr(float(m3[i])),
                repr(float(m3_std[i])),
                repr(float(m3_low[i])),
                repr(float(m3_high[i])),
                *[repr(float(x)) for x in x0[i]],
                *[repr(float(x)) for x in x0_std[i]],
                *[v[i] if isinstance(v, list) else repr(float(v[i])) for v in extra_values],
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
    scored = n_params if n_scored is None else n_scored
    columns = {
        "index": index.long(),
        "params": params[:, :scored].double(),
        "std": std[:, :scored].double(),
        "m3_low": m3_low.double(),
        "m3_high": m3_high.double(),
        "status": result.status.long(),
        "iterations": result.iterations.long(),
        "restarts": record["restarts"].long(),
    }
    return rows, status_rows, columns


def skipped_tables(
    index: torch.Tensor, status: torch.Tensor, true: torch.Tensor | None, header: Sequence[str], n_scored: int
) -> tuple[list, list, dict]:
    """The rows of windows kept from the fit (estimation/window_check.py) in block_tables' layout:
    their status, no estimate (nan), no iterations. index, status: [k]; true: [k, 10] or None."""
    k = int(index.shape[0])
    labels = [ALL_STATUS_LABELS[int(s)] for s in status]
    nan = repr(math.nan)
    rows = [
        [int(i) if name == "index" else label if name == "status" else nan for name in header]
        for i, label in zip(index.tolist(), labels)
    ]
    status_rows = [[int(i), label, 0, nan, nan, 0, nan, nan, nan] for i, label in zip(index.tolist(), labels)]
    blank = torch.full((k,), math.nan, dtype=torch.float64)
    columns = {
        "index": index.long(),
        "params": torch.full((k, n_scored), math.nan, dtype=torch.float64),
        "std": torch.full((k, n_scored), math.nan, dtype=torch.float64),
        "m3_low": blank,
        "m3_high": blank.clone(),
        "status": status.long(),
        "iterations": torch.zeros(k, dtype=torch.int64),
        "restarts": torch.zeros(k, dtype=torch.int64),
        "true": None if true is None else true.double(),
    }
    return rows, status_rows, columns


def merge_block_tables(first: tuple, second: tuple) -> tuple[list, list, dict]:
    """Two (rows, status rows, columns) of one block merged in sample-index order."""
    rows, status_rows = first[0] + second[0], first[1] + second[1]
    columns = {}
    for key in first[2]:
        a, b = first[2][key], second[2].get(key)
        columns[key] = None if a is None or b is None else torch.cat([a, b])
    order = torch.argsort(columns["index"])
    columns = {key: None if v is None else v[order] for key, v in columns.items()}
    return [rows[i] for i in order.tolist()], [status_rows[i] for i in order.tolist()], columns


def block_stage_stats(record: Mapping) -> dict:
    """Per stage: loss per iteration summed over the block's samples (finished samples carry their
    last loss), sample count, status counts and iteration sum: mergeable over blocks (JSON)."""
    out = {}
    for name, x in record["stages"].items():
        out[name] = {
            "loss_total": [float(v) for v in x.loss_history.sum(1)],
            "count": int(x.loss_history.shape[1]),
            "status": x.status_counts(),
            "iterations": int(x.iterations.sum()),
            "n": int(x.iterations.numel()),
        }
    return out


def merge_stage_stats(blocks: Sequence[Mapping], stage_names: Sequence[str]) -> tuple[dict, dict]:
    """(stage_loss, stage_status) of summary.json from the blocks' stats, in block order.

    A block whose history is shorter than the longest is extended with its last total: that is the
    sum of its samples' last losses, which is what padding each sample with its last loss adds."""
    stage_loss, stage_status = {}, {}
    for name in stage_names:
        parts = [b[name] for b in blocks if name in b]
        if not parts:  # (an occupant selection's stages are its candidates' "<model>/<stage>")
            continue
        length = max((len(p["loss_total"]) for p in parts), default=0)
        total = torch.zeros(length, dtype=torch.float64)
        count = 0
        for p in parts:
            t = torch.tensor(p["loss_total"], dtype=torch.float64)
            total += torch.cat([t, t[-1:].expand(length - t.shape[0])]) if t.shape[0] < length else t
            count += p["count"]
        stage_loss[name] = (total / max(count, 1)).tolist()
        counts: dict[str, int] = {}
        for p in parts:
            for k, v in p["status"].items():
                counts[k] = counts.get(k, 0) + int(v)
        stage_status[name] = counts
        n = sum(p["n"] for p in parts)
        stage_status[name + "_iterations_mean"] = float(sum(p["iterations"] for p in parts) / n) if n else math.nan
    return stage_loss, stage_status


def noise_label(noise_sigma: float, sensor) -> str:
    """The noise the estimator saw, in words: the sensor model and/or the source's multiplicative
    `noise_sigma` (SPEC §5); 'none' when neither is set."""
    parts = [f"source multiplicative σ = {float(noise_sigma):g}"] if float(noise_sigma) > 0 else []
    if sensor is not None and sensor.active:
        parts.append(sensor.describe())
    return "; ".join(parts) or "none"


def coverage_95(estimate: torch.Tensor, truth: torch.Tensor, std: torch.Tensor, failed: torch.Tensor) -> float:
    """Fraction of samples [M] whose truth lies in estimate ± 1.96 std; failed or non-finite ones count as not covered."""
    ok = ~failed & torch.isfinite(estimate) & torch.isfinite(std)
    inside = ok & ((estimate - truth).abs() <= 1.96 * std)
    return float(inside.double().mean())


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
    # A diverged or non-finite sample counts as failed / not covered, never as a success.
    failed = ~torch.isfinite(params).all(1) | (status_codes == int(SolverStatus.DIVERGED))
    err = ((params - true).abs() / true.abs())[:, free]
    err = torch.where(failed[:, None] | ~torch.isfinite(err), torch.full_like(err, math.inf), err)
    summary["failed_samples"] = int(failed.sum())
    summary["all_within_1pct"] = float((err <= 0.01).all(1).double().mean())
    summary["all_within_10pct"] = float((err <= 0.10).all(1).double().mean())
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


__all__ = [
    "STATUS_HEADER",
    "estimates_header",
    "m3_interval",
    "block_tables",
    "skipped_tables",
    "merge_block_tables",
    "block_stage_stats",
    "merge_stage_stats",
    "coverage_95",
    "write_metrics",
    "log_stage_losses",
    "print_report",
]
