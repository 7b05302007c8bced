"""qcm-estimate's per-block tables: the rows of estimates.csv and status.csv and the per-sample columns
the run's metrics need, written by the rank that solved the block (estimation/shards.py), merged once.

estimates.csv: index, p (P), status, std_p (P), m3, m3_std, m3_low, m3_high, x0 (S), std_x0 (S), extra.
The 95 % interval of m3 is the image of p2's (m3 = K3/p2 is monotone): skewed, unlike m3 ± 1.96σ
(metrics.m3_interval).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

from hybridqcm.estimation.solver import STATUS_LABELS
from hybridqcm.estimation.window_check import WINDOW_STATUS_LABELS
from hybridqcm.metrics import m3_interval

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


# With a seat file (qcm-estimate seat_file=...; estimation/calibration.py): the occupant alone from the seat's law
SEAT_COLUMNS = ("occupant_mass", "occupant_mass_low", "occupant_mass_high")


def status_rows(record: Mapping, index: Sequence[int], status: Sequence[str]) -> list[list]:
    """A block's status.csv rows (STATUS_HEADER) from the refinement's record (its final fit); ``index``
    [b] the recordings' rows in the file, ``status`` [b] their labels. Each column is read once (a row at
    a time re-derived the condition numbers of the whole block per row: quadratic in the block)."""
    result = record["final"]
    columns = (
        result.iterations.tolist(),
        result.loss.tolist(),
        record["relative_loss"].tolist(),
        record["restarts"].tolist(),
        result.condition_number.tolist(),
        result.relative_residual.tolist(),
        result.whiteness.tolist(),
    )
    return [
        [
            i,
            label,
            int(it),
            repr(float(loss)),
            repr(float(rel)),
            int(rs),
            repr(float(c)),
            repr(float(rr)),
            repr(float(w)),
        ]
        for i, label, it, loss, rel, rs, c, rr, w in zip(index, status, *columns, strict=True)
    ]


def texts(values: torch.Tensor) -> list:
    """The csv text of every entry of ``values`` [b, ...] (repr of the float), nested as the tensor."""
    if values.dim() == 1:
        return [repr(float(x)) for x in values.tolist()]
    return [[repr(float(x)) for x in row] for row in values.flatten(1).tolist()]


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
    status = [STATUS_LABELS[s] for s in result.status.tolist()]
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
    indices = [int(i) for i in index.tolist()]
    extra_texts = [v if isinstance(v, list) else texts(torch.as_tensor(v)) for v in extra_values]
    p_t, std_t, x0_t, x0_std_t = texts(params), texts(std), texts(x0), texts(x0_std)
    m3_t, m3_std_t, low_t, high_t = texts(m3), texts(m3_std), texts(m3_low), texts(m3_high)
    rows = [
        [
            indices[i],
            *p_t[i],
            status[i],
            *std_t[i],
            m3_t[i],
            m3_std_t[i],
            low_t[i],
            high_t[i],
            *x0_t[i],
            *x0_std_t[i],
            *[v[i] for v in extra_texts],
        ]
        for i in range(len(indices))
    ]
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
    return rows, status_rows(record, indices, status), columns


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


__all__ = [
    "ALL_STATUS_LABELS",
    "SEAT_COLUMNS",
    "STATUS_HEADER",
    "block_stage_stats",
    "block_tables",
    "estimates_header",
    "merge_block_tables",
    "merge_stage_stats",
    "skipped_tables",
]
