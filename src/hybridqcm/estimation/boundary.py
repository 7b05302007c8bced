"""Nested models at a boundary: a parameter whose zero is a smaller model held there (SolverConfig.boundary_test).

A seated person's body mode with mass ratio r_i = m_i / m_s (physics/occupant.py) is, at r_i = 0, the model
without that mode (body1 -> rigid, body2 -> body1): the models are nested at the boundary of the parameter
space. Where the data hold no such mode (a rigid occupant), the mode's r_i, k_i, c_i are not identifiable near
r_i = 0 — its output is r_i times a shape set by k_i, c_i — and Gauss-Newton crawls toward r_i -> 0 with steps
that overshoot it 2–1600× (30 iterations a pass), or ends across it, r_i < 0, `diverged`, its work lost.

The test. Where a sample's full Gauss-Newton step θ − δ would take a boundary parameter θ_j (ResponseModel.boundary)
to 0 or below — the fit heads to the nested model — the loss is evaluated at θ with θ_j = 0 and the rest as they
are. In a noise-whitened fit the loss is −log likelihood (+ the prior's ½Σλ(θ − μ)²) in nats, so its rise
L(θ|θ_j=0) − L(θ) is an upper bound on half the likelihood-ratio statistic of the mode (the nested model
re-optimised can only do better). Below ``threshold`` the data do not resolve what the mode adds: the sample takes
that point and holds θ_j at 0 for the rest of its solve (a held parameter takes no step; a later pass that starts
there holds it too) — it is its nested model, which the selection has fitted in its own right
(estimation/occupant.OccupantSelection.collapsed). The level: the likelihood-ratio test of a parameter on its
boundary has the null distribution ½χ²₀ + ½χ²₁ (Self & Liang 1987, JASA 82: 605–610), 5 % at 2ΔL = 2.71, i.e.
1.35 nats (plan_occupant.BOUNDARY_NATS). A mode the data resolve (a person's, ΔL of tens to hundreds of nats) is
never held; none is tested before its step heads to 0.
"""

from __future__ import annotations

import torch
from torch import Tensor


def boundary_test(solver, run, index: Tensor, step: Tensor) -> Tensor:
    """In place on ``run`` (the solver's _Run): for each boundary parameter the full step δ [b, n_free] of the
    samples ``index`` would take to 0 or below, the loss with it at 0; where it rises by less than the solver's
    ``boundary_test`` nats, θ takes that point and the parameter is held at 0. Returns [b] bool: the samples moved."""
    snapped = torch.zeros(index.numel(), dtype=torch.bool)
    for j in solver._boundary.nonzero().flatten().tolist():
        column = int(run.free[j])
        value = run.params[index, column]
        crossing = (~run.held[index, j] & (value > 0) & (value - step[:, j] <= 0)).nonzero().squeeze(1)
        if crossing.numel() == 0:
            continue
        rows = index[crossing]
        trial = run.params[rows].clone()
        trial[:, column] = 0.0
        loss = run.evaluation.loss_at(trial, rows)
        take = loss - run.loss[rows] < solver.config.boundary_test
        rows = rows[take]
        run.params[rows] = trial[take]
        run.loss[rows] = loss[take]
        run.held[rows, j] = True
        snapped[crossing[take]] = True
    return snapped


def without_held(held: Tensor, fisher: Tensor, gradient: Tensor) -> tuple[Tensor, Tensor]:
    """The normal equations F [b, n, n], g [b, n] with the rows and columns of the ``held`` [b, n] parameters
    zeroed (a held parameter takes no step); unchanged where none is held."""
    if not bool(held.any()):
        return fisher, gradient
    keep = (~held).to(fisher.dtype)
    return fisher * keep[:, :, None] * keep[:, None, :], gradient * keep
