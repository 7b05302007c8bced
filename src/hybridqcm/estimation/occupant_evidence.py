"""The Laplace evidence of an occupant candidate's fit (estimation/occupant.py's module docstring): the
polish under the common noise model, the Occam factors, the initial state's prior, and the embedding of a
nested candidate's estimate in the larger one."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .occupant_records import put_result, select_rows
from .refinement import GaussNewtonRefinement
from .solver import SolverStatus
from .state_prior import initial_state_prior

if TYPE_CHECKING:
    from .occupant import OccupantSelection


def nest(
    selection: OccupantSelection, outputs, records, smaller: str, larger: str, v_out, v_in, assigned: Tensor
) -> None:
    """In place: where the ``larger`` candidate (which nests ``smaller``: an added body mode, or the delay)
    fits worse under the common noise model than ``smaller``'s estimate embedded in it (a new mode with a
    tenth of the rigid part's mass at the prior's frequency and damping, τ = 0, new states at rest) and
    polished, take that. A nesting model can always fit as well as the one it nests; a fit that does not
    is in another basin, and would lose the comparison for it."""
    b = assigned.shape[0]
    big, small = selection.all_models[larger].response, selection.all_models[smaller].response
    rows = (
        (
            assigned
            & (records[smaller]["final"].status != SolverStatus.DIVERGED)
            & (records[larger]["final"].status != SolverStatus.DIVERGED)
            & ~selection.collapsed(larger, records[larger]["params"])  # held at its boundary: the smaller one
        )
        .nonzero()
        .squeeze(1)
    )
    if rows.numel() == 0 or not set(small.theta_names) <= set(big.theta_names):
        return
    fill = selection.starts.get(larger.split("+")[0], torch.zeros(0, dtype=torch.float64))
    embedded = torch.zeros(rows.numel(), big.n_theta, dtype=torch.float64)
    theirs = records[smaller]["params"][rows].double()
    for j, name in enumerate(big.theta_names):
        if name in small.theta_names:
            embedded[:, j] = theirs[:, small.theta_names.index(name)]
        elif selection.n_lead <= j < big.n_params and name != "tau":  # a new body mode's (r, k, c)
            embedded[:, j] = 0.1 if name.startswith("r") else fill[j - selection.n_lead]
    refinement = selection.all_models[larger]
    sub = select_rows(outputs, rows, b)
    variances = (v_out[rows], None if v_in is None else v_in[rows])
    mine = records[larger]["params"][rows].double()
    problem = refinement.final_problem(sub, mine, variances=variances)
    solver = evaluation_solver(refinement, 3 * selection.polish_iterations)
    result = solver.solve(problem, embedded)
    better = (result.status != SolverStatus.DIVERGED) & (
        solver.objective(problem, result.params) < solver.objective(problem, mine)
    )
    if bool(better.any()):
        put_result(records[larger], result, rows[better], result.params[better], subset=better)


def polish_and_weigh(
    selection: OccupantSelection, name: str, outputs: Mapping, record: dict, rows: Tensor, variances
) -> Tensor:
    """[rows] log Z of candidate ``name``'s fits of the recordings ``rows`` (module docstring) under the
    noise ``variances``, after a few iterations from its estimate under them (``record`` updated where
    they lower the loss); -inf where not finite."""
    refinement = selection.all_models[name]
    params = record["params"][rows].double()
    problem = refinement.final_problem(outputs, params, variances=variances)
    polish = evaluation_solver(refinement, selection.polish_iterations)
    before = polish.objective(problem, params)
    result = polish.solve(problem, params)
    after = polish.objective(problem, result.params)
    take = (result.status != SolverStatus.DIVERGED) & (after <= before)
    params = torch.where(take[:, None], result.params, params)
    loss = torch.where(take, after, before)
    if not bool(take.all()):  # the covariance at the kept estimate
        result = evaluation_solver(refinement, 0).solve(problem, params)
    put_result(record, result, rows, params)
    n_steps = problem.targets.shape[1]
    free = ~problem.known
    cov = result.covariance[:, free][:, :, free]
    sign, log_det_post = torch.linalg.slogdet(cov)
    log_det_post = torch.where(sign > 0, log_det_post, torch.full_like(log_det_post, -math.inf))
    precision = (torch.zeros_like(params) if problem.prior_precision is None else problem.prior_precision.double())[
        :, free
    ]
    proper = precision > 0
    names = [n for n, f in zip(refinement.response.theta_names, free.tolist()) if f]
    state = torch.tensor([n.startswith("x0_") for n in names])
    n_components = (n_steps - 1) * len(problem.observed_index)
    sigma = cov.diagonal(dim1=1, dim2=2).clamp_min(1e-300).sqrt()
    occam_flat = torch.where(proper | state, 0.0, 0.5 * math.log(n_components) + sigma.log()).sum(1)
    occam_prior = 0.5 * torch.where(proper, precision.clamp_min(1e-300).log(), 0.0).sum(1)
    x0 = params[:, [j for j, n in enumerate(refinement.response.theta_names) if n.startswith("x0_")]]
    value = -loss + 0.5 * log_det_post + occam_prior - occam_flat
    value = value + initial_state_prior(refinement.response, problem, params, x0, cov[:, state][:, :, state])
    diverged = record["final"].status[rows] == SolverStatus.DIVERGED
    return torch.where(torch.isfinite(value) & ~diverged, value, torch.full_like(value, -math.inf))


def evaluation_solver(refinement: GaussNewtonRefinement, max_iterations: int, parametrization: str | None = None):
    """The refinement's last-stage solver with the model-based covariance, ``max_iterations`` and, where given,
    another ``parametrization`` (a profile's points: "log", so that a step cannot take a body mass near zero
    through it and end the constrained solve `diverged`)."""
    solver = refinement.stages[-1].solver
    config = dataclasses.replace(
        solver.config,
        covariance="model",
        max_iterations=int(max_iterations),
        parametrization=parametrization or solver.config.parametrization,
    )
    return type(solver)(config)
