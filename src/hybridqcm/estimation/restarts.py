"""Multi-start of the refinement (:class:`Restarts`, the settings; :func:`restart`, the attempts) and the
peer test for the misfit status among the recordings of one batch (:func:`flag_outliers`).

Samples left `misfit` (structured residual: a local minimum) or diverged, and — for the Euler model on its
own data — samples whose final loss stays above ``threshold`` x ½Σa² (noise-free fits end near 1e-15, local
minima at >= 1e-8), run all stages again from init (1 + sigma δ'); the lower loss wins. Seeded, so runs
repeat exactly. (With the exact model the noise-free floor is the hold's model error, so a loss threshold
means nothing there: threshold=inf.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from hybridqcm.data.sensor import keyed_normals

from .solver import SolverResult, SolverStatus

if TYPE_CHECKING:
    from .refinement import GaussNewtonRefinement


@dataclass
class Restarts:
    """Multi-start settings (module docstring).

    count: attempts for every sample the rule retries; failed: after them, up to ``failed`` more attempts
    for the recordings still misfit or diverged (a wrong basin the first attempts did not leave), nothing
    else retried. seed: restart draws come from one stream per (seed, recording, attempt): a recording's
    restarts do not depend on which others share its batch or are retried with it. mass_factors: restart
    k (k < len) also rescales the start of p1, p2 by mass_factors[k]: both are (C3, K3)/m3, and a wrong
    occupant mass puts the seat mode's phase off by whole cycles, which a 10 % perturbation cannot undo
    (e.g. [0.6, 1.6, 0.4, 2.5] walks m3 over the prior). batch: attempts run together while retried
    samples x attempts <= batch: a solver call on a few samples costs its fixed per-step overhead; on
    more, attempts that are not needed cost more. far_from_start: a fit that fits but ends with p1 or p2
    more than this (relative) away from a start the networks gave is retried too: under noise a
    one-channel loss can hold several minima of nearly equal depth, and the lowest-loss attempt wins (the
    same rule as above); None: off. center [n_params] (a vehicle, e.g. the reference one), or None:
    restarts draw the vehicle's parameters (all but the occupant's p1, p2, which keep the first start and
    the mass ladder) around it instead of around the first start. A random start that ended in a wrong
    minimum is a bad centre for the next ones: draws around it land in the same basin.
    """

    count: int = 0
    threshold: float = 1e-10
    sigma: float = 0.1
    seed: int = 0
    mass_factors: Sequence[float] = ()
    batch: int = 64
    failed: int = 0
    far_from_start: float | None = None
    center: Tensor | None = None

    def __post_init__(self):
        self.count = int(self.count)
        if int(self.failed) < 0:
            raise ValueError(f"restarts_failed must be >= 0, got {self.failed!r}")
        self.failed = int(self.failed)
        self.threshold = float(self.threshold)
        self.sigma = float(self.sigma)
        self.batch = int(self.batch)
        self.seed = int(self.seed)
        self.mass_factors = [float(f) for f in self.mass_factors]
        if self.far_from_start is not None and not float(self.far_from_start) > 0:
            raise ValueError(f"restart_far must be None or > 0, got {self.far_from_start!r}")
        self.far_from_start = None if self.far_from_start is None else float(self.far_from_start)
        if self.center is not None:
            self.center = torch.as_tensor(self.center, dtype=torch.float64)

    def draws(self, index: Tensor, attempt: int, width: int) -> Tensor:
        """[len(index), width] float64 standard normal draws for restart ``attempt`` of the recordings
        ``index``, each from its own generator seeded by (seed, recording, attempt)."""
        keys = [[self.seed % 2**63, int(i) % 2**63, int(attempt), 2] for i in index.tolist()]
        return keyed_normals(keys, (width,)).to(index.device)


def flag_outliers(
    result: SolverResult, peer_factor: float | None, min_batch: int, typical: Tensor | None = None
) -> Tensor | None:
    """Peer test for the misfit status, in place: among recordings of one batch, a structured
    residual (whiteness > 1) more than ``peer_factor`` x the batch's median relative residual is
    `misfit` even below the solver's absolute floor. Noise-free data are where it matters: a
    correct exact-model fit leaves the hold's model error (~1e-5 of a3), a wrong local minimum
    that mimics the signal leaves ~1e-3 — both far below any absolute floor. With sensor noise
    every residual is noise, white, and nothing is flagged. Returns the batch's median (kept
    from the first pass, so restarts on a subset are judged against the whole batch); a batch of
    fewer than ``min_batch`` recordings has no peers."""
    if peer_factor is None or (typical is None and result.status.numel() < min_batch):
        return typical
    settled = result.status != SolverStatus.DIVERGED
    rel = result.relative_residual
    if typical is None:
        ok = settled & torch.isfinite(rel)
        if not bool(ok.any()):
            return None
        typical = rel[ok].median()
    outlier = settled & (result.whiteness > 1) & (rel > peer_factor * typical)
    result.status[outlier] = SolverStatus.MISFIT
    return typical


@dataclass
class BatchFit:
    """A batch's current fit per sample: the solver result, θ [batch, n_theta], relative loss and score
    [batch] (lower: the better attempt), and the peer test's median."""

    result: SolverResult
    params: Tensor
    relative: Tensor
    score: Tensor
    typical: Tensor | None


def restart(refinement: GaussNewtonRefinement, outputs: Mapping, module: Any, init: Tensor, fit: BatchFit) -> Tensor:
    """The attempts of ``refinement.restarts`` on the samples the rule retries, in place into ``fit``;
    returns the restarts run per sample [batch]."""
    settings = refinement.restarts
    result = fit.result
    restarted = torch.zeros(init.shape[0], dtype=torch.int64)
    attempt = 0
    while attempt < settings.count + settings.failed:
        failed = (result.status == SolverStatus.MISFIT) | (result.status == SolverStatus.DIVERGED)
        if attempt < settings.count:
            retry = (fit.relative > settings.threshold) | failed | refinement.far_from_start(fit.params, init)
            tier_end = settings.count
        else:  # the extra attempts: failed recordings only
            retry, tier_end = failed, settings.count + settings.failed
        retry = retry.nonzero().squeeze(1)
        if retry.numel() == 0:
            if attempt >= settings.count:
                break
            attempt = settings.count  # nothing to retry in the first tier; the failed tier may still run
            continue
        # A few retried samples: run several attempts in one solver call (a small batch costs
        # the solver's fixed per-step overhead, not its size); many: one attempt at a time, so
        # samples that succeed are not retried again.
        group = min(tier_end - attempt, max(1, settings.batch // retry.numel()))
        _attempts(refinement, outputs, module, init, fit, retry, attempt, group)
        restarted[retry] += group
        flag_outliers(result, refinement.peer_factor, refinement.peer_min_batch, fit.typical)
        attempt += group
    return restarted


def _attempts(
    refinement, outputs, module, init: Tensor, fit: BatchFit, retry: Tensor, attempt: int, group: int
) -> None:
    """Attempts ``attempt`` .. ``attempt + group - 1`` of the samples ``retry``, in one call of the stages;
    each replaces a sample's current fit where it is better."""
    settings = refinement.restarts
    starts = []
    for number in range(attempt, attempt + group):
        delta = settings.draws(outputs["index"][retry], number, init.shape[1])
        centre = init[retry].clone()
        if settings.center is not None:
            n_p = settings.center.numel()
            centre[:, 2:n_p] = settings.center[2:].to(centre)
        new_init = centre * (1.0 + settings.sigma * delta)
        if number < len(settings.mass_factors):
            new_init[:, :2] = new_init[:, :2] * settings.mass_factors[number]
        starts.append(torch.where(refinement.known[: init.shape[1]] | (new_init <= 0), init[retry], new_init))
    rows = retry.repeat(group)
    sub = {
        k: (v[rows] if isinstance(v, Tensor) and v.ndim > 0 and v.shape[0] == init.shape[0] else v)
        for k, v in outputs.items()
    }
    # x0_start="alternate": restarts 1, 3, 5, ... start x0 at rest, the others projected.
    at_rest = torch.tensor(
        [refinement.x0_start == "alternate" and number % 2 == 0 for number in range(attempt, attempt + group)]
    ).repeat_interleave(retry.numel())
    _, sub_result, sub_params, sub_relative, sub_score = refinement.run_stages(
        sub, torch.cat(starts), module, restart=True, x0_at_rest=at_rest
    )
    # In attempt order: an attempt replaces a sample's current fit if it fits (not misfit or
    # diverged) where the current does not, or fits as well and has the lower score; a lower
    # loss at a misfit is a structured residual, not a better fit. Candidates are judged by
    # the same peer test as the first fits.
    flag_outliers(sub_result, refinement.peer_factor, refinement.peer_min_batch, fit.typical)
    fits = sub_result.status.ne(SolverStatus.MISFIT) & sub_result.status.ne(SolverStatus.DIVERGED)
    result = fit.result
    for number in range(group):
        mask = torch.zeros(rows.numel(), dtype=torch.bool)
        part = slice(number * retry.numel(), (number + 1) * retry.numel())
        current = result.status[retry]
        current_fits = current.ne(SolverStatus.MISFIT) & current.ne(SolverStatus.DIVERGED)
        better = (fits[part] & ~current_fits) | ((fits[part] == current_fits) & (sub_score[part] < fit.score[retry]))
        mask[part] = better
        take = retry[better]
        fit.params[take] = sub_params[part][better]
        fit.relative[take] = sub_relative[part][better]
        fit.score[take] = sub_score[part][better]
        take_samples(result, sub_result, mask, take)


def far_from_start(far: float | None, known: Tensor, params: Tensor, init: Tensor) -> Tensor:
    """[batch] bool: free (``known`` [n_theta] bool) p1 or p2 of ``params`` more than ``far`` (relative,
    either way) from ``init``; none when ``far`` is None."""
    if far is None:
        return torch.zeros(params.shape[0], dtype=torch.bool)
    ratio = params[:, :2].double() / init[:, :2].double()
    far_off = ~(ratio.abs().log().abs() <= math.log1p(far))  # a non-positive ratio is far
    return (far_off & ~known[:2]).any(1)


_PER_SAMPLE = (
    "params",
    "status",
    "iterations",
    "loss",
    "std",
    "covariance",
    "singular_values",
    "residual_variance",
    "relative_residual",
    "whiteness",
)


def take_samples(into: SolverResult, other: SolverResult, mask: Tensor, rows: Tensor | None = None) -> None:
    """In place: the samples ``rows`` of ``into`` (default: where ``mask``) take ``other``'s per-sample
    results at ``mask`` (``other`` may hold a subset of ``into``'s samples)."""
    rows = mask.nonzero().squeeze(1) if rows is None else rows
    for name in _PER_SAMPLE:
        getattr(into, name)[rows] = getattr(other, name)[mask]
    if into.model_std is not None and other.model_std is not None:
        into.model_std[rows] = other.model_std[mask]
