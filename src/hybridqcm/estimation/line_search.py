"""Per-sample Armijo backtracking of the batched least-squares solver (estimation/solver.py).

The trial steps are α = α0 2^-e, e = 0..max_backtracks, for every sample at once; a sample stops at its first
passing e ("halve") or, with "interpolate", at the same e found in fewer trials where the Armijo test passes
for every e from some e* on (:func:`_next_exponent`). The solver supplies the step's application (linear or
log parametrization), the relative-step cap and which entries must stay positive.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .boundary import boundary_cap


def line_search(solver, run, index: Tensor, step: Tensor, loss_now: Tensor, predicted: Tensor):
    """Per-sample Armijo backtracking over α = α0 2^-e, e = 0..max_backtracks; returns (α [b] with 0 = none
    found, new loss [b]). "halve" tries e = 0, 1, 2, ... and takes the first that passes; "interpolate" takes
    the same α where the test passes for every e from some e* on (_next_exponent), in fewer trials: it starts
    one e above the sample's last accepted one (a weakly identified direction overshoots alike from one
    iteration to the next), where a failure confirms everything above it."""
    cfg, params, free = solver.config, run.params, run.free
    b = index.numel()
    alpha0 = torch.full((b,), cfg.initial_step, dtype=params.dtype)
    if cfg.max_relative_step:
        relative = solver._relative_step(step, params[index][:, free])
        alpha0 = torch.minimum(alpha0, cfg.max_relative_step / relative.clamp_min(1e-300))
    if cfg.boundary_test is not None and bool(solver._boundary.any()):  # every stage: none crosses r = 0
        alpha0 = torch.minimum(alpha0, boundary_cap(solver, run, index, step))
    exponent = torch.zeros(b, dtype=torch.long)  # the trial's e
    if cfg.backtrack == "interpolate":  # one e above the last accepted one: where it fails, e* is known
        exponent = (run.exponent[index] - 1).clamp(0, cfg.max_backtracks)
    failed = torch.full((b,), -1, dtype=torch.long)  # the largest e that failed (-1: none yet)
    passed = torch.full((b,), cfg.max_backtracks + 1, dtype=torch.long)  # the smallest e that passed
    new_loss = loss_now.clone()
    searching = predicted > 0  # a zero direction cannot decrease the loss
    for _ in range(2 * (cfg.max_backtracks + 1)):
        pos = searching.nonzero().squeeze(1)
        if pos.numel() == 0:
            break
        alpha = alpha0[pos] * 0.5 ** exponent[pos].to(params.dtype)
        trial = params[index[pos]].clone()
        trial[:, free] = solver._apply_step(trial[:, free], alpha.unsqueeze(1) * step[pos])
        positive = (
            ((trial[:, free] > 0) | run.held[index[pos]])[:, solver._positive].all(1)
            if cfg.parametrization != "unconstrained"
            else torch.ones(pos.numel(), dtype=torch.bool)
        )
        positive &= torch.isfinite(trial).all(1)  # an overflowing step (log space) is a failed trial
        trial_loss = torch.full((pos.numel(),), math.inf, dtype=params.dtype)
        if bool(positive.any()):
            # Evaluate only positive trials; the others count as Armijo failures.
            sub = positive.nonzero().squeeze(1)
            trial_loss[sub] = run.evaluation.loss_at(trial[sub], index[pos[sub]])
        ok = torch.isfinite(trial_loss) & (trial_loss <= loss_now[pos] - cfg.armijo_c * alpha * predicted[pos])
        passed[pos[ok]] = exponent[pos[ok]]
        new_loss[pos[ok]] = trial_loss[ok]
        failed[pos[~ok]] = exponent[pos[~ok]]
        if cfg.backtrack == "halve":
            nxt = exponent[pos] + 1
            searching[pos[ok]] = False
        else:
            nxt = _next_exponent(
                failed[pos], passed[pos], alpha, trial_loss, loss_now[pos], predicted[pos], cfg.max_backtracks
            )
            searching[pos[nxt < 0]] = False
        searching[pos[nxt > cfg.max_backtracks]] = False
        exponent[pos] = nxt
    found = passed <= cfg.max_backtracks
    run.exponent[index[found]] = passed[found]
    accepted_alpha = torch.where(found, alpha0 * 0.5 ** passed.clamp_max(cfg.max_backtracks).to(params.dtype), 0.0)
    return accepted_alpha, torch.where(found, new_loss, loss_now)


def _next_exponent(
    failed: Tensor, passed: Tensor, alpha: Tensor, trial_loss: Tensor, loss_now: Tensor, predicted: Tensor, last: int
) -> Tensor:
    """The next trial's e [b] of the "interpolate" line search (-1: done), from the largest e that failed and the
    smallest that passed (``last`` + 1: none yet) and the trial just made at α (failed where ``trial_loss`` is
    above the Armijo line). Until a trial passes, e jumps to where the quadratic through L(0), L'(0) = −δᵀJᵀR
    and the failed L(α) comes back to L(0) (2 α_q, α_q its minimum), rounded up to the grid (the largest
    2^-j α ≥ 2 α_q, at least a halving; a halving where L(α) was not finite); then the gap between the
    largest failed and the smallest passed e is bisected. Where the Armijo
    test passes for every e ≥ e* and fails below, the search ends on halving's e* — a body model's GN steps,
    10-1000× too long (docs/measurements/persons.md), needed up to 15 halvings, and at most 7 trials here."""
    curvature = trial_loss - loss_now + alpha * predicted  # > (1 − c) α δᵀJᵀR > 0 where the test failed
    ratio = curvature / (predicted * alpha)  # α / (2 α_q): 2 α_q, where the parabola crosses L(0)
    jump = torch.where(torch.isfinite(ratio) & (ratio > 0), ratio.clamp(1.0, 2.0**62).log2().floor(), 1.0)
    jump = jump.clamp_min(1).to(torch.long)
    nxt = torch.where(passed > last, (failed + jump).clamp_max(last), failed + (passed - failed) // 2)
    done = (passed == failed + 1) | ((passed > last) & (failed >= last))
    return torch.where(done, torch.full_like(nxt, -1), nxt)


__all__ = ["line_search"]
