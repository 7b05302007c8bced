"""Nested models at a boundary: a parameter whose zero is a smaller model held there (SolverConfig.boundary_test).

A seated person's body mode with mass ratio r_i = m_i / m_s (physics/occupant.py) is, at r_i = 0, the model
without that mode (body1 -> rigid, body2 -> body1): the models are nested at the boundary of the parameter
space. Where the data hold no such mode (a rigid occupant), the fit still finds something for the mode to do — its
free response from the initial state, r_i (c_i y_i' + k_i y_i) in a3, fits a transient at the window's start, of
which the data fix only the amplitude r_i·y_i(0) — and Gauss-Newton crawls along that ridge, r_i -> 0 with
y_i(0) ~ 1/r_i, with steps that overshoot r_i 2–1600× (30 iterations a pass), or ends across it, r_i < 0,
`diverged`, its work lost (docs/measurements/persons.md: on rigid_n5 r_i went from 6e-2 to 9e-4 with the loss
4.5–370 nats below r_i = 0's all the way).

What a body mode is, physically, is its apparent mass: the forced response it adds to a3, not a start transient.
The test. Where a sample's full Gauss-Newton step θ − δ would take a boundary parameter θ_j (ResponseModel.boundary)
to 0 or below — the fit heads to the nested model — the mode's forced contribution is Δy = y(θ₀) − y(θ_b), θ₀ = θ
with the mode's initial state at rest and θ_b = θ₀ with θ_j = 0. It is unresolved where either
  - its energy under the fit's noise model, ½‖W Δy‖² (nats), is below ``boundary_test``: no likelihood-ratio test
    could tell the two apart at that level. 1.35 = ½ · 2.71: the 5 % level of the test of a parameter on its
    boundary, whose null distribution is ½χ²₀ + ½χ²₁ (Self & Liang 1987, JASA 82: 605–610; plan_occupant.BOUNDARY_NATS);
  - or its RMS is below SolverConfig.misfit_floor (1e-3) of the data's: within what the exact model's own error
    (the hold's, <= 2e-4 on two simulators' noise-free recordings) leaves unresolved — noise-free recordings, whose
    fitted noise is that error, would otherwise call any mode that fits the hold's error resolved.
Then the sample takes θ_b and holds θ_j at 0 — it is its nested model, which the selection fits in its own right
(estimation/occupant.OccupantSelection.collapsed). A held parameter takes no step, nor do the parameters and states
it removes, on which the output no longer depends (a body mode's k_i, c_i, dy_i(0), y_i(0): their Jacobian columns
are round-off there); a later pass that starts at 0 holds them too. Where the test finds the mode resolved, the line search keeps the parameter at half its value or
more (``boundary_cap``): it approaches the boundary but never crosses it.
"""

from __future__ import annotations

import torch
from torch import Tensor


def boundary_test(solver, run, index: Tensor, step: Tensor) -> Tensor:
    """In place on ``run`` (the solver's _Run): for each boundary parameter the full step δ [b, n_free] of the
    samples ``index`` would take to 0 or below, the mode's apparent-mass contribution (module docstring); where the
    data do not resolve it, θ takes the nested point and the parameter is held at 0. Returns [b] bool: the samples
    moved."""
    problem = run.evaluation.problem
    response = problem.model
    snapped = torch.zeros(index.numel(), dtype=torch.bool)
    for j in solver._boundary.nonzero().flatten().tolist():
        column = int(run.free[j])
        value = run.params[index, column]
        crossing = (~run.held[index, j] & (value > 0) & (value - step[:, j] <= 0)).nonzero().squeeze(1)
        if crossing.numel() == 0:
            continue
        rows = index[crossing]
        states = [c for c in response.boundary_removes(column) if response.theta_names[c].startswith("x0_")]
        at_rest = run.params[rows].clone()
        at_rest[:, states] = 0.0  # the mode's forced response only: its apparent mass, not a start transient
        nested = at_rest.clone()
        nested[:, column] = 0.0
        energy, relative = contribution(run, at_rest, nested, rows)
        take = (energy < solver.config.boundary_test) | (relative < solver.config.misfit_floor)
        rows = rows[take]
        if rows.numel():
            run.params[rows] = nested[take]
            run.loss[rows] = run.evaluation.loss_at(nested[take], rows)
            run.held[rows] |= held_columns(response, run.free, j)
        snapped[crossing[take]] = True
    return snapped


def contribution(run, theta: Tensor, nested: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
    """What θ's mode adds to the outputs over the window, Δy = y(θ) − y(θ_b) (θ_b = ``nested``, the recordings
    ``rows``): ([rows] ½‖W Δy‖², its energy in nats under the fit's noise model W — below the test's level no
    likelihood-ratio test could tell the two apart —, [rows] the RMS of Δy over that of the data, the largest over
    the observed channels — below SolverConfig.misfit_floor it is within the exact model's own error, the hold's
    (noise-free data, whose fitted noise is that error))."""
    problem, evaluation = run.evaluation.problem, run.evaluation
    obs = problem.observed_index
    road = evaluation.road[rows]
    delta = (
        problem.model.outputs(theta, road, *problem.window)[:, :, obs]
        - problem.model.outputs(nested, road, *problem.window)[:, :, obs]
    )
    energy = 0.5 * problem.noise.whiten_residual(delta, theta, rows, frequency_rows=False).square().sum((1, 2))
    size = evaluation.targets[rows].square().mean(1).sqrt().clamp_min(1e-300)
    return energy, (delta.square().mean(1).sqrt() / size).amax(1)


def held_columns(response, free: Tensor, j: int) -> Tensor:
    """[n_free] bool: the free entry ``j`` (a boundary parameter) and those it removes at 0 (boundary_removes)."""
    columns = torch.zeros(free.numel(), dtype=torch.bool)
    columns[j] = True
    removed = torch.tensor(response.boundary_removes(int(free[j])), dtype=torch.long)
    return columns | torch.isin(free, removed)


def initial_held(solver, problem, params: Tensor, free: Tensor) -> Tensor:
    """[b, n_free] bool: what a solve starting at ``params`` [b, n_theta] holds — the boundary parameters at 0 (a
    previous pass held them there) and what they remove; none without the test. Sets solver._boundary [n_free]."""
    boundary = problem.model.boundary[free] if hasattr(problem.model, "boundary") else torch.zeros(free.numel())
    solver._boundary = boundary.bool()
    held = torch.zeros(params.shape[0], free.numel(), dtype=torch.bool)
    if solver.config.boundary_test is None:
        return held
    for j in solver._boundary.nonzero().flatten().tolist():
        at_zero = params[:, int(free[j])] == 0
        held[at_zero] |= held_columns(problem.model, free, j)
    return held


def boundary_cap(solver, run, index: Tensor, step: Tensor) -> Tensor:
    """[b] the largest α of the samples ``index`` that keeps every free boundary parameter at half its value or
    more (fraction to the boundary): where the test finds the mode resolved, the line search approaches r_i = 0
    but never crosses it (a fit that ended at r_i < 0 was `diverged`); inf where no step heads there."""
    j = solver._boundary.nonzero().flatten()
    value, down = run.params[index][:, run.free[j]], step[:, j]
    heading = (down > 0) & ~run.held[index][:, j]
    cap = torch.where(heading, 0.5 * value / torch.where(heading, down, 1.0), torch.inf)
    return cap.amin(1)


def applies(config, problem) -> bool:
    """Whether the test applies: on, and the loss whitened by a noise model (in nats)."""
    return config.boundary_test is not None and problem.noise is not None


def without_held(held: Tensor, fisher: Tensor, gradient: Tensor) -> tuple[Tensor, Tensor]:
    """The normal equations F [b, n, n], g [b, n] with the rows and columns of the ``held`` [b, n] parameters
    zeroed (a held parameter takes no step); unchanged where none is held."""
    if not bool(held.any()):
        return fisher, gradient
    keep = ~held
    both = keep[:, :, None] & keep[:, None, :]  # where, not a product: a round-off column may hold inf or NaN
    return torch.where(both, fisher, 0.0), torch.where(keep, gradient, 0.0)
