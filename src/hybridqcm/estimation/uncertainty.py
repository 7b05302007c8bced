"""Uncertainty at a solve's final estimate (SolverConfig.covariance): the model-based covariance
σ̂² (JᵀJ)⁺ with the AR(1) inflation of serially correlated residuals, the Huber-White sandwich over
groups of adjacent frequencies or time steps, the delete-a-group jackknife, their "robust_*" maxima
with the model's, and a prior's Laplace posterior (data information + prior precision)⁻¹."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from scipy.stats import t as student_t
from torch import Tensor

from ._linalg import pseudo_inverse, pseudo_inverse_solve
from .boundary import without_held
from .diagnostics import residual_tests

if TYPE_CHECKING:
    from .problems import LeastSquaresProblem, ProblemEvaluation
    from .solver import SolverConfig


@dataclass
class Uncertainty:
    """What the final Jacobian pass finds, per sample of the batch: std and model_std [batch, n_theta] (inf
    where not identifiable or diverged, 0 for known entries), covariance [batch, n_theta, n_theta],
    singular_values [batch, n_free] of the column-scaled J, residual_variance σ̂² [batch], the residual
    tests' relative_residual and whiteness [batch] (inf where not evaluated), the final data loss [batch],
    and the sample ids found ``singular`` (rank deficient or not finite) and ``misfit``."""

    std: Tensor
    model_std: Tensor
    covariance: Tensor
    singular_values: Tensor
    residual_variance: Tensor
    relative_residual: Tensor
    whiteness: Tensor
    loss: Tensor
    singular: Tensor
    misfit: Tensor


def final_uncertainty(
    config: SolverConfig,
    evaluation: ProblemEvaluation,
    params: Tensor,
    free: Tensor,
    diverged: Tensor,
    loss: Tensor,
    held: Tensor | None = None,
) -> Uncertainty:
    """Uncertainty and conditioning at the final estimate ``params`` [batch, n_theta] (one more Jacobian
    pass over the samples not ``diverged`` [batch] bool); ``loss`` [batch] is the loop's, replaced by the
    final pass's where finite. ``held`` [batch, n_free] bool: entries held at a boundary (estimation/boundary.py),
    known there: their Jacobian columns are round-off."""
    problem = evaluation.problem
    batch, n_free, n_theta = params.shape[0], free.numel(), problem.n_theta
    covariance = torch.zeros(batch, n_theta, n_theta, dtype=params.dtype)
    std = torch.zeros(batch, n_theta, dtype=params.dtype)
    relative_residual = torch.full((batch,), math.inf, dtype=params.dtype)
    whiteness = torch.full((batch,), math.inf, dtype=params.dtype)
    singular_values = torch.zeros(batch, n_free, dtype=params.dtype)
    residual_variance = torch.zeros(batch, dtype=params.dtype)
    index = (~diverged).nonzero().squeeze(1)
    std[diverged] = math.inf
    std[:, problem.known] = 0.0
    model_std = std.clone()
    loss = loss.clone()
    no_sample = torch.zeros(0, dtype=torch.long)
    result = Uncertainty(
        std, model_std, covariance, singular_values, residual_variance, relative_residual, whiteness, loss,
        no_sample, no_sample,
    )  # fmt: skip
    if index.numel():
        _fill(result, config, evaluation, params, free, index, None if held is None else held[index])
    return result


def unevaluated_uncertainty(problem: LeastSquaresProblem, params: Tensor, free: Tensor, loss: Tensor) -> Uncertainty:
    """The report without the final Jacobian pass (SolverConfig.uncertainty = False): std inf (not evaluated;
    0 for known entries), no covariance, residual tests not run (inf)."""
    batch, n_theta = params.shape[0], problem.n_theta
    std = torch.full((batch, n_theta), math.inf, dtype=params.dtype)
    std[:, problem.known] = 0.0
    unknown = torch.full((batch,), math.inf, dtype=params.dtype)
    no_sample = torch.zeros(0, dtype=torch.long)
    return Uncertainty(
        std=std,
        model_std=std.clone(),
        covariance=torch.zeros(batch, n_theta, n_theta, dtype=params.dtype),
        singular_values=torch.zeros(batch, free.numel(), dtype=params.dtype),
        residual_variance=torch.zeros(batch, dtype=params.dtype),
        relative_residual=unknown,
        whiteness=unknown.clone(),
        loss=loss,
        singular=no_sample,
        misfit=no_sample,
    )


def _fill(
    result: Uncertainty, config: SolverConfig, evaluation: ProblemEvaluation, params, free, index, held=None
) -> None:
    """The final pass over the samples ``index`` into ``result``."""
    cfg, problem = config, evaluation.problem
    n_free, n_theta = free.numel(), problem.n_theta
    robust = cfg.covariance != "model"
    if robust:
        fisher, _, final_loss, meat, groups = evaluation.data_normal_equations(
            params, index, band=int(cfg.covariance_band)
        )
    else:
        fisher, _, final_loss = evaluation.data_normal_equations(params, index)
    if held is not None and bool(held.any()):
        fisher = without_held(held, fisher, torch.zeros_like(fisher[..., 0]))[0]
        if robust:
            meat = without_held(held, meat, torch.zeros_like(meat[..., 0]))[0]
    ok = torch.isfinite(fisher).flatten(1).all(1) & torch.isfinite(final_loss)
    fisher = torch.where(ok[:, None, None], fisher, torch.zeros_like(fisher))
    final_loss = torch.where(ok, final_loss, result.loss[index])
    result.loss[index] = final_loss
    pinv, unidentified, result.singular_values[index], rank_deficient = pseudo_inverse(fisher, cfg.rcond)
    dof = max(problem.n_residuals - n_free, 1)
    sigma2 = 2.0 * final_loss / dof
    result.residual_variance[index] = sigma2
    misfit, result.relative_residual[index], result.whiteness[index], inflation = residual_tests(
        cfg, evaluation, params, index
    )
    cov_free = (inflation * sigma2)[:, None, None] * pinv
    if problem.prior_mean is not None:
        # Laplace posterior: (data information + prior precision)⁻¹; the prior identifies
        # what the data alone cannot.
        precision, _ = evaluation.prior_terms(params[index][:, free], index)
        information = fisher / (inflation * sigma2).clamp_min(1e-300)[:, None, None] + torch.diag_embed(precision)
        cov_free, unidentified, _, rank_deficient = pseudo_inverse(information, cfg.rcond)
    model_std_free = cov_free.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt()
    if robust:
        precision = None
        if problem.prior_mean is not None:
            precision, _ = evaluation.prior_terms(params[index][:, free], index)
        cov_free = robust_covariance(cfg, fisher, meat, groups, cov_free, precision)
    std_free = torch.where(
        unidentified,
        torch.full_like(sigma2[:, None], math.inf),
        cov_free.diagonal(dim1=1, dim2=2).clamp_min(0).sqrt(),
    )
    rows = index.unsqueeze(1)
    result.std[rows, free.unsqueeze(0)] = std_free
    result.model_std[rows, free.unsqueeze(0)] = torch.where(
        unidentified, torch.full_like(model_std_free, math.inf), model_std_free
    )
    cov_full = torch.zeros(index.numel(), n_theta, n_theta, dtype=params.dtype)
    cov_full[:, free.unsqueeze(1), free.unsqueeze(0)] = cov_free
    result.covariance[index] = cov_full
    result.singular = index[rank_deficient | ~ok]
    result.misfit = index[misfit]


def robust_covariance(
    config: SolverConfig, fisher: Tensor, meat: Tensor, groups, model_cov: Tensor, precision: Tensor | None
) -> Tensor:
    """Covariance [b, n_free, n_free] of the free θ by the ``covariance`` setting (SolverConfig).

    Sandwich: for the estimate θ̂ = argmin ½‖e(θ)‖², θ̂ − θ* ≈ −F⁻¹ Σ_g s_g with F = JᵀJ and s_g the
    score of group g, so Cov θ̂ ≈ F⁻¹ (Σ_g E s_g s_gᵀ) F⁻¹ whatever the residual's distribution, as
    long as the groups are uncorrelated. At θ̂ the scores sum to zero (n_free linear constraints),
    hence the small-sample factor G/(G − n_free) (G groups). Jackknife: ``meat`` is already the
    delete-a-group covariance (:func:`score_groups`). With a prior (MAP, ``precision`` λ [b, n_free])
    this data covariance C combines with the prior precision Λ as (C⁻¹ + Λ)⁻¹, as the model-based one does.
    "robust_*": per parameter the larger variance of ``model_cov`` and the robust one, applied as a
    diagonal rescaling of ``model_cov`` (stays positive semi-definite, keeps its correlations).
    With no more groups than unknowns there is no robust estimate: ``model_cov`` is returned.
    """
    cfg = config
    n_free = fisher.shape[-1]
    n_groups, dof = groups
    if n_groups <= n_free:  # fewer groups than unknowns (a short window, a wide band): nothing to estimate from
        return model_cov
    if cfg.covariance.endswith("jackknife"):
        data_cov = meat
        if cfg.covariance_dof:
            # The variance is estimated from few effective groups: widen to the Student-t quantile.
            nu = dof.clamp_min(1.0).cpu().numpy()
            ratio = torch.from_numpy(student_t.ppf(0.975, nu) / student_t.ppf(0.975, math.inf)).to(data_cov)
            ratio = ratio.nan_to_num(1.0)  # a column without variance (held at a boundary) has no dof
            data_cov = data_cov * ratio.unsqueeze(2) * ratio.unsqueeze(1)
    else:
        factor = n_groups / (n_groups - n_free)
        inverse, _, _, _ = pseudo_inverse(fisher, cfg.rcond)
        data_cov = factor * inverse @ meat @ inverse
    if precision is not None:
        information, _, _, _ = pseudo_inverse(data_cov, cfg.rcond)
        data_cov, _, _, _ = pseudo_inverse(information + torch.diag_embed(precision), cfg.rcond)
    if not cfg.covariance.startswith("robust"):
        return data_cov
    model_var = model_cov.diagonal(dim1=1, dim2=2).clamp_min(0)
    ratio = data_cov.diagonal(dim1=1, dim2=2) / model_var.clamp_min(1e-300)
    scale = torch.where(model_var > 0, ratio.clamp_min(1.0), torch.ones_like(ratio)).sqrt()
    return model_cov * scale.unsqueeze(2) * scale.unsqueeze(1)


def score_groups(
    augmented: Tensor, band: int, spectral: bool, jackknife: bool = False
) -> tuple[Tensor, int, Tensor | None]:
    """Σ_g s_g s_gᵀ [b, n, n] of the per-group scores s_g = Σ_{rows in g} J_rᵀ e_r of the (whitened)
    stack ``augmented`` = (e | J) [b, rows, o, 1 + n], and the number of groups G. Spectral stack
    (rows = Re of K frequencies, then Im): a group is ``band`` adjacent frequencies from k = 1 (DC
    carries no rows), real and imaginary parts and all outputs together — at one frequency they are
    correlated, across frequencies asymptotically not (the DFT of a stationary process). Time-domain
    stack: ``band`` consecutive time steps.

    ``jackknife``: instead the delete-a-group jackknife covariance (G − 1)/G Σ_g (d_g − d̄)(d_g − d̄)ᵀ of
    the one-step shifts d_g = (F − F_g)⁻¹ s_g that leaving group g out makes (F = JᵀJ, F_g = J_gᵀJ_g):
    the sandwich with each score taken at its own leave-out fit, so a group that carries much of the
    information (a sharp resonance) is not under-weighted (the cluster "CR3" estimator)."""
    J = augmented[..., 1:]
    contributions = (J * augmented[..., :1]).sum(2)  # [b, rows, n]
    outer = torch.einsum("broi,broj->brij", J, J) if jackknife else None  # [b, rows, n, n]
    if spectral:
        K = contributions.shape[1] // 2
        contributions = (contributions[:, :K] + contributions[:, K:])[:, 1:]
        if outer is not None:
            outer = (outer[:, :K] + outer[:, K:])[:, 1:]
    b, rows, n = contributions.shape
    groups = -(-rows // band)
    pad = groups * band - rows
    scores = torch.nn.functional.pad(contributions, (0, 0, 0, pad)).view(b, groups, band, n).sum(2)
    if not jackknife:
        return torch.bmm(scores.transpose(1, 2), scores), groups, None
    group_fisher = torch.nn.functional.pad(outer, (0, 0, 0, 0, 0, pad)).view(b, groups, band, n, n).sum(2)
    fisher = group_fisher.sum(1, keepdim=True)  # [b, 1, n, n]
    left = fisher - group_fisher  # [b, G, n, n]
    # column scaling by F's diagonal, as in the steps (θ mixes parameters and initial states)
    scale = fisher.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()  # [b, 1, n]
    scaled = left / (scale.unsqueeze(-1) * scale.unsqueeze(-2))
    shifts, _ = pseudo_inverse_solve(scaled.reshape(b * groups, n, n), (scores / scale).reshape(b * groups, n), 1e-7)
    shifts = shifts.view(b, groups, n) / scale  # d_g [b, G, n]
    centred = shifts - shifts.mean(1, keepdim=True)
    # Satterthwaite: a sum of G independent squares a_g² has (Σ a_g²)² / Σ a_g⁴ degrees of freedom.
    squares = centred.square()
    dof = squares.sum(1).square() / squares.square().sum(1).clamp_min(1e-300)  # [b, n]
    return (groups - 1) / groups * torch.bmm(centred.transpose(1, 2), centred), groups, dof
