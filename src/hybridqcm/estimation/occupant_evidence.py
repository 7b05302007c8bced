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
from .restarts import take_samples
from .solver import SolverStatus

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
    # the uncertainty pass only where the embedded start wins (most recordings keep their own fit)
    solver = evaluation_solver(refinement, 3 * selection.polish_iterations, uncertainty=False)
    result = solver.solve(problem, embedded)
    better = (result.status != SolverStatus.DIVERGED) & (
        solver.objective(problem, result.params) < solver.objective(problem, mine)
    )
    if bool(better.any()):
        won = better.nonzero().squeeze(1)
        sub = problem.subset(won)
        final = evaluation_solver(refinement, 0).solve(sub, result.params[won])
        put_result(records[larger], final, rows[won], result.params[won], problem=sub)


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
    if not bool(take.all()):  # the covariance at the kept estimate, where the polish did not move it
        kept = (~take).nonzero().squeeze(1)
        again = evaluation_solver(refinement, 0).solve(problem.subset(kept), params[kept])
        take_samples(result, again, torch.ones(kept.numel(), dtype=torch.bool), rows=kept)
    put_result(record, result, rows, params, problem=problem)
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


def evaluation_solver(
    refinement: GaussNewtonRefinement,
    max_iterations: int,
    parametrization: str | None = None,
    uncertainty: bool = True,
):
    """The refinement's last-stage solver with the model-based covariance, ``max_iterations`` and, where given,
    another ``parametrization`` (a profile's points: "log", so that a step cannot take a body mass near zero
    through it and end the constrained solve `diverged`). ``uncertainty`` False: no final Jacobian pass, for
    solves whose estimate and `diverged` status alone are read (its covariance and residual tests are not)."""
    solver = refinement.stages[-1].solver
    config = dataclasses.replace(
        solver.config,
        covariance="model",
        max_iterations=int(max_iterations),
        parametrization=parametrization or solver.config.parametrization,
        uncertainty=uncertainty,
    )
    return type(solver)(config)


def initial_state_prior(response, problem, params: Tensor, x0: Tensor, posterior: Tensor) -> Tensor:
    """[b] log N(x̂0; 0, P + Σ_x) without its 2π: the initial state's prior integrated against its Gaussian
    posterior (covariance ``posterior`` Σ_x [b, n, n], mean x̂0 = ``x0``; the outputs are linear in x0, so
    this is the exact marginal at the Laplace level). P is the state's covariance in steady state under
    the measured input (Parseval over the window's periodogram, P = Σ_k c_k Re(X_k U_k U_kᴴ X_kᴴ) / T²,
    X_k = (jω_k I − A)⁻¹ B). An initial state is informed by the window's first instants only (its
    transient decays): charging it the unit-information Occam factor ½ log N, as a parameter that every
    sample informs, would penalise a body model's two extra states by ~6 nats and hand light persons to
    the rigid model."""
    linear = response.model
    p = params[:, : linear.n_params].double()
    A, B, _, _ = linear.matrices(p)
    inputs = problem.inputs.samples if hasattr(problem.inputs, "samples") else problem.inputs
    start, n_steps = problem.window
    window = inputs[:, start : start + n_steps].double()
    window = window if window.ndim == 3 else window[..., None]
    U = torch.fft.rfft(window, dim=1).to(torch.complex128)  # [b, K, m]
    omega = 2 * math.pi * torch.fft.rfftfreq(n_steps, d=float(response.h), dtype=torch.float64)
    n = A.shape[-1]
    eye = torch.eye(n, dtype=torch.complex128)
    pencil = (1j * omega)[None, :, None, None] * eye - A.to(torch.complex128)[:, None]
    X = torch.linalg.solve(pencil, B.to(torch.complex128)[:, None] @ U[..., None])  # [b, K, n, 1]
    c = torch.full((omega.numel(),), 2.0, dtype=torch.float64)
    c[0] = 0.0
    if n_steps % 2 == 0:
        c[-1] = 1.0
    P = ((X @ X.conj().transpose(-1, -2)).real * c[None, :, None, None]).sum(1) / n_steps**2  # [b, n, n]
    P = (
        P
        + posterior.double()
        + 1e-12 * P.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-300)[:, None, None] * torch.eye(n)
    )
    sign, log_det = torch.linalg.slogdet(P)
    quad = (x0.double()[:, None, :] @ torch.linalg.solve(P, x0.double()[:, :, None]))[:, 0, 0]
    value = -0.5 * log_det - 0.5 * quad
    return torch.where((sign > 0) & torch.isfinite(value), value, torch.full_like(value, -math.inf))
