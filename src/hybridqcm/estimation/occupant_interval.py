"""The occupant's static-mass interval (estimation/occupant.py's module docstring): the winner's profile-
likelihood interval of p2, joined with the Laplace intervals of the candidates the evidence cannot rule out."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .occupant_evidence import evaluation_solver
from .occupant_records import select_rows
from .profile import profile_interval
from .solver import SolverStatus

if TYPE_CHECKING:
    from .occupant import OccupantSelection

# A candidate leaves m3's interval only where the evidence against it is "very strong", 2 ln B > 10 (Kass &
# Raftery 1995, J. Am. Stat. Assoc. 90: 773-795): Occam's window (Madigan & Raftery 1994) with C = e^5 ≈ 148,
# not the "strong" 20 (e^-3). A seated person is none of the candidates, and under such model error the
# evidence of the simpler, biased model is over-confident (docs/design/persons.md, "The interval's window").
VERY_STRONG = math.exp(-5.0)


def static_mass_interval(
    selection: OccupantSelection, outputs, records, logz: Tensor, fits: Tensor, choice: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """(m3_low, m3_high, profiled) [b]: the winner's 95 % interval (profile likelihood where it could be
    computed, else Laplace) joined with the Laplace intervals of the other candidates that fit and weigh at
    least interval_weight of the winner."""
    b = choice.numel()
    lows, highs = [], []
    for name in selection.names:
        res = records[name]["final"]
        p2, s2 = records[name]["params"][:, 1].double(), res.std[:, 1].double() * records[name]["robust"][:, 1]
        high_p2, low_p2 = p2 + 1.96 * s2, p2 - 1.96 * s2
        lows.append(selection.K3 / high_p2)
        highs.append(torch.where(low_p2 > 0, selection.K3 / low_p2.clamp_min(1e-300), torch.full_like(p2, math.inf)))
    low, high = torch.stack(lows, 1), torch.stack(highs, 1)  # [b, C] (NaN where a candidate did not run)
    profiled = torch.zeros(b, dtype=torch.bool)
    if selection.profile:
        jobs = []
        for j, name in enumerate(selection.names):
            rows = ((choice == j) & (records[name]["final"].status != SolverStatus.DIVERGED)).nonzero().squeeze(1)
            if rows.numel():
                jobs.append((j, name, rows))
        profiles = selection.solve_all(
            lambda job: profile_p2(selection, job[1], select_rows(outputs, job[2], b), records[job[1]], job[2]),
            jobs,
            [selection.cost(name, rows.numel()) for _, name, rows in jobs],
        )
        for (j, name, rows), (p2_low, p2_high, _) in zip(jobs, profiles):
            ok = torch.isfinite(p2_low) & torch.isfinite(p2_high) & (p2_high > 0)
            rows, p2_low, p2_high = rows[ok], p2_low[ok], p2_high[ok]
            # widened as the jackknife widened the candidate's own interval (the residual's spread)
            p2, ratio = records[name]["params"][rows, 1].double(), records[name]["robust"][rows, 1]
            p2_low, p2_high = p2 - ratio * (p2 - p2_low), p2 + ratio * (p2_high - p2)
            # never narrower than the Laplace interval it refines
            low[rows, j] = torch.minimum(low[rows, j], selection.K3 / p2_high)
            high[rows, j] = torch.maximum(
                high[rows, j],
                torch.where(p2_low > 0, selection.K3 / p2_low.clamp_min(1e-300), torch.full_like(p2_low, math.inf)),
            )
            profiled[rows] = True
    member = interval_members(logz, fits, choice, selection.interval_weight)
    member &= torch.isfinite(low) & ~torch.isnan(high)
    low = torch.where(member, low, torch.full_like(low, math.inf)).amin(1)
    high = torch.where(member, high, torch.full_like(high, -math.inf)).amax(1)
    return low, high, profiled


def profile_p2(
    selection: OccupantSelection, name: str, outputs: Mapping, record: dict, rows: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """(p2_low, p2_high, reached) [rows] of candidate ``name``'s fits of the recordings ``rows``."""
    refinement = selection.all_models[name]
    params = record["params"][rows].double()
    v_out, v_in, log_std = record.get("variances", (None, None, None))
    variances = None if v_out is None else (v_out[rows], None if v_in is None else v_in[rows])
    problem = refinement.final_problem(outputs, params, variances=variances)
    evaluated = evaluation_solver(refinement, 0).solve(problem, params)
    # the profile's points read each solve's estimate and whether it diverged, never its covariance or misfit test
    solver = evaluation_solver(refinement, selection.profile_iterations, "log", uncertainty=False)
    # in units of the residual variance where it exceeds the noise model's (as the Laplace covariance)
    scale = evaluated.residual_variance.double().clamp_min(1.0)
    low, high, reached = profile_interval(solver, problem, params, evaluated.covariance, 1, scale=scale)
    if v_in is None or log_std is None:
        return low, high, reached
    # The input noise's variance is fitted from this window and uncertain by tens of per cent
    # (noise.input_noise_log_std); the interval at its estimate treats it as known. Its effect on p2, by
    # a polish at e^δ times it, adds in quadrature to each half-width (delta method in log v_in).
    delta = 0.5
    shifted = problem.noise.subset(torch.arange(rows.numel()))
    shifted.v_in = shifted.v_in * math.exp(delta)
    moved = evaluation_solver(refinement, selection.polish_iterations, uncertainty=False).solve(
        dataclasses.replace(problem, noise=shifted), params
    )
    slope = (moved.params[:, 1] - params[:, 1]) / delta
    spread = 1.96 * slope.abs() * log_std[rows].amax(1)
    spread = torch.where(torch.isfinite(spread) & (moved.status != SolverStatus.DIVERGED), spread, 0.0)
    p2 = params[:, 1]
    high = p2 + ((high - p2).square() + spread.square()).sqrt()
    low = p2 - ((p2 - low).square() + spread.square()).sqrt()
    return low, high, reached


def interval_members(logz: Tensor, fits: Tensor, choice: Tensor, interval_weight: float) -> Tensor:
    """[b, C] bool: the candidates whose intervals m3's interval joins — the chosen one, those that fit with an
    evidence weight exp(log Z_c - log Z_chosen) of at least ``interval_weight``, and those with more evidence
    than the chosen one although the residual tests reject them (a model that explains the data better but
    not to the noise floor: under sensor noise its answer, 50 % from the chosen one's, was the truth's)."""
    b = choice.numel()
    weight = torch.exp(logz - logz.gather(1, choice[:, None]))  # 0 where -inf
    chosen = torch.zeros_like(fits)
    chosen[torch.arange(b), choice] = True
    return chosen | ((fits | (weight > 1)) & (weight >= interval_weight))
