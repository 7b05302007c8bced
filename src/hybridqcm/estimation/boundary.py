"""Nested models at a boundary: a parameter whose zero is a smaller model held there (SolverConfig.boundary_test).

A seated person's body mode with mass ratio r_i = m_i / m_s (physics/occupant.py) is, at r_i = 0, the model
without that mode (body1 -> rigid, body2 -> body1): the models are nested at the boundary of the parameter
space. Where the data hold no such mode (a rigid occupant), the fit still finds something for the mode to do: its
free response from the initial state, r_i (c_i y_i' + k_i y_i) in a3, fits a transient at the window's start, and
the data fix only its amplitude r_i·y_i(0). Gauss-Newton then crawls along that ridge, r_i -> 0 with y_i(0) ~ 1/r_i,
with steps that overshoot r_i 2–1600× (30 iterations a pass), or ends across it, r_i < 0, `diverged`, its work
lost (docs/measurements/persons.md: rigid_n5, r_i from 6e-2 to 9e-4 at a loss 4.5–370 nats below r_i = 0's).

An initial state is not free, though: it is the system's state at the window's start, driven by the same input,
with the steady-state covariance P(θ) (estimation/state_prior.py) that the selection already charges in every
candidate's evidence. The test. Where a sample's full Gauss-Newton step θ − δ would take a boundary parameter θ_j
(ResponseModel.boundary) to 0 or below — the fit heads to the nested model — the nested point θ_b is θ with θ_j = 0
and the initial states it removes (ResponseModel.boundary_removes) at 0, and the two are compared by

    D = [L(θ_b) − log N(x0_b; 0, P(θ_b))] − [L(θ) − log N(x0; 0, P(θ))]

(L the noise-whitened loss, −log likelihood plus the prior's ½Σλ(θ − μ)², in nats). Without the initial state's
prior D is L's rise, an upper bound on half the likelihood-ratio statistic of the mode (the nested model
re-optimised can only do better). Below ``threshold`` the data do not resolve what the mode adds beyond what a
physical initial state explains: the sample takes θ_b and holds θ_j at 0 for the rest of its solve (a held
parameter takes no step, nor do the parameters and states it removes, on which the output no longer depends:
a body mode's k_i, c_i, dy_i(0), y_i(0); a later pass that starts there holds them too) — it is its nested model, which the
selection fits in its own right (estimation/occupant.OccupantSelection.collapsed). The level: the likelihood-ratio
test of a parameter on its boundary has the null distribution ½χ²₀ + ½χ²₁ (Self & Liang 1987, JASA 82: 605–610),
5 % at 2D = 2.71, i.e. 1.35 nats (plan_occupant.BOUNDARY_NATS). A mode the data resolve (a person's: D of tens to
thousands of nats) is never held, and none is tested before its step heads to 0. Where the test finds the
mode resolved, the line search keeps the parameter at half its value or more (``boundary_cap``): it approaches
the boundary but never crosses it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .state_prior import initial_state_prior


def boundary_test(solver, run, index: Tensor, step: Tensor) -> Tensor:
    """In place on ``run`` (the solver's _Run): for each boundary parameter the full step δ [b, n_free] of the
    samples ``index`` would take to 0 or below, the comparison D of the module docstring; where D is below the
    solver's ``boundary_test`` nats, θ takes the nested point and the parameter is held at 0. Returns [b] bool: the
    samples moved."""
    problem = run.evaluation.problem
    response = problem.model
    x0 = [i for i, name in enumerate(response.theta_names) if name.startswith("x0_")]

    def state_cost(theta: Tensor, rows: Tensor) -> Tensor:  # −log N(x0; 0, P(θ)), up to a constant
        if not x0:
            return torch.zeros(rows.numel(), dtype=theta.dtype)
        zero = torch.zeros(rows.numel(), len(x0), len(x0), dtype=theta.dtype)
        return -initial_state_prior(response, problem, theta, theta[:, x0], zero, rows)

    snapped = torch.zeros(index.numel(), dtype=torch.bool)
    for j in solver._boundary.nonzero().flatten().tolist():
        column = int(run.free[j])
        value = run.params[index, column]
        crossing = (~run.held[index, j] & (value > 0) & (value - step[:, j] <= 0)).nonzero().squeeze(1)
        if crossing.numel() == 0:
            continue
        rows = index[crossing]
        trial = run.params[rows].clone()
        removed = response.boundary_removes(column)
        trial[:, [column, *(c for c in removed if response.theta_names[c].startswith("x0_"))]] = 0.0
        loss = run.evaluation.loss_at(trial, rows)
        rise = loss - run.loss[rows] + state_cost(trial, rows) - state_cost(run.params[rows], rows)
        take = rise < solver.config.boundary_test
        rows = rows[take]
        run.params[rows] = trial[take]
        run.loss[rows] = loss[take]
        run.held[rows] |= held_columns(response, run.free, j)
        snapped[crossing[take]] = True
    return snapped


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


def without_held(held: Tensor, fisher: Tensor, gradient: Tensor) -> tuple[Tensor, Tensor]:
    """The normal equations F [b, n, n], g [b, n] with the rows and columns of the ``held`` [b, n] parameters
    zeroed (a held parameter takes no step); unchanged where none is held."""
    if not bool(held.any()):
        return fisher, gradient
    keep = (~held).to(fisher.dtype)
    return fisher * keep[:, :, None] * keep[:, None, :], gradient * keep
