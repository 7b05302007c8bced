"""The per-recording records of the occupant selection's candidates (estimation/occupant.py): one candidate's
fit of a batch, subsets and scatters of records, and the merge of the chosen candidates' results into the
common layout."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .refinement import GaussNewtonRefinement
from .solver import SolverResult, SolverStatus

if TYPE_CHECKING:
    from .occupant import OccupantSelection


def fit_candidate(refinement: GaussNewtonRefinement, outputs: Mapping, module) -> dict:
    """One candidate's refinement of the batch, with ``robust`` [b, n_theta]: its reported standard deviations
    (the run's ``intervals.covariance``, a delete-a-band jackknife for a measured input) over the model-based
    ones, at least 1 — what the residual's own spread says beyond the noise model, kept for the intervals
    after the polish has replaced the standard deviations by model-based ones."""
    if hasattr(refinement, "refine_block"):  # keeps nothing between calls
        record = refinement.refine_block(outputs, module, 0)
    else:
        record = refinement.refine(outputs, module)
    final = record["final"]
    ratio = torch.ones_like(final.std, dtype=torch.float64)
    if final.model_std is not None:
        ratio = (final.std.double() / final.model_std.double().clamp_min(1e-300)).nan_to_num(1.0, 1.0, 1.0)
    record["robust"] = ratio.clamp_min(1.0)
    return record


def record_fits(record: dict) -> Tensor:
    """[b] bool: the record's fits that neither diverged nor are misfit."""
    status = record["final"].status
    return status.ne(SolverStatus.MISFIT) & status.ne(SolverStatus.DIVERGED)


def select_rows(outputs: Mapping, rows: Tensor, b: int) -> dict:
    """The batch's outputs of the recordings ``rows`` (every per-recording tensor indexed)."""
    return {k: (v[rows] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == b else v) for k, v in outputs.items()}


def empty_like(record: dict, n_theta: int, n_params: int) -> dict:
    """A record of the same batch where nothing was fitted: NaN estimates, status diverged."""
    final = record["final"]
    b = final.status.shape[0]
    nan = torch.full((b, n_theta), math.nan, dtype=torch.float64)
    result = SolverResult(
        params=nan.clone(),
        status=torch.full_like(final.status, int(SolverStatus.DIVERGED)),
        iterations=torch.zeros_like(final.iterations),
        loss=torch.full_like(final.loss, math.inf),
        loss_history=torch.zeros(1, b, dtype=torch.float64),
        std=torch.full_like(nan, math.inf),
        covariance=torch.full((b, n_theta, n_theta), math.nan, dtype=torch.float64),
        singular_values=torch.zeros(b, n_theta, dtype=torch.float64),
        residual_variance=torch.full((b,), math.nan, dtype=torch.float64),
        relative_residual=torch.full((b,), math.inf, dtype=torch.float64),
        whiteness=torch.full((b,), math.inf, dtype=torch.float64),
        model_std=torch.full_like(nan, math.inf),
    )
    return {
        "index": record["index"],
        "init": torch.full((b, n_params), math.nan, dtype=torch.float64),
        "stages": {},
        "final": result,
        "params": nan,
        "restarts": torch.zeros(b, dtype=torch.int64),
        "relative_loss": torch.full((b,), math.inf, dtype=torch.float64),
        "robust": torch.ones(b, n_theta, dtype=torch.float64),
    }


def scatter(into: dict, record: dict, rows: Tensor) -> None:
    """In place: the sub-batch ``record`` (of the recordings ``rows``) into the full-batch record ``into``."""
    src, dst = record["final"], into["final"]
    for field in ("params", "status", "iterations", "loss", "std", "covariance", "residual_variance"):
        getattr(dst, field)[rows] = getattr(src, field).to(getattr(dst, field).dtype)
    for field in ("relative_residual", "whiteness", "model_std"):
        if getattr(src, field) is not None:
            getattr(dst, field)[rows] = getattr(src, field).to(getattr(dst, field).dtype)
    n_sv = src.singular_values.shape[1]
    dst.singular_values[rows, :n_sv] = src.singular_values.double()
    history = torch.zeros(src.loss_history.shape[0], dst.status.shape[0], dtype=torch.float64)
    history[:, rows] = src.loss_history.double()
    dst.loss_history = history
    into["params"][rows] = record["params"].double()
    into["init"][rows] = record["init"].double()
    into["robust"][rows] = record["robust"].double()
    for key in ("prior_mean", "prior_precision"):  # the prior in the covariance (put_result); NaN: not known
        if key in record or key in into:
            into.setdefault(key, torch.full(into["params"].shape, math.nan, dtype=torch.float64))
            into[key][rows] = record[key].double() if key in record else math.nan
    if "variances" in record:  # the noise model the sub-batch was weighed under
        b = into["params"].shape[0]
        mine = into.get("variances") or tuple(
            None if v is None else torch.zeros(b, *v.shape[1:], dtype=v.dtype) for v in record["variances"]
        )
        into["variances"] = tuple(
            None if (m is None or v is None) else m.index_copy(0, rows, v) for m, v in zip(mine, record["variances"])
        )
    into["restarts"][rows] = record["restarts"]
    into["relative_loss"][rows] = record["relative_loss"].double()
    into["stages"] = {**into["stages"], **record["stages"]}


def subset(record: dict, rows: Tensor) -> dict:
    """The record of the recordings ``rows`` (a copy)."""
    final = record["final"]
    fields = {f.name: getattr(final, f.name) for f in dataclasses.fields(final)}
    for key, value in fields.items():
        if isinstance(value, Tensor) and value.ndim > 0:
            fields[key] = value[:, rows].clone() if key == "loss_history" else value[rows].clone()
    return {
        "index": record["index"][rows],
        "init": record["init"][rows],
        "stages": {},
        "final": SolverResult(**fields),
        "params": record["params"][rows].clone(),
        "restarts": record["restarts"][rows].clone(),
        "relative_loss": record["relative_loss"][rows].clone(),
        "robust": record["robust"][rows].clone(),
        **{k: record[k][rows].clone() for k in ("prior_mean", "prior_precision") if k in record},
    }


def put_result(
    record: dict, result: SolverResult, rows: Tensor, params: Tensor, subset: Tensor | None = None, problem=None
) -> None:
    """In place: the polished estimates ``params`` [rows] with ``result``'s uncertainty and residual tests
    (under the common noise model, at ``params``; ``result``'s samples ``subset`` where given) into
    ``record``'s rows; with ``problem`` (the one ``result`` solved) also its prior, as ``record["prior_mean"]``
    and ``record["prior_precision"]`` [b, n_theta] (precision 0: none): the prior in that covariance, which a
    drive takes out again to count it once (estimation/drive_prior.py)."""
    final = record["final"]
    record["params"][rows] = params.to(record["params"].dtype)
    final.params[rows] = params.to(final.params.dtype)
    pick = slice(None) if subset is None else subset
    if problem is not None:
        for key in ("prior_mean", "prior_precision"):
            if key not in record:
                record[key] = torch.full(record["params"].shape, math.nan, dtype=torch.float64)
        if problem.prior_mean is None:
            record["prior_mean"][rows], record["prior_precision"][rows] = 0.0, 0.0
        else:
            record["prior_mean"][rows] = problem.prior_mean[pick].double()
            record["prior_precision"][rows] = problem.prior_precision[pick].double()
    for field in ("std", "covariance", "model_std", "relative_residual", "whiteness", "residual_variance"):
        value = getattr(result, field)
        if value is not None and getattr(final, field) is not None:
            getattr(final, field)[rows] = value[pick].to(getattr(final, field).dtype)
    # The refinement's status stands (a short polish ends at its iteration limit by design), except that
    # the residual tests under the common noise model can expose a misfit that a model's own noise fit hid.
    status = final.status[rows]
    exposed = (result.status[pick] == SolverStatus.MISFIT) & (status != SolverStatus.DIVERGED)
    final.status[rows] = torch.where(exposed, result.status[pick].to(status.dtype), status)


def merge(selection: OccupantSelection, records: Mapping[str, dict], choice: Tensor) -> dict:
    """The chosen candidate's results per recording, in the common layout (NaN where it has no entry)."""
    layout = selection.response.theta_names
    b = choice.numel()
    params = torch.full((b, len(layout)), math.nan, dtype=torch.float64)
    std = torch.full_like(params, math.nan)
    model_std = torch.full_like(params, math.nan)
    covariance = torch.full((b, len(layout), len(layout)), math.nan, dtype=torch.float64)
    first = records[selection.names[0]]["final"]
    n_sv = max(r["final"].singular_values.shape[1] for r in records.values())
    n_hist = max(r["final"].loss_history.shape[0] for r in records.values())
    merged = SolverResult(
        params=params,
        status=first.status.clone(),
        iterations=first.iterations.clone(),
        loss=first.loss.clone(),
        loss_history=torch.zeros(n_hist, b, dtype=torch.float64),
        std=std,
        covariance=covariance,
        singular_values=torch.zeros(b, n_sv, dtype=torch.float64),
        residual_variance=first.residual_variance.clone(),
        relative_residual=first.relative_residual.clone(),
        whiteness=first.whiteness.clone(),
        model_std=model_std,
    )
    restarts = torch.zeros(b, dtype=torch.int64)
    relative = torch.zeros(b, dtype=torch.float64)
    for j, name in enumerate(selection.names):
        rows = (choice == j).nonzero().squeeze(1)
        if rows.numel() == 0:
            continue
        rec, res = records[name], records[name]["final"]
        theta_names = selection.all_models[name].response.theta_names
        cols = torch.tensor([layout.index(n) for n in theta_names])
        if "tau" in layout and "tau" not in theta_names:
            params[rows, layout.index("tau")] = 0.0  # fitted on one clock
            std[rows, layout.index("tau")] = 0.0
        params[rows[:, None], cols] = rec["params"][rows].double()
        std[rows[:, None], cols] = res.std[rows].double()
        if res.model_std is not None:
            model_std[rows[:, None], cols] = res.model_std[rows].double()
        covariance[rows[:, None, None], cols[None, :, None], cols[None, None, :]] = res.covariance[rows].double()
        for field in ("status", "iterations", "loss", "residual_variance", "relative_residual", "whiteness"):
            getattr(merged, field)[rows] = getattr(res, field)[rows].to(getattr(merged, field).dtype)
        sv = res.singular_values[rows]
        merged.singular_values[rows, : sv.shape[1]] = sv.double()
        hist = res.loss_history[:, rows].double()
        merged.loss_history[:, rows] = torch.cat([hist, hist[-1:].expand(n_hist - hist.shape[0], -1)])
        restarts[rows] = rec["restarts"][rows]
        relative[rows] = rec["relative_loss"][rows].double()
    stages = {
        f"{name}/{stage}": result
        for name, rec in records.items()
        for stage, result in rec["stages"].items()
    }  # fmt: skip
    return {
        "index": records[selection.names[0]]["index"],
        "init": records[selection.names[0]]["init"][:, : selection.n_lead],
        "stages": stages,
        "final": merged,
        "params": params,
        "restarts": restarts,
        "relative_loss": relative,
    }
