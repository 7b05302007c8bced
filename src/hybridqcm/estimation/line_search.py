"""Per-sample Armijo backtracking of the batched least-squares solver (estimation/solver.py).

The trial steps are α = α0 2^-e, e = 0..max_backtracks, for every sample at once; a sample stops at its first
passing e ("halve") or, with "interpolate", at the same e found in fewer trials where the Armijo test passes
for every e from some e* on (:func:`_next_exponent`). The solver supplies the step's application (linear or
log parametrization), the relative-step cap and which entries must stay positive.

"halve" tries the exponents in blocks, each block of every sample still searching evaluated in one call of the
model, and takes each sample's first passing e: the α of one trial at a time. A sample's first block reaches its
last accepted e (e = 0 .. e_last: a direction that overshoots does so alike from one iteration to the next), each
next block is twice as long (from rest: 0 | 1, 2 | 3..6 | 7..14 | ...), so at most 5 calls instead of up to 31,
and one where the overshoot repeats. A call's fixed cost (hundreds of small operations, whatever the rows) is what
a line search costs at the batch sizes of a solve's last iterations; the trials past a sample's first pass are the
price. "interpolate" does the same where few samples search: their calls also evaluate the two exponents each
search goes to next, kept in a cache from which the search reads (:func:`_with_speculation`; the same path).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .boundary import boundary_cap

# "interpolate": the most samples whose trials get the next two candidates besides (_with_speculation)
_SPECULATE = 16


def line_search(solver, run, index: Tensor, step: Tensor, loss_now: Tensor, predicted: Tensor):
    """Per-sample Armijo backtracking over α = α0 2^-e, e = 0..max_backtracks; returns (α [b] with 0 = none
    found, new loss [b]). "halve" takes the first e = 0, 1, 2, ... that passes (_halve); "interpolate" takes
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
    if cfg.backtrack == "halve":
        return _halve(solver, run, index, step, loss_now, predicted, alpha0)
    # the first trial one e above the last accepted one: where it fails, e* is known
    exponent = (run.exponent[index] - 1).clamp(0, cfg.max_backtracks)
    failed = torch.full((b,), -1, dtype=torch.long)  # the largest e that failed (-1: none yet)
    passed = torch.full((b,), cfg.max_backtracks + 1, dtype=torch.long)  # the smallest e that passed
    new_loss = loss_now.clone()
    searching = predicted > 0  # a zero direction cannot decrease the loss
    known = torch.full((b, cfg.max_backtracks + 1), math.nan, dtype=params.dtype)  # trial losses by e (NaN: not yet)
    for _ in range(2 * (cfg.max_backtracks + 1)):
        pos = searching.nonzero().squeeze(1)
        if pos.numel() == 0:
            break
        need = pos[torch.isnan(known[pos, exponent[pos]])]
        if need.numel():
            which, tried = _with_speculation(
                need, exponent[need], failed[need], passed[need], known, cfg.max_backtracks
            )
            alpha = alpha0[which] * 0.5 ** tried.to(params.dtype)
            trial = params[index[which]].clone()
            trial[:, free] = solver._apply_step(trial[:, free], alpha.unsqueeze(1) * step[which])
            known[which, tried] = _trial_losses(solver, run, index[which], trial)
        alpha = alpha0[pos] * 0.5 ** exponent[pos].to(params.dtype)
        trial_loss = known[pos, exponent[pos]]
        ok = torch.isfinite(trial_loss) & (trial_loss <= loss_now[pos] - cfg.armijo_c * alpha * predicted[pos])
        passed[pos[ok]] = exponent[pos[ok]]
        new_loss[pos[ok]] = trial_loss[ok]
        failed[pos[~ok]] = exponent[pos[~ok]]
        nxt = _next_exponent(
            failed[pos], passed[pos], alpha, trial_loss, loss_now[pos], predicted[pos], cfg.max_backtracks
        )
        searching[pos[nxt < 0]] = False
        searching[pos[nxt > cfg.max_backtracks]] = False
        exponent[pos] = nxt
    return _accepted(run, index, passed, alpha0, new_loss, loss_now, cfg.max_backtracks)


def _accepted(run, index: Tensor, passed: Tensor, alpha0: Tensor, new_loss: Tensor, loss_now: Tensor, last: int):
    """(α [b], 0 where no e <= ``last`` passed; the loss there [b]) from each sample's first passing e ``passed``
    [b], which becomes its last accepted one (run.exponent, where the next search starts)."""
    found = passed <= last
    run.exponent[index[found]] = passed[found]
    accepted_alpha = torch.where(found, alpha0 * 0.5 ** passed.clamp_max(last).to(alpha0.dtype), 0.0)
    return accepted_alpha, torch.where(found, new_loss, loss_now)


def _with_speculation(need: Tensor, exponent: Tensor, failed: Tensor, passed: Tensor, known: Tensor, last: int):
    """The trials of one call of the "interpolate" search: (samples [r], exponents [r]) — each sample in ``need`` at its
    ``exponent`` e and, where at most _SPECULATE samples need a trial, also at the two e the search goes to next: after
    a failure at e (the bisection's midpoint where a larger e passed, else e + 1: the parabola's shortest jump) and
    after a pass at e (the midpoint down to the largest failure), where the search would not end there and the loss is
    not known. A call's fixed cost (the model's hundreds of small ops) is what a trial costs at a few recordings: 2 ms
    for 1 row, 3.5 ms for 17-64 (the occupant selection's candidates; docs/measurements/persons.md), so the extra rows
    are nearly free and a search whose next trial is among them needs no call for it. The search itself, and so its
    result, is the same: the losses only come from a cache (``known`` [b, last + 1], NaN where not yet evaluated)."""
    samples, exponents = [need], [exponent]
    if need.numel() <= _SPECULATE:
        after_failure = torch.where(passed > last, exponent + 1, exponent + (passed - exponent) // 2)
        after_failure[(passed == exponent + 1) | ((passed > last) & (exponent >= last))] = -1  # it would end
        after_pass = failed + (exponent - failed) // 2
        after_pass[exponent == failed + 1] = -1
        for guess in (after_failure, after_pass):
            take = (guess >= 0) & (guess <= last) & (guess != exponent)
            take &= torch.isnan(known[need, guess.clamp(0, last)])
            samples.append(need[take])
            exponents.append(guess[take])
    return torch.cat(samples), torch.cat(exponents)


def _trial_losses(solver, run, rows: Tensor, trial: Tensor) -> Tensor:
    """The loss [r] at the trial points ``trial`` [r, n_theta] of the samples ``rows`` (a sample may appear more than
    once), in one evaluation; inf for a trial outside the domain (linear/log parametrization) or not finite, which
    counts as an Armijo failure."""
    free = run.free
    positive = (
        ((trial[:, free] > 0) | run.held[rows])[:, solver._positive].all(1)
        if solver.config.parametrization != "unconstrained"
        else torch.ones(rows.numel(), dtype=torch.bool)
    )
    positive &= torch.isfinite(trial).all(1)  # an overflowing step (log space) is a failed trial
    trial_loss = torch.full((rows.numel(),), math.inf, dtype=trial.dtype)
    if bool(positive.any()):
        sub = positive.nonzero().squeeze(1)
        trial_loss[sub] = run.evaluation.loss_at(trial[sub], rows[sub])
    return trial_loss


def _halve(solver, run, index: Tensor, step: Tensor, loss_now: Tensor, predicted: Tensor, alpha0: Tensor):
    """The "halve" search: each sample's first e = 0, 1, 2, ... whose α = α0 2^-e passes the Armijo test, exponents in
    blocks per call (module docstring): the first block reaches the sample's last accepted e (a direction that
    overshoots overshoots alike from one iteration to the next), each next one is twice as long. Returns (α [b],
    0 = none found; new loss [b])."""
    cfg, params, free = solver.config, run.params, run.free
    b, last = index.numel(), cfg.max_backtracks
    passed = torch.full((b,), last + 1, dtype=torch.long)  # the first e that passed (last + 1: none)
    new_loss = loss_now.clone()
    first = torch.zeros(b, dtype=torch.long)  # the first e of the sample's next block
    searching = predicted > 0  # a zero direction cannot decrease the loss
    width = (run.exponent[index] + 1).clamp(1, last + 1)  # [b] the length of the sample's next block
    while bool(searching.any()):
        pos = searching.nonzero().squeeze(1)
        span = torch.arange(int(width[pos].max()))
        exponent = first[pos, None] + span  # [p, span]
        valid = (span < width[pos, None]) & (exponent <= last)
        which = pos[:, None].expand_as(exponent)[valid]  # the block's trials, sample by sample
        exponent = exponent[valid]
        alpha = alpha0[which] * 0.5 ** exponent.to(params.dtype)
        trial = params[index[which]].clone()
        trial[:, free] = solver._apply_step(trial[:, free], alpha.unsqueeze(1) * step[which])
        trial_loss = _trial_losses(solver, run, index[which], trial)
        ok = torch.isfinite(trial_loss) & (trial_loss <= loss_now[which] - cfg.armijo_c * alpha * predicted[which])
        best = torch.full((b,), last + 1, dtype=torch.long)
        best.scatter_reduce_(0, which[ok], exponent[ok], "amin")
        take = ok & (exponent == best[which])
        passed[which[take]] = exponent[take]
        new_loss[which[take]] = trial_loss[take]
        first[pos] += width[pos]
        width[pos] *= 2
        searching[pos] = (best[pos] > last) & (first[pos] <= last)
    return _accepted(run, index, passed, alpha0, new_loss, loss_now, last)


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
