"""Uncertainty at a solve's final estimate (SolverConfig.covariance): the model-based covariance
σ̂² (JᵀJ)⁺ with the AR(1) inflation of serially correlated residuals, the Huber-White sandwich over
groups of adjacent frequencies or time steps, the delete-a-group jackknife, their "robust_*" maxima
with the model's, and a prior's Laplace posterior (data information + prior precision)⁻¹."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from scipy.stats import chi2
from scipy.stats import t as student_t
from torch import Tensor

from ._linalg import psd_inverse, pseudo_inverse, pseudo_inverse_solve
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
        cov_free = robust_covariance(cfg, fisher, meat, groups, cov_free, precision, sigma2)
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
    config: SolverConfig,
    fisher: Tensor,
    meat: Tensor,
    groups,
    model_cov: Tensor,
    precision: Tensor | None,
    sigma2: Tensor | None = None,
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

    ``jackknife_test`` (a level α; σ̂² ``sigma2`` [b] the whitened residual's variance): the delete-a-group
    jackknife over-states a parameter's variance by its Efron–Stein excess where a group carries much of the
    information, by the factor c tr A / (F⁻¹)_kk ≥ 1 of :func:`jackknife_moments` where the working model holds
    (the whitened residual white): a rigid occupant's 95 % interval covered 99 %. The excess is divided out, and
    the t quantile taken at Bell and McCaffrey's ν, where the jackknife's variance is consistent with its mean
    under the working model, V_k / (excess_k σ̂² (F⁻¹)_kk) ≤ χ²_ν(1 − α) / ν; where it is larger the working model
    is in doubt (the residual holds model error: a person who is not our body model), and the uncorrected
    jackknife's surplus is what covers that error (measured: docs/measurements/persons.md), so it stays.
    """
    cfg = config
    n_free = fisher.shape[-1]
    n_groups, moments = groups  # moments [b, n, 3] of score_groups (jackknife), else None
    if n_groups <= n_free:  # fewer groups than unknowns (a short window, a wide band): nothing to estimate from
        return model_cov
    if cfg.covariance.endswith("jackknife"):
        data_cov = meat
        dof = moments[..., 0]  # the realised squares' degrees of freedom
        if cfg.jackknife_test and sigma2 is not None:
            data_cov, dof = _unbiased_where_consistent(cfg, fisher, meat, moments, sigma2)
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


def _unbiased_where_consistent(cfg, fisher: Tensor, meat: Tensor, moments: Tensor, sigma2: Tensor):
    """(data covariance, dof [b, n]): the jackknife ``meat`` over its working-model mean and Bell-McCaffrey's ν
    per parameter where its variance passes the χ² test of :func:`robust_covariance`, else as it was with the
    realised squares' dof. ``moments`` [b, n, 3]: realised dof, ν, excess (:func:`score_groups`)."""
    realised, nu, excess = moments.unbind(-1)
    inverse, _, _, _ = pseudo_inverse(fisher, cfg.rcond)
    expected = excess * sigma2.unsqueeze(1) * inverse.diagonal(dim1=1, dim2=2)  # E V_k under the working model
    variance = meat.diagonal(dim1=1, dim2=2)
    usable = torch.isfinite(excess) & (excess > 0) & torch.isfinite(nu) & (nu > 0) & (expected > 0)
    nu_safe = torch.where(usable, nu, torch.ones_like(nu)).clamp_min(1e-3)
    limit = torch.from_numpy(chi2.ppf(1.0 - float(cfg.jackknife_test), nu_safe.cpu().numpy())).to(nu) / nu_safe
    consistent = usable & (variance <= limit * expected)
    factor = torch.where(consistent, excess.clamp_min(1e-300).rsqrt(), torch.ones_like(excess))
    dof = torch.where(consistent, nu, realised)
    return meat * factor.unsqueeze(2) * factor.unsqueeze(1), dof


def score_groups(
    augmented: Tensor, band: int, spectral: bool, jackknife: bool = False, moments: bool = True
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
    information (a sharp resonance) is not under-weighted (the cluster "CR3" estimator), and its moments
    [b, n, 3] per parameter: the realised squares' degrees of freedom, and Bell-McCaffrey's ν and the
    Efron-Stein excess under the working model (:func:`jackknife_moments`; NaN without ``moments``, which
    costs a factorisation per group); None for the sandwich."""
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
    if moments:
        pair = scale.unsqueeze(-1) * scale.unsqueeze(-2)  # [b, 1, n, n]
        nu, excess = jackknife_moments((fisher / pair).squeeze(1), scaled, group_fisher / pair)
    else:
        nu = excess = torch.full_like(dof, math.nan)
    covariance = (groups - 1) / groups * torch.bmm(centred.transpose(1, 2), centred)
    return covariance, groups, torch.stack([dof, nu, excess], -1)


def jackknife_moments(fisher: Tensor, left: Tensor, group_fisher: Tensor, rcond: float = 1e-7) -> tuple[Tensor, Tensor]:
    """(ν, excess) [b, n] of each parameter's delete-a-group jackknife variance under the working model (the
    whitened residual white, variance σ²; Bell & McCaffrey 2002): V_k = c Σ_g (d_gk − d̄_k)² (c = (G − 1)/G)
    is a quadratic form εᵀAε in the noise, ν = (tr A)² / tr A² its Satterthwaite match to σ² χ²_ν / ν, and
    excess = c tr A / (F⁻¹)_kk its mean over the parameter's variance σ² (F⁻¹)_kk (≥ 1 by Efron–Stein: the
    one-step shifts of a group that carries much of the information are large). From ``fisher`` F [b, n, n],
    ``left`` F − F_g [b, G, n, n] and ``group_fisher`` F_g [b, G, n, n] (one column scaling throughout; ν and
    the excess do not depend on it): with v_g = (F − F_g)⁻¹ e_k, d_gk = a_gᵀ ε has the Gram matrix
    a_gᵀ a_h = δ_gh q_g − w_gᵀ F⁻¹ w_h (q_g = v_gᵀ F_g v_g, w_g = F_g v_g; the fit's residual is (I − H) ε), so
    with the centring C the nonzero spectrum of A is c CΓC's, whose trace and squared Frobenius norm take
    O(G n²) through Γ = diag q − W F⁻¹ Wᵀ. The realised squares' (Σ a_g²)² / Σ a_g⁴ scatters and runs low
    (G/3 for G equal groups: a normal's fourth moment is 3σ⁴)."""
    b, groups, n, _ = left.shape
    inverse = psd_inverse(left.reshape(b * groups, n, n), rcond).view(b, groups, n, n)  # P_g = (F − F_g)⁻¹
    weighted = group_fisher @ inverse  # [b, G, n, k]: column k is w_g
    q = (inverse * weighted).sum(2)  # [b, G, k]: v_gᵀ F_g v_g (P_g symmetric)
    f_inv, _, _, _ = pseudo_inverse(fisher, rcond)  # [b, n, n]
    w = weighted - weighted.mean(1, keepdim=True)  # C W
    fw = torch.einsum("bij,bgjk->bgik", f_inv, w)  # F⁻¹ (C w_g)
    cross = (w * fw).sum(2)  # [b, G, k]: (C w_g)ᵀ F⁻¹ (C w_g)
    gram = torch.einsum("bgik,bgjk->bkij", w, w)  # [b, k, n, n]: W_cᵀ W_c
    m = torch.einsum("bij,bkjl->bkil", f_inv, gram)  # F⁻¹ W_cᵀ W_c
    trace = (1 - 1 / groups) * q.sum(1) - cross.sum(1)
    square = (
        (1 - 2 / groups) * q.square().sum(1)
        + q.sum(1).square() / groups**2
        - 2 * (q * cross).sum(1)
        + (m * m.transpose(-1, -2)).sum((-1, -2))
    )
    excess = (1 - 1 / groups) * trace / f_inv.diagonal(dim1=1, dim2=2)
    return trace.square() / square.clamp_min(1e-300), excess
