"""Fusion: a network's prediction with its own variance as the Gaussian prior of Gauss-Newton (MAP).

The solver minimises, per sample, ½‖W (y − f(θ))‖² + ½ Σ_j λ_j (θ_j − μ_j)² with W = 1/σ_c per
channel (residual re-weighting makes the weighted residual unit-variance noise), so the minimum
is the maximum a posteriori estimate under the prior θ_j ~ N(μ_j, 1/λ_j), and its Laplace
covariance is (JᵀWᵀWJ / σ̂² + diag λ)⁻¹ (solver.py). For a model linear in θ, y = Jθ + noise,
both are the closed form of two Gaussian sources of information:

    Σ_post = (JᵀJ / σ² + Λ)⁻¹,    θ_post = Σ_post (Jᵀy / σ² + Λ μ)

— for one scalar parameter, the precision-weighted mean of the data's estimate and the network's.

The network's prediction is a normal law of log p (models.uncertainty): median m = exp(E log p)
and std s of log p. The solver's θ holds p itself, so the prior is its first-order image,
μ = m and σ_p = m s (delta method; the log-normal's skew is below 1 % of σ_p for s ≤ 2 %, and
~s/2 relative in general). `scale` multiplies s (a calibration knob; 1 = trust the network).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

PRIOR_KINDS = ("network",)


def prior_from_log_normal(median: Tensor, log_std: Tensor, scale: float = 1.0) -> tuple[Tensor, Tensor]:
    """(mean, std) [B, P] of the Gaussian prior on p from a normal law of log p: median [B, P] and
    std of log p [B, P]; std = median · log_std · scale (first order)."""
    if not scale > 0:
        raise ValueError(f"prior scale must be > 0, got {scale}")
    return median.double(), median.double().abs() * log_std.double() * float(scale)


def network_prior(cnn, a3: Tensor, a2: Tensor, scale: float = 1.0) -> dict[str, Tensor]:
    """The CNN's p1, p2 and their std as the prior the GN refinement reads: {"prior_p12" [B, 2],
    "prior_p12_std" [B, 2]} from raw a3, a2 [B, N ≥ window] (the network's own input window)."""
    median, log_std = cnn.estimate_distribution(a3.float(), a2.float())
    mean, std = prior_from_log_normal(median, log_std, scale)
    return {"prior_p12": mean, "prior_p12_std": std}


def check_cnn_prior(kind: str | None, cnn, rel_std: float | None) -> None:
    """One-line ValueError unless `init.cnn_prior` can be served: a known kind, a CNN that predicts
    its variance (GaussianEstimator: has estimate_distribution), and not together with a fixed
    init.cnn_prior_rel_std."""
    if kind is None:
        return
    if kind not in PRIOR_KINDS:
        raise ValueError(f"init.cnn_prior={kind!r}: choose one of {list(PRIOR_KINDS)} or null")
    if cnn is None:
        raise ValueError(f"init.cnn_prior={kind}: needs the CNN (init.cnn=true and cnn_ckpt=PATH)")
    if not hasattr(cnn, "estimate_distribution"):
        raise ValueError(
            f"init.cnn_prior={kind}: cnn_ckpt holds a {type(cnn).__name__}, which predicts no variance; "
            f"train one with experiment=exp13_cnn_uncertainty (GaussianEstimator) or use init.cnn_prior_rel_std"
        )
    if rel_std:
        raise ValueError(
            f"init.cnn_prior={kind} and init.cnn_prior_rel_std={rel_std}: the prior's std comes from one of them"
        )


def gaussian_posterior(
    design: Tensor, observations: Tensor, noise_std: float | Tensor, prior_mean: Tensor, prior_precision: Tensor
) -> tuple[Tensor, Tensor]:
    """Closed-form posterior of y = X θ + e, e ~ N(0, σ² I), θ ~ N(μ, diag λ⁻¹), batched:
    design [B, T, P], observations [B, T], prior [B, P] -> (mean [B, P], covariance [B, P, P])."""
    x, y = design.double(), observations.double()
    sigma2 = torch.as_tensor(noise_std, dtype=torch.float64).reshape(-1, 1, 1) ** 2
    information = x.transpose(1, 2) @ x / sigma2 + torch.diag_embed(prior_precision.double())
    covariance = torch.linalg.inv(information)
    rhs = (x.transpose(1, 2) @ y[..., None])[..., 0] / sigma2[:, :, 0] + prior_precision * prior_mean
    return (covariance @ rhs[..., None])[..., 0], covariance


def interval_summary(estimate: Tensor, low: Tensor, high: Tensor, truth: Tensor) -> Mapping[str, float]:
    """Mean and 95th-percentile relative error, coverage of [low, high] and its mean / median width
    relative to the truth, over samples [B] (non-finite intervals cover nothing, width inf)."""
    err = ((estimate - truth).abs() / truth.abs()).double()
    err = torch.where(torch.isfinite(err), err, torch.full_like(err, float("inf")))
    finite = torch.isfinite(low) & torch.isfinite(high)
    inside = finite & (truth >= low) & (truth <= high)
    width = torch.where(finite, (high - low) / truth.abs(), torch.full_like(truth, float("inf"))).double()
    return {
        "mean_rel_err": float(err.mean()),
        "p95_rel_err": float(err.quantile(0.95)),
        "coverage_95": float(inside.double().mean()),
        "mean_rel_width": float(width.mean()),
        "median_rel_width": float(width.median()),
    }


__all__ = [
    "PRIOR_KINDS",
    "prior_from_log_normal",
    "network_prior",
    "check_cnn_prior",
    "gaussian_posterior",
    "interval_summary",
]
