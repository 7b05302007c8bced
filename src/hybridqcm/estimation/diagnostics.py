"""Diagnostics of a fit from its final residual: the misfit test and the covariance inflation.

Honest status: a least-squares fit always ends somewhere, so "the iteration stopped" is not
"the answer is right". After the solver's loop the residual of every sample is tested for whiteness
(Ljung-Box statistic over the first ``misfit_lags`` lags, per observed channel): a model that fits
leaves residuals that look like sensor noise, a wrong model or a local minimum leaves structure.
A sample whose residual is structured *and* larger than ``misfit_floor`` of the channel's RMS is
`misfit`, whatever the iteration said; no noise level needs to be known. So is one whose residual is
larger than the channel itself, white or not: such a fit explains less than predicting zero (a noise
model fitted to that residual whitens it, so whiteness alone cannot tell). Serially correlated
residuals also widen the standard deviations by the AR(1) factor (1 + ρ)/(1 − ρ), the usual
effective-sample-size correction, where ρ is their lag-1 autocorrelation.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from scipy.stats import chi2
from torch import Tensor

if TYPE_CHECKING:
    from .problems import ProblemEvaluation
    from .solver import SolverConfig


def residual_tests(
    config: SolverConfig, evaluation: ProblemEvaluation, params: Tensor, index: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Misfit test and covariance inflation from the final residuals of the samples ``index``.

    Per observed channel c: relative RMS r_c = ‖R_c‖/‖a_c‖ and the Ljung-Box statistic
    Q_c = N(N+2) Σ_{k≤K} ρ_k²/(N−k) of the residual's autocorrelations ρ_k (about the origin,
    so an unexplained offset counts as structure). Returns (misfit [b] bool, max_c r_c [b],
    max_c Q_c / χ²_K(1−α) [b] (> 1: not white), covariance inflation [b]).
    """
    cfg = config
    problem, targets, inputs = evaluation.problem, evaluation.targets, evaluation.road
    misfits, rel, white, inflation = [], [], [], []
    n_steps = targets.shape[1]
    lags = min(int(cfg.misfit_lags), n_steps - 2)
    threshold = float(chi2.ppf(1.0 - cfg.misfit_alpha, lags)) if lags > 0 else math.inf
    for start in range(0, index.numel(), cfg.chunk_size * 2):
        chunk = index[start : start + cfg.chunk_size * 2]
        residual = (
            problem.model.outputs(params[chunk], inputs[chunk], *problem.window)[:, :, problem.observed_index]
            - targets[chunk]
        )
        if problem.noise is not None:
            # Sensor offsets are outside the model (DC dropped): judge the size without them,
            # and test whiteness on the residual whitened by the noise model.
            residual = residual - residual.mean(1, keepdim=True)
            relative = (residual.square().sum(1) / targets[chunk].square().sum(1).clamp_min(1e-300)).sqrt()
            residual = problem.noise.white_time_residual(residual, params[chunk], chunk)
        energy = residual.square().sum(1)  # [b, n_obs]
        if problem.noise is None:
            relative = (energy / targets[chunk].square().sum(1).clamp_min(1e-300)).sqrt()
        q = torch.zeros_like(energy)
        rho1 = torch.zeros_like(energy)
        for k in range(1, lags + 1):
            rho = (residual[:, k:] * residual[:, :-k]).sum(1) / energy.clamp_min(1e-300)
            q += rho.square() / (n_steps - k)
            if k == 1:
                rho1 = rho
        q *= n_steps * (n_steps + 2)
        structured = (q > threshold) & (relative > cfg.misfit_floor)
        misfits.append((structured | (relative > 1.0)).any(1))
        rel.append(relative.amax(1))
        white.append((q / threshold).amax(1) if lags > 0 else torch.zeros(chunk.numel(), dtype=q.dtype))
        # AR(1) effective-sample-size factor where the lag-1 correlation is significant.
        rho = rho1.mean(1)
        significant = rho > 2.0 / math.sqrt(n_steps)
        rho = rho.clamp(0.0, 0.98)
        inflation.append(torch.where(significant, (1 + rho) / (1 - rho), torch.ones_like(rho)))
    return torch.cat(misfits), torch.cat(rel), torch.cat(white), torch.cat(inflation)
