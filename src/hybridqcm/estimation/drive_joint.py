"""The joint fit of a drive's windows (issue 32): one set of shared parameters, each window its own nuisance.

Windows w of a drive segment g share θ_s (the occupant model's parameters: the seat's p1, p2, body modes, and
τ where it is one clock) and each keeps its own ℓ_w (its initial state; τ where drive.per_window keeps it).
The segment's loss is its windows' losses plus the prior once (not once per window, as a combination of
per-window posteriors counts it):

    L_g(θ_s, ℓ) = Σ_{w ∈ g} L_w(θ_s, ℓ_w) + ½ (θ_s − μ)ᵀ Λ₀ (θ_s − μ).

Gauss-Newton's normal equations of the stacked problem are block-arrow shaped (the windows are independent
given θ_s). With each window's F_w = J_wᵀJ_w = [[F_ss, F_sℓ], [F_ℓs, F_ℓℓ]] and g_w = J_wᵀR_w = [g_s, g_ℓ],
every δℓ_w is eliminated (the Schur complement; variable projection to first order):

    S = Σ_w (F_ss − F_sℓ F_ℓℓ⁻¹ F_ℓs) + Λ₀,      r = Σ_w (g_s − F_sℓ F_ℓℓ⁻¹ g_ℓ) + Λ₀ (θ_s − μ),
    S δ_s = r,      δℓ_w = F_ℓℓ⁻¹ (g_ℓ − F_ℓs δ_s),      θ ← θ − α δ,

exactly the stacked system's solution, at a cost linear in the number of windows (one [n, n] block per
window, never the [s + W ℓ]² matrix). α: Armijo backtracking on L_g per segment, positive parameters kept
positive. Converged when the GN decrement δᵀ(g) ≤ ``decrement_tol`` (whitened residuals: the full step moves
θ by under √tol standard deviations). The Laplace covariance of θ_s is S⁻¹ at the estimate: the shared block
of the stacked inverse, i.e. the windows' nuisance marginalised.

A window's F_w, g_w and loss come from the solver's own evaluation (estimation/problems.ProblemEvaluation,
batched over all windows of all segments: the shared entries broadcast to each window's θ row), so the joint
fit uses the very response model, noise whitening and chunking the per-window fits use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ._linalg import pseudo_inverse, pseudo_inverse_solve
from .solver import SolverStatus


@dataclass
class JointFit:
    """The result per segment g (G of them) and per window w (W).

    params [W, n_theta]: each window's θ at the joint estimate (the shared entries equal within a segment);
    shared [G, s]: the shared free parameters; covariance [G, s, s]: S⁻¹ (Laplace, nuisance marginalised);
    loss [G]: the segment's loss (data + prior once); data_loss [W]; status [G] (SolverStatus values);
    iterations [G]; log_det [G]: log det S (for a Laplace evidence); history [k, 2, G]: each iteration's loss
    and GN decrement (NaN for a segment no longer active)."""

    params: Tensor
    shared: Tensor
    covariance: Tensor
    loss: Tensor
    data_loss: Tensor
    status: Tensor
    iterations: Tensor
    log_det: Tensor
    history: Tensor


def schur_reduce(fisher: Tensor, gradient: Tensor, shared: Tensor, rcond: float = 1e-10):
    """Per window, the nuisance ℓ eliminated from F [W, n, n] δ = g [W, n] (shared [n] bool marks θ_s).

    Returns (S_w [W, s, s], r_w [W, s], back) with ``back(δ_s [W, s]) -> δ [W, n]`` the full step of each
    window given its segment's δ_s."""
    s_idx, l_idx = shared.nonzero().squeeze(1), (~shared).nonzero().squeeze(1)
    f_ss = fisher[:, s_idx][:, :, s_idx]
    g_s = gradient[:, s_idx]
    n = fisher.shape[1]
    if l_idx.numel() == 0:
        return f_ss, g_s, lambda d_s: d_s.new_zeros(d_s.shape[0], n).index_copy(1, s_idx, d_s)
    f_sl = fisher[:, s_idx][:, :, l_idx]
    f_ll = fisher[:, l_idx][:, :, l_idx]
    g_l = gradient[:, l_idx]
    f_ll_inv = pseudo_inverse(f_ll, rcond)[0]  # [W, ℓ, ℓ]: column-scaled, an unobservable state direction dropped
    coupling = f_sl @ f_ll_inv  # F_sℓ F_ℓℓ⁻¹ [W, s, ℓ]
    reduced = f_ss - coupling @ f_sl.transpose(1, 2)
    reduced = 0.5 * (reduced + reduced.transpose(1, 2))
    rhs = g_s - (coupling @ g_l.unsqueeze(2)).squeeze(2)

    def back(d_s: Tensor) -> Tensor:
        d_l = (f_ll_inv @ (g_l - (f_sl.transpose(1, 2) @ d_s.unsqueeze(2)).squeeze(2)).unsqueeze(2)).squeeze(2)
        step = d_s.new_zeros(d_s.shape[0], n)
        step[:, s_idx] = d_s
        step[:, l_idx] = d_l
        return step

    return reduced, rhs, back


def _segment_sum(values: Tensor, group: Tensor, n_groups: int) -> Tensor:
    return values.new_zeros(n_groups, *values.shape[1:]).index_add_(0, group, values)


def joint_normal_equations(fisher, gradient, shared, group, n_groups, prior_precision=None, prior_deviation=None):
    """The segments' reduced systems: (S [G, s, s], r [G, s], back) from the windows' F [W, n, n], g [W, n]
    (over the free parameters; shared [n] bool), group [W] (segment of each window); the prior's precision
    λ [G, s] and deviation θ_s − μ [G, s] added once per segment."""
    reduced, rhs, back = schur_reduce(fisher, gradient, shared)
    S = _segment_sum(reduced, group, n_groups)
    r = _segment_sum(rhs, group, n_groups)
    if prior_precision is not None:
        S = S + torch.diag_embed(prior_precision)
        r = r + prior_precision * prior_deviation
    return S, r, back


# converged where the Gauss-Newton decrement is below this fraction of the loss: the loss's rounding level (a few
# float64 ulps summed over its terms), not a tolerance on the fit
_ROUNDING = 1e-15


def joint_gauss_newton(
    evaluation,
    params: Tensor,
    group: Tensor,
    shared: Tensor,
    prior: tuple[Tensor, Tensor] | None = None,
    positive: Tensor | None = None,
    max_iterations: int = 30,
    decrement_tol: float = 1e-6,
    max_backtracks: int = 30,
    armijo_c: float = 1e-4,
    rcond: float = 1e-7,
) -> JointFit:
    """Gauss-Newton on the segments' joint losses (module docstring).

    evaluation: a ProblemEvaluation of the W windows (its problem without a prior: the prior is the segment's);
    params [W, n_theta] the start (shared entries are taken from each segment's first window); group [W] long
    in 0..G-1; shared [n_theta] bool; prior (mean [G, n_theta], precision [G, n_theta]) or None; positive
    [n_theta] bool: entries kept > 0."""
    problem = evaluation.problem
    free = torch.tensor(problem.free_index)
    n_theta = params.shape[1]
    group = group.long()
    n_groups = int(group.max()) + 1
    params = params.double().clone()
    first = torch.full((n_groups,), -1, dtype=torch.long)
    first = first.scatter_reduce(0, group, torch.arange(group.numel()), "amin", include_self=False)
    params[:, shared] = params[first[group]][:, shared]  # one θ_s per segment
    shared_free = shared[free]
    s_cols = free[shared_free]
    positive = torch.zeros(n_theta, dtype=torch.bool) if positive is None else positive.bool()
    if prior is not None:
        prior_mean, prior_precision = prior[0][:, s_cols].double(), prior[1][:, s_cols].double()

    def prior_terms(theta_s):
        if prior is None:
            return None, None, torch.zeros(theta_s.shape[0], dtype=torch.float64)
        deviation = theta_s - prior_mean
        return prior_precision, deviation, 0.5 * (prior_precision * deviation.square()).sum(1)

    every = torch.arange(group.numel())
    status = torch.full((n_groups,), int(SolverStatus.MAX_ITERATIONS), dtype=torch.long)
    iterations = torch.zeros(n_groups, dtype=torch.long)
    active = torch.ones(n_groups, dtype=torch.bool)
    history = []
    for _ in range(max_iterations + 1):
        rows = active[group].nonzero().squeeze(1)
        if rows.numel() == 0:
            break
        fisher, gradient, loss_w = evaluation.data_normal_equations(params, rows)
        theta_s = params[first][:, s_cols]
        lam, dev, prior_loss = prior_terms(theta_s)
        S, r, back = joint_normal_equations(
            fisher, gradient, shared_free, group[rows], n_groups, lam, dev if lam is not None else None
        )
        loss = _segment_sum(loss_w, group[rows], n_groups) + prior_loss
        d_s, _ = pseudo_inverse_solve(S, r, rcond)
        step_free = back(d_s[group[rows]])
        decrement = _segment_sum((step_free * gradient).sum(1), group[rows], n_groups)
        if lam is not None:  # the prior's share of the gradient: once per segment
            decrement = decrement + (d_s * lam * dev).sum(1)
        nan = torch.full_like(loss, math.nan)
        history.append(torch.stack([torch.where(active, loss, nan), torch.where(active, decrement, nan)]))
        # ... or the decrease it predicts is at the loss's rounding level: there a full step changes the loss by
        # rounding, and on some CPUs every such step passes the Armijo test, for ever (max_iterations)
        done = active & ((decrement <= decrement_tol) | (decrement <= _ROUNDING * loss.abs()))
        status[done] = int(SolverStatus.CONVERGED)
        active &= ~done
        bad = active & ~torch.isfinite(loss)
        status[bad] = int(SolverStatus.DIVERGED)
        active &= ~bad
        if not bool(active.any()) or int(iterations.max()) >= max_iterations:
            break
        step = params.new_zeros(rows.numel(), n_theta)
        step[:, free] = step_free
        alpha = torch.ones(n_groups, dtype=torch.float64)
        pending = active.clone()
        for _ in range(max_backtracks + 1):
            trial = params[rows] - alpha[group[rows], None] * step
            inside = ((trial > 0) | ~positive).all(1)
            trial_loss_w = evaluation.loss_at(trial, rows)
            trial_loss_w = torch.where(inside, trial_loss_w, torch.full_like(trial_loss_w, math.inf))
            full = params.clone()
            full[rows] = trial
            trial_s = full[first][:, s_cols]
            trial_loss = _segment_sum(trial_loss_w, group[rows], n_groups) + prior_terms(trial_s)[2]
            ok = pending & (trial_loss <= loss - armijo_c * alpha * decrement)
            take = ok[group[rows]]
            params[rows[take]] = trial[take]
            pending &= ~ok
            if not bool(pending.any()):
                break
            alpha = torch.where(pending, alpha * 0.5, alpha)
        # no acceptable step: at a numerical minimum if the decrease it predicts is at the loss's rounding level
        at_minimum = pending & (decrement <= 1e-10 * loss.abs())
        status[at_minimum] = int(SolverStatus.CONVERGED)
        status[pending & ~at_minimum] = int(SolverStatus.STALLED)
        active &= ~pending
        iterations[active] += 1
    # The Laplace covariance at the estimate (S⁻¹ of the last evaluation is one step behind: evaluate again).
    fisher, gradient, loss_w = evaluation.data_normal_equations(params, every)
    theta_s = params[first][:, s_cols]
    lam, dev, prior_loss = prior_terms(theta_s)
    S = joint_normal_equations(fisher, gradient, shared_free, group, n_groups, lam, dev)[0]
    covariance, _, singular, deficient = pseudo_inverse(S, rcond)
    status = torch.where(deficient & (status == int(SolverStatus.CONVERGED)), int(SolverStatus.SINGULAR), status)
    log_det = torch.linalg.slogdet(S)[1]
    return JointFit(
        params=params,
        shared=theta_s,
        covariance=0.5 * (covariance + covariance.transpose(1, 2)),
        loss=_segment_sum(loss_w, group, n_groups) + prior_loss,
        data_loss=loss_w,
        status=status,
        iterations=iterations,
        log_det=log_det,
        history=torch.stack(history) if history else torch.zeros(0, 2, n_groups, dtype=torch.float64),
    )


__all__ = ["JointFit", "schur_reduce", "joint_normal_equations", "joint_gauss_newton"]
