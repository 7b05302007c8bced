"""One drive's windows combined with the parameters' prior counted once (drive.prior=once; issue 32).

A window's fit is a posterior where a prior applies (a person's body modes on a recording with a sensor noise
floor: physics/occupant.BODY_PRIOR, estimation/refinement.stage_prior), and its Laplace covariance includes the
prior's precision (estimation/uncertainty.py: (data information + prior precision)⁻¹). Combining n such windows
as likelihoods (estimation/drive.InformationCombiner: Λ = Σ_w Λ_w) counts the prior n times. Here each window's
prior is taken out, the windows' likelihoods summed, and the prior added once.

In the combiner's coordinates x (log θ where a parameter is combined in its logarithm, else θ), for a Gaussian
prior in θ (mean μ_j, precision λ_j; 0: none), at window w's estimate θ_w:

    P_w = diag(λ_j (dθ_j/dx_j)²),   g_w = ∂ log π / ∂x = −λ (θ_w − μ) dθ/dx,

the prior's curvature (as the window's Gauss-Newton covariance holds it: D diag(λ) D in x, D = dθ/dx) and
slope. The window's log posterior is −½ (x − x_w)ᵀ Λ_w (x − x_w) around its optimum x_w, where the likelihood's
slope cancels the prior's, so its likelihood alone is the Gaussian of precision and natural mean

    L_w = Λ_w − P_w,   η_w = L_w x_w − g_w   (its own optimum x_w − L_w⁻¹ g_w),

and the drive's posterior maximises Σ_w (η_wᵀ x − ½ xᵀ L_w x) + log π(θ(x)): Newton steps with the prior's
curvature,

    x̂ ← (Σ_w L_w + P(x̂))⁻¹ (Σ_w η_w + P(x̂) x̂ + g(x̂)),    Cov x̂ = (Σ_w L_w + P(x̂))⁻¹,

from the windows' own combination (exact in one step for a linear prior: combined in θ).

Which Λ_w. The exact one is the model-based covariance's (the prior's precision is in it as such); the covariance
a window reports is that one scaled per parameter by a robust ratio r ≥ 1 (estimation/drive_plan: drive_cand_cov
against drive_cand_model_cov), which also scaled the prior's part. With ``model_covariance`` (source "model") the
prior is taken out of the model-based precision, the likelihood's optimum kept and its precision scaled as the
window's is: L_w = R⁻¹ (Λ_w^model − P_w) R⁻¹ (R = diag r), η_w = L_w (x_w − (Λ_w^model − P_w)⁻¹ g_w). Without it
(source "reported") P_w comes out of the reported precision, which over-subtracts where r > 1.

A direction that the prior alone informed has L_w ≈ 0 (or < 0 after rounding, or over-subtraction): in the basis
whitened by Λ_w, L_w's eigenvalues (each direction's share of data in its information, in [0, 1]) are kept at least
``floor`` (``floored``: how many were raised, per window).

Consistency, jackknife and the split tests see the likelihoods, not the posteriors (estimation/drive.py's
docstring): χ² = Σ_w (x̃_w − x̄)ᵀ L_w (x̃_w − x̄) of each window's likelihood optimum x̃_w = L_w⁻¹ η_w about
their flat combination x̄ = (Σ L_w)⁻¹ Σ η_w (χ²_{d(n−1)} for linear-Gaussian windows, whatever the prior), the
focus's χ²_f with the likelihoods' variances (L_w⁻¹)_ff, and the delete-one-window jackknife
x̂_(−w) = (Σ_{v≠w} L_v + P(x̂))⁻¹ (Σ_{v≠w} η_v + P(x̂) x̂ + g(x̂)) (one Newton step from x̂, the prior kept).
A segment's combination counts the prior once too (one window's combination is its own posterior again). Two
segments' posteriors share that prior, so they are not independent estimates: the tests between combinations
(estimation/drive.wald, pooled_f: the outliers and the change of occupant) compare their likelihoods' own
combinations x̄ with covariance (Σ L_w)⁻¹ (``Gaussian.flat``), scaled as the posterior is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from hybridqcm.estimation.drive import Gaussian, checked_inputs, in_theta, scaled, to_coordinates, to_theta

FLOOR = 1e-3  # a direction keeps at least this share of its information as the window's likelihood


class PriorOnceCombiner:
    """The windows' likelihoods combined with the prior once (module docstring).

    theta [W, d], covariance [W, d, d] (the reported posterior covariances), prior_mean [W, d] and prior_precision
    [W, d] (each window's Gaussian prior in θ, precision 0: none; the drive's prior is, per parameter, the largest
    precision among the windows combined), model_covariance [W, d, d] or None (module docstring: which Λ_w),
    scale, focus, log: as :class:`~hybridqcm.estimation.drive.InformationCombiner`."""

    def __init__(
        self,
        theta: Tensor,
        covariance: Tensor,
        prior_mean: Tensor,
        prior_precision: Tensor,
        model_covariance: Tensor | None = None,
        scale="none",
        focus: int | None = None,
        log: Tensor | None = None,
        floor: float = FLOOR,
    ):
        self.focus, self.log = checked_inputs(theta, covariance, scale, focus, log)
        if prior_mean.shape != theta.shape or prior_precision.shape != theta.shape:
            raise ValueError(f"prior_mean and prior_precision must be [W, d] = {list(theta.shape)}")
        if not bool((prior_precision >= 0).all()) or not bool(torch.isfinite(prior_mean).all()):
            raise ValueError("prior_precision must be >= 0 and prior_mean finite")
        self.dim, self.scale = int(theta.shape[1]), scale
        theta = theta.double()
        self.x, slope = to_coordinates(theta, self.log)  # slope: dθ/dx [W, d]
        outer = slope.unsqueeze(2) * slope.unsqueeze(1)
        self.posterior = torch.linalg.inv(covariance.double() / outer)  # Λ_w in x
        self.mu, self.lam = prior_mean.double(), prior_precision.double()
        curvature = torch.diag_embed(self.lam * slope.square())  # P_w
        grad = -self.lam * (theta - self.mu) * slope  # g_w
        if model_covariance is None:
            self.L, self.floored = _floored(self.posterior - curvature, self.posterior, floor)
            self.eta = (self.L @ self.x.unsqueeze(-1)).squeeze(-1) - grad
        else:
            model = torch.linalg.inv(model_covariance.double() / outer)
            likelihood, self.floored = _floored(model - curvature, model, floor)
            optimum = self.x - torch.linalg.solve(likelihood, grad)
            ratio = covariance.double().diagonal(dim1=1, dim2=2) / model_covariance.double().diagonal(dim1=1, dim2=2)
            inv_r = ratio.clamp_min(1e-300).rsqrt()
            self.L = likelihood * inv_r.unsqueeze(2) * inv_r.unsqueeze(1)
            self.eta = (self.L @ optimum.unsqueeze(-1)).squeeze(-1)
        self.L = 0.5 * (self.L + self.L.transpose(1, 2))
        self.optimum = torch.linalg.solve(self.L, self.eta)  # x̃_w: each window's likelihood optimum

    def _prior_terms(self, x: Tensor, lam: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
        """(P(x) [d], g(x) [d]): the prior's curvature and slope in x at x [d]."""
        theta, slope = to_theta(x, self.log)
        return lam * slope.square(), -lam * (theta - mu) * slope

    def combine(self, windows: Sequence[int]) -> Gaussian:
        if len(windows) == 0:
            raise ValueError("combine: no windows")
        idx = torch.as_tensor(list(windows), dtype=torch.long)
        n = len(idx)
        L, eta, x = self.L[idx], self.eta[idx], self.x[idx]
        total, moment = L.sum(0), eta.sum(0)
        lam, which = self.lam[idx].max(0)  # the drive's prior: the largest precision a window had
        mu = self.mu[idx].gather(0, which[None])[0]
        # the windows' own combination (each prior counted) as the start; Newton steps with the prior's curvature
        post = self.posterior[idx]
        mean = torch.linalg.solve(post.sum(0), (post @ x.unsqueeze(-1)).squeeze(-1).sum(0))
        for _ in range(50):
            curv, grad = self._prior_terms(mean, lam, mu)
            new = torch.linalg.solve(total + torch.diag(curv), moment + curv * mean + grad)
            step = float((new - mean).abs().max())
            mean = new
            if step < 1e-13 * (1.0 + float(mean.abs().max())):
                break
        if not bool(torch.isfinite(mean).all()):
            raise ValueError("combine: the prior-once combination is not finite")
        curv, grad = self._prior_terms(mean, lam, mu)
        information = total + torch.diag(curv)
        covariance = torch.linalg.inv(information)
        covariance = 0.5 * (covariance + covariance.T)
        flat = torch.linalg.solve(total, moment)  # x̄: the likelihoods' own combination
        residual = self.optimum[idx] - flat
        chi2 = float(torch.einsum("wi,wij,wj->", residual, L, residual))
        dof = self.dim * (n - 1)
        focus_chi2, focus_scatter = math.nan, math.nan
        if self.focus is not None and n > 1:
            f = self.focus
            variance = torch.linalg.inv(L)[:, f, f]
            focus_chi2 = float((residual[:, f].square() / variance).sum())
            rhs = moment + curv * mean + grad - eta
            loo = torch.linalg.solve(information - L, rhs)[:, f]
            focus_scatter = float((loo - loo.mean()).square().sum()) * (n - 1) / n
        flat_cov = torch.linalg.inv(total)
        flat = (flat, 0.5 * (flat_cov + flat_cov.T))
        g = Gaussian(mean, covariance, chi2, dof, n, covariance, focus_chi2, focus_scatter, flat)
        g = scaled(g, self.scale, self.focus)
        return in_theta(g, self.log, self.focus)


def _floored(likelihood: Tensor, posterior: Tensor, floor: float) -> tuple[Tensor, Tensor]:
    """(L [W, d, d], how many directions were raised [W]): ``likelihood`` with its eigenvalues in the basis
    whitened by ``posterior`` (a direction's share of data in its information) kept at least ``floor``."""
    chol = torch.linalg.cholesky(0.5 * (posterior + posterior.transpose(1, 2)))
    half = torch.linalg.solve_triangular(chol, likelihood, upper=False)
    whitened = torch.linalg.solve_triangular(chol, half.transpose(1, 2), upper=False)
    share, vectors = torch.linalg.eigh(0.5 * (whitened + whitened.transpose(1, 2)))
    raised = (share < floor).sum(1)
    kept = (vectors * share.clamp_min(floor).unsqueeze(1)) @ vectors.transpose(1, 2)
    return chol @ kept @ chol.transpose(1, 2), raised


__all__ = ["PriorOnceCombiner", "FLOOR"]
