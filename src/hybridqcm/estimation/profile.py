"""Profile-likelihood intervals: what a nonlinear fit's data allow for one parameter, without the
Laplace approximation's symmetry.

For a posterior loss L(θ) (½ the whitened residual's squares plus the prior's ½ Σ λ (θ − μ)²) at its
minimum θ̂, the profile of entry c is L_c(v) = min over the other entries of L with θ_c = v, and the
(1 − α) interval is {v : 2 (L_c(v) − L(θ̂)) ≤ z²}, z the normal quantile (Wilks: the deviance is
χ²₁ for a regular problem; the interval is invariant to reparametrisation, which the Laplace one is
not). Where the posterior is a banana — a seated person's static mass against the share of the body
that resonates, under sensor noise — the Laplace interval θ̂_c ± z σ_c is too short on one side; the
profile follows the ridge.

Each end is found per sample by a secant on the signed root deviance r(t) = √(2 ΔL), which is t
for a Gaussian posterior, along v(t) = θ̂_c exp(± t σ_c / θ̂_c) (positive parameters stay positive;
σ_c the Laplace standard deviation): t₀ = z, then t ← t z / r(t) (at most ×4 or ÷4 per round),
every point a solve of the problem with θ_c held at v(t), started from the previous point's solution
moved along the Laplace ridge Σ[:, c] / Σ[c, c] (continuation: a curved ridge is followed, not cut). The end is interpolated between the last two points (or taken at
the last, where the deviance stays below z² out to ``max_sigmas``: the data and prior do not bound
the parameter there, and the interval says so by reaching that far).

A point whose deviance is negative has found a lower loss than θ̂ (θ̂ was not the global minimum
on that side): its deviance counts as 0 and the search goes on outward, so the interval covers it.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from .problems import LeastSquaresProblem
from .solver import NonlinearLeastSquares, SolverStatus

MAX_LOG = 50.0  # the farthest step in log θ_c: e^50 ≈ 5e21 times θ_c, far past any interval end


def profile_interval(
    solver: NonlinearLeastSquares,
    problem: LeastSquaresProblem,
    params: Tensor,
    covariance: Tensor,
    column: int,
    z: float = 1.959963984540054,
    rounds: int = 3,
    max_sigmas: float = 12.0,
    scale: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """(low, high, reached) [b] of θ[:, column] for the fits ``params`` [b, Q] of ``problem``.

    ``covariance`` [b, Q, Q]: their Laplace covariance (for the first points and the ridge);
    ``solver``: the constrained solves (its max_iterations bounds each). ``reached`` [b] bool: both
    ends were bracketed within ``max_sigmas`` Laplace standard deviations (else that end is the
    farthest point searched). Samples whose σ_c is not finite and positive get (nan, nan, False).
    ``scale`` [b]: the deviance is read in units of it (the residual variance σ̂² that the Laplace
    covariance carries, for an interval on the same footing; default 1: the loss is in noise units)."""
    params = params.double()
    b = params.shape[0]
    value = params[:, column]
    sigma = covariance[:, column, column].double().clamp_min(0).sqrt()
    valid = torch.isfinite(sigma) & (sigma > 0) & torch.isfinite(params).all(1) & (value > 0)
    best = solver.objective(problem, params)
    valid &= torch.isfinite(best)
    known = problem.known.clone()
    known[column] = True
    fixed = dataclasses.replace(problem, known=known)
    ridge = covariance[:, :, column].double() / covariance[:, column, column].double().clamp_min(1e-300)[:, None]
    positive = problem.model.positive
    ends, reached = [], torch.ones(b, dtype=torch.bool)
    for side in (-1.0, 1.0):
        rows = valid.nonzero().squeeze(1)
        t = torch.full((b,), z, dtype=torch.float64)
        history: list[tuple[Tensor, Tensor]] = []
        current = params.clone()  # continuation: each point starts from the last one's solution
        for _ in range(rounds):
            if rows.numel() == 0:
                break
            # in log θ_c; a σ_c many times θ_c (a window with next to no signal in θ_c) would step to exp(inf)
            target = value[rows] * torch.exp((side * t[rows] * sigma[rows] / value[rows]).clamp(-MAX_LOG, MAX_LOG))
            here = current[rows]
            start = here + ridge[rows] * (target - here[:, column])[:, None]
            start[:, column] = target
            bad = (start[:, positive] <= 0).any(1) | ~torch.isfinite(start).all(1)  # left the physical domain
            start[bad] = here[bad]
            start[bad, column] = target[bad]
            sub = fixed.subset(rows)
            result = solver.solve(sub, start)
            loss = solver.objective(sub, result.params)
            failed = (result.status == SolverStatus.DIVERGED) | ~torch.isfinite(loss)
            current[rows[~failed]] = result.params[~failed]
            deviance = (2.0 * (loss - best[rows]) / (1.0 if scale is None else scale[rows])).clamp_min(0.0)
            root = torch.where(failed, torch.full_like(deviance, math.nan), deviance.sqrt())
            t_now = torch.full((b,), math.nan, dtype=torch.float64)
            r_now = torch.full((b,), math.nan, dtype=torch.float64)
            t_now[rows], r_now[rows] = t[rows], root
            history.append((t_now, r_now))
            # a failed point (its solve diverged) says nothing of the deviance: step on outwards
            step = torch.where(root > 0, z / root.clamp_min(1e-300), torch.full_like(root, 4.0)).clamp(0.25, 4.0)
            step = torch.where(failed, torch.full_like(step, 2.0), step)
            t[rows] = (t[rows] * step).clamp_max(max_sigmas)
        end_t, ok = _end(history, z, max_sigmas, b)
        reached &= ok | ~valid
        ends.append(value * torch.exp(side * end_t * sigma / value.clamp_min(1e-300)))
    low, high = ends
    nan = torch.full_like(low, math.nan)
    return torch.where(valid, low, nan), torch.where(valid, high, nan), reached & valid


def _end(history: list[tuple[Tensor, Tensor]], z: float, max_sigmas: float, b: int) -> tuple[Tensor, Tensor]:
    """(t where r(t) = z, found) [b] from the search's points (t_k, r_k) [b] each (NaN: not searched):
    interpolated in the last pair that brackets z, else extrapolated by the secant of the last two points
    (when that lands within twice the farther one and ``max_sigmas``), else — a single point — scaled as
    r ∝ t; not found: the farthest point tried. Points whose solve failed (r NaN) bracket nothing."""
    end_t = torch.full((b,), math.nan, dtype=torch.float64)
    ok = torch.zeros(b, dtype=torch.bool)
    for t_a, _ in history:  # not found: the farthest point tried (failed ones too), the wider interval
        end_t = torch.where(torch.isfinite(t_a), torch.maximum(end_t.nan_to_num(0.0), t_a), end_t)
    for (t_a, r_a), (t_b, r_b) in zip(history, history[1:]):
        both = torch.isfinite(r_a) & torch.isfinite(r_b) & (r_a != r_b)
        secant = t_b + (z - r_b) * (t_b - t_a) / torch.where(both, r_b - r_a, torch.ones_like(r_a))
        bracket = both & ((r_a - z) * (r_b - z) <= 0)
        end_t = torch.where(bracket, secant, end_t)
        ok |= bracket
    if len(history) >= 2:
        (t_a, r_a), (t_b, r_b) = history[-2], history[-1]
        both = torch.isfinite(r_a) & torch.isfinite(r_b) & (r_a != r_b)
        secant = t_b + (z - r_b) * (t_b - t_a) / torch.where(both, r_b - r_a, torch.ones_like(r_a))
        near = ~ok & both & (secant > 0) & (secant <= torch.clamp(2 * t_b, max=max_sigmas))
        end_t = torch.where(near, secant, end_t)
        ok |= near
    t_b, r_b = history[-1] if history else (end_t, end_t)
    single = ~ok & torch.isfinite(r_b) & (r_b >= z)
    end_t = torch.where(single, t_b * z / r_b.clamp_min(1e-300), end_t)
    return end_t, ok | single
