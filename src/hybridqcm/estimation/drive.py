"""One occupant estimate per drive: per-window estimates combined, checked, and split where the occupant changed.

A drive is cut into windows (qcm-import window=/stride=) and the estimator answers each window on its
own, with its own initial state. Window w gives θ_w [d], the parameters every window of the drive shares
(the seat and occupant: p1, p2, and τ or body modes where they are fitted), and their covariance Σ_w
[d, d]: the shared block of the solver's covariance [n_θ, n_θ], which marginalises the window's own
initial state (for a Gaussian, taking the block *is* integrating the other components out).

**Combination** (:class:`InformationCombiner`). With Λ_w = Σ_w⁻¹,

    Λ = Σ_w Λ_w,    θ̂ = Λ⁻¹ Σ_w Λ_w θ_w,    Cov θ̂ = Λ⁻¹.

For a model linear around the common estimate this is exactly the Gaussian posterior (flat prior) of
the joint fit of all windows — θ shared, an initial state each: each window's likelihood with its
initial state profiled out is N(θ_w; θ, Σ_w) to that order, and a product of Gaussians in θ is the
above. Weights can come from another covariance than the one reported (``weight_covariance``: e.g. the
model-based σ̂²(JᵀJ)⁻¹, smooth from window to window, where the reported one is a jackknife with few
degrees of freedom whose noise, used as a weight, costs accuracy): W_w = (Σ'_w)⁻¹,
θ̂ = (Σ W_w)⁻¹ Σ W_w θ_w and, the windows being independent, Cov θ̂ = A (Σ W_w Σ_w W_w) A with
A = (Σ W_w)⁻¹ (the sandwich; = Λ⁻¹ when Σ' = Σ).

**Consistency.** χ² = Σ_w (θ_w − θ̂)ᵀ Λ_w (θ_w − θ̂), about χ²_{d(n−1)} when the windows agree within
their uncertainty. ``scale="birge"`` multiplies Cov θ̂ by max(1, χ²/dof) (the Birge ratio, as the
Particle Data Group scales inconsistent measurements): windows that scatter more than they claim widen
the drive's interval instead of being trusted.

**A change of occupant** (:func:`segment`). For a split of windows S into L (before) and R (after) the
Wald statistic (θ̂_L − θ̂_R)ᵀ (Cov_L + Cov_R)⁻¹ (θ̂_L − θ̂_R) is χ²_d when nothing changed (and, with Λ
weights, equals the two-segment likelihood ratio χ²(S) − χ²(L) − χ²(R)). Binary segmentation: the split
with the largest statistic over every position leaving at least ``min_windows`` windows on each side is
kept when it exceeds the χ²_d quantile at α / (number of positions) (Bonferroni: a drive without a change
is split with probability ≤ α per test), and each side is searched again.

**Isolated outliers** (:func:`isolated_outliers`). A single window that disagrees with the windows on
*both* sides of it (its ``neighbours`` nearest used windows each side; at a drive's end, with the one
side it has) and with all the others together, beyond the χ²_d quantile at α / n, is a wrong answer (a
stop's noise fitted, a local minimum, a bump), not a new occupant: it is rejected, the worst first, one
at a time. A change of occupant agrees with one side; a precise window among imprecise neighbours agrees
with the rest of the drive.

**Time to decision** (:func:`time_to_precision`): the driving time after which the 95 % interval of the
drive's running estimate stays within ±x of that estimate.

Pluggable: segmentation, outliers and progress talk only to a :class:`Combiner` (``combine(windows) ->
Gaussian``), so a joint multi-window fit can replace the information combination.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import torch
from scipy.stats import chi2 as chi2_dist
from torch import Tensor

Z95 = 1.959963984540054  # two-sided 95 % quantile of N(0, 1)


@dataclass(frozen=True)
class Gaussian:
    """A combined estimate: mean [d], covariance [d, d] (scaled if the combiner scales), the consistency
    χ² with its degrees of freedom, and the number of windows n."""

    mean: Tensor
    covariance: Tensor
    chi2: float
    dof: int
    n: int

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    @property
    def p_value(self) -> float:
        """P(χ²_dof ≥ χ²): small when the windows do not agree with one estimate."""
        return float(chi2_dist.sf(self.chi2, self.dof)) if self.dof > 0 else math.nan


class Combiner(Protocol):
    """What segmentation, outlier rejection and progress need: the posterior of any set of windows."""

    dim: int

    def combine(self, windows: Sequence[int]) -> Gaussian: ...


class InformationCombiner:
    """Information-weighted combination of per-window Gaussians (module docstring).

    theta [W, d], covariance [W, d, d] (positive definite; see :func:`usable_windows`), weight_covariance
    [W, d, d] or None (weights from ``covariance``), scale: "none" | "birge"."""

    def __init__(self, theta: Tensor, covariance: Tensor, weight_covariance: Tensor | None = None, scale="none"):
        if theta.ndim != 2 or covariance.shape != (*theta.shape, theta.shape[1]):
            raise ValueError(
                f"theta [W, d] and covariance [W, d, d], got {tuple(theta.shape)}, {tuple(covariance.shape)}"
            )
        if scale not in ("none", "birge"):
            raise ValueError(f"scale={scale!r}: choose none or birge")
        self.theta = theta.double()
        self.covariance = covariance.double()
        self.precision = torch.linalg.inv(self.covariance)
        self.weights = self.precision if weight_covariance is None else torch.linalg.inv(weight_covariance.double())
        self.sandwich = weight_covariance is not None
        self.scale = scale
        self.dim = int(theta.shape[1])

    def combine(self, windows: Sequence[int]) -> Gaussian:
        if len(windows) == 0:
            raise ValueError("combine: no windows")
        idx = torch.as_tensor(list(windows), dtype=torch.long)
        theta, weights = self.theta[idx], self.weights[idx]
        total = weights.sum(0)
        inverse = torch.linalg.inv(total)
        mean = inverse @ (weights @ theta.unsqueeze(-1)).squeeze(-1).sum(0)
        if self.sandwich:
            meat = (weights @ self.covariance[idx] @ weights).sum(0)
            covariance = inverse @ meat @ inverse
        else:
            covariance = inverse
        covariance = 0.5 * (covariance + covariance.T)
        residual = theta - mean
        chi2 = float(torch.einsum("wi,wij,wj->", residual, self.precision[idx], residual))
        dof = self.dim * (len(idx) - 1)
        if self.scale == "birge" and dof > 0 and chi2 > dof:
            covariance = covariance * (chi2 / dof)
        return Gaussian(mean, covariance, chi2, dof, len(idx))


def usable_windows(theta: Tensor, covariance: Tensor) -> Tensor:
    """[W] bool: finite θ_w and a finite, symmetric positive definite Σ_w (Cholesky succeeds)."""
    finite = torch.isfinite(theta).all(1) & torch.isfinite(covariance).flatten(1).all(1)
    safe = torch.where(finite[:, None, None], covariance, torch.eye(theta.shape[1], dtype=covariance.dtype))
    _, info = torch.linalg.cholesky_ex(0.5 * (safe + safe.transpose(1, 2)))
    return finite & (info == 0)


def wald(a: Gaussian, b: Gaussian) -> float:
    """(μ_a − μ_b)ᵀ (C_a + C_b)⁻¹ (μ_a − μ_b): χ²_d when both estimate the same θ independently."""
    diff = a.mean - b.mean
    return float(diff @ torch.linalg.solve(a.covariance + b.covariance, diff))


def _quantile(alpha: float, tests: int, dim: int) -> float:
    return float(chi2_dist.isf(alpha / max(tests, 1), dim))


def segment(combiner: Combiner, windows: Sequence[int], min_windows: int = 2, alpha: float = 0.01) -> list[list[int]]:
    """Windows (in time order) split where the estimate changes (module docstring): a list of segments."""
    windows = list(windows)
    n, m = len(windows), max(int(min_windows), 1)
    if n < 2 * m:
        return [windows]
    best, where = -math.inf, None
    for k in range(m, n - m + 1):
        stat = wald(combiner.combine(windows[:k]), combiner.combine(windows[k:]))
        if stat > best:
            best, where = stat, k
    if best <= _quantile(alpha, n - 2 * m + 1, combiner.dim):
        return [windows]
    return segment(combiner, windows[:where], m, alpha) + segment(combiner, windows[where:], m, alpha)


def isolated_outliers(
    combiner: Combiner, windows: Sequence[int], alpha: float = 0.001, neighbours: int = 2
) -> list[int]:
    """The windows (in time order) rejected as isolated outliers (module docstring), in rejection order."""
    kept, rejected = list(windows), []
    while len(kept) > 2:
        threshold = _quantile(alpha, len(kept), combiner.dim)
        worst, which = threshold, None
        for i, w in enumerate(kept):
            sides = [kept[max(0, i - neighbours) : i], kept[i + 1 : i + 1 + neighbours], kept[:i] + kept[i + 1 :]]
            stats = [wald(combiner.combine([w]), combiner.combine(side)) for side in sides if side]
            if min(stats) > worst:
                worst, which = min(stats), i
        if which is None:
            break
        rejected.append(kept.pop(which))
    return rejected


def progress(combiner: Combiner, windows: Sequence[int]) -> list[Gaussian]:
    """The running estimate after each window (in time order) of one segment: [combine(windows[:j + 1])]."""
    return [combiner.combine(list(windows[: j + 1])) for j in range(len(windows))]


def static_mass(g: Gaussian, index: int, K3: float | None = None) -> tuple[float, float, float, float]:
    """(m3, std, low, high) of the static mass from a combined estimate. K3 given: θ[index] is p2 = K3/m3,
    so m3 = K3/p2 with the delta-method std and the 95 % interval mapped from p2's (skewed: m3 is monotone
    in p2; high = inf when p2's interval reaches 0). K3 None: θ[index] is the mass itself (± 1.96 std)."""
    value = float(g.mean[index])
    std = math.sqrt(max(float(g.covariance[index, index]), 0.0))
    if K3 is None:
        return value, std, value - Z95 * std, value + Z95 * std
    low_p2, high_p2 = value - Z95 * std, value + Z95 * std
    m3 = K3 / value
    return m3, K3 / value**2 * std, K3 / high_p2, (K3 / low_p2 if low_p2 > 0 else math.inf)


def time_to_precision(
    ends: Sequence[float], m3: Sequence[float], low: Sequence[float], high: Sequence[float], level: float
) -> float:
    """The driving time ends[j] of the first step j from which on every running 95 % interval lies within
    ±level of its own estimate ((1 - level) m3 <= low, high <= (1 + level) m3); NaN if never."""
    answer = math.nan
    for j in range(len(ends) - 1, -1, -1):
        inside = math.isfinite(high[j]) and low[j] >= (1 - level) * m3[j] and high[j] <= (1 + level) * m3[j]
        if not inside:
            break
        answer = float(ends[j])
    return answer


def non_overlapping(starts: Sequence[float], length: float, tolerance: float = 1e-9) -> list[bool]:
    """Windows (sorted by start time) kept so that no two overlap: each starts at or after the end of the
    last one kept. Overlapping windows share data, so their errors are correlated and the information of
    both is not the sum (stride < window); the ones left out are not used in the combination."""
    keep, end = [], -math.inf
    for start in starts:
        ok = start >= end - tolerance * max(1.0, abs(length))
        keep.append(ok)
        if ok:
            end = start + length
    return keep


__all__ = [
    "Z95",
    "Gaussian",
    "Combiner",
    "InformationCombiner",
    "usable_windows",
    "wald",
    "segment",
    "isolated_outliers",
    "progress",
    "static_mass",
    "time_to_precision",
    "non_overlapping",
]
