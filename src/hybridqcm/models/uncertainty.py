"""A network's own uncertainty: the Gaussian negative log-likelihood and interval calibration.

A parameter network with a variance head predicts, per sample and parameter, a mean mu and a
log-variance s = log sigma^2 of its (normalised, log-parameter) target z. Under z ~ N(mu, sigma^2)

    NLL = 1/2 (log 2 pi + s + (z - mu)^2 e^{-s}),

minimised over s at e^s = (z - mu)^2: trained on a stream, sigma^2 learns the expected squared
error of the mean given the input (noisy recordings get wide intervals). beta-NLL (Seitzer et
al., 2022) weights each sample's term by stop_grad(sigma^{2 beta}); beta = 0 is the plain NLL,
beta = 0.5 keeps the mean from under-fitting where the network is unsure. The weight does not
move the per-sample optimum of sigma^2.

Intervals live in log-parameter space (z is standardised log p), so the central interval of
level q is log p in mu_log +- z_q sigma_log and its image exp(.) for p; for the occupant mass
m3 = K3 / p2 it is K3 / exp(.), reversed (a monotone map keeps the coverage of p2).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from statistics import NormalDist

import torch
from torch import Tensor

LEVELS = (0.5, 0.9, 0.95)


def clamp_log_var(raw: Tensor, low: float, high: float) -> Tensor:
    """log sigma^2 kept in [low, high] (bounded away from 0 and inf: a sample fitted exactly must not
    drive its variance, and the NLL, to -inf)."""
    return raw.clamp(low, high)


def gaussian_nll(mean: Tensor, log_var: Tensor, target: Tensor, beta: float = 0.0) -> Tensor:
    """Mean over all entries of 1/2 (log 2 pi + s + (z - mu)^2 e^{-s}) [scalar]; mean, log_var,
    target [B, P]. beta > 0: beta-NLL weights stop_grad(e^{beta s})."""
    per_entry = 0.5 * (math.log(2 * math.pi) + log_var + (target - mean).square() * torch.exp(-log_var))
    if beta > 0:
        per_entry = per_entry * torch.exp(beta * log_var).detach()
    return per_entry.mean()


def z_quantile(level: float) -> float:
    """Half-width of the central interval of probability `level` in standard deviations (1.96 at 0.95)."""
    return NormalDist().inv_cdf(0.5 + level / 2)


def interval_calibration(
    log_mean: Tensor, log_std: Tensor, log_true: Tensor, levels: Sequence[float] = LEVELS, invert_scale: float = 0.0
) -> dict[float, tuple[float, float]]:
    """Coverage and sharpness of central Gaussian intervals in log space, per level.

    log_mean, log_std, log_true: [B] (log of a positive quantity). Returns {level: (fraction of
    samples whose truth lies inside, mean width relative to the truth)}, widths of the quantity
    exp(log) — or of K / exp(log) when invert_scale = K > 0 (m3 = K3 / p2).
    """
    out = {}
    for level in levels:
        half = z_quantile(level) * log_std
        low, high = log_mean - half, log_mean + half
        inside = ((log_true >= low) & (log_true <= high)).double().mean()
        if invert_scale > 0:
            width = (invert_scale * (torch.exp(-low) - torch.exp(-high))) / (invert_scale * torch.exp(-log_true))
        else:
            width = (torch.exp(high) - torch.exp(low)) / torch.exp(log_true)
        out[float(level)] = (float(inside), float(width.double().mean()))
    return out


def calibration_rows(
    log_mean: Tensor, log_std: Tensor, log_true: Tensor, names: Sequence[str], K3: float | None = None
) -> list[Mapping]:
    """One row per quantity (each parameter, and m3 from p2 when K3 is given) with coverage_<L> and
    width_<L> for L in 50, 90, 95 %; inputs [B, P] in log parameter space."""
    rows = []
    quantities = [(name, j, 0.0) for j, name in enumerate(names)]
    if K3 is not None and "p2" in names:
        quantities.append(("m3", list(names).index("p2"), float(K3)))
    for name, j, scale in quantities:
        cal = interval_calibration(log_mean[:, j], log_std[:, j], log_true[:, j], invert_scale=scale)
        row = {"quantity": name, "n": int(log_mean.shape[0])}
        for level, (coverage, width) in cal.items():
            row[f"coverage_{round(100 * level)}"] = coverage
            row[f"width_{round(100 * level)}"] = width
        rows.append(row)
    return rows


__all__ = ["gaussian_nll", "clamp_log_var", "interval_calibration", "calibration_rows", "z_quantile", "LEVELS"]
