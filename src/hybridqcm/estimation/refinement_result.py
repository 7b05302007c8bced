"""What a refinement found over all its batches: :class:`RefinementResult`, merged from the per-batch
records of :meth:`GaussNewtonRefinement.refine <hybridqcm.estimation.refinement.GaussNewtonRefinement.refine>`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .solver import SolverResult


@dataclass
class RefinementResult:
    """Concatenated per-sample results of all batches, in batch order."""

    index: Tensor
    init: Tensor
    result: SolverResult
    stage_loss: dict = field(default_factory=dict)  # stage -> mean loss per iteration (list)
    stage_status: dict = field(default_factory=dict)  # stage -> status counts
    restarts: Tensor | None = None  # [batch] restarts run per sample
    relative_loss: Tensor | None = None  # [batch] final L / ½Σa² (observed channels)


def merge_records(records: Sequence[dict], stage_names: Sequence[str]) -> RefinementResult:
    """The records of GaussNewtonRefinement.refine, one per batch, concatenated (final stage), plus the mean loss per
    iteration of every stage in ``stage_names``."""
    b = list(records)
    final = [r["final"] for r in b]
    history_len = max(f.loss_history.shape[0] for f in final)
    n_free_max = max(f.singular_values.shape[1] for f in final)

    def pad_history(h: Tensor) -> Tensor:  # finished samples carry their last loss
        return torch.cat([h, h[-1:].expand(history_len - h.shape[0], -1)]) if h.shape[0] < history_len else h

    merged = SolverResult(
        params=torch.cat([r["params"] for r in b]),
        status=torch.cat([f.status for f in final]),
        iterations=torch.cat([f.iterations for f in final]),
        loss=torch.cat([f.loss for f in final]),
        loss_history=torch.cat([pad_history(f.loss_history) for f in final], 1),
        std=torch.cat([f.std for f in final]),
        covariance=torch.cat([f.covariance for f in final]),
        singular_values=torch.cat(
            [torch.nn.functional.pad(f.singular_values, (0, n_free_max - f.singular_values.shape[1])) for f in final]
        ),
        residual_variance=torch.cat([f.residual_variance for f in final]),
        seconds=[s for f in final for s in f.seconds],
        relative_residual=torch.cat([f.relative_residual for f in final]),
        whiteness=torch.cat([f.whiteness for f in final]),
        model_std=None if any(f.model_std is None for f in final) else torch.cat([f.model_std for f in final]),
    )
    stage_loss, stage_status = {}, {}
    for name in stage_names:
        results = [r["stages"][name] for r in b]
        length = max(x.loss_history.shape[0] for x in results)
        total = torch.zeros(length, dtype=torch.float64)
        count = 0
        for x in results:
            h = x.loss_history
            h = torch.cat([h, h[-1:].expand(length - h.shape[0], -1)]) if h.shape[0] < length else h
            total += h.sum(1)
            count += h.shape[1]
        stage_loss[name] = (total / max(count, 1)).tolist()
        counts: dict[str, int] = {}
        for x in results:
            for k, v in x.status_counts().items():
                counts[k] = counts.get(k, 0) + v
        stage_status[name] = counts
        stage_status[name + "_iterations_mean"] = float(torch.cat([x.iterations for x in results]).double().mean())
    return RefinementResult(
        index=torch.cat([r["index"] for r in b]),
        init=torch.cat([r["init"] for r in b]),
        result=merged,
        stage_loss=stage_loss,
        stage_status=stage_status,
        restarts=torch.cat([r["restarts"] for r in b]),
        relative_loss=torch.cat([r["relative_loss"] for r in b]),
    )
