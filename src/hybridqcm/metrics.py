"""Error statistics of parameter estimates: the source study's "error distribution table".

Per parameter over a set of samples, with the relative error e = |p_hat - p| / |p|:
max, mean and std of e and the fractions with e <= 1 %, <= 5 %, <= 10 %, <= 25 % and > 25 %.
Column names match ../shared/reference/thesis_tables.csv so rows can be set side by side.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric

from hybridqcm.atomic import atomic_write_text

THRESHOLDS = (0.01, 0.05, 0.10, 0.25)
COLUMNS = (
    "param",
    "n",
    "max_err",
    "mean_err",
    "std_err",
    "within_1pct",
    "within_5pct",
    "within_10pct",
    "within_25pct",
    "over_25pct",
)


def relative_errors(pred: Tensor | np.ndarray, target: Tensor | np.ndarray) -> Tensor:
    """e = |pred - target| / |target| [batch, n_params] (float64). Non-finite predictions count as e = inf."""
    pred = torch.as_tensor(pred, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    if pred.shape != target.shape:
        raise ValueError(f"predictions {tuple(pred.shape)} and targets {tuple(target.shape)} differ in shape")
    error = (pred - target).abs() / target.abs()
    return torch.where(torch.isfinite(error), error, torch.full_like(error, float("inf")))


def error_distribution_rows(pred, target, names: Sequence[str]) -> list[dict]:
    """One row per parameter (dict keyed by COLUMNS)."""
    error = relative_errors(pred, target)
    if error.ndim == 1:
        error = error[:, None]
    if error.shape[1] != len(names):
        raise ValueError(f"{error.shape[1]} parameters but {len(names)} names")
    return [_row(name, error[:, j]) for j, name in enumerate(names)]


def _row(name: str, e: Tensor) -> dict:
    n = e.numel()
    finite = e[torch.isfinite(e)]
    row = {
        "param": name,
        "n": n,
        "max_err": float(e.max()) if n else float("nan"),
        "mean_err": float(e.mean()) if n else float("nan"),
        "std_err": float(e.std(unbiased=False)) if n else float("nan"),
    }
    if finite.numel() < n:  # report the non-finite count plainly instead of a silent inf mean
        row["non_finite"] = n - finite.numel()
    for t in THRESHOLDS:
        row[f"within_{round(t * 100)}pct"] = float((e <= t).double().mean()) if n else float("nan")
    row["over_25pct"] = float((e > 0.25).double().mean()) if n else float("nan")
    return row


class ErrorDistribution(Metric):
    """torchmetrics Metric accumulating relative errors; `compute()` returns the table rows.

    Errors are kept per sample (the max and the fractions need them); 17 000 x 10 float64 is small.
    """

    full_state_update = False

    def __init__(self, names: Sequence[str], **kwargs) -> None:
        super().__init__(**kwargs)
        self.names = list(names)
        self.add_state("errors", default=[], dist_reduce_fx="cat")

    def update(self, pred: Tensor, target: Tensor) -> None:
        self.errors.append(relative_errors(pred.detach().reshape(target.shape), target.detach()))

    def _all_errors(self) -> Tensor:
        """The accumulated errors [n, n_params] float64 (a list before a sync, a tensor after one)."""
        errors = self.errors
        if isinstance(errors, list):
            errors = torch.cat(errors) if errors else torch.zeros(0, len(self.names), dtype=torch.float64)
        return errors

    def compute(self) -> list[dict]:
        errors = self._all_errors()
        return [_row(name, errors[:, j]) for j, name in enumerate(self.names)]

    def mean_error(self) -> float:
        """Mean of e over all samples and parameters (the training monitor `val/mean_rel_err`); this process's errors."""
        return float(self._all_errors().mean())

    def scalars(self, prefix: str = "") -> dict[str, float]:
        """Flat {prefix/p1/mean_err: ...} for loggers."""
        return {
            f"{prefix}{row['param']}/{k}": float(v)
            for row in self.compute()
            for k, v in row.items()
            if k not in ("param", "n", "non_finite")
        }


def rows_to_markdown(rows: Sequence[dict], title: str | None = None) -> str:
    header = ["param", "max", "mean", "std", "≤1 %", "≤5 %", "≤10 %", "≤25 %", ">25 %"]
    lines = ([f"**{title}**", ""] if title else []) + ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        lines.append(
            f"| {r['param']} | {100 * r['max_err']:.3g} % | {100 * r['mean_err']:.3g} % | {100 * r['std_err']:.3g} % | "
            f"{100 * r['within_1pct']:.2f} % | {100 * r['within_5pct']:.2f} % | {100 * r['within_10pct']:.2f} % | "
            f"{100 * r['within_25pct']:.2f} % | {100 * r['over_25pct']:.2f} % |"
        )
    return "\n".join(lines) + "\n"


def write_error_distribution(
    rows: Sequence[dict], directory: str | Path, stem: str = "error_distribution", title: str | None = None
) -> tuple[Path, Path]:
    """Write `stem.csv` and `stem.md` into `directory` (atomically). Returns both paths."""
    directory = Path(directory)
    csv_path, md_path = directory / f"{stem}.csv", directory / f"{stem}.md"
    import io

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(COLUMNS) + ["non_finite"], extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({**{k: r.get(k) for k in COLUMNS}, "non_finite": r.get("non_finite", 0)})
    atomic_write_text(csv_path, buffer.getvalue())
    atomic_write_text(md_path, rows_to_markdown(rows, title))
    return csv_path, md_path


def read_error_distribution(path: str | Path) -> list[dict]:
    """Rows of an error_distribution.csv written by `write_error_distribution` (floats parsed)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: error distribution table not found")
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: malformed error distribution table, missing columns {missing}")
        rows = []
        for line_no, raw in enumerate(reader, start=2):
            try:
                row = {k: (raw[k] if k == "param" else float(raw[k])) for k in COLUMNS}
                row["n"] = int(row["n"]) if float(row["n"]).is_integer() else row["n"]
                if raw.get("non_finite") not in (None, "", "0"):  # written only when there were some
                    row["non_finite"] = int(raw["non_finite"])
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"{path}:{line_no}: malformed value in row {raw}") from None
            if row["param"] in (None, ""):
                raise ValueError(f"{path}:{line_no}: row without a parameter name: {raw}")
            rows.append(row)
    return rows


def m3_interval(params: torch.Tensor, std: torch.Tensor, K3: float) -> tuple[torch.Tensor, ...]:
    """(m3, m3_std, m3_low, m3_high) [b] from p [b, P] and its std [b, P] (delta method; interval mapped)."""
    m3 = K3 / params[:, 1]
    m3_std = K3 / params[:, 1].square() * std[:, 1]
    p2_low, p2_high = params[:, 1] - 1.96 * std[:, 1], params[:, 1] + 1.96 * std[:, 1]
    m3_low = K3 / p2_high
    m3_high = torch.where(p2_low > 0, K3 / p2_low.clamp_min(1e-300), torch.full_like(p2_low, math.inf))
    return m3, m3_std, m3_low, m3_high


def coverage_95(estimate: torch.Tensor, truth: torch.Tensor, std: torch.Tensor, failed: torch.Tensor) -> float:
    """Fraction of samples [M] whose truth lies in estimate ± 1.96 std; failed or non-finite ones count as not covered."""
    ok = ~failed & torch.isfinite(estimate) & torch.isfinite(std)
    inside = ok & ((estimate - truth).abs() <= 1.96 * std)
    return float(inside.double().mean())
