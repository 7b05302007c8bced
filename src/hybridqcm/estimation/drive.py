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

**In logarithms** (``log``). Information weights that grow as the estimate falls bias the combination: a
window's σ(p2) is about proportional to its p2 (a relative precision), so Λ_w ∝ 1/p2_w² and the windows that
came out low weigh most: E θ̂ ≈ θ (1 − s²) for windows of relative scatter s (a person's 5 s windows, s ≈ 0.1 to
0.15: p2 1-2 % low, m3 as much high; measured +2.0 % signed mean over 20 persons' drives). Positive parameters
are therefore combined as log θ (Σ_w,ij / (θ_w,i θ_w,j), the delta method), where a relative precision is one
weight whatever the value, and the answer mapped back (θ̂ = exp, its covariance D C D with D = diag θ̂); χ²,
the focus's χ² and its jackknife are those of the logarithms. For windows of 1 % (a rigid occupant) the two
agree to a few 1e-4 of θ (the linear one's bias, ~s²).

**Consistency.** χ² = Σ_w (θ_w − θ̂)ᵀ Λ_w (θ_w − θ̂), about χ²_{d(n−1)} when the windows agree within
their uncertainty. ``scale="birge"`` multiplies Cov θ̂ by max(1, χ²/dof) (the Birge ratio, as the
Particle Data Group scales inconsistent measurements): windows that scatter more than they claim widen
the drive's interval instead of being trusted. ``scale="marginal"`` (the default) does that and takes the
variance of one parameter, the ``focus`` (p2: what the drive reports), from the windows' own scatter where
that is the larger: the delete-one-window jackknife of the combination,

    V_f = (n − 1)/n Σ_w (θ̂_f,(−w) − mean_w θ̂_f,(−w))² · (t_{n−1, 0.975} / z_0.975)²,
    θ̂_(−w) = (Λ − W_w)⁻¹ (Σ_v W_v θ_v − W_w θ_w),

which needs no trust in the windows' covariances (only that the windows are independent), the t factor for its
n − 1 degrees of freedom (the interval stays ±1.96 σ). A person's windows scatter in p2 up to 3× what their
covariances claim while other parameters agree, and the combination leans on the claimed correlations: the
Birge ratio, an average over all d parameters, left such drives' intervals too narrow (simulated, the focus
scattering 2.5× beyond its claims, 12 windows, d = 3: Birge covers 70 %, this 93 %; windows as claimed: 96 and
98 %; a residual sandwich n/(n − 1) Σ_w ([A W_w r_w]_f)² only 79 %: it misses the leverage of the precise
windows). Only row and column f of the covariance are scaled (D C D, D = diag(1, …, √r, …, 1)): still
positive definite, the other variances unchanged. Only where the focus's windows disagree by a test,
χ²_f = Σ_w (θ_w,f − θ̂_f)² / Σ_w,ff beyond χ²_{n−1}'s 75 % quantile (FOCUS_P = 0.25, the level Bancroft
advised for a pre-test of pooling; on 50 persons' drives 92 % covered, 90 % at 0.05): where they agree the
combination is the joint fit's, unchanged, and a running estimate of two or three windows is not widened by
t_{1, 2}'s tails (rigid drives' median time to ±5 % went from 5 s to 15 s without the test).

**A change of occupant** (:func:`segment`). For a split of windows S into L (before) and R (after) the
Wald statistic (θ̂_L − θ̂_R)ᵀ (Cov_L + Cov_R)⁻¹ (θ̂_L − θ̂_R) is χ²_d when nothing changed (and, with Λ
weights, equals the two-segment likelihood ratio χ²(S) − χ²(L) − χ²(R)). Binary segmentation: the split
with the largest statistic over every position leaving at least ``min_windows`` windows on each side is
kept when it exceeds the χ²_d quantile at α / (number of positions) (Bonferroni: a drive without a change
is split with probability ≤ α per test), and each side is searched again (``test="wald"``).

That test trusts the windows' covariances; where they understate the windows' scatter (a person's windows:
χ²/dof up to 3) it splits drives where nothing changed, and a short side whose few windows happen to agree
looks precise. ``test="pooled"`` (the default) asks whether two occupants explain the windows better than one
whose windows scatter more than they claim (Chow's test, a change in the focus f, the occupant's p2): the
scatter is estimated *within* the two sides (a real change does not inflate it, a scatter does),

    s² = max(1, (χ²_L + χ²_R) / (dof_L + dof_R), ((n_L − 1) V_f,L / C_L,ff + (n_R − 1) V_f,R / C_R,ff) / (n − 2))

(the two-segment fit's Birge ratio; each side's jackknife variance of its focus over its claimed one, pooled
by degrees of freedom), and

    F = (θ̂_f,L − θ̂_f,R)² / (s² (C_L,ff + C_R,ff))     (C: the unscaled combinations' covariances)

is compared with the F(1, n − 2) quantile at α / (number of positions): for windows with Gaussian errors of
a common unknown scale ≥ their covariances this is the test of one mean against two; a drive whose windows
scatter is widened (scale) instead of split. (Simulated, 12 windows whose focus scatters 3× beyond its claims,
α = 0.05: the Wald test with Birge-scaled sides splits 40 of 100 such drives, this 7.)

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

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import torch
from scipy.stats import chi2 as chi2_dist
from scipy.stats import f as f_dist
from scipy.stats import t as t_dist
from torch import Tensor

Z95 = 1.959963984540054  # two-sided 95 % quantile of N(0, 1)
SCALES = ("none", "birge", "marginal")
SPLIT_TESTS = ("wald", "pooled")
FOCUS_P = (
    0.25  # scale="marginal": the focus's windows inconsistent below this p-value of χ²_f (a pre-test: Bancroft's level)
)


@dataclass(frozen=True)
class Gaussian:
    """A combined estimate: mean [d], covariance [d, d] (scaled if the combiner scales), the consistency
    χ² with its degrees of freedom, and the number of windows n."""

    mean: Tensor
    covariance: Tensor
    chi2: float
    dof: int
    n: int
    unscaled: Tensor | None = None  # [d, d] the covariance before any scale (None: as ``covariance``)
    focus_chi2: float = math.nan  # Σ_w (θ_w,f − θ̂_f)² / Σ_w,ff of the focus parameter (NaN: no focus)
    focus_scatter: float = math.nan  # the focus's variance from the windows' scatter (jackknife; NaN: none)
    flat: tuple[Tensor, Tensor] | None = None  # prior once: the likelihoods' own combination (mean, unscaled cov)

    def tested(self) -> tuple[Tensor, Tensor, Tensor]:
        """(mean, covariance, unscaled covariance) that the tests between combinations compare (wald, pooled_f):
        with the prior counted once (estimation/drive_prior.py) the windows' likelihoods alone (``flat``, scaled
        as the posterior is), for two posteriors that share one prior are not independent; else the posterior."""
        if self.flat is None:
            return self.mean, self.covariance, self.raw
        scale = (self.covariance.diagonal() / self.raw.diagonal().clamp_min(1e-300)).sqrt()
        return self.flat[0], self.flat[1] * scale[:, None] * scale[None, :], self.flat[1]

    @property
    def raw(self) -> Tensor:
        return self.covariance if self.unscaled is None else self.unscaled

    @property
    def focus_ratio(self) -> float:
        """The focus parameter's own Birge ratio χ²_f / (n − 1) (NaN with one window or no focus)."""
        return self.focus_chi2 / (self.n - 1) if self.n > 1 else math.nan

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
    [W, d, d] or None (weights from ``covariance``), scale: "none" | "birge" | "marginal", focus: the index of
    the parameter reported (p2; needed by scale="marginal" and segment(test="pooled")), log [d] bool or None:
    the parameters combined in their logarithm (module docstring), each positive in every window."""

    def __init__(
        self,
        theta: Tensor,
        covariance: Tensor,
        weight_covariance: Tensor | None = None,
        scale="none",
        focus: int | None = None,
        log: Tensor | None = None,
    ):
        self.focus, self.log = checked_inputs(theta, covariance, scale, focus, log)
        # combined in log θ_i where log[i] (the delta method: Σ_w,ij / (θ_w,i θ_w,j)), answered in θ
        self.theta, factor = to_coordinates(theta, self.log)  # factor: dθ/dx [W, d]
        jacobian = factor.unsqueeze(2) * factor.unsqueeze(1)
        self.covariance = covariance.double() / jacobian
        self.precision = torch.linalg.inv(self.covariance)
        self.weights = (
            self.precision if weight_covariance is None else torch.linalg.inv(weight_covariance.double() / jacobian)
        )
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
        focus_chi2, focus_scatter = math.nan, math.nan
        if self.focus is not None and len(idx) > 1:
            f = self.focus
            focus_chi2 = float((residual[:, f].square() / self.covariance[idx, f, f]).sum())
            # the combination's variance from the windows' own scatter: the delete-one-window jackknife
            n = len(idx)
            moment = (weights @ theta.unsqueeze(-1)).squeeze(-1)  # [n, d]: W_w θ_w
            loo = torch.linalg.solve(total - weights, moment.sum(0) - moment)[:, f]  # [n]: θ̂_f without w
            focus_scatter = float((loo - loo.mean()).square().sum()) * (n - 1) / n
        g = scaled(
            Gaussian(mean, covariance, chi2, dof, len(idx), covariance, focus_chi2, focus_scatter),
            self.scale,
            self.focus,
        )
        return in_theta(g, self.log, self.focus)


def checked_inputs(
    theta: Tensor, covariance: Tensor, scale: str, focus: int | None, log: Tensor | None
) -> tuple[int | None, Tensor]:
    """The combiners' common checks of their windows (one-line ValueErrors): theta [W, d], covariance [W, d, d],
    scale one of SCALES, focus an index (needed by "marginal"), every parameter combined in its logarithm positive.
    Returns (focus as int or None, log [d] bool)."""
    if theta.ndim != 2 or covariance.shape != (*theta.shape, theta.shape[1]):
        raise ValueError(f"theta [W, d] and covariance [W, d, d], got {tuple(theta.shape)}, {tuple(covariance.shape)}")
    if scale not in SCALES:
        raise ValueError(f"scale={scale!r}: choose one of {list(SCALES)}")
    if focus is not None and not 0 <= int(focus) < theta.shape[1]:
        raise ValueError(f"focus={focus}: not one of the {theta.shape[1]} parameters")
    if scale == "marginal" and focus is None:
        raise ValueError("scale='marginal' needs the focus parameter's index")
    log = torch.zeros(theta.shape[1], dtype=torch.bool) if log is None else log.bool()
    if bool(log.any()) and not bool((theta[:, log] > 0).all()):
        raise ValueError("log: a parameter combined in logarithm must be positive in every window")
    return (None if focus is None else int(focus)), log


def to_coordinates(theta: Tensor, log: Tensor) -> tuple[Tensor, Tensor]:
    """(x, dθ/dx) [..., d] of θ [..., d]: x = log θ where ``log`` [d], else θ (the combiners' coordinates)."""
    theta = theta.double()
    return torch.where(log, theta.clamp_min(1e-300).log(), theta), torch.where(log, theta, torch.ones_like(theta))


def to_theta(x: Tensor, log: Tensor) -> tuple[Tensor, Tensor]:
    """(θ, dθ/dx) [..., d] of the combiners' coordinates x [..., d]: the inverse of :func:`to_coordinates`."""
    theta = torch.where(log, x.exp(), x)
    return theta, torch.where(log, theta, torch.ones_like(theta))


def in_theta(g: Gaussian, log: Tensor, focus: int | None = None) -> Gaussian:
    """A combination in the combiner's coordinates answered in θ: the parameters ``log`` [d] bool combined in
    their logarithm mapped back (θ = exp, covariances D C D with D = diag θ, the focus's scatter likewise)."""
    if not bool(log.any()):
        return g
    value, d = to_theta(g.mean, log)
    jac = d.unsqueeze(1) * d.unsqueeze(0)
    scatter = g.focus_scatter * float(d[focus]) ** 2 if focus is not None else math.nan
    flat = None
    if g.flat is not None:
        flat_value, e = to_theta(g.flat[0], log)
        flat = (flat_value, g.flat[1] * e.unsqueeze(1) * e.unsqueeze(0))
    return Gaussian(value, g.covariance * jac, g.chi2, g.dof, g.n, g.raw * jac, g.focus_chi2, scatter, flat)


def scaled(g: Gaussian, scale: str, focus: int | None = None) -> Gaussian:
    """``g`` with its covariance (``g.raw``) widened as ``scale`` says (module docstring): "none"; "birge" by
    max(1, χ²/dof); "marginal" that, and where the focus's windows are inconsistent (χ²_f beyond χ²_{n−1}'s
    1 − FOCUS_P quantile) the focus's row and column by √(V_f / birge C_ff) where the focus's variance from the
    windows' scatter V_f (``g.focus_scatter``) is the larger."""
    covariance = g.raw
    birge = g.chi2 / g.dof if scale in ("birge", "marginal") and g.dof > 0 and g.chi2 > g.dof else 1.0
    covariance = covariance * birge
    if scale == "marginal" and focus is not None and g.n > 1 and g.focus_chi2 > _chi2_level(g.n - 1):
        scatter = g.focus_scatter * (_t95(g.n - 1) / Z95) ** 2  # n − 1 degrees of freedom: t's interval
        if scatter > float(covariance[focus, focus]):
            factor = torch.ones(covariance.shape[0], dtype=covariance.dtype)
            factor[focus] = math.sqrt(scatter / float(covariance[focus, focus]))
            covariance = covariance * factor[:, None] * factor[None, :]
    return Gaussian(g.mean, covariance, g.chi2, g.dof, g.n, g.raw, g.focus_chi2, g.focus_scatter, g.flat)


@functools.cache
def _t95(dof: int) -> float:
    return float(t_dist.isf(0.025, dof))


@functools.cache
def _chi2_level(dof: int) -> float:
    """χ²_dof's 1 − FOCUS_P quantile: the focus's windows are inconsistent beyond it."""
    return float(chi2_dist.isf(FOCUS_P, dof))


def usable_windows(theta: Tensor, covariance: Tensor) -> Tensor:
    """[W] bool: finite θ_w and a finite, symmetric positive definite Σ_w (Cholesky succeeds)."""
    finite = torch.isfinite(theta).all(1) & torch.isfinite(covariance).flatten(1).all(1)
    safe = torch.where(finite[:, None, None], covariance, torch.eye(theta.shape[1], dtype=covariance.dtype))
    _, info = torch.linalg.cholesky_ex(0.5 * (safe + safe.transpose(1, 2)))
    return finite & (info == 0)


def wald(a: Gaussian, b: Gaussian) -> float:
    """(μ_a − μ_b)ᵀ (C_a + C_b)⁻¹ (μ_a − μ_b): χ²_d when both estimate the same θ independently."""
    (mean_a, cov_a, _), (mean_b, cov_b, _) = a.tested(), b.tested()
    diff = mean_a - mean_b
    return float(diff @ torch.linalg.solve(cov_a + cov_b, diff))


def _quantile(alpha: float, tests: int, dim: int) -> float:
    return float(chi2_dist.isf(alpha / max(tests, 1), dim))


def pooled_f(a: Gaussian, b: Gaussian, focus: int) -> float:
    """Chow's F of one focus mean against two (module docstring): (μ_a,f − μ_b,f)² over s² (C_a,ff + C_b,ff), the
    unscaled covariances widened by the scatter s² ≥ 1 within the two sides; F(1, n_a + n_b − 2) when nothing
    changed."""
    ratios = [1.0]
    if a.dof + b.dof > 0:
        ratios.append((a.chi2 + b.chi2) / (a.dof + b.dof))
    if a.n + b.n > 2:  # each side's jackknife over its claimed variance, pooled by degrees of freedom
        ratios.append(
            sum((g.n - 1) * g.focus_scatter / float(g.raw[focus, focus]) for g in (a, b) if g.n > 1) / (a.n + b.n - 2)
        )
    (mean_a, _, raw_a), (mean_b, _, raw_b) = a.tested(), b.tested()
    diff = float(mean_a[focus] - mean_b[focus])
    return diff**2 / (max(ratios) * float(raw_a[focus, focus] + raw_b[focus, focus]))


def segment(
    combiner: Combiner, windows: Sequence[int], min_windows: int = 2, alpha: float = 0.01, test: str = "wald"
) -> list[list[int]]:
    """Windows (in time order) split where the estimate changes (module docstring): a list of segments.
    test: "wald" (the windows' covariances trusted) | "pooled" (Chow's F in the combiner's focus parameter,
    the scatter estimated within the sides)."""
    if test not in SPLIT_TESTS:
        raise ValueError(f"test={test!r}: choose one of {list(SPLIT_TESTS)}")
    focus = getattr(combiner, "focus", None)
    if test == "pooled" and focus is None:
        raise ValueError("segment(test='pooled') needs a combiner with a focus parameter")
    windows = list(windows)
    n, m = len(windows), max(int(min_windows), 1)
    if n < 2 * m:
        return [windows]
    best, where = -math.inf, None
    for k in range(m, n - m + 1):
        left, right = combiner.combine(windows[:k]), combiner.combine(windows[k:])
        stat = pooled_f(left, right, focus) if test == "pooled" else wald(left, right)
        if stat > best:
            best, where = stat, k
    positions = n - 2 * m + 1
    if test == "pooled":
        threshold = float(f_dist.isf(alpha / positions, 1, max(n - 2, 1)))
    else:
        threshold = _quantile(alpha, positions, combiner.dim)
    if best <= threshold:
        return [windows]
    return segment(combiner, windows[:where], m, alpha, test) + segment(combiner, windows[where:], m, alpha, test)


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
    "pooled_f",
    "scaled",
    "in_theta",
    "checked_inputs",
    "to_coordinates",
    "to_theta",
    "SCALES",
    "SPLIT_TESTS",
    "isolated_outliers",
    "progress",
    "static_mass",
    "time_to_precision",
    "non_overlapping",
]
